"""Compiled closed-form starts of M-NLS: :mod:`diffpos.estimators.mnls.starts` in one loop.

:func:`los_start_kernel` (straight-line multilateration, in (x, y) or free z) and
:func:`edge_start_kernel` (every link diffracts over one horizontal edge: a straight line in
the (x, rho) half-plane) run the Gauss-Newton steps of ``_los_start`` / ``_edge_start`` for
every row with numpy's operation order: einsum's sums over the links in link order, the
3-term dot product of ``einsum("nmi,nmi->nm")`` as ``(d0 d0 + d2 d2) + d1 d1`` (numpy's
unrolled loop), the solve by LAPACK's ``gesv`` (numba's ``np.linalg.solve``), ``hypot`` of
the C library, ``np.clip`` as max-then-min. The numpy functions stay the reference
(``mnls(..., kernel=False)``; tests/core/test_mnls.py compares the two).

Fixed compiled signatures, C-contiguous inputs; ``cache=True``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types

__all__ = ["edge_start_kernel", "los_start_kernel"]

_f8_1d = types.float64[::1]
_f8_2d = types.float64[:, ::1]
_f8_3d = types.float64[:, :, ::1]
_b1_2d = types.boolean[:, ::1]
_OPTS = {"cache": True, "error_model": "numpy"}


@njit(**_OPTS, inline="always")
def _clip(v, lo, hi):
    """np.clip of one value: max then min, NaN stays NaN."""
    if v < lo:
        v = lo
    if v > hi:
        v = hi
    return v


@njit(types.void(_f8_3d, _f8_2d, _b1_2d, _f8_2d, _f8_2d, _f8_1d, types.int64, types.boolean,
                 _f8_2d), **_OPTS)
def los_start_kernel(anchors, r, mask, lo, hi, z_mid, iters, free_z, x_out):
    """``_los_start`` for every row: ``x_out`` (N, 3)."""
    n, m = r.shape
    nd = 3 if free_z else 2
    jac = np.empty((m, 3))
    dist = np.empty(m)
    h = np.empty((nd, nd))
    g = np.empty(nd)
    for i in range(n):
        x = np.array([0.5 * (lo[i, 0] + hi[i, 0]), 0.5 * (lo[i, 1] + hi[i, 1]), z_mid[i]])
        for _ in range(iters):
            for j in range(m):
                d0 = x[0] - anchors[i, j, 0]
                d1 = x[1] - anchors[i, j, 1]
                d2 = x[2] - anchors[i, j, 2]
                ds = math.sqrt((d0 * d0 + d2 * d2) + d1 * d1)
                dist[j] = ds
                jac[j, 0] = d0 / ds
                jac[j, 1] = d1 / ds
                jac[j, 2] = d2 / ds
            for u in range(nd):
                g[u] = 0.0
                for v in range(nd):
                    h[u, v] = 0.0
            for j in range(m):
                w = 1.0 if mask[i, j] else 0.0
                res = r[i, j] - dist[j]
                for u in range(nd):
                    wu = w * jac[j, u]
                    for v in range(nd):
                        h[u, v] += wu * jac[j, v]
                    g[u] += (w * res) * jac[j, u]
            for u in range(nd):
                for v in range(nd):
                    h[u, v] = h[u, v] + (1e-2 if u == v else 0.0)
            step = np.linalg.solve(h, g)
            for u in range(nd):
                x[u] += step[u]
            x[0] = _clip(x[0], lo[i, 0], hi[i, 0])
            x[1] = _clip(x[1], lo[i, 1], hi[i, 1])
        x_out[i, 0], x_out[i, 1], x_out[i, 2] = x[0], x[1], x[2]


@njit(types.void(_f8_3d, _f8_2d, _b1_2d, _f8_2d, _f8_2d, _f8_1d, _f8_1d, _f8_1d, types.int64,
                 types.boolean, _f8_2d), **_OPTS)
def edge_start_kernel(anchors, r, mask, lo, hi, z_mid, z_edge, z_mirror, iters, mirrored,
                      x_out):
    """``_edge_start`` for every row (``z_mirror`` used when ``mirrored``): ``x_out``."""
    n, m = r.shape
    rho_a = np.empty(m)
    jac = np.empty((m, 2))
    dist = np.empty(m)
    h = np.empty((2, 2))
    g = np.empty(2)
    for i in range(n):
        ze = z_edge[i]
        for j in range(m):
            rho_a[j] = math.hypot(anchors[i, j, 1], anchors[i, j, 2] - ze)
        u0 = 0.5 * (lo[i, 0] + hi[i, 0])
        u1 = 0.5 * hi[i, 1]
        u1_hi = math.hypot(hi[i, 1], 3 * (hi[i, 2] - lo[i, 2]))
        for _ in range(iters):
            for j in range(m):
                dx = u0 - anchors[i, j, 0]
                dr = u1 + rho_a[j]
                ds = math.hypot(dx, dr)
                if ds < 1e-9:  # np.maximum(ds, 1e-9): NaN stays NaN
                    ds = 1e-9
                dist[j] = ds
                jac[j, 0] = dx / ds
                jac[j, 1] = dr / ds
            g[0] = g[1] = 0.0
            h[0, 0] = h[0, 1] = h[1, 0] = h[1, 1] = 0.0
            for j in range(m):
                w = 1.0 if mask[i, j] else 0.0
                res = r[i, j] - dist[j]
                for a in range(2):
                    wa = w * jac[j, a]
                    for b in range(2):
                        h[a, b] += wa * jac[j, b]
                    g[a] += (w * res) * jac[j, a]
            h[0, 0] = h[0, 0] + 1e-2
            h[0, 1] = h[0, 1] + 0.0
            h[1, 0] = h[1, 0] + 0.0
            h[1, 1] = h[1, 1] + 1e-2
            step = np.linalg.solve(h, g)
            u0 += step[0]
            u1 += step[1]
            u0 = _clip(u0, lo[i, 0], hi[i, 0])
            u1 = _clip(u1, lo[i, 1], u1_hi)
        z_pt = 2 * z_mirror[i] - z_mid[i] if mirrored else z_mid[i]
        dz = _clip(z_pt - ze, -u1, u1)
        y2 = u1 ** 2 - dz ** 2
        if y2 < 0.0:  # np.maximum(y2, 0): NaN stays NaN
            y2 = 0.0
        y = math.sqrt(y2)
        x_out[i, 0] = _clip(u0, lo[i, 0], hi[i, 0])
        x_out[i, 1] = _clip(y, lo[i, 1], hi[i, 1])
        x_out[i, 2] = _clip(z_mid[i], lo[i, 2], hi[i, 2])
