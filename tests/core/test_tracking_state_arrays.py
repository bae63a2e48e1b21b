"""The new state of :func:`diffpos.tracking.tracker.update` owns its arrays (session 25: a
call that updates every row takes the measurement update's arrays over instead of copying the
state and writing every row into the copy, ``tracker._merged``). Properties: the same bits as
the copy-and-write reference; the input state unchanged; no array of the new state shared
with the input state or with another field (the fusion's bank writes the rows back and the
next call updates them in place).

Input: the channel emulator's first arrivals (seeded) from eight static UAVs to six static
nodes of the default building; calls where every row is updated (all ranged), where only some
are (a node without ranges: COASTING; new nodes: initialised), and the first call (nothing
placed yet)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.tracking import tracker
from diffpos.tracking.state import TrackerConfig, TrackStatus
from diffpos.tracking.tracker import init_state, update

SC = default_scenario()
B = SC.building
ANCHORS = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.0],
                    [-25.0, -12.0, 3.0], [25.0, -12.0, 3.0], [-8.0, -10.0, 2.0],
                    [8.0, -25.0, 0.5]])
NODES = np.array([[-4.0, 3.0, 4.5], [2.0, 6.0, 7.5], [6.0, 2.5, 10.5], [-1.0, 8.0, 13.5],
                  [3.5, 4.0, 4.2], [-6.0, 5.0, 7.8]])


def _reference_merged(st, idx, new):
    """The state's arrays as before: a copy of each, the rows ``idx`` written into it."""
    out = {}
    for k in (*tracker._UPDATED, *tracker._LINK_STATE):
        out[k] = getattr(st, k).copy()
        if k in new:
            out[k][idx] = new[k]
    return out


def _run(seed: int, monkeypatch=None) -> list:
    """Every call's (state before, state after, output) of 7 epochs: epoch 3 with node 2 out
    of range, nodes 4-5 ranged from epoch 4 on (initialised there)."""
    rng = np.random.default_rng(seed)
    cfg = TrackerConfig()
    st = init_state(len(NODES), B)
    calls = []
    for k in range(7):
        fa = first_arrival(emulate_channel(ANCHORS, NODES, building=B, radio=SC.radio),
                           radio=SC.radio, rng=rng)
        mask = fa.detected.copy()
        mask[2] &= k != 3
        mask[4:] &= k >= 4
        a = np.broadcast_to(ANCHORS, (len(NODES), *ANCHORS.shape))
        t = np.full(len(NODES), k * 100_000_000, np.int64)
        before = {f.name: np.copy(getattr(st, f.name)) for f in dataclasses.fields(st)}
        new, out = update(st, a, fa.range_m, fa.sigma_m, mask, t, B, cfg, snr_db=fa.snr_db,
                          radio=SC.radio)
        calls.append((st, before, new, out))
        st = new
    return calls


def _bits(x) -> list:
    return [(f.name, v.dtype.str, v.shape, np.ascontiguousarray(v).tobytes())
            for f in dataclasses.fields(x) if (v := getattr(x, f.name)) is not None]


@pytest.mark.parametrize("seed", [1, 4])
def test_update_owns_its_arrays_and_equals_copy_and_write(seed, monkeypatch):
    calls = _run(seed)
    statuses = {TrackStatus(s).name for _, _, new, _ in calls for s in new.status}
    assert {"INITIALISING", "TRACKING", "COASTING"} <= statuses
    for st, before, new, _ in calls:
        for f in dataclasses.fields(st):  # the input state is not modified
            assert np.array_equal(getattr(st, f.name), before[f.name], equal_nan=True), f.name
        arrays = [(f.name, getattr(new, f.name)) for f in dataclasses.fields(new)]
        for i, (name, v) in enumerate(arrays):
            assert v.flags.writeable, name
            for g in dataclasses.fields(st):
                assert not np.shares_memory(v, getattr(st, g.name)), (name, g.name)
            for name2, w in arrays[i + 1:]:
                assert not np.shares_memory(v, w), (name, name2)
    monkeypatch.setattr(tracker, "_merged", _reference_merged)
    ref = _run(seed)
    for (_, _, new, out), (_, _, rnew, rout) in zip(calls, ref, strict=True):
        assert _bits(new) == _bits(rnew)
        assert _bits(out) == _bits(rout)


def test_merged_takes_over_only_whole_matching_arrays():
    """``_merged`` hands back ``new``'s array only for a call that updates every row with an
    array of the state's shape, dtype and layout, not twice the same array; else a copy with
    the rows written."""
    st = init_state(3, B)
    idx = np.arange(3)
    mean = np.ones_like(st.mean)
    nis32 = np.ones(3, np.float32)
    got = tracker._merged(st, idx, {"mean": mean, "nis": nis32, "log_prob": mean[..., 0],
                                    "link_out": st.link_out.copy(), "link_all": None})
    assert got["mean"] is mean
    assert got["nis"] is not nis32 and got["nis"].dtype == st.nis.dtype
    assert got["log_prob"].flags.c_contiguous and not np.shares_memory(got["log_prob"], mean)
    assert np.array_equal(got["log_prob"], np.ones_like(st.log_prob))
    part = tracker._merged(st, np.array([1]), {"mean": mean[1:2]})
    assert part["mean"] is not mean and np.array_equal(part["mean"][1], mean[1])
    assert np.array_equal(part["mean"][[0, 2]], st.mean[[0, 2]])
    same = np.zeros_like(st.link_ev)
    twice = tracker._merged(st, idx, {"link_all": same, "below_epochs": None, "link_ev": same})
    assert twice["link_all"] is same and twice["link_ev"] is not same
    assert np.array_equal(twice["link_ev"], same)
    for k, v in got.items():
        assert not np.shares_memory(v, getattr(st, k)), k
