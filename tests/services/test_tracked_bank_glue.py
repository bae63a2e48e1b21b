"""The tracker bank's glue without per-row Python (fusion/tracked.py, session 25): the rows of
a call read and written through a slice when they are consecutive, ``hold_inits`` returning at
once when no node can start, the vectorised snapshot decision; and the tracker's own state
arrays taken over without a copy when a call updates every row (tracking/tracker.py
``_merged``). None of them may change a number.

Independent references: the same bank updated through a gather (rows out of bank order),
every state and output field bit for bit; ``hold_inits`` with its shortcut off (the loop over
the rounds it skips); the snapshot decision as the loop over the rows it replaced.

Input made independently of the fusion: the channel emulator's first arrivals (seeded) from
five static UAVs to eight static nodes on three floors of the default building.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
from diffpos_services.fusion import step, tracked
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.tracked import TrackBank

from diffpos.alignment import PendingEpoch
from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.tracking.state import TrackerState, TrackStatus, has_position

SC = default_scenario()
B = SC.building
PERIOD = 100_000_000
T0 = 1_800_000_000_000_000_000
ANCHORS = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0],
                    [15.0, -20.0, 1.0], [-25.0, -12.0, 3.0]])
H, F0, FH = B.nominal_node_height_m, B.first_floor_z_m, B.floor_height_m
NODES = np.array([[x, y, F0 + f * FH + H] for x, y, f in
                  [(-10.0, 3.0, 0), (-4.0, 6.0, 0), (2.0, 4.0, 1), (8.0, 7.0, 1),
                   (12.0, 3.0, 1), (-8.0, 5.0, 2), (0.0, 8.0, 2), (6.0, 3.0, 0)]])
IDS = [f"n{i}" for i in range(len(NODES))]
FIELDS = TrackerState.__dataclass_fields__


@functools.cache
def _ranges(epochs: int, seed: int) -> tuple:
    """Per epoch the emulator's first arrivals to every node: (range, sigma, snr, detected)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(epochs):
        fa = first_arrival(emulate_channel(ANCHORS, NODES, building=B, radio=SC.radio),
                           radio=SC.radio, rng=rng)
        out.append((fa.range_m, fa.sigma_m, fa.snr_db, fa.detected))
    return tuple(out)


def _bits(x) -> list:
    """Every array field of a dataclass as (name, dtype, shape, raw bytes): equal = same bits."""
    return [(f.name, None) if (v := getattr(x, f.name)) is None
            else (f.name, v.dtype.str, v.shape, np.ascontiguousarray(v).tobytes())
            for f in dataclasses.fields(x)]


def _call(k: int, rows: list[int], seed: int, drop: tuple = ()) -> tuple:
    """The arguments of ``TrackBank.update`` for epoch ``k`` of nodes ``rows`` (``drop``:
    nodes without ranges this epoch)."""
    rng_m, sig, snr, det = _ranges(8, seed)[k]
    mask = det[rows].copy()
    mask[[rows.index(d) for d in drop]] = False
    n = len(rows)
    return ([IDS[i] for i in rows], np.broadcast_to(ANCHORS, (n, *ANCHORS.shape)).copy(),
            np.where(mask, rng_m[rows], np.nan), np.where(mask, sig[rows], np.nan), mask,
            np.full(n, T0 + k * PERIOD, np.int64), np.where(mask, snr[rows], np.nan))


def _row_state(bank: TrackBank, node: str) -> TrackerState:
    return TrackerState(*(getattr(bank.state, f)[[bank.index[node]]] for f in FIELDS))


@pytest.mark.parametrize("seed", [5, 11])
def test_consecutive_rows_through_a_slice_equal_a_gather(seed):
    """Two banks with the same rows: one updated with its nodes in bank order (consecutive
    rows: read and written through a slice), the other with the same nodes in another order
    (a gather and a scatter). After every epoch (initialisations, tracking, a node without
    ranges, a call of a part of the rows) both banks and both outputs, node by node, are
    the same bits."""
    a, b = TrackBank(B, radio=SC.radio), TrackBank(B, radio=SC.radio)
    everyone = list(range(len(IDS)))
    a.rows_of(IDS), b.rows_of(IDS)
    perm = [5, 1, 0, 7, 6, 3, 2, 4]
    for k, (rows, drop) in enumerate([(everyone, ()), (everyone, ()), (everyone, (3,)),
                                      ([2, 3, 4, 5], ()), (everyone, (7,)), (everyone, ()),
                                      ([0, 1, 2], (1,)), (everyone, ())]):
        assert tracked._as_slice(a.rows_of([IDS[i] for i in rows])) == slice(rows[0],
                                                                             rows[-1] + 1)
        out_a = a.update(*_call(k, rows, seed, drop), radio=SC.radio)
        order = [i for i in perm if i in rows]
        out_b = b.update(*_call(k, order, seed, drop), radio=SC.radio)
        back = [order.index(i) for i in rows]
        for f in dataclasses.fields(out_a):
            va, vb = getattr(out_a, f.name), getattr(out_b, f.name)
            assert np.array_equal(va, vb[back], equal_nan=True), (k, f.name)
            assert va.tobytes() == np.ascontiguousarray(vb[back]).tobytes(), (k, f.name)
        assert _bits(a.state) == _bits(b.state), k
    assert {TrackStatus(s).name for s in a.state.status} & {"TRACKING", "COASTING"}


