"""The compiled learned-link bookkeeping (:mod:`diffpos.tracking.evidence_nb`) against its numpy
references in :mod:`diffpos.tracking.evidence`: the same outputs bit for bit, on random inputs
that exercise every branch (links found within the tolerance, free links, the least recently
seen one restarted, columns absent, more columns than links; counts of every size)."""

from __future__ import annotations

import numpy as np
import pytest

from diffpos.tracking.evidence import (
    LINK_FIELDS,
    _doubt_dist_numpy,
    _learn_counts_numpy,
    _link_eps,
    _link_eps_numpy,
    _match_links_numpy,
    learn,
    match_links,
    reset_links,
)
from diffpos.tracking.evidence_nb import doubt_dist_kernel, learn_counts_kernel
from diffpos.tracking.links import Links
from diffpos.tracking.state import TrackerConfig


def _tables(rng, n: int, m: int, nl: int):
    """Learned tables where some links are free, some near this update's anchors (within and
    beyond the 1 m tolerance), some far; anchors on a few shared positions (ties)."""
    anchors = rng.choice([-10.0, 0.0, 5.0, 20.0], size=(n, m, 3))
    table = rng.uniform(-20, 20, (n, nl, 3))
    for i in range(n):
        k = rng.integers(0, min(m, nl) + 1)
        src = rng.choice(m, k, replace=False)
        dst = rng.choice(nl, k, replace=False)
        table[i, dst] = anchors[i, src] + rng.normal(0, rng.choice([0.0, 0.3, 2.0]), (k, 3))
    table[rng.random((n, nl)) < 0.3] = np.nan
    seen = rng.integers(0, 5, (n, nl)).astype(np.int64)  # ties in the age
    mask = rng.random((n, m)) < 0.8
    return table, seen, anchors, mask, rng.integers(5, 10, n).astype(np.int64)


@pytest.mark.parametrize("m,nl", [(8, 16), (8, 4), (3, 3), (12, 5)])
def test_match_links_kernel_is_the_numpy_reference(m, nl):
    rng = np.random.default_rng(m * 100 + nl)
    n_reset = n_hit = 0
    for _ in range(40):
        args = _tables(rng, 9, m, nl)
        table, seen = args[0].copy(), args[1].copy()
        got = match_links(*args, 1.0)
        want = _match_links_numpy(*args, 1.0)
        for g, w in zip(got, want, strict=True):
            assert g.dtype == w.dtype and g.shape == w.shape
            np.testing.assert_array_equal(g, w)
        assert np.array_equal(args[0], table, equal_nan=True) and np.array_equal(args[1], seen)
        n_reset += int(want[3].sum())
        n_hit += int((want[0] >= 0).sum() - want[3].sum())
    assert n_reset > 50 and n_hit > 50  # both branches exercised


def test_learned_eps_and_doubt_kernels_are_the_numpy_references():
    rng = np.random.default_rng(7)
    cfg = TrackerConfig()
    n, h, m, nl = 11, 10, 8, 16
    out = rng.uniform(0, 8, (n, h, nl)) * (rng.random((n, h, nl)) < 0.5)
    n_all = out + rng.uniform(0, 12, (n, h, nl))
    col = np.where(rng.random((n, m)) < 0.8, rng.integers(0, nl, (n, m)), -1)
    for c in (cfg, TrackerConfig(link_outlier_max=0.01)):
        got, want = _link_eps(out, n_all, col, c), _link_eps_numpy(out, n_all, col, c)
        np.testing.assert_array_equal(got, want)
    q = rng.uniform(0, 1, (n, nl)) * (rng.random((n, nl)) < 0.4)
    dist = np.empty((n, nl + 1))
    doubt_dist_kernel(q, dist)
    np.testing.assert_array_equal(dist, _doubt_dist_numpy(q))


def test_learn_counts_kernel_is_the_numpy_reference():
    rng = np.random.default_rng(3)
    n, h, m, nl = 7, 10, 8, 16
    base = {k: rng.uniform(0, 5, (n, h, nl)) for k in ("link_out", "link_all", "link_ev")}
    mask = rng.random((n, m)) < 0.8
    run = rng.random((n, h)) < 0.6
    col = np.stack([np.where(rng.random(m) < 0.9, rng.choice(nl, m, replace=False), -1)
                    for _ in range(n)])  # distinct links per node
    slot = rng.integers(-1, 18, (n, h, m))
    ev = rng.normal(0, 3, (n, h, m))
    a = {k: v.copy() for k, v in base.items()}
    b = {k: v.copy() for k, v in base.items()}
    learn_counts_kernel(mask, run, col, slot, ev, 0.95, a["link_out"], a["link_all"],
                        a["link_ev"])
    _learn_counts_numpy(b, mask, run, col, slot, ev, 0.95)
    for k in base:
        np.testing.assert_array_equal(a[k], b[k])
        assert not np.array_equal(a[k], base[k])
    # through learn(): the inputs untouched, the new arrays the reference's
    lk = {k: rng.uniform(0, 3, (n, h, nl)) for k in LINK_FIELDS}
    lk["link_t_ns"] = np.zeros((n, h, nl), np.int64)
    keep = {k: v.copy() for k, v in lk.items()}
    links = Links.from_arrays(rng.uniform(-5, 5, (n, m, 3)), rng.uniform(5, 20, (n, m)),
                              np.full((n, m), 0.1), mask, 0.03)
    got = learn(lk, col, run, None, None, slot, links, np.zeros(n, np.int64), TrackerConfig(),
                ev)
    want = {k: v.copy() for k, v in keep.items()}
    _learn_counts_numpy(want, links.mask[:, 0], run, col, slot, ev, 0.95)
    for k in LINK_FIELDS:
        np.testing.assert_array_equal(lk[k], keep[k])
        np.testing.assert_array_equal(got[k], want[k])


def test_reset_links_without_a_reset_changes_nothing_and_with_one_clears_it():
    rng = np.random.default_rng(1)
    lk = {k: rng.uniform(1, 2, (3, 4, 5)) for k in LINK_FIELDS}
    keep = {k: v.copy() for k, v in lk.items()}
    reset_links(lk, np.arange(3), np.zeros((3, 5), bool))
    for k in LINK_FIELDS:
        np.testing.assert_array_equal(lk[k], keep[k])
    sel = np.zeros((2, 5), bool)
    sel[1, 2] = True
    reset_links(lk, np.array([0, 2]), sel)
    assert lk["link_out"][2, :, 2].tolist() == [0.0] * 4 and np.isnan(lk["link_bias"][2, :, 2]).all()
    assert np.count_nonzero(lk["link_out"] != keep["link_out"]) == 4
