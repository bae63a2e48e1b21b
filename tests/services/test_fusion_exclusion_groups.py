"""The fusion's per-row anchor lists (services/diffpos_services/fusion/step.py,
``exclusion_groups``): rows grouped by identical (used anchors, exclusion reasons) must give
every row exactly the lists it gets when it is alone in a batch (brute force, row by row),
groups numbered in order of first appearance with their first row as representative, and
distinct groups distinct lists. Random batches with many repeated rows, a few unique ones,
lost anchors and gating reasons; seeds fixed."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from diffpos_services.fusion.step import exclusion_groups

from diffpos.estimators.result import ExclusionReason

REASONS = [0, *(int(r) for r in ExclusionReason)]


def _batch(rng, b: int, m: int):
    names = [f"a{j}" for j in range(m)]
    base = rng.random((4, m)) < 0.85  # a few typical patterns, repeated
    pick = rng.integers(0, 4, b)
    reported = base[pick] | (rng.random((b, m)) < 0.02)
    detected = reported & (rng.random((b, m)) < 0.95)
    have_state = rng.random((b, m)) < 0.97
    used = detected & have_state & (rng.random((b, m)) < 0.9)
    reason = np.where(~used & detected & have_state, rng.choice(REASONS, (b, m)), 0)
    batch = SimpleNamespace(names=names, reported=reported, detected=detected,
                            have_state=have_state)
    return batch, SimpleNamespace(used=used, reason=reason), {names[0], names[-1]}


def _row(batch, res, lost, i):
    one = SimpleNamespace(names=batch.names, reported=batch.reported[i:i + 1],
                          detected=batch.detected[i:i + 1], have_state=batch.have_state[i:i + 1])
    g, shared = exclusion_groups(one, SimpleNamespace(used=res.used[i:i + 1],
                                                      reason=res.reason[i:i + 1]), lost)
    assert g == [0] and len(shared) == 1
    return shared[0]


@pytest.mark.parametrize("seed,b,m", [(0, 60, 8), (1, 200, 16), (2, 5, 3), (3, 1, 1),
                                      (4, 0, 4)])
def test_groups_give_every_row_its_own_lists(seed, b, m):
    rng = np.random.default_rng(seed)
    batch, res, lost = _batch(rng, b, m)
    group_l, shared = exclusion_groups(batch, res, lost)
    assert len(group_l) == b
    firsts = {}
    for i, g in enumerate(group_l):
        firsts.setdefault(g, i)
        assert shared[g] == _row(batch, res, lost, i)
    # numbered by first appearance, each group's representative its first row
    assert list(firsts) == list(range(len(shared)))
    assert all(shared[g] == _row(batch, res, lost, i) for g, i in firsts.items())
    keys = [(tuple(s[0]), tuple(s[1]), tuple(s[2]), s[3]) for s in shared]
    assert len(set(keys)) == len(keys)  # distinct groups, distinct lists
    if b > 20:
        assert len(shared) < b  # the repeated rows did share their lists
