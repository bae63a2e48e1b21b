"""Start points of the M-NLS search (:mod:`diffpos.estimators.mnls.solver`): the coarse grid and
the closed-form starts of one-mechanism hypotheses (straight line, images, window edges).

``p`` is the estimator's flattened problem (anchors, ranges, mask, floor boxes ``lo``/``hi``,
mid-floor heights ``z_mid``); ``rows`` selects its hypotheses. ``kernel=True``: the same
steps in :mod:`diffpos.estimators.mnls.starts_nb` (bitwise the same starts on the tested
sets; these numpy functions are the reference).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

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


def _c(a, dtype=np.float64):
    """A C-contiguous writable copy (the kernels' one signature)."""
    return np.array(a, dtype=dtype, order="C")


def _los_start(p, rows, building, iters: int = 8, free_z: bool = False, kernel: bool = False
               ) -> FloatArray:
    """Gauss-Newton on straight-line ranges from the floor's centre: in (x, y) at z =
    mid-floor, clipped to the floor plan, or (``free_z``) in 3D with y >= 0 and z unbounded
    (damped); (len(rows), 3)."""
    if kernel:
        out = np.empty((len(rows), 3))
        los_start_kernel(_c(p.anchors[rows]), _c(p.r[rows]), _c(p.mask[rows], bool),
                         _c(p.lo[rows]), _c(p.hi[rows]), _c(p.z_mid[rows]), int(iters),
                         bool(free_z), out)
        return out
    a, r, w = p.anchors[rows], p.r[rows], p.mask[rows].astype(float)
    x = np.stack([0.5 * (p.lo[rows, 0] + p.hi[rows, 0]), 0.5 * (p.lo[rows, 1] + p.hi[rows, 1]),
                  p.z_mid[rows]], axis=-1)
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


def _edge_start(p, rows, z_edge: FloatArray, iters: int = 8,
                z_mirror: FloatArray | None = None, kernel: bool = False) -> FloatArray:
    """Start of the hypothesis "every link diffracts over the horizontal edge at height
    ``z_edge`` (y = 0)": the Fermat length is ``sqrt((x_a - x)^2 + (rho_a + rho)^2)`` with
    ``rho`` the distance to the edge line, a straight-line range in the (x, rho) half-plane;
    Gauss-Newton there, then the point at mid-floor height (or nearest to it) at distance
    ``rho`` from the edge; (len(rows), 3). With ``z_mirror`` (a ceiling's height), the
    hypothesis is "diffraction, then a reflection in that plane": the point at distance
    ``rho`` is the node's image, at the mirror of mid-floor height."""
    if kernel:
        out = np.empty((len(rows), 3))
        ze = _c(np.broadcast_to(z_edge, (len(rows),)))
        edge_start_kernel(_c(p.anchors[rows]), _c(p.r[rows]), _c(p.mask[rows], bool),
                          _c(p.lo[rows]), _c(p.hi[rows]), _c(p.z_mid[rows]), ze,
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
    z_pt = p.z_mid[rows] if z_mirror is None else 2 * z_mirror - p.z_mid[rows]
    dz = np.clip(z_pt - z_edge, -u[:, 1], u[:, 1])
    y = np.sqrt(np.maximum(u[:, 1] ** 2 - dz**2, 0.0))
    x = np.column_stack([u[:, 0], y, p.z_mid[rows]])
    return np.clip(x, p.lo[rows], p.hi[rows])
