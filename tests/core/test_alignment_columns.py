"""The epoch book's columns (diffpos/alignment.py, issue 37 item 2): ``add_columns`` keeps what
``add_many`` keeps, and ``epoch_columns`` / ``epoch_reports`` / ``reported_anchors`` give what
a per-range walk over each released epoch's ``ranges`` gives (the former ``gather``), on random
streams with undetected, late, replaced and stray ranges."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from diffpos.alignment import (
    AlignmentConfig,
    EpochBook,
    PendingEpoch,
    RangeEntry,
    epoch_columns,
    epoch_reports,
    reported_anchors,
)


def _ref_columns(epochs, ids):
    """Per range, from each epoch's ``ranges`` mapping (as the per-range gather did)."""
    col = {a: j for j, a in enumerate(ids)}
    b, m = len(epochs), len(ids)
    t, pub = np.zeros((b, m), np.int64), np.zeros((b, m), np.int64)
    rng, sig, snr = np.full((b, m), np.nan), np.ones((b, m)), np.full((b, m), np.nan)
    rep = np.zeros((b, m), bool)
    for i, pe in enumerate(epochs):
        for a, x in pe.ranges.items():
            j = col[a]
            rep[i, j], t[i, j], pub[i, j] = True, x.t_ns, x.t_pub_wall_ns
            if x.range_m is not None:
                rng[i, j], sig[i, j], snr[i, j] = x.range_m, x.sigma_m, x.snr_db
    return t, rng, sig, snr, rep, pub, np.array([len(pe.ranges) for pe in epochs])


def _stream(seed: int):
    """(anchor, t, [(node, entry)]) batches and ready() calls of a random run."""
    rnd = random.Random(seed)
    anchors = [f"a{i}" for i in range(rnd.randint(3, 6))]
    nodes = [f"n{i}" for i in range(rnd.randint(2, 8))]
    clock = {a: rnd.randint(0, 50) for a in anchors}
    wall = 10_000
    for _ in range(300):
        wall += rnd.choice([1, 5, 20, 50, 400])
        a = rnd.choice(anchors)
        clock[a] += rnd.randint(0, 60)
        t = clock[a] - (rnd.randint(100, 300) if rnd.random() < 0.1 else 0)
        if rnd.random() < 0.03:
            t += 3_000  # a stray
        ids = rnd.sample(nodes, rnd.randint(0, len(nodes)))
        entries = [(n, RangeEntry(t, None if rnd.random() < 0.2 else rnd.random() * 30,
                                  0.1 + rnd.random(), -math.inf if rnd.random() < 0.1
                                  else rnd.random() * 40, wall - 3, wall)) for n in ids]
        yield a, t, entries, wall, frozenset(anchors) if rnd.random() < 0.9 else frozenset(
            anchors[:-1]), rnd.random() < 0.5


@pytest.mark.parametrize("seed", range(8))
def test_columns_match_the_per_range_walk(seed):
    cfg = AlignmentConfig(epoch_period_ns=100, clock_tolerance_ns=5, deadline_ns=150,
                          max_lag_ns=600, min_reports=2, max_future_ns=400)
    cols, many = EpochBook(cfg), EpochBook(cfg)
    released = 0
    for a, t, entries, wall, live, step in _stream(seed):
        late = many.add_many(a, t, entries)
        r = np.array([math.nan if x.range_m is None else x.range_m for _, x in entries])
        got = cols.add_columns(a, t, [n for n, _ in entries], r,
                               [x.sigma_m for _, x in entries], [x.snr_db for _, x in entries],
                               t, [x.t_pub_wall_ns for _, x in entries], wall)
        assert got == late
        if not step:
            continue
        out, ref = cols.ready(live, wall), many.ready(live, wall)
        assert [(p.node_id, p.epoch) for p in out] == [(p.node_id, p.epoch) for p in ref]
        assert [dict(p.ranges) for p in out] == [dict(p.ranges) for p in ref]
        released += len(out)
        ids = sorted(reported_anchors(out) | set(live))
        assert reported_anchors(out) == {a for p in out for a in p.ranges}
        # a dict-backed copy of each epoch: the per-range path of the same functions
        loose = [PendingEpoch(p.node_id, p.epoch, p.first_rx_wall_ns, dict(p.ranges))
                 for p in out]
        want = _ref_columns(loose, ids)
        for got_c in (epoch_columns(out, ids), epoch_columns(loose, ids)):
            t_, rng, sig, snr, rep, det, pub, count = got_c
            for g, w in zip((t_, rng, sig, snr, rep, pub, count), want, strict=True):
                np.testing.assert_array_equal(g, w)
            np.testing.assert_array_equal(det, ~np.isnan(want[1]))
        live_ids = sorted(live)
        rep_c, count_c = epoch_reports(out, live_ids)
        np.testing.assert_array_equal(rep_c, _ref_columns(loose, ids)[4][
            :, [ids.index(x) for x in live_ids]])
        np.testing.assert_array_equal(count_c, want[6])
    assert {k: dict(v.ranges) for k, v in cols.pending.items()} == {
        k: dict(v.ranges) for k, v in many.pending.items()}
    assert (cols.late, cols.replaced, cols.strays) == (many.late, many.replaced, many.strays)
    assert released > 0


def test_add_columns_scalars_late_and_replaced():
    cfg = AlignmentConfig(epoch_period_ns=100, min_reports=1)
    book = EpochBook(cfg)
    assert book.add_columns("a", 110, ["n1", "n2"], [1.0, math.nan], [0.1, 1.0],
                            [20.0, -math.inf], 110, 105, 111) == 0
    assert book.add_columns("a", 120, ["n2"], [2.0], 0.2, 10.0, 120, 115, 121) == 0
    assert book.replaced == 1
    r1, r2 = (book.pending[(n, 1)].ranges for n in ("n1", "n2"))
    assert dict(r1) == {"a": RangeEntry(110, 1.0, 0.1, 20.0, 105, 111)}
    assert dict(r2) == {"a": RangeEntry(120, 2.0, 0.2, 10.0, 115, 121)}
    assert len(r2) == 1 and "a" in r2 and "b" not in r2
    out = book.ready(frozenset({"a"}), 200)
    assert [p.node_id for p in out] == ["n1", "n2"]
    # n1's epoch 1 is solved: late; n3 is new in epoch 1: kept
    assert book.add_columns("b", 150, ["n1", "n3"], [3.0, math.nan], [0.1, 1.0],
                            [20.0, -math.inf], 150, 150, 151) == 1
    assert book.late_by_anchor["b"] == 1
    assert dict(book.pending[("n3", 1)].ranges) == {
        "b": RangeEntry(150, None, 1.0, -math.inf, 150, 151)}
    assert book.pending[("n3", 1)].first_rx_wall_ns == 151
