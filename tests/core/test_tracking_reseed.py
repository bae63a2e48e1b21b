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
