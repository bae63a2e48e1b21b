"""The starts of the M-NLS search (:mod:`diffpos.estimators.mnls.solver`): the coarse grid, the
closed-form starts of one-mechanism hypotheses (straight line, images, window edges).

``p`` is the estimator's flattened problem (anchors, ranges, mask, floor boxes ``lo``/``hi``,
mid-floor heights ``z_mid``); ``rows`` selects its hypotheses. ``kernel=True``: the same
steps in :mod:`diffpos.estimators.mnls.starts_nb` (bitwise the same starts on the tested
sets; these numpy functions are the reference).

The search layout: where the starts of every fix x floor go (:func:`_start_points`: the grid
at mid-floor height, seven cells replaced by the closed-form starts above, the caller's
start) and which screened cells go on (:func:`_kept`); the stages themselves (screen,
re-scoring, refinement) are in :mod:`diffpos.estimators.mnls.solver` beside the stage
counters and the constants they read.

The search, its measured cost and the compiled steps (from the estimator's model description):

* **Search.** Per floor, an ``nx x ny`` grid of (x, y) cells at mid-floor height (default
  4 x 3, in farthest-point order so that the cells left over cover the whole plan: in raster
  order the 5 left of 4 x 3 all lay in its left half), seven cells replaced by closed-form
  starts of one-mechanism hypotheses (above), from the window band's mid-height
  (:func:`_window_mid_z`): a straight-line multilateration (direct path; most first arrivals
  are a few cm to dm longer than the straight line) over the links left after dropping those
  metres longer than it (:func:`_trimmed_los_start`); the images a free-z straight-line fit
  gives for specular links (ceiling image, ceiling-floor double bounce); per window edge,
  "every link diffracts over this edge" (the Fermat length over a horizontal edge is
  ``sqrt((x_a - x)^2 + (rho_a + rho)^2)``, ``rho`` the distance to the edge line: a
  straight-line multilateration in the (x, rho) half-plane) and "diffraction over this edge,
  then the ceiling" (the same for the node's ceiling image). Optionally a caller's start
  ``x0_m`` (a tracker's prediction). Every cell gets ``SCREEN_ITER`` LM steps (a cell's cost
  before any step says little: a metre off, every link picks the wrong mechanism), the
  closed-form and caller's starts with the SNR terms of their starting point, the remaining
  grid cells with the ranges only; per floor the ``keep_starts`` best of the former and the
  best grid cell are re-scored with the SNR at their screened point (only on floors whose best
  screened cost is within ``RESCORE_NATS`` of the best floor's; the others are dropped);
  floors whose best is ``PRUNE_NATS`` above the best floor's keep that mode with zero
  posterior, the others run up to ``max_iter`` LM steps (a hypothesis stops when an accepted
  step is below ``CONVERGED_M``). Measured on the default study (seed 0, receivers
  subsampled): the edge starts took the floor accuracy from 89.0 % to 93.0 % (400 receivers),
  the edge + ceiling starts from 89.8 % to 91.7 % (1,500 receivers, 4 x 2 grid); with a start
  at the truth it would be 92.9 %: the remaining floor misses are mostly ambiguity, not
  search.
* **Search cost** (``benchmarks/bench_mnls.py --stages``: node-anchor pairs through the path
  model and the SNR prediction per fix and stage). The screen is most of both: every start of
  every floor gets ``SCREEN_ITER + 1`` path-model evaluations, every closed-form start one SNR
  prediction. 8 anchors (``bench_estimator_cost.py``'s layout, 512 fixes, seed 1), per fix:
  path-model pairs 3,116 -> 2,214, SNR pairs 594 -> 367 (screen 480 -> 265). Grid cells with
  the ranges only (were with the SNR, and the ``keep_starts`` best of all cells went on): SNR
  pairs -30 % at 8 anchors, -20 % at 4, and better answers: of 3,072 paired synthetic fixes (4
  and 8 anchors, seeds 0-2) the floor right only with it for 39, only without for 28; 3D error
  0.1 m better for 162, worse for 51; ellipsoid coverage +0.8 to +1.6 points; two
  1,500-receiver studies (``diffpos reproduce --quick``, seeds 0 and 1): floor 91.9 -> 92.3 %,
  92.2 -> 92.5 %, p80 0.57 -> 0.55 m, 0.55 -> 0.52 m. Screening every start with the ranges
  only loses floors at 4 anchors (-11 net of 1,024); with the SNR at the straight-line and
  image starts only: +13 floors of 1,024 synthetic fixes at 4 anchors, but in the two studies
  floor 92.3 -> 91.6 %, 92.5 -> 91.2 % and coverage -1.5 / -0.9 points (not taken). Cut
  without changing answers: the start's terms computed once (were twice), the SNR predicted
  for the linked pairs only, re-scoring only floors within ``RESCORE_NATS`` (512 synthetic
  fixes each at 4 and 8 anchors and a 1,500-receiver study: identical positions and floors).
  ``SCREEN_ITER`` 4 -> 3 changes ~5 % of the fixes, in both directions: of 3,072 paired
  synthetic fixes (4 and 8 anchors, seeds 0-2), the floor is right only with 4 steps for 9,
  only with 3 steps for 6; the 3D error 0.1 m worse for 28, better for 30; ellipsoid coverage
  within +-0.5 points; and floor accuracy 91.9 / 91.9 % and 92.2 / 92.1 % in two
  1,500-receiver studies (seeds 0 and 1, ``diffpos reproduce --quick``); 2 steps lose floors
  (-4 of 512 at 8 anchors). Measured and *not* taken (each loses floors in paired runs, 8
  anchors, 512 fixes): dropping the 5 grid cells (-5 floors), screening a floor's grid cells
  only when its closed-form starts come within 30 nats of the best floor (-3; even within 200
  nats: -2: a grid cell sometimes rescues the true floor when all its closed-form starts
  fail), one kept start per floor (-1; at 4 anchors 4 vs 9), a range-only pre-screen (its
  ranks are unrelated to the SNR-aware screen's), dropping screened rows by their cost after
  1-2 steps (a row 10^4 nats behind after 2 steps can end first).
* **Compiled steps** (``kernel=True``, the default): every Levenberg-Marquardt run (the
  screen, the refinement between two SNR refreshes, the final refinement with the mechanisms
  held) is one call of :func:`diffpos.estimators.mnls.solver_nb.lm_kernel` per chunk (path model per
  row and slot, link choice, cost, damped 3x3 normal equations, box clamp, acceptance), and
  the closed-form starts are :mod:`diffpos.estimators.mnls.starts_nb`; both reproduce numpy's
  operation order (einsum's and ``sum``'s summation orders, LAPACK ``gesv``), so the answers
  are those of the reference steps (``kernel=False``): bitwise equal positions, covariances,
  floors, mechanisms and statuses on ``bench_estimator_cost.py``'s sets (4 and 8 anchors,
  256 fixes, seeds 0 and 1) and on the tests' held-out buildings (tests/core/test_mnls.py
  asserts 1e-9 m). Cost per fix (``bench_estimator_cost.py --quick``, 8 anchors, CPU;
  2026-11-27 06:35 UTC, 2-core VM shared, load 4.5-6.2, before = commit adf3856, two
  interleaved runs each): batched 6.03 / 4.91 -> 3.79 / 3.07 ms, single 14.6 / 13.4 -> 6.57 /
  5.41 ms (4 anchors: batched 4.03 / 3.42 -> 2.25 / 2.25, single 13.0 / 16.2 -> 4.17 / 4.15);
  the issue-13 target (<= 2 ms at 8 anchors) is not met. Where it goes now
  (``bench_mnls.py --stages --batch 128``, 8 anchors, per fix): screen 3.0 ms (compiled LM
  2.0, SNR prediction at the closed-form starts 0.9), rescore 0.4, refine 0.3, final 0.2,
  starts 0.2; cProfile of 64 fixes (``bench_path_model.py --profile-mnls 64``): ``lm_kernel``
  52 %, ``pair_snr_db`` 26 %, the rest 22 %. The compiled LM spends ~0.8-1.1 us per
  node-anchor pair and step, nearly all in the path model's 18 slots; a further cut needs
  fewer evaluations (the search's answers change) or a faster path model / SNR prediction.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from diffpos.estimators.mnls.problem import CAP_MIN_LINKS, _Problem
from diffpos.estimators.mnls.starts_nb import edge_start_kernel, los_start_kernel

FloatArray = NDArray[np.float64]


def _grid(building, nx: int, ny: int) -> FloatArray:
    """Cell centres of an nx x ny grid over the floor plan, (nx * ny, 2) [m], in farthest-point
    order: the cell nearest the plan's centre first, then each time the cell farthest from
    those already taken (ties: the lowest raster index). The search replaces the LAST cells by
    its closed-form starts, so whatever number of cells stays a grid cell covers the whole plan
    (in raster order the 5 cells left of a 4 x 3 grid all lay in the left half)."""
    x0, x1 = building.edge_x_m
    xs = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
    ys = (np.arange(ny) + 0.5) * building.depth_m / ny
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    cells = np.stack([gx.ravel(), gy.ravel()], axis=-1)
    return cells[_farthest_point_order(cells, np.array([(x0 + x1) / 2, building.depth_m / 2]))]


def _farthest_point_order(cells: FloatArray, centre: FloatArray) -> NDArray[np.int_]:
    """Greedy farthest-point order of ``cells`` (n, 2) starting from the one nearest ``centre``."""
    n = cells.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int_)
    order = [int(np.argmin(np.sum((cells - centre) ** 2, axis=1)))]
    d = np.sum((cells - cells[order[0]]) ** 2, axis=1)
    for _ in range(n - 1):
        k = int(np.argmax(d))
        order.append(k)
        d = np.minimum(d, np.sum((cells - cells[k]) ** 2, axis=1))
    return np.asarray(order)


#: The straight-line start drops links with a large excess (:func:`_trimmed_los_start`) only
#: in fixes with at least :data:`diffpos.estimators.mnls.problem.CAP_MIN_LINKS` links (with
#: four, the others cannot outvote a link: as for the out-of-model cap), and only while more
#: links than this are left (two unknowns in (x, y): three links still over-determine them).
TRIM_MIN_LINKS = 3


def _c(a, dtype=np.float64):
    """A C-contiguous writable copy (the kernels' one signature)."""
    return np.array(a, dtype=dtype, order="C")


def _los_start(p, rows, building, iters: int = 8, free_z: bool = False, kernel: bool = False,
               z_start: FloatArray | None = None, mask=None) -> FloatArray:
    """Gauss-Newton on straight-line ranges from the floor's centre: in (x, y) at z =
    ``z_start`` (default mid-floor; one per row of ``rows``), clipped to the floor plan, or
    (``free_z``) in 3D from that height with y >= 0 and z unbounded (damped); (len(rows), 3).
    ``mask`` (len(rows), M): the links fitted (default ``p.mask[rows]``)."""
    zs = p.z_mid[rows] if z_start is None else np.broadcast_to(z_start, (len(rows),))
    mask = p.mask[rows] if mask is None else mask
    if kernel:
        out = np.empty((len(rows), 3))
        los_start_kernel(_c(p.anchors[rows]), _c(p.r[rows]), _c(mask, bool),
                         _c(p.lo[rows]), _c(p.hi[rows]), _c(zs), int(iters),
                         bool(free_z), out)
        return out
    a, r, w = p.anchors[rows], p.r[rows], mask.astype(float)
    x = np.stack([0.5 * (p.lo[rows, 0] + p.hi[rows, 0]), 0.5 * (p.lo[rows, 1] + p.hi[rows, 1]),
                  zs], axis=-1)
    nd = 3 if free_z else 2
    for _ in range(iters):
        d = x[:, None, :] - a
        dist = np.sqrt(np.einsum("nmi,nmi->nm", d, d))
        jac = d[..., :nd] / dist[..., None]
        res = r - dist
        h = np.einsum("nm,nmi,nmj->nij", w, jac, jac) + 1e-2 * np.eye(nd)
        g = np.einsum("nm,nm,nmi->ni", w, res, jac)
        x[:, :nd] += np.linalg.solve(h, g[..., None])[..., 0]
        x[:, :2] = np.clip(x[:, :2], p.lo[rows, :2], p.hi[rows, :2])
    return x


def _trimmed_los_start(p, rows, building, kernel: bool = False,
                       z_start: FloatArray | None = None) -> FloatArray:
    """:func:`_los_start` (in (x, y)) that drops, one at a time, the link whose range exceeds
    its straight-line distance the most, while that excess is above ``3 sigma`` of the link
    and more than :data:`TRIM_MIN_LINKS` links are left; refitted after each drop.

    Every path is at least as long as the straight line, so a link whose first arrival is not
    the direct path has a positive excess (metres for a ground or slab bounce); in a least
    squares fit over all links one such link pulls the start metres off and the search then
    misses the floor's mode (random held-out building heldout-1, Sionna's trace, K = 4:
    receivers 175 and 177, four direct links of six, the true floor's mode found only from a
    start at the truth). Fixes with fewer than ``CAP_MIN_LINKS`` links keep the plain fit (on
    the emulator's default study, four anchors, dropping one of four moved p80 0.557 -> 0.560 m
    and the ellipsoid coverage 95.9 -> 95.8 %)."""
    zs = p.z_mid[rows] if z_start is None else np.broadcast_to(z_start, (len(rows),))
    mask = p.mask[rows].copy()
    x = _los_start(p, rows, building, kernel=kernel, z_start=zs, mask=mask)
    a, r, sig = p.anchors[rows], p.r[rows], p.sig[rows]
    go = np.flatnonzero(mask.sum(axis=-1) >= CAP_MIN_LINKS)
    while go.size:
        go = go[mask[go].sum(axis=-1) > TRIM_MIN_LINKS]
        d = np.sqrt(np.einsum("nmi,nmi->nm", x[go, None, :] - a[go], x[go, None, :] - a[go]))
        e = np.where(mask[go], r[go] - d, -np.inf)
        j = np.argmax(e, axis=-1)
        k = np.arange(go.size)
        over = e[k, j] > 3.0 * sig[go][k, j]
        go, j = go[over], j[over]
        if not go.size:
            break
        mask[go, j] = False
        x[go] = _los_start(p, rows[go], building, kernel=kernel, z_start=zs[go], mask=mask[go])
    return x


def _edge_start(p, rows, z_edge: FloatArray, iters: int = 8,
                z_mirror: FloatArray | None = None, kernel: bool = False,
                z_start: FloatArray | None = None) -> FloatArray:
    """Start of the hypothesis "every link diffracts over the horizontal edge at height
    ``z_edge`` (y = 0)": the Fermat length is ``sqrt((x_a - x)^2 + (rho_a + rho)^2)`` with
    ``rho`` the distance to the edge line, a straight-line range in the (x, rho) half-plane;
    Gauss-Newton there, then the point at mid-floor height (or nearest to it) at distance
    ``rho`` from the edge; (len(rows), 3). With ``z_mirror`` (a ceiling's height), the
    hypothesis is "diffraction, then a reflection in that plane": the point at distance
    ``rho`` is the node's image, at the mirror of mid-floor height. ``z_start`` (one per row
    of ``rows``): that height instead of mid-floor."""
    zs = p.z_mid[rows] if z_start is None else np.broadcast_to(z_start, (len(rows),))
    if kernel:
        out = np.empty((len(rows), 3))
        ze = _c(np.broadcast_to(z_edge, (len(rows),)))
        edge_start_kernel(_c(p.anchors[rows]), _c(p.r[rows]), _c(p.mask[rows], bool),
                          _c(p.lo[rows]), _c(p.hi[rows]), _c(zs), ze,
                          ze if z_mirror is None else _c(np.broadcast_to(z_mirror, ze.shape)),
                          int(iters), z_mirror is not None, out)
        return out
    a, r, w = p.anchors[rows], p.r[rows], p.mask[rows].astype(float)
    ze = z_edge[:, None]
    rho_a = np.hypot(a[..., 1], a[..., 2] - ze)
    u = np.stack([0.5 * (p.lo[rows, 0] + p.hi[rows, 0]), 0.5 * p.hi[rows, 1]], axis=-1)
    for _ in range(iters):
        dx = u[:, None, 0] - a[..., 0]
        dr = u[:, None, 1] + rho_a
        dist = np.maximum(np.hypot(dx, dr), 1e-9)
        jac = np.stack([dx, dr], axis=-1) / dist[..., None]
        h = np.einsum("nm,nmi,nmj->nij", w, jac, jac) + 1e-2 * np.eye(2)
        g = np.einsum("nm,nm,nmi->ni", w, r - dist, jac)
        u += np.linalg.solve(h, g[..., None])[..., 0]
        u[:, 0] = np.clip(u[:, 0], p.lo[rows, 0], p.hi[rows, 0])
        u[:, 1] = np.clip(u[:, 1], p.lo[rows, 1],
                          np.hypot(p.hi[rows, 1], 3 * (p.hi[rows, 2] - p.lo[rows, 2])))
    z_pt = zs if z_mirror is None else 2 * z_mirror - zs
    dz = np.clip(z_pt - z_edge, -u[:, 1], u[:, 1])
    y = np.sqrt(np.maximum(u[:, 1] ** 2 - dz**2, 0.0))
    x = np.column_stack([u[:, 0], y, zs])
    return np.clip(x, p.lo[rows], p.hi[rows])


def _window_mid_z(building, floors: NDArray[np.int_]) -> FloatArray:
    """Height of the window band's middle on ``floors`` [m]: where the closed-form starts put
    the node (:func:`_start_points`).

    A direct or specular path enters through the window, so a node near the facade has one
    from every anchor only at the band's height: at mid-floor, above or below a band that
    does not straddle it, every link of a direct-path receiver starts on another mechanism
    and the search settles in a wrong mode (random held-out building rand-3-6: floor 3.95 m,
    band 0.38-1.57 m, mid-floor 1.98 m; 28 of 200 receivers on a wrong floor, every one of
    them right from a start at the truth). The node's prior stays uniform over the floor
    (``z_mid``); on the paper building both heights are 1.5 m (the same starts)."""
    return building.floor_z_m(floors) + (building.sill_height_m + 0.5 * building.window_height_m)


def _start_points(p0: _Problem, grid: FloatArray, building, b: int, x0=None,
                  kernel: bool = False) -> tuple[FloatArray, NDArray[np.bool_]]:
    """The start of every row of ``p0`` (B fixes x F floors x G cells): the grid at mid-floor
    height with seven cells replaced by the closed-form starts (from the window's mid-height:
    :func:`_window_mid_z`), and the caller's start; and which rows hold a closed-form or the
    caller's start (the others: grid cells)."""
    nf = building.n_floors
    g = grid.shape[0]
    x = np.empty((b * nf * g, 3))
    closed = np.zeros(b * nf * g, dtype=bool)
    x[:, :2] = np.tile(grid, (b * nf, 1))
    x[:, 2] = p0.z_mid
    # the last cell of every floor is replaced by a straight-line (LoS) multilateration at
    # the window's mid-height: most first arrivals (direct, lower-edge diffraction near the
    # window's height) are a few cm to dm longer than the straight line, so it lands in their
    # basin
    last = np.arange(b * nf) * g + g - 1
    zw = _window_mid_z(building, p0.floor[last])
    x[last] = _trimmed_los_start(p0, last, building, kernel=kernel, z_start=zw)
    closed[last] = True
    # two more cells: a free-z straight-line fit is the node's image when the links are
    # specular; the node is then its ceiling image (2 z_c - z) or, for the ceiling-floor double
    # bounce, 2H below it (image method), clipped into the floor
    if g >= 4:
        img = _los_start(p0, last, building, free_z=True, kernel=kernel, z_start=zw)
        h = building.floor_height_m
        for cell, z in ((g - 2, 2 * (p0.lo[last, 2] + h) - img[:, 2]), (g - 3, img[:, 2] - 2 * h)):
            x[last - (g - 1) + cell] = np.clip(np.column_stack([img[:, :2], z]), p0.lo[last],
                                               p0.hi[last])
            closed[last - (g - 1) + cell] = True
    # per floor and window edge, the closed-form start of "every link diffracts over this
    # edge" (the Fermat path over a horizontal edge unfolds to a straight line in (x, rho))
    # and (two more cells) of "diffraction over the edge, then the ceiling" (the node's
    # ceiling image diffracts): deep inside, these are the common first arrivals
    zf = p0.lo[last, 2] - 1e-3
    zc = zf + building.floor_height_m
    z_lo = zf + building.sill_height_m
    for cell, ze, zm in ((g - 4, z_lo, None), (g - 5, z_lo + building.window_height_m, None),
                         (g - 6, z_lo, zc), (g - 7, z_lo + building.window_height_m, zc)):
        if cell >= 1:
            x[last - (g - 1) + cell] = _edge_start(p0, last, ze, z_mirror=zm, kernel=kernel,
                                                   z_start=zw)
            closed[last - (g - 1) + cell] = True
    if x0 is not None:  # a caller's start (e.g. a tracker's prediction) on its own floor
        has = np.flatnonzero(np.all(np.isfinite(x0), axis=-1))
        k0 = np.clip(building.floor_index(x0[has, 2]), 0, nf - 1)
        row0 = (has * nf + k0) * g
        x[row0] = np.clip(x0[has], p0.lo[row0], p0.hi[row0])
        closed[row0] = True
    return x, closed



def _kept(c0: FloatArray, split, keep: int) -> NDArray[np.int_]:
    """Per fix and floor, the cells that go on, (B, F, keep) or (B, F, keep + 1): the
    ``keep`` lowest screened costs ``c0`` (B, F, G); with ``split`` (B, F, G: the cells
    screened with the SNR), the ``keep`` lowest of those and the lowest grid cell (its
    range-only cost is not comparable with the others before the re-scoring)."""
    if split is None:
        return np.argsort(c0, axis=-1, kind="stable")[..., :keep]
    b1 = np.argsort(np.where(split, c0, np.inf), axis=-1, kind="stable")[..., :keep]
    b2 = np.argsort(np.where(split, np.inf, c0), axis=-1, kind="stable")[..., :1]
    return np.concatenate([b1, b2], axis=-1)



def _link_terms_rows(t_rows, sel: NDArray[np.bool_], n: int) -> dict:
    """Arrays of ``n`` rows holding ``t_rows(sel)`` on the rows ``sel`` (the others are
    written by the caller)."""
    ts = t_rows(np.flatnonzero(sel))
    out = {}
    for key, v in ts.items():
        out[key] = np.empty((n, *v.shape[1:]), dtype=v.dtype)
        out[key][sel] = v
    return out

