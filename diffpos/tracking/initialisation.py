"""The grid search of the tracker's snapshot initialisation (:mod:`diffpos.tracking.model`).

:func:`grid_starts` ranks a grid of cells at the nominal node height on every listed floor
by the robust max-mixture range cost (the range variance widened by the grid's resolution)
in one compiled pass (:func:`diffpos.tracking.initialisation_nb.grid_cost_kernel`), bit-identical
to the numpy reference :func:`_grid_starts_numpy`; the snapshot fit from the best cells
(:func:`diffpos.tracking.model.snapshot`, :func:`~diffpos.tracking.model.snapshot_init`)
runs the measurement update and stays beside it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from diffpos._kernels.pool import GRID_MIN_CELL_LINKS, run_rows
from diffpos.paths.model_nb import building_planes
from diffpos.tracking.initialisation_nb import grid_cost_kernel
from diffpos.tracking.links import _IS_BAND, _IS_DIFF, Links, _c, _los, all_paths, candidates

FloatArray = NDArray[np.float64]


def _grid_cells(building, step_m: float) -> FloatArray:
    x0, x1 = building.edge_x_m
    xs = np.arange(x0 + step_m / 2, x1, step_m)
    ys = np.arange(step_m / 2, building.depth_m, step_m)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    return np.stack([gx.ravel(), gy.ravel()], axis=-1)


def grid_starts(links: Links, floors: NDArray, building, config) -> FloatArray:
    """Best ``init_starts`` grid cells on each listed floor per node: (N, Fs * S, 3).

    ``floors`` (N, Fs): the floors to search for every node. The cost of a cell is the robust
    max-mixture cost over the links with the range variance widened by the grid's own
    resolution (``(step / 2)^2``). Every cell of every node in one compiled pass
    (:func:`diffpos.tracking.initialisation_nb.grid_cost_kernel`: lengths without Jacobians, no
    temporaries), bit-identical to :func:`_grid_starts_numpy`. The kernel abandons a cell as
    soon as its links so far cost more than the ``init_starts``-th best cell finished before it
    (exact: the same cells, totals and order; the grid was ~20 % of the fusion's CPU over the
    first 2 s of a real-time ``large`` run, 3.9 ms per node with 8 anchors, 1.4 ms with the
    pruning: cProfile of ``benchmarks/bench_fusion_cost.py --schedule`` on a 20 s real-time
    ``large`` recording).
    """
    cells = _grid_cells(building, config.init_grid_m)  # (C, 2)
    n, nf = floors.shape
    m = links.rho.shape[-1]
    if m > 128:  # the kernel's summation order is numpy's up to 128 links
        return _grid_starts_numpy(links, floors, building, config)
    c, ns = cells.shape[0], config.init_starts
    z = building.floor_z_m(floors) + building.nominal_node_height_m  # (N, Fs)
    var = links.var + (0.5 * config.init_grid_m) ** 2
    w_out = np.log(config.outlier_span_m / config.outlier_weight)
    total = np.empty((n, nf, c))
    fl = np.empty((n, nf))
    fl[...] = floors
    cc, zc, anc = _c(cells), _c(z, dtype=np.float64), _c(links.anchors[:, 0])
    rho, vr, mask = _c(links.rho[:, 0]), _c(var[:, 0]), _c(links.mask[:, 0])
    planes = building_planes(building)

    def rows(lo: int, hi: int) -> None:  # the node rows [lo, hi) (diffpos._kernels.pool)
        grid_cost_kernel(cc, zc[lo:hi], fl[lo:hi], anc[lo:hi], rho[lo:hi], vr[lo:hi],
                         mask[lo:hi], _IS_BAND, _IS_DIFF, 0.5 * config.init_grid_m,
                         float(w_out), int(ns), *planes, total[lo:hi])

    run_rows(rows, n, min_rows=-(-GRID_MIN_CELL_LINKS // max(nf * c * m, 1)))
    order = np.argsort(total, axis=2, kind="stable")[..., :ns]  # (N, Fs, S)
    pos = np.concatenate([np.broadcast_to(cells[None, None], (n, nf, c, 2)),
                          np.broadcast_to(z[:, :, None, None], (n, nf, c, 1))], axis=-1)
    return np.take_along_axis(pos, order[..., None], axis=2).reshape(n, nf * ns, 3)


def _grid_starts_numpy(links: Links, floors: NDArray, building, config) -> FloatArray:
    """The numpy reference of :func:`grid_starts` (one node at a time)."""
    cells = _grid_cells(building, config.init_grid_m)  # (C, 2)
    n, nf = floors.shape
    c, ns = cells.shape[0], config.init_starts
    z = building.floor_z_m(floors) + building.nominal_node_height_m  # (N, Fs)
    var = links.var + (0.5 * config.init_grid_m) ** 2
    w_out = np.log(config.outlier_span_m / config.outlier_weight)
    starts = np.zeros((n, nf * ns, 3))
    for i in range(n):  # one node at a time keeps the arrays small (K x Fs x C x M)
        pos = np.concatenate([np.broadcast_to(cells[None], (nf, c, 2)),
                              np.broadcast_to(z[i][:, None, None], (nf, c, 1))], axis=-1)
        pos = pos.reshape(1, nf * c, 3)
        li = Links(links.rho[i:i + 1], var[i:i + 1], links.mask[i:i + 1],
                   links.anchors[i:i + 1])
        total = _cell_costs(pos, li, np.repeat(floors[i], c)[None], building,
                            0.5 * config.init_grid_m, w_out)[0].reshape(nf, c)
        order = np.argsort(total, axis=1, kind="stable")[:, :ns]
        starts[i] = pos[0].reshape(nf, c, 3)[np.arange(nf)[:, None], order].reshape(-1, 3)
    return starts


def _cell_costs(pos: FloatArray, li: Links, floors: NDArray, building, relax_m: float,
                w_out: float) -> FloatArray:
    """The robust max-mixture range cost (n, C) of the cells ``pos`` (n, C, 3) on ``floors``
    (n, C) for the links ``li`` (n nodes, their variances already widened): per link the
    smallest ``0.5 e^2 / var`` over the candidate mechanisms, capped by the outlier's cost
    ``w_out`` plus the hinge of a range shorter than the straight line."""
    pe = all_paths(pos, li, floors, building, relax_m)
    e = li.rho[..., None] - pe.length
    cost = np.where(candidates(pe), 0.5 * e * e / li.var[..., None], np.inf).min(axis=-1)
    los, _ = _los(pos, li.anchors)
    short = np.minimum(li.rho - los, 0.0)
    cost = np.minimum(cost, w_out + 0.5 * short**2 / li.var)
    return np.where(li.mask, cost, 0.0).sum(axis=-1)


#: Half-width of :func:`local_starts`' window in standard deviations of its prior.
LOCAL_SIGMAS = 2.0
#: At most this many cells of :func:`local_starts` (its caller fits each one).
LOCAL_STARTS = 1


def local_starts(links: Links, floors: NDArray, centre: FloatArray, cov_xy: FloatArray,
                 building, config) -> tuple[FloatArray, FloatArray]:
    """The best ``init_starts`` cells (k, S, 3) of a local grid around each of ``k`` prior
    positions ``centre`` (k, 3) on ``floors`` (k,), ranked by the grid's robust range cost
    (the snapshot grid's: :func:`grid_starts`' kernel, the range variance widened by the
    grid's resolution) plus the prior term ``0.5 d^T C^-1 d`` of the cell's horizontal offset
    ``d`` under ``cov_xy`` (k, 2, 2): the modes of a floor within reach of the prediction
    (:func:`diffpos.tracking.tracker._mode_pairs`). Cells ``init_grid_m / 2`` apart within
    :data:`LOCAL_SIGMAS` standard deviations and inside the building, at the centre's height
    (within the floor's band); the centre itself is a cell; ``S = min(init_starts,
    LOCAL_STARTS)``. Also returns the starts' ranking costs (k, S) (+inf: no cell). One
    compiled pass per pair over its cells (:func:`grid_cost_kernel` with ``keep`` 0: every
    cell in full, the numpy cost of :func:`_cell_costs` bit for bit)."""
    k = centre.shape[0]
    step = 0.5 * config.init_grid_m
    inv = np.linalg.inv(cov_xy)
    half = int(np.ceil(LOCAL_SIGMAS * np.sqrt(np.linalg.eigvalsh(cov_xy)[:, -1].max()) / step))
    o = step * np.arange(-half, half + 1, dtype=np.float64)
    off = np.stack(np.meshgrid(o, o, indexing="ij"), axis=-1).reshape(-1, 2)  # (C, 2)
    pen = 0.5 * np.einsum("ci,kij,cj->kc", off, inv, off)
    xy = centre[:, None, :2] + off[None]
    x0, x1 = building.edge_x_m
    inside = ((pen <= 0.5 * LOCAL_SIGMAS**2) & (xy[..., 0] > x0) & (xy[..., 0] < x1)
              & (xy[..., 1] > 0.0) & (xy[..., 1] < building.depth_m))
    zf = building.floor_z_m(floors)
    z = np.clip(centre[:, 2], zf + config.z_margin_m,
                zf + building.floor_height_m - config.z_margin_m)
    var = links.var + (0.5 * step) ** 2
    w_out = float(np.log(config.outlier_span_m / config.outlier_weight))
    anc, rho, vr, mask = (_c(a) for a in (links.anchors[:, 0], links.rho[:, 0], var[:, 0],
                                          links.mask[:, 0]))
    planes = building_planes(building)
    ns = min(config.init_starts, LOCAL_STARTS)
    starts, costs = np.zeros((k, ns, 3)), np.full((k, ns), np.inf)
    for i in range(k):  # every pair its own window (a few pairs per epoch)
        cells = _c(xy[i][inside[i]], dtype=np.float64)
        total = np.empty((1, 1, cells.shape[0]))
        grid_cost_kernel(cells, np.full((1, 1), z[i]), np.full((1, 1), float(floors[i])),
                         anc[i:i + 1], rho[i:i + 1], vr[i:i + 1], mask[i:i + 1], _IS_BAND,
                         _IS_DIFF, 0.5 * step, w_out, 0, *planes, total)
        t = total[0, 0] + pen[i][inside[i]]
        order = np.argsort(t, kind="stable")[:ns]
        starts[i, :order.size, :2] = cells[order]
        starts[i, :, 2] = z[i]
        costs[i, :order.size] = t[order]
    return starts, costs
