"""Re-seeding a lost floor hypothesis from its floor's snapshot, only where the ranges test it
(``TrackerConfig.reseed_max``, ``reseed_min_links``; issue 34, docs/tracking_evidence.md
"Session 24: where Sionna paper's misses are").

A static node of the paper building on floor 3 is tracked from the emulator's channel (ranges
and SNR, fixed seeds) until its tracks have converged; then its true floor's tracks (both
modes) are moved 8 m deeper into the building, far beyond their covariance, after failing their ranges for
``reseed_epochs - 1`` epochs already, and one more epoch is processed:

* four ranges: with the re-seed (``reseed_min_links`` 4) the floor's snapshot puts its level
  track back at the node (the reference: the emulator's truth, 0.3 m), without it the track
  stays metres away;
* three ranges (one anchor unheard): a snapshot fits three ranges on any floor, so
  ``reseed_min_links`` 4 leaves the node exactly as without the re-seed (every output
  equal), while at 0 (``min_ranges_init``: the behaviour before) it is re-seeded.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import diffpos.tracking.model as model_mod
import diffpos.tracking.tracker as tracker_mod
from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import init_state, update

SC = default_scenario()
B, RADIO = SC.building, SC.radio
ANCHORS = np.asarray(SC.anchor_positions_m(0.0))
NODE = np.array([10.0, 6.12, 14.5])
ON = TrackerConfig()  # the re-seed is on by default since 208fb2e (2026-12-07)
OFF = dataclasses.replace(ON, reseed_max=0, reseed_min_links=0)
OFFSET = np.array([0.0, 8.0, 0.0])  # 8 m deeper into the building: its ranges fail there


def _moved(config, seed, drop=None, k0=30):
    """The state and output after the epoch that follows moving the true floor's tracks by
    ``OFFSET`` (epoch ``k0``), and the number of ranges of that epoch."""
    rng = np.random.default_rng(seed)
    channel = emulate_channel(ANCHORS, NODE[None], building=B, radio=RADIO)
    f, nf = int(B.floor_index(NODE[2])), B.n_floors
    state = init_state(1, B)
    for k in range(k0 + 1):
        if k == k0:
            mean, bad = state.mean.copy(), state.floor_bad.copy()
            mean[0, [f, f + nf], :3] += OFFSET
            bad[0, [f, f + nf]] = config.reseed_epochs - 1
            state = dataclasses.replace(state, mean=mean, floor_bad=bad)
        fa = first_arrival(channel, radio=RADIO, rng=rng)
        det = fa.detected.copy()
        if drop is not None:  # an anchor never heard: the node's other ranges only
            det[..., drop] = False
        state, out = update(state, ANCHORS[None], fa.range_m, fa.sigma_m, det,
                            10**9 + k * 10**8, B, config, snr_db=fa.snr_db, radio=RADIO)
    return state, out, int(det.sum()), f


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_floor_track_moved_far_off_is_reseeded_at_the_node_with_four_ranges(seed):
    state, _, n, f = _moved(OFF, seed)
    assert n == 4
    assert np.linalg.norm(state.mean[0, f, :3] - NODE) > 2.0  # stays off without
    state, _, n, f = _moved(ON, seed)
    assert np.linalg.norm(state.mean[0, f, :3] - NODE) < 0.3  # the floor's snapshot


@pytest.mark.parametrize("seed", [1, 2])
def test_three_ranges_are_not_reseeded_with_reseed_min_links_4(seed):
    off_state, off_out, n, f = _moved(OFF, seed, drop=3)
    assert n == 3
    s4, o4, _, _ = _moved(ON, seed, drop=3)
    for name in ("mean", "cov", "log_prob", "floor_bad"):
        assert np.array_equal(getattr(off_state, name), getattr(s4, name)), name
    for name in ("position_m", "floor_index", "floor_probabilities"):
        assert np.array_equal(getattr(off_out, name), getattr(o4, name)), name
    s0, _, _, _ = _moved(dataclasses.replace(ON, reseed_min_links=0), seed, drop=3)
    assert not np.array_equal(off_state.mean[0, f], s0.mean[0, f])  # re-seeded at 0


def test_on_by_default():
    assert ON.reseed_max == 2 and ON.reseed_min_links == 4


# ``reseed_period_s`` (off by default): a hypothesis is re-seeded only in an epoch that
# crosses one of its period's boundaries (phase h / H of the period; session 26,
# docs/performance.md). The epochs of ``_moved`` are 0.1 s apart.
STATE_FIELDS = ("mean", "cov", "log_prob", "floor_bad", "status")
OUT_FIELDS = ("position_m", "covariance_m2", "floor_index", "floor_probabilities")


def _same(a, b):
    (sa, oa), (sb, ob) = a[:2], b[:2]
    return (all(np.array_equal(getattr(sa, k), getattr(sb, k)) for k in STATE_FIELDS)
            and all(np.array_equal(getattr(oa, k), getattr(ob, k), equal_nan=True)
                    for k in OUT_FIELDS))


@pytest.mark.parametrize("seed", [1, 2])
def test_reseed_period_of_one_epoch_is_every_epoch_and_a_longer_than_the_run_one_never(seed):
    """A period of one epoch puts a boundary of every hypothesis in every epoch: bit for bit
    the default (no period); a period longer than the run crosses none: bit for bit no
    re-seed at all (``reseed_max`` 0), the moved track left off."""
    assert _same(_moved(dataclasses.replace(ON, reseed_period_s=0.1), seed), _moved(ON, seed))
    never = _moved(dataclasses.replace(ON, reseed_period_s=1000.0), seed)
    assert _same(never, _moved(OFF, seed))
    assert np.linalg.norm(never[0].mean[0, never[3], :3] - NODE) > 2.0


def test_reseed_period_of_ten_epochs_reseeds_the_moved_track_in_one_epoch_of_ten():
    """With a 1 s period (ten epochs) the moved level track is re-seeded in the epoch after
    the move for exactly one of ten consecutive move epochs (its boundary's); in the others
    it waits (still metres off), as without the re-seed."""
    cfg = dataclasses.replace(ON, reseed_period_s=1.0)
    back = []
    for k0 in range(20, 30):
        state, _, n, f = _moved(cfg, 1, k0=k0)
        assert n == 4
        d = np.linalg.norm(state.mean[0, f, :3] - NODE)
        assert d < 0.3 or d > 2.0
        back.append(bool(d < 0.3))
    assert sum(back) == 1, back


def test_reseed_period_off_by_default():
    assert ON.reseed_period_s == 0.0


# ``reseed_starts`` (0 by default: ``init_starts``): the grid cells a re-seed's snapshot fits
# (issue 37: fewer hypothesis updates per re-seed; docs/replay_speed.md "Session 28").
def test_reseed_starts_default_and_init_starts_are_the_same_bits():
    """0 (the default) is ``init_starts``: the same state and output bit for bit."""
    assert ON.reseed_starts == 0
    assert _same(_moved(dataclasses.replace(ON, reseed_starts=ON.init_starts), 1),
                 _moved(ON, 1))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_one_start_reseeds_the_moved_track_at_the_node(seed, monkeypatch):
    """With ``reseed_starts`` 1 the re-seed's snapshot fits the grid's best cell only (the
    snapshot is asked for one start, its measurement updates get one hypothesis per floor),
    and still puts the moved level track back at the node (0.3 m, as with three)."""
    seen, hyps = [], []
    snap, mu = tracker_mod.snapshot, model_mod.measurement_update

    def spy_snapshot(links, floors, building, config, starts=None, passes=2):
        seen.append(starts)  # (the tracker's own snapshots: its re-seeds)
        try:
            return snap(links, floors, building, config, starts, passes)
        finally:
            seen.append(None if seen[-1] is None else "done")

    def spy_update(x_prior, *a, **k):
        if seen and seen[-1] not in (None, "done"):  # inside a re-seed's snapshot
            hyps.append(x_prior.shape[1])
        return mu(x_prior, *a, **k)

    monkeypatch.setattr(tracker_mod, "snapshot", spy_snapshot)
    monkeypatch.setattr(model_mod, "measurement_update", spy_update)
    state, _, n, f = _moved(dataclasses.replace(ON, reseed_starts=1), seed)
    assert n == 4 and set(seen) == {1, "done"} and len(hyps) == 2 * seen.count(1)
    assert set(hyps) == {1}  # one start of one floor per re-seeded hypothesis
    assert np.linalg.norm(state.mean[0, f, :3] - NODE) < 0.3
