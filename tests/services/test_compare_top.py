"""Replay's comparison keeps the 5 largest live/replayed position differences as examples:
the heap skips a pair no larger than its smallest (issue 37 item 2). Checked against every
pair sorted (largest first, the earlier pair first among equal distances), with many ties."""

from __future__ import annotations

import math
import random
from types import SimpleNamespace

from diffpos_services.replay.report_stream import Comparison


def _est(node, epoch, pos):
    return SimpleNamespace(node_id=node, epoch=epoch, status="TRACKING", position_m=pos,
                           peb_m=0.1)


def test_examples_are_the_five_largest_differences_earliest_first_among_ties():
    rng = random.Random(7)
    c = Comparison(10**12)
    pairs = []  # (dist, order, node, epoch)
    for k in range(3000):
        node, epoch = f"n{k % 37:02d}", k // 37
        live = (rng.randint(-20, 20) / 4, rng.randint(-20, 20) / 4, rng.randint(0, 36) / 4)
        step = rng.choice([0.0, 0.5, 1.0, 3.0, rng.uniform(0, 3)])  # many equal distances
        rep = (live[0] + step, live[1], live[2])
        c.add(0, _est(node, epoch, live), 1000 + k)
        c.add(1, _est(node, epoch, rep), 2000 + k)
        d = math.dist(live, rep)
        if live != rep:
            pairs.append((d, len(pairs), node, epoch))
    want = sorted(pairs, key=lambda p: (-p[0], p[1]))[:5]
    got = c.result()["examples"]
    assert [(g["diff_m"], g["node"], g["epoch"]) for g in got] == \
        [(d, n, e) for d, _, n, e in want]
    assert sum(1 for p in pairs if p[0] == want[-1][0]) > 5  # the ties were exercised