def test_rows_as_a_slice_only_when_consecutive():
    assert tracked._as_slice(np.array([3, 4, 5])) == slice(3, 6)
    assert tracked._as_slice(np.array([7])) == slice(7, 8)
    for rows in ([3, 5, 4], [3, 4, 6], [3, 5, 4, 6], [5, 4, 3], [2, 2]):
        got = tracked._as_slice(np.array(rows))
        assert isinstance(got, np.ndarray) and got.tolist() == rows
    assert isinstance(tracked._as_slice(np.array([], np.int64)), np.ndarray)


def _hold_reference(bank: TrackBank, epochs, budget, newest, monkeypatch):
    """``hold_inits`` with its shortcut off (every round looked at, as before)."""
    with monkeypatch.context() as m:
        m.setattr(TrackBank, "_may_start", lambda self, ids: True)
        return bank.hold_inits(epochs, budget, newest)


@pytest.mark.parametrize("seed", range(4))
def test_hold_inits_shortcut_changes_nothing(seed, monkeypatch):
    """Random banks (every status, nodes known or new), steps with one or two epochs per
    node: the held / solved split with the shortcut equals the full loop's, and neither adds
    rows but for new nodes."""
    rng = np.random.default_rng(seed)
    n = 12
    ids = [f"m{i}" for i in range(n)]
    for trial in range(20):
        bank = TrackBank(B)
        known = ids[: n - (trial % 3)]  # sometimes a node the bank has never seen
        bank.rows_of(known)
        st = bank.state.status
        st[:] = np.where(rng.random(st.size) < 0.8, int(TrackStatus.TRACKING),
                         rng.integers(0, len(TrackStatus), st.size))
        if trial % 4 == 0:
            st[:] = int(TrackStatus.TRACKING)
        step = [ids[i] for i in rng.permutation(n)[: rng.integers(1, n)]]
        step += [x for x in step if rng.random() < 0.3]  # a second epoch of some nodes
        epochs = [PendingEpoch(x, T0 + i, T0 + i,
                               {f"a{j}": None for j in range(int(rng.integers(0, 6)))})
                  for i, x in enumerate(step)]
        budget, newest = int(rng.integers(0, 4)), bool(rng.random() < 0.5)
        ref_bank = TrackBank(B)
        ref_bank.rows_of(known)
        ref_bank.state.status[:] = st
        want = _hold_reference(ref_bank, epochs, budget, newest, monkeypatch)
        got = bank.hold_inits(epochs, budget, newest)
        assert [[id(e) for e in part] for part in got] == [[id(e) for e in part]
                                                          for part in want]
        if set(step) <= set(known):
            assert bank.index == {x: i for i, x in enumerate(known)}


def _reference_due(bank, ids, t_ref, cfg, limit, behind, starting):
    """The snapshot decision as a loop over the rows (``_snapshot_due`` before it was
    vectorised), without its side effects: (due, the times it records)."""
    status = bank.status_of(ids)
    placed = ~np.isin(status, (int(TrackStatus.UNINITIALISED), int(TrackStatus.LOST)))
    sure = (status == int(TrackStatus.TRACKING)) & bank.confident_of(ids)
    period = round(cfg.snapshot_period_s * 1e9)
    long_period = (float("inf") if cfg.confident_snapshot_period_s is None
                   else max(period, round(cfg.confident_snapshot_period_s * 1e9)))
    due = np.ones(len(ids), bool)
    lasts = [bank.snapshot_ns.get(n) for n in ids]
    for i, last in enumerate(lasts):
        if placed[i] and last is not None and 0 <= t_ref[i] - last < (
                long_period if sure[i] else period):
            due[i] = False
    if behind:
        due &= ~placed
    start = np.zeros(len(ids), bool) if starting is None or cfg.snapshot_at_start else starting
    due &= ~start
    todo = list(np.flatnonzero(due))
    if len(todo) > limit:
        todo.sort(key=lambda i: -(2**63) if lasts[i] is None else lasts[i])
        due[todo[int(limit):]] = False
    recorded = {ids[i]: int(t_ref[i]) for i in [*np.flatnonzero(due), *np.flatnonzero(start)]}
    return due, recorded


