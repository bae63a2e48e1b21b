"""count_releases (fusion/ingest.py) from the epoch book's columns against the rule written per
released epoch over its ``ranges`` (as before issue 37 item 2), on random streams."""

from __future__ import annotations

import collections
import random

import pytest
from diffpos_services.fusion.ingest import count_releases

from diffpos.alignment import AlignmentConfig, EpochBook, RangeEntry


def _ref(book, released, live, rel):
    align = book.config
    for pe in released:
        missing = live - pe.ranges.keys()
        if not missing:
            rel["complete"] += 1
            continue
        end = (pe.epoch + 1) * align.epoch_period_ns + align.clock_tolerance_ns
        if len(pe.ranges) >= align.min_reports and all(
                book.latest_t_ns.get(a, end - 1) >= end for a in missing):
            rel["passed"] += 1
        elif pe.epoch <= book.closed_upto:
            rel["watermark"] += 1
        else:
            rel["wall_fallback"] += 1


@pytest.mark.parametrize("seed", range(6))
def test_release_reasons_match_the_per_epoch_rule(seed):
    rnd = random.Random(seed)
    cfg = AlignmentConfig(epoch_period_ns=100, clock_tolerance_ns=5, deadline_ns=150,
                          max_lag_ns=600, min_reports=rnd.choice([2, 3]), max_future_ns=400)
    book = EpochBook(cfg)
    anchors = [f"a{i}" for i in range(5)]
    nodes = [f"n{i}" for i in range(6)]
    clock = {a: rnd.randint(0, 50) for a in anchors}
    got, want = collections.Counter(), collections.Counter()
    wall = 0
    for _ in range(400):
        wall += 700 if rnd.random() < 0.02 else rnd.choice([1, 5, 20])
        a = rnd.choice(anchors)
        clock[a] += rnd.randint(0, 60)
        ids = rnd.sample(nodes, rnd.randint(len(nodes) - 2, len(nodes)))
        book.add_many(a, clock[a], [(n, RangeEntry(clock[a], 1.0, 0.1, 10.0, wall, wall))
                                    for n in ids])
        live = frozenset(anchors if rnd.random() < 0.8 else rnd.sample(anchors, 4))
        out = book.ready(live, wall)
        count_releases(book, out, live, got)
        _ref(book, out, live, want)
    assert got == want and len(want) >= 3, want
