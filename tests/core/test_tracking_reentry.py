"""Graceful re-entry of the tracker (issue 36 item 2): after a stall and with too few anchors.

* A stall (the fusion stopped: the tracker is not called at all for 15 s, then epochs come
  again): ``lost_on_gap`` makes the stale track LOST and re-initialises it from a snapshot
  (INITIALISING for ``confirm_epochs``), instead of updating the 15 s old state and publishing
  it TRACKING with the floor probabilities of before the stall.
* Two anchors (``min_anchors_tracking``): the node is published COASTING, its floor probability
  capped at ``few_anchors_floor_p_max``; the filter itself (positions, floor choice) is
  unchanged. References: the same runs with the settings off (the tracker before).
Ranges and SNR from the emulator's channel (fixed seeds).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.tracking.state import TrackerConfig, TrackStatus
from diffpos.tracking.tracker import init_state, update
from diffpos.trajectory import trajectory_from_dict

SC = default_scenario()
B = SC.building
RADIO = SC.radio
# the few-anchor rules alone: floor_hold_max_links (default 2 since 2026-12-07) would keep the
# floor probabilities of the two-anchor epochs as predicted
ON = dataclasses.replace(TrackerConfig(), floor_hold_max_links=0, family_few_links=0,
                         family_fit_links=0)
#: the re-entry rules off (and the contest rule, which also tempers a node with < 4 ranges)
OFF = dataclasses.replace(ON, lost_on_gap=False, min_anchors_tracking=0, floor_contest_s=0.0)
ANCHORS8 = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.0],
                     [-25.0, -12.0, 3.0], [25.0, -12.0, 3.0], [-8.0, -10.0, 2.0],
                     [8.0, -25.0, 0.5]])
WALKERS = [trajectory_from_dict({"kind": "waypoints", "points_m": p, "speed_m_s": v})
           for p, v in (([[-8.0, 4.0, 8.5], [8.0, 4.0, 8.5], [8.0, 12.0, 8.5]], 1.0),
                        ([[3.0, 12.0, 11.5], [3.0, 2.0, 11.5], [-9.0, 2.0, 11.5]], 0.8),
                        ([[-12.0, 15.0, 5.5], [4.0, 15.0, 5.5], [4.0, 6.0, 5.5]], 1.2))]
TRUE_FLOOR = np.asarray(B.floor_index(np.array([8.5, 11.5, 5.5])))


def _epochs(t_s, seed: int):
    rng = np.random.default_rng(seed)
    out = []
    for t in t_s:
        nodes = np.stack([w.position_m(t) for w in WALKERS])
        fa = first_arrival(emulate_channel(ANCHORS8, nodes, building=B, radio=RADIO),
                           radio=RADIO, rng=rng)
        out.append((round(t * 1e9), fa.range_m, fa.sigma_m, fa.detected, fa.snr_db))
    return out


def _run(epochs, config, keep=None):
    """Outputs of the tracker over ``epochs``; ``keep(i)``: the anchors' mask of epoch i."""
    n = len(WALKERS)
    state = init_state(n, B)
    outs = []
    for i, (t_ns, r, s, m, snr) in enumerate(epochs):
        m = m if keep is None else m & keep(i)[None, :]
        state, out = update(state, np.broadcast_to(ANCHORS8, (n, *ANCHORS8.shape)), r, s, m,
                            t_ns, B, config, snr_db=snr, radio=RADIO)
        outs.append(out)
    return outs


def test_after_a_stall_the_stale_track_is_reinitialised_not_published_tracking():
    before = np.arange(0.0, 4.0, 0.1)
    after = np.arange(19.0, 21.0, 0.1)  # 15 s without any call (the fusion was stopped)
    epochs = _epochs(np.concatenate([before, after]), seed=11)
    k = before.size
    on, off = _run(epochs, ON), _run(epochs, OFF)
    assert all(np.all(o.status == TrackStatus.TRACKING) for o in on[k - 5:k])  # tracked before
    # before the change: the first epoch after the stall updated the stale track, TRACKING
    assert np.all(off[k].status == TrackStatus.TRACKING)
    # now: re-initialised from a snapshot, INITIALISING until confirm_epochs updates
    for i in range(k, k + ON.confirm_epochs - 1):
        assert np.all(on[i].status == TrackStatus.INITIALISING), (i, on[i].status)
    assert np.all(on[k + ON.confirm_epochs].status == TrackStatus.TRACKING)
    # and the re-entry is no worse: right floor over the 2 s after the stall
    right = [sum(int(np.sum(o.floor_index == TRUE_FLOOR)) for o in outs[k:])
             for outs in (on, off)]
    assert right[0] >= right[1], right


def test_two_anchors_are_not_tracking_at_high_confidence():
    t = np.arange(0.0, 6.0, 0.1)
    epochs = _epochs(t, seed=12)
    two = np.zeros(len(ANCHORS8), bool)
    two[[1, 2]] = True
    full = np.ones(len(ANCHORS8), bool)
    k = 30  # 3 s with 8 anchors, then 3 s with two

    def keep(i):
        return full if i < k else two

    on, off = _run(epochs, ON, keep), _run(epochs, OFF, keep)
    placed = 0
    for i in range(k, len(t)):
        n_ranges = (epochs[i][3] & two).sum(axis=1)
        few = (n_ranges > 0) & (n_ranges < 3)
        assert np.array_equal(on[i].position_m, off[i].position_m, equal_nan=True)
        assert np.array_equal(on[i].floor_index, off[i].floor_index)  # publication only
        assert not np.any(few & (on[i].status == TrackStatus.TRACKING)), on[i].status
        assert np.all(on[i].floor_probabilities[few].max(axis=1) <= 0.75 + 1e-12)
        np.testing.assert_allclose(on[i].floor_probabilities.sum(axis=1), 1.0, atol=1e-12)
        placed += int(np.sum(few & (off[i].status == TrackStatus.TRACKING)
                             & (off[i].floor_probabilities.max(axis=1) > 0.9)))
    assert placed > 0  # before: two-anchor fixes were TRACKING at > 0.9
