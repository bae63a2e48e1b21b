"""The grid search of the tracker's snapshot initialisation, compiled
(:func:`diffpos.tracking.initialisation.grid_starts`): :func:`grid_cost_kernel` ranks every grid cell of
every listed floor per node by the robust max-mixture range cost, visiting the cells by a lower
bound of their cost and abandoning those that cannot be among the ``keep`` cheapest.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from diffpos._kernels.npsum_nb import pairwise_sum as _pairwise_sum
from diffpos.paths.model_nb import edge_axis, row_planes, slot_path

__all__ = ["GRID_BOUND_SLACK_M", "grid_cost_kernel", "warm_grid"]

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}
#: numba keys this file's on-disk cache on this file only, not on the ``*_nb`` code its
#: kernels compile in: a digest of that code (tests/core/test_kernel_stamps.py names the new
#: value after a callee's edit; writing it here is what invalidates a warm cache).
CALLEES_SHA256 = "b407ab71c5258cbf"


@njit(**_OPTS)
def _keep_smallest(best, n_best, keep, t):
    """Insert ``t`` into ``best[:n_best]`` (ascending) keeping the ``keep`` smallest values
    (``t`` dropped when there are ``keep`` already and it is not smaller than the largest);
    returns the new count."""
    i = n_best if n_best < keep else keep - 1
    if n_best == keep and not t < best[i]:
        return n_best
    while i > 0 and best[i - 1] > t:
        best[i] = best[i - 1]
        i -= 1
    best[i] = t
    return n_best + 1 if n_best < keep else n_best


#: Rounding slack of :func:`grid_cost_kernel`'s lower bound [m]: a mechanism's computed length
#: may fall short of the computed straight line by rounding (~1e-13 m at 100 m); the bound
#: counts a range as short only beyond this.
GRID_BOUND_SLACK_M = 1e-6


@njit(**_OPTS)
def _grid_bounds(cells, z, anchors, rho, var, mask, bound):
    """A lower bound of every cell's link costs summed (writes ``bound`` (C,)): per present
    link ``0.5 max(los - rho - slack, 0)^2 / var`` (``los``: the straight line from the anchor
    to the cell at height ``z``); a link with a NaN adds nothing (no bound)."""
    for c in range(cells.shape[0]):
        s = 0.0
        for m in range(anchors.shape[0]):
            if not mask[m]:
                continue
            d0, d1, d2 = cells[c, 0] - anchors[m, 0], cells[c, 1] - anchors[m, 1], \
                z - anchors[m, 2]
            short = math.sqrt((d0 * d0 + d2 * d2) + d1 * d1) - rho[m] - GRID_BOUND_SLACK_M
            if short > 0.0:
                b = 0.5 * short * short / var[m]
                if b == b:
                    s += b
        bound[c] = s


@njit(**_OPTS)
def _link_cost(anchor, p0, p1, p2, zf, zc, lo, hi, x0, x1, depth, edge, is_band, is_diff, relax,
               rho, var, w_out, length, loose, sure):
    """One link's cost at the point (p0, p1, p2) for :func:`grid_cost_kernel`: the smallest
    ``0.5 e^2 / var`` over the candidate mechanisms, capped by the outlier's cost plus the
    hinge (NaN propagates); ``length``, ``loose``, ``sure`` (K,): scratch."""
    a0, a1, a2 = anchor[0], anchor[1], anchor[2]
    e_spec = np.inf
    spec_nan = False
    for k in range(is_band.shape[0]):
        ln, ok, _, _, _, _, _, ez = slot_path(k, a0, a1, a2, p0, p1, p2, zf, zc, lo, hi, x0, x1,
                                              depth, edge, True, False)
        lz = ok
        sz = ok
        if is_band[k]:
            lz = ok and (ez > lo - relax) and (ez < hi + relax)
            m1, m2 = ez - lo, hi - ez
            sz = lz and (m1 if m1 < m2 else m2) > relax
        length[k], loose[k], sure[k] = ln, lz, sz
        if sz and not is_diff[k]:
            if math.isnan(ln):
                spec_nan = True
            elif ln < e_spec:
                e_spec = ln
    if spec_nan:
        e_spec = np.nan
    cost = np.inf
    for k in range(is_band.shape[0]):
        ln = length[k]
        cand = loose[k] and ((ln < e_spec) if is_diff[k] else (ln <= e_spec))
        if cand:
            e = rho - ln
            v = 0.5 * e * e / var
            if math.isnan(v) or math.isnan(cost):
                cost = np.nan
            elif v < cost:
                cost = v
    d0, d1, d2 = p0 - a0, p1 - a1, p2 - a2
    los = math.sqrt((d0 * d0 + d2 * d2) + d1 * d1)
    short = rho - los
    if not short < 0.0 and not math.isnan(short):
        short = 0.0
    out = w_out + 0.5 * (short * short) / var
    if math.isnan(cost) or math.isnan(out):
        return np.nan
    return out if out < cost else cost


@njit(**_OPTS)
def grid_cost_kernel(cells, z, floor, anchors, rho, var, mask, is_band, is_diff, relax, w_out,
                     keep, first_z, floor_h, sill, win_h, x0, x1, depth, total):
    """Robust max-mixture cost of every grid cell of the snapshot initialisation
    (``tracking_model.grid_starts``): writes ``total`` (N, Fs, C).

    ``cells`` (C, 2) x, y; ``z`` (N, Fs) cell height per node and listed floor, ``floor``
    (N, Fs) float64 floor index; ``anchors`` (N, M, 3); ``rho``, ``var`` (N, M) (``var``
    already widened by the grid's resolution), ``mask`` (N, M); ``is_band`` / ``is_diff``
    (K,): the slots whose entry point must lie in the window band / the diffraction slots;
    ``relax``: the band's widening (``graded_paths``' ``relax_m``); ``w_out``: the outlier's
    cost. Per link: the smallest ``0.5 e^2 / var`` over the candidate mechanisms (lengths
    without Jacobians; existence graded as ``graded_paths``, candidates as
    ``tracking_model.candidates``), capped by the outlier's cost plus the hinge; summed over
    the present links in numpy's order.

    ``keep`` > 0: only the ``keep`` cheapest cells per (node, floor) are needed (the caller
    ranks ``total``): a cell is abandoned (``total`` +inf) as soon as the plain sum of its
    links so far exceeds the ``keep``-th smallest total of the cells finished before it by a
    relative margin of 1e-9 (every link's cost is >= 0 when ``w_out`` >= 0, and numpy's
    pairwise sum of non-negative terms differs from their plain sum by far less, so such a
    cell's total would be larger than that ``keep``-th total: it is not among the ``keep``
    cheapest, and the ``keep`` cheapest cells, their totals and their order are those of the
    full evaluation, bit for bit). ``keep`` <= 0 or ``w_out`` < 0: every cell in full.

    With pruning the cells are visited by a lower bound of their totals (smallest first) and
    the rest are abandoned at once when the bound of the next exceeds that ``keep``-th total
    by the same margin: every mechanism's path runs from the anchor to the cell, so it is no
    shorter than the straight line (minus :data:`GRID_BOUND_SLACK_M` for rounding), and a link
    whose range is shorter than the straight line costs at least ``0.5 (los - rho)^2 / var``
    (the outlier's cost too, ``w_out`` >= 0). The bound costs one distance per link, and
    which cells are visited first changes only which cells are abandoned, never the ``keep``
    cheapest (the argument above holds for any visiting order). Measured
    (``benchmarks/bench_tracker_kernels.py``, the replays' first initialisations): 2.2 ->
    0.93 ms per node with 16 anchors (the 16 x 200 soak), 1.3 -> 0.48 ms with 8 (``large``).
    """
    edge = edge_axis(x0, x1)
    n_n, n_f = z.shape
    prune = keep > 0 and w_out >= 0.0
    best = np.empty(max(keep, 1))  # the ``keep`` smallest totals so far, ascending
    n_c = cells.shape[0]
    n_m = anchors.shape[1]
    n_k = is_band.shape[0]
    length = np.empty(n_k)
    loose = np.empty(n_k, dtype=np.bool_)
    sure = np.empty(n_k, dtype=np.bool_)
    link = np.empty(n_m)
    bound = np.zeros(n_c)
    order = np.arange(n_c)
    for n in range(n_n):
        for f in range(n_f):
            zf, zc, lo, hi = row_planes(floor[n, f], first_z, floor_h, sill, win_h)
            p2 = z[n, f]
            n_best = 0
            if prune:
                _grid_bounds(cells, p2, anchors[n], rho[n], var[n], mask[n], bound)
                order = np.argsort(bound, kind="mergesort")
            for i in range(n_c):
                c = order[i]
                if prune and n_best == keep and bound[c] * (1.0 - 1e-9) > best[keep - 1]:
                    for j in range(i, n_c):  # the bounds ascend: none of the rest can be
                        total[n, f, order[j]] = np.inf
                    break
                p0, p1 = cells[c, 0], cells[c, 1]
                partial = 0.0
                gone = False
                for m in range(n_m):
                    if not mask[n, m]:
                        link[m] = 0.0
                        continue
                    cost = _link_cost(anchors[n, m], p0, p1, p2, zf, zc, lo, hi, x0, x1, depth,
                                      edge, is_band, is_diff, relax, rho[n, m], var[n, m],
                                      w_out, length, loose, sure)
                    link[m] = cost
                    if prune and n_best == keep:
                        partial += cost
                        gone = partial * (1.0 - 1e-9) > best[keep - 1]
                        if gone:
                            break
                if gone:
                    total[n, f, c] = np.inf
                    continue
                t = _pairwise_sum(link, n_m)
                total[n, f, c] = t
                if prune and t < np.inf:  # finite (not NaN, not +inf)
                    n_best = _keep_smallest(best, n_best, keep, t)


def warm_grid(planes: tuple, anc: np.ndarray) -> None:
    """Compile (or load from numba's cache) :func:`grid_cost_kernel` on tiny inputs (called by
    :func:`diffpos.tracking.tracker.warm_tracking`). ``planes``: the building's planes
    (:func:`diffpos.paths.model_nb.building_planes`), ``anc`` (1, 1, 3)."""
    one, mask, flags = np.ones((1, 1)), np.ones((1, 1), np.bool_), np.zeros(18, np.bool_)
    grid_cost_kernel(np.ones((1, 2)), np.array([[4.5]]), np.zeros((1, 1)), anc, one, one, mask,
                     flags, flags, 1.0, 7.0, 3, *planes, np.empty((1, 1, 1)))