@pytest.mark.parametrize("seed", range(6))
def test_the_snapshot_decision_equals_the_loop_over_the_rows(seed):
    """``_snapshot_due`` (vectorised) against the loop it replaced, on random banks: every
    status, confident or not, snapshots never / too old / young / in the future, both
    confident periods (none: never again), behind or not, limited or not, tracks starting."""
    rng = np.random.default_rng(seed)
    n = 40
    ids = [f"m{i}" for i in range(n)]
    bank = TrackBank(B)
    bank.rows_of(ids)
    st = bank.state
    st.status[:] = rng.integers(0, len(TrackStatus), n)
    st.log_prob[:] = np.log(np.maximum(rng.dirichlet(np.full(st.log_prob.shape[1], 0.05), n),
                                       1e-300))
    st.nis[:] = rng.uniform(0.0, 8.0, n)
    st.status[:8], st.nis[:8] = int(TrackStatus.TRACKING), 1.0  # confident ones
    st.log_prob[:8] = np.log(np.where(np.eye(st.log_prob.shape[1])[0], 0.999, 1e-5))
    t_ref = 10**18 + rng.integers(0, 10**8, n)
    for i, nid in enumerate(ids):
        kind = rng.integers(4)
        if kind:
            bank.snapshot_ns[nid] = int(t_ref[i] - [0, 5 * 10**8, 3 * 10**9, -10**8][kind]
                                        - rng.integers(0, 2 * 10**9) * (kind == 2))
    before = dict(bank.snapshot_ns)
    assert (bank.confident_of(ids) & (st.status == int(TrackStatus.TRACKING))).any()
    for confident_s in (None, 2.0):
        cfg = FusionConfig.from_scenario(SC, site="b", epoch_period_s=0.1, method="mnls",
                                         confident_snapshot_period_s=confident_s)
        for behind in (False, True):
            for limit in (float("inf"), 3):
                starting = rng.random(n) < 0.2 if rng.random() < 0.7 else None
                bank.snapshot_ns = dict(before)
                want, recorded = _reference_due(bank, ids, t_ref, cfg, limit, behind,
                                                starting)
                epochs = [PendingEpoch(nid, 0, 0) for nid in ids]
                got = tracked._snapshot_due(bank, epochs, t_ref, cfg, limit, behind, starting)
                assert got.tolist() == want.tolist(), (confident_s, behind, limit)
                assert bank.snapshot_ns == {**before, **recorded}
                assert 0 < want.sum() < n  # both kinds of row


def test_membership_by_comparisons_equals_isin():
    """``has_position`` and the gated count's reason test (two comparisons instead of np.isin,
    whose setup costs ~20 us per call) against np.isin, on every status / reason code and
    on random arrays of both dtypes they see."""
    rng = np.random.default_rng(3)
    st = np.concatenate([np.arange(len(TrackStatus)), rng.integers(0, len(TrackStatus), 500)]
                        ).astype(np.int8)
    no_position = (int(TrackStatus.UNINITIALISED), int(TrackStatus.LOST))
    assert has_position(st).tolist() == np.isin(st, no_position, invert=True).tolist()
    assert has_position(st[:0]).shape == (0,)
    reason = rng.integers(0, 12, (40, 9)).astype(np.int64)
    shape = reason.shape
    flags = {k: rng.random(shape) < 0.9 for k in ("reported", "detected", "have_state")}
    batch = step.Batch(names=["a"] * shape[1], t=None, rng=None, sig=None, pub_wall=None,
                       apos=None, asig=None, use=None, t_ref=None, dt_s=None, snr=None,
                       **flags)
    res = step.Results(*shape)
    res.used, res.reason = rng.random(shape) < 0.4, reason
    want = int((batch.reported & batch.detected & batch.have_state & ~res.used
                & np.isin(reason, step._GATE_CODES)).sum())
    assert step.gated_count(batch, res) == want > 0
