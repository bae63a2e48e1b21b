"""EpochBook's release and ingest (diffpos/alignment.py) against a reference written
per range and per pending epoch: the rule as the module docstring states it (a closure
per epoch for the timeouts, the solved test for every range, every not-released epoch
blocks its node). Random streams with out-of-order, late, duplicate and future-stamped
ranges, anchors that come and go, quiet periods and both release rules: the optimised
book must release the same epochs in the same order and keep the same state."""

from __future__ import annotations

import random

import pytest

from diffpos.alignment import _NEVER, AlignmentConfig, EpochBook, PendingEpoch, RangeEntry


def _ref_add_many(book: EpochBook, anchor_id: str, t_ns: int, entries) -> int:
    """add_many as the rule states it: late when closed or at/below the node's solved epoch."""
    e = int(t_ns // book.config.epoch_period_ns)
    book.note_anchor_time(anchor_id, t_ns)
    late = 0
    for node_id, entry in entries:
        if e <= book.closed_upto or e <= book.solved_upto.get(node_id, _NEVER):
            late += 1
            continue
        pe = book.pending.get((node_id, e))
        if pe is None:
            pe = book.pending[(node_id, e)] = PendingEpoch(node_id, e, entry.rx_wall_ns)
        elif anchor_id in pe.ranges:
            book.replaced += 1
        pe.ranges[anchor_id] = entry
    if entries:
        book._adds += 1
        book._note_rx(entries[-1][1].rx_wall_ns)
    if late:
        book.late += late
        book.late_by_anchor[anchor_id] += late
    return late


def _ref_timed_out(book: EpochBook, now: int):
    cfg = book.config
    if cfg.release == "wall":
        return lambda pe: now - pe.first_rx_wall_ns >= cfg.deadline_ns
    if book.last_rx_wall_ns is not None and now - book.last_rx_wall_ns >= book.max_lag_ns:
        return lambda pe: True
    return lambda pe: pe.epoch <= book.closed_upto or now - pe.first_rx_wall_ns >= book.max_lag_ns


def _ref_ready(book: EpochBook, live: frozenset[str], now: int) -> list[PendingEpoch]:
    """ready() without the idle shortcut (it only skips calls that release nothing)."""
    cfg = book.config
    out, blocked = [], set()
    timed_out = _ref_timed_out(book, now)
    t_c = book.consensus_t_ns(live)
    horizon = None if t_c is None else (t_c + cfg.max_future_ns) // cfg.epoch_period_ns
    for key in sorted(book.pending, key=lambda k: (k[1], k[0])):
        pe = book.pending[key]
        if pe.node_id in blocked:
            continue
        done = timed_out(pe)
        if not done and len(pe.ranges) >= cfg.min_reports:
            end = (pe.epoch + 1) * cfg.epoch_period_ns + cfg.clock_tolerance_ns
            done = all(a in pe.ranges for a in live if book.latest_t_ns.get(a, _NEVER) < end)
        if done:
            out.append(pe)
            del book.pending[key]
            if horizon is not None and pe.epoch > horizon:
                book.strays += 1
                continue
            book.solved_upto[pe.node_id] = max(pe.epoch, book.solved_upto.get(pe.node_id, _NEVER))
        else:
            blocked.add(pe.node_id)
    return out


def _state(book: EpochBook):
    return (sorted((k, sorted(pe.ranges.items()), pe.first_rx_wall_ns)
                   for k, pe in book.pending.items()),
            dict(book.solved_upto), book.late, dict(book.late_by_anchor), book.replaced,
            book.strays, book.closed_upto, book.watermark_ns)


@pytest.mark.parametrize("release", ["measurement", "wall"])
@pytest.mark.parametrize("seed", range(6))
def test_release_and_ingest_match_the_per_range_reference(release, seed):
    rnd = random.Random(seed)
    period = 100
    cfg = AlignmentConfig(epoch_period_ns=period, clock_tolerance_ns=rnd.choice([0, 5]),
                          deadline_ns=rnd.choice([150, 300]), max_lag_ns=rnd.choice([None, 600]),
                          min_reports=rnd.choice([2, 3]), max_future_ns=400, release=release)
    new, ref = EpochBook(cfg), EpochBook(cfg)
    anchors = [f"a{i}" for i in range(rnd.randint(3, 6))]
    nodes = [f"n{i}" for i in range(rnd.randint(2, 6))]
    live = set(anchors)
    clock = {a: rnd.randint(0, 50) for a in anchors}
    wall = 10_000
    released = 0
    for _ in range(400):
        wall += rnd.choice([1, 5, 20, 20, 50, 2_000 if rnd.random() < 0.02 else 30])
        a = rnd.choice(anchors)
        r = rnd.random()
        if r < 0.05:  # an anchor vanishes or comes back
            live ^= {a}
        elif r < 0.12:  # a state report only (moves the anchor's time)
            clock[a] += rnd.randint(0, 80)
            new.note_anchor_time(a, clock[a])
            ref.note_anchor_time(a, clock[a])
        else:
            clock[a] += rnd.randint(0, 60)
            t = clock[a] - (rnd.randint(100, 400) if rnd.random() < 0.1 else 0)  # old stamp
            if rnd.random() < 0.03:
                t += 3_000  # future stamp (a stray)
            ids = rnd.sample(nodes, rnd.randint(0, len(nodes)))
            if ids and rnd.random() < 0.1:
                ids.append(ids[0])  # a duplicate range in one batch
            entries = [(n, RangeEntry(t, rnd.random() * 30, 0.1, 10.0, wall, wall)) for n in ids]
            assert new.add_many(a, t, entries) == _ref_add_many(ref, a, t, entries)
        if rnd.random() < 0.5:
            lv = frozenset(live)
            got, want = new.ready(lv, wall), _ref_ready(ref, lv, wall)
            assert [(p.node_id, p.epoch) for p in got] == [(p.node_id, p.epoch) for p in want]
            released += len(got)
        assert _state(new) == _state(ref)
    assert released > 0
