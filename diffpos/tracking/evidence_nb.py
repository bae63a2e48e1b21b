"""Compiled bookkeeping of the tracker's learned links (:mod:`diffpos.tracking.evidence`): the
matching of an update's anchor columns to the learned links, the outlier weights at every
column's link, the counts' update and the Poisson-binomial distribution of the doubt. Data
movement, comparisons and the same sums and products as the numpy references in
:mod:`diffpos.tracking.evidence` (``_match_links_numpy``, ``_eps_numpy``,
``_learn_counts_numpy``, ``_doubt_dist_numpy``), in the same order, so the results are
numpy's bit for bit (tested); what needs numpy's order of summation (the distances) or its
transcendental functions (``log``, ``log1p``) stays numpy's. Replaced ~15 numpy calls per
anchor column (matching), per learned link (doubt) and the gathers of the weights: about a
quarter of a one-node tracker call.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["doubt_dist_kernel", "eps_kernel", "learn_counts_kernel", "match_links_kernel",
           "warm_evidence"]

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}
_I64_MAX = np.iinfo(np.int64).max


@njit(**_OPTS)
def match_links_kernel(d, mask, anchors, tol_m, t_ns, tab, seen, col, reset):
    """``d`` (n, M, L): every column's anchor's distance to every learned link's position at
    the call (NaN: a free link); ``mask`` (n, M); ``anchors`` (n, M, 3); ``t_ns`` (n,).
    Updates ``tab`` (n, L, 3) and ``seen`` (n, L) in place, writes ``col`` (n, M) and
    ``reset`` (n, L) (:func:`diffpos.tracking.evidence.match_links`'s rule, column by column:
    a link taken by an earlier column keeps its distance out of the later ones, the others'
    positions do not change meanwhile, so ``d`` holds for them)."""
    n, m, nl = d.shape
    taken = np.zeros(nl, np.bool_)
    for i in range(n):
        taken[:] = False
        for k in range(nl):
            reset[i, k] = False
        for j in range(m):
            col[i, j] = -1
            near, dmin = 0, np.inf
            for k in range(nl):
                v = d[i, j, k]
                if math.isfinite(v) and not taken[k] and v < dmin:
                    near, dmin = k, v
            hit = mask[i, j] and dmin <= tol_m
            alloc = -1
            for k in range(nl):
                if math.isnan(tab[i, k, 0]) and not taken[k]:
                    alloc = k
                    break
            if alloc < 0:
                amin = _I64_MAX
                alloc = 0
                for k in range(nl):
                    a = _I64_MAX if taken[k] else seen[i, k]
                    if a < amin:
                        alloc, amin = k, a
            new = mask[i, j] and not hit and not taken[alloc]
            if not (hit or new):
                continue
            li = near if hit else alloc
            col[i, j] = li
            if new:
                reset[i, li] = True
            taken[li] = True
            for c in range(3):
                tab[i, li, c] = anchors[i, j, c]
            seen[i, li] = t_ns[i]


@njit(**_OPTS)
def _finite(v):
    """``np.nan_to_num`` of a float64."""
    if math.isnan(v):
        return 0.0
    if v == np.inf:
        return 1.7976931348623157e308
    if v == -np.inf:
        return -1.7976931348623157e308
    return v


@njit(**_OPTS)
def eps_kernel(out, n_all, col, e0, s, hi, eps):
    """Every column's learned outlier weight (n, H, M) into ``eps``: the Beta-Bernoulli mean of
    the counts ``out``, ``n_all`` (n, H, L) at the column's link ``col`` (n, M) (-1: none, no
    counts), clipped to ``[e0, hi]``."""
    n, h_n, m = eps.shape
    e0s = e0 * s
    for i in range(n):
        for h in range(h_n):
            for j in range(m):
                c = col[i, j]
                o = _finite(out[i, h, c]) if c >= 0 else 0.0
                a = _finite(n_all[i, h, c]) if c >= 0 else 0.0
                e = (e0s + o) / (s + a)
                eps[i, h, j] = min(max(e, e0), hi)


@njit(**_OPTS)
def learn_counts_kernel(mask, run, col, slot, ev_link, f, out, n_all, ev):
    """The forgotten counts (in place, (n, H, L)) of every present link (``mask`` (n, M), a
    hypothesis that ``run`` (n, H), a column with a link ``col`` (n, M)): ``out`` += outlier
    (``slot`` (n, H, M) < 0), ``n_all`` += 1, ``ev`` += ``ev_link`` (n, H, M), each after
    the factor ``f`` (a node's columns hold distinct links)."""
    n, h_n, m = slot.shape
    for i in range(n):
        for h in range(h_n):
            if not run[i, h]:
                continue
            for j in range(m):
                c = col[i, j]
                if not mask[i, j] or c < 0:
                    continue
                out[i, h, c] = f * out[i, h, c] + (1.0 if slot[i, h, j] < 0 else 0.0)
                n_all[i, h, c] = f * n_all[i, h, c] + 1.0
                ev[i, h, c] = f * ev[i, h, c] + ev_link[i, h, j]


@njit(**_OPTS)
def doubt_dist_kernel(q, dist):
    """The distribution (n, L + 1) of the number of links out of the model, independent links
    with the probabilities ``q`` (n, L), into ``dist`` (the links added one by one)."""
    n, nl = q.shape
    for i in range(n):
        dist[i, 0] = 1.0
        for k in range(1, nl + 1):
            dist[i, k] = 0.0
        for j in range(nl):
            qj = q[i, j]
            pj = 1.0 - qj
            for k in range(nl, 0, -1):
                dist[i, k] = dist[i, k] * pj + dist[i, k - 1] * qj
            dist[i, 0] *= pj


def warm_evidence() -> None:
    """Compile (or load from numba's cache) the kernels on tiny inputs of the tracker's types
    (called by :func:`diffpos.tracking.tracker.warm_tracking`)."""
    n, h, m, nl = 1, 2, 2, 3
    tab = np.full((n, nl, 3), np.nan)
    seen = np.zeros((n, nl), np.int64)
    col, reset = np.empty((n, m), np.int64), np.empty((n, nl), np.bool_)
    mask = np.ones((n, m), np.bool_)
    match_links_kernel(np.full((n, m, nl), np.nan), mask, np.zeros((n, m, 3)), 1.0,
                       np.zeros(n, np.int64), tab, seen, col, reset)
    cnt = np.zeros((n, h, nl))
    eps_kernel(cnt, cnt, col, 0.02, 10.0, 0.5, np.empty((n, h, m)))
    learn_counts_kernel(mask, np.ones((n, h), np.bool_), col, np.zeros((n, h, m), np.int64),
                        np.zeros((n, h, m)), 0.95, cnt, cnt.copy(), cnt.copy())
    doubt_dist_kernel(np.zeros((n, nl)), np.empty((n, nl + 1)))
