"""Compiled pieces of the tracker's measurement model (:mod:`diffpos.tracking_model`).

:func:`model_kernel` evaluates, in one loop over every (node, hypothesis, anchor) link, the
chosen mechanism's raw length and Jacobian (:func:`diffpos._kernels.paths_nb.slot_path` with
``raw=True``: the same call the path kernel makes for ``graded_paths``, so the same floating-
point operations), the straight line and the link's model value, Jacobian and weight of the
IEKF (:func:`diffpos.tracking_model._model`). Before, the path model was called once per
distinct slot and Gauss-Newton iteration (~10 numpy/kernel calls per iteration, each with
its broadcasting and slot tables) and the straight line by ``einsum``. The numpy version
stays as the reference (``tracking_model._model_numpy``); tests/core/test_tracking_kernel.py
holds them to bit equality.
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit

from .npsum_nb import pairwise_sum as _pairwise_sum
from .paths_nb import edge_axis, row_planes, slot_path

__all__ = ["all_paths_kernel", "grid_cost_kernel", "iekf_terms_kernel", "model_kernel",
           "select_prep_kernel", "warm_tracking"]

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}


@njit(**_OPTS)
def model_kernel(pos, anchors, floor, slot, extra_var, rho, var, mask, first_z, floor_h, sill,
                 win_h, x0, x1, depth, model, jm, w):
    """Model value, Jacobian and IEKF weight of every link (writes ``model``, ``jm``, ``w``).

    ``pos`` (N, H, 3) hypothesis positions, ``anchors`` (N, M, 3), ``floor`` (N, H) float64
    floor index, ``slot`` (N, H, M) chosen slot (-1: none), ``extra_var`` (N, H, M), ``rho``,
    ``var`` (N, M), ``mask`` (N, M) bool. A used link (slot >= 0 with a finite length and
    Jacobian) models its slot's length with weight ``1 / (var + extra_var)``; an unused
    present link whose range is shorter than the straight line (the hinge) models the
    straight line with weight ``1 / var``; any other link models its own range, weight 0.
    """
    edge = edge_axis(x0, x1)
    n_n, n_h, n_m = slot.shape
    for n in range(n_n):
        for h in range(n_h):
            p0, p1, p2 = pos[n, h, 0], pos[n, h, 1], pos[n, h, 2]
            zf, zc, lo, hi = row_planes(floor[n, h], first_z, floor_h, sill, win_h)
            for m in range(n_m):
                a0, a1, a2 = anchors[n, m, 0], anchors[n, m, 1], anchors[n, m, 2]
                s = slot[n, h, m]
                use = False
                ln = np.nan
                j0 = j1 = j2 = 0.0
                if s >= 0:
                    ln, _, j0, j1, j2, _, _, _ = slot_path(s, a0, a1, a2, p0, p1, p2, zf, zc,
                                                          lo, hi, x0, x1, depth, edge, True,
                                                          True)
                    use = (math.isfinite(ln) and math.isfinite(j0) and math.isfinite(j1)
                           and math.isfinite(j2))
                if use:
                    model[n, h, m] = ln
                    jm[n, h, m, 0] = j0
                    jm[n, h, m, 1] = j1
                    jm[n, h, m, 2] = j2
                    w[n, h, m] = 1.0 / (var[n, m] + extra_var[n, h, m])
                    continue
                # the straight line, as tracking_model._los: sqrt(d . d), d / max(|d|, 1e-12);
                # numpy's einsum sums a 3-vector as (d0^2 + d2^2) + d1^2 (two SIMD lanes, the
                # odd element into the first), so the same order here (the test checks it)
                d0, d1, d2 = p0 - a0, p1 - a1, p2 - a2
                los = math.sqrt((d0 * d0 + d2 * d2) + d1 * d1)
                if mask[n, m] and rho[n, m] < los:
                    den = max(los, 1e-12)
                    model[n, h, m] = los
                    jm[n, h, m, 0] = d0 / den
                    jm[n, h, m, 1] = d1 / den
                    jm[n, h, m, 2] = d2 / den
                    w[n, h, m] = 1.0 / var[n, m]
                else:
                    model[n, h, m] = rho[n, m]
                    jm[n, h, m, 0] = 0.0
                    jm[n, h, m, 1] = 0.0
                    jm[n, h, m, 2] = 0.0
                    w[n, h, m] = 0.0


@njit(**_OPTS)
def select_prep_kernel(length, jac, sure, loose, is_diff, pos_cov, var, snr, snr_c, use_snr,
                       g_const, span_ll, valid, s_ll, s_var):
    """The transcendental-free part of ``tracking_model.select`` per (node, hypothesis,
    anchor, slot): the candidates (``tracking_model.candidates``, then without power only
    near an existence boundary), the SNR log-likelihood term ``s_ll`` and the innovation
    variance ``s_var = J P J^T + R`` (0 Jacobian for a non-candidate), with numpy's order of
    operations (``einsum`` sums ``(J_i P_ij) J_j`` over i outer, j inner), so bit-identical.

    ``length`` (N, H, M, K), ``jac`` (N, H, M, K, 3), ``sure``/``loose`` (N, H, M, K) bool,
    ``is_diff`` (K,) bool, ``pos_cov`` (N, H, 3, 3), ``var`` (N, M), ``snr`` (N, M) and
    ``snr_c`` (N, H, M, K) (ignored unless ``use_snr``), ``g_const``: ``log(sigma_snr) +
    log(2 pi) / 2`` is subtracted as ``(-c - log(sigma)) - log(2 pi) / 2``: given as the two
    terms ``g_const[0]``, ``g_const[1]``; ``span_ll = -log(SNR_SPAN_DB)``.
    """
    n_n, n_h, n_m, n_k = length.shape
    for n in range(n_n):
        for h in range(n_h):
            for m in range(n_m):
                e_spec = np.inf  # earliest sure specular path (NaN propagates as in min)
                for k in range(n_k):
                    if sure[n, h, m, k] and not is_diff[k]:
                        ln = length[n, h, m, k]
                        if math.isnan(ln):
                            e_spec = np.nan
                            break
                        if ln < e_spec:
                            e_spec = ln
                has_snr = use_snr and math.isfinite(snr[n, m])
                for k in range(n_k):
                    ln = length[n, h, m, k]
                    ok = loose[n, h, m, k] and ((ln < e_spec) if is_diff[k] else (ln <= e_spec))
                    sl = 0.0
                    if use_snr:
                        c = snr_c[n, h, m, k]
                        powered = math.isfinite(c)
                        ok = ok and (powered or not sure[n, h, m, k])
                        if has_snr:
                            sl = ((-c - g_const[0]) - g_const[1]) if powered else span_ll
                    valid[n, h, m, k] = ok
                    s_ll[n, h, m, k] = sl
                    acc = 0.0
                    if ok:
                        for i in range(3):
                            for j in range(3):
                                acc += jac[n, h, m, k, i] * pos_cov[n, h, i, j] * jac[n, h, m, k, j]
                    else:  # the reference's einsum over a zeroed Jacobian: 0, or NaN
                        for i in range(3):  # when the covariance holds inf/NaN
                            for j in range(3):
                                acc += 0.0 * pos_cov[n, h, i, j] * 0.0
                    s_var[n, h, m, k] = acc + var[n, m]


@njit(**_OPTS)
def grid_cost_kernel(cells, z, floor, anchors, rho, var, mask, is_band, is_diff, relax, w_out,
                     first_z, floor_h, sill, win_h, x0, x1, depth, total):
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
    """
    edge = edge_axis(x0, x1)
    n_n, n_f = z.shape
    n_c = cells.shape[0]
    n_m = anchors.shape[1]
    n_k = is_band.shape[0]
    length = np.empty(n_k)
    loose = np.empty(n_k, dtype=np.bool_)
    sure = np.empty(n_k, dtype=np.bool_)
    link = np.empty(n_m)
    for n in range(n_n):
        for f in range(n_f):
            zf, zc, lo, hi = row_planes(floor[n, f], first_z, floor_h, sill, win_h)
            p2 = z[n, f]
            for c in range(n_c):
                p0, p1 = cells[c, 0], cells[c, 1]
                for m in range(n_m):
                    if not mask[n, m]:
                        link[m] = 0.0
                        continue
                    a0, a1, a2 = anchors[n, m, 0], anchors[n, m, 1], anchors[n, m, 2]
                    e_spec = np.inf
                    spec_nan = False
                    for k in range(n_k):
                        ln, ok, _, _, _, _, _, ez = slot_path(k, a0, a1, a2, p0, p1, p2, zf,
                                                              zc, lo, hi, x0, x1, depth, edge,
                                                              True, False)
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
                    for k in range(n_k):
                        ln = length[k]
                        cand = loose[k] and ((ln < e_spec) if is_diff[k] else (ln <= e_spec))
                        if cand:
                            e = rho[n, m] - ln
                            v = 0.5 * e * e / var[n, m]
                            if math.isnan(v) or math.isnan(cost):
                                cost = np.nan
                            elif v < cost:
                                cost = v
                    d0, d1, d2 = p0 - a0, p1 - a1, p2 - a2
                    los = math.sqrt((d0 * d0 + d2 * d2) + d1 * d1)
                    short = rho[n, m] - los
                    if not short < 0.0 and not math.isnan(short):
                        short = 0.0
                    out = w_out + 0.5 * (short * short) / var[n, m]
                    if math.isnan(cost) or math.isnan(out):
                        cost = np.nan
                    elif out < cost:
                        cost = out
                    link[m] = cost
                total[n, f, c] = _pairwise_sum(link, n_m)


@njit(**_OPTS)
def all_paths_kernel(pos, anchors, floor, relax, is_band, first_z, floor_h, sill, win_h, x0,
                     x1, depth, length, jac, strict, loose, sure):
    """Every slot of every (node, hypothesis, anchor) link with graded existence, as
    ``diffpos.paths.graded_paths`` computes it for ``tracking_model.all_paths`` (the same
    per-row path function with ``raw=True`` and the same band tests), without its flat-row
    broadcasting: ``pos`` (N, H, 3), ``anchors`` (N, M, 3), ``floor`` (N, H) float64,
    ``relax`` (N, H) float64 (every hypothesis' own widening of the band, [m]);
    writes ``length`` (N, H, M, K), ``jac`` (N, H, M, K, 3) and the three existence grades.
    """
    edge = edge_axis(x0, x1)
    n_n, n_h, n_m, n_k = length.shape
    for n in range(n_n):
        for h in range(n_h):
            p0, p1, p2 = pos[n, h, 0], pos[n, h, 1], pos[n, h, 2]
            zf, zc, lo, hi = row_planes(floor[n, h], first_z, floor_h, sill, win_h)
            r = relax[n, h]
            for m in range(n_m):
                a0, a1, a2 = anchors[n, m, 0], anchors[n, m, 1], anchors[n, m, 2]
                for k in range(n_k):
                    ln, ok, j0, j1, j2, _, _, ez = slot_path(k, a0, a1, a2, p0, p1, p2, zf, zc,
                                                             lo, hi, x0, x1, depth, edge, True,
                                                             True)
                    length[n, h, m, k] = ln
                    jac[n, h, m, k, 0] = j0
                    jac[n, h, m, k, 1] = j1
                    jac[n, h, m, k, 2] = j2
                    if is_band[k]:
                        lz = ok and (ez > lo - r) and (ez < hi + r)
                        m1, m2 = ez - lo, hi - ez
                        margin = m1 if m1 < m2 else m2
                        strict[n, h, m, k] = lz and margin > 0
                        sure[n, h, m, k] = lz and margin > r
                    else:
                        lz = ok
                        strict[n, h, m, k] = lz
                        sure[n, h, m, k] = lz
                    loose[n, h, m, k] = lz


@njit(**_OPTS)
def iekf_terms_kernel(y, x, lo, hi, z_nom, rho, model, jm, w, wb, wh, a, e, eb, eh, gpart):
    """One Gauss-Newton iteration's terms of ``tracking_model.iekf`` except the prior's
    gradient ``-Y (x - x_prior)`` and the solve, with numpy's operations in numpy's order
    (``einsum`` sums over the links in sequence): writes the information matrix ``a`` (N, H,
    6, 6) = Y + J^T W J + the box and height pseudo-measurements, the residuals ``e`` (N, H,
    M), the box residuals ``eb`` (N, H, 3), the height residual ``eh`` (N, H) and the
    position gradient ``gpart`` (N, H, 3) = J^T W e + wb eb.
    """
    n_n, n_h, n_m = model.shape
    for n in range(n_n):
        for h in range(n_h):
            for m in range(n_m):
                e[n, h, m] = rho[n, m] - model[n, h, m]
            for i in range(6):
                for j in range(6):
                    a[n, h, i, j] = y[n, h, i, j]
            for i in range(3):
                p = x[n, h, i]
                c = p if p > lo[n, h, i] else lo[n, h, i]  # np.clip: min(max(p, lo), hi)
                c = c if c < hi[n, h, i] else hi[n, h, i]
                eb[n, h, i] = c - p
            eh[n, h] = z_nom[n, h] - x[n, h, 2]
            for i in range(3):
                for j in range(3):
                    acc = 0.0
                    for m in range(n_m):
                        acc += jm[n, h, m, i] * w[n, h, m] * jm[n, h, m, j]
                    a[n, h, i, j] = a[n, h, i, j] + acc
            for i in range(3):
                a[n, h, i, i] = a[n, h, i, i] + (wb if eb[n, h, i] != 0 else 0.0)
            a[n, h, 2, 2] = a[n, h, 2, 2] + wh[n, h]
            for i in range(3):
                acc = 0.0
                for m in range(n_m):
                    acc += jm[n, h, m, i] * (w[n, h, m] * e[n, h, m])
                gpart[n, h, i] = acc + wb * eb[n, h, i]


def warm_tracking() -> float:
    """Compile the tracker's kernels (or load them from numba's on-disk cache) on tiny inputs:
    ~4-6 s the first time on a machine, then ~0.2-0.3 s (the callers in
    ``tracking_model`` pass C-contiguous writable arrays, so one signature per kernel).
    Returns the seconds it took. (The fusion's warm-up runs a throw-away tracker update,
    which does the same.)"""
    t0 = time.perf_counter()
    f8 = np.float64
    planes = (3.0, 3.0, 0.9, 1.5, -20.0, 20.0, 22.0)
    pos, anc = np.array([[[1.0, 5.0, 4.5]]]), np.array([[[0.0, -15.0, 1.0]]])
    one, onef = np.ones((1, 1)), np.ones((1, 1, 1))
    mask = np.ones((1, 1), np.bool_)
    model_kernel(pos, anc, np.zeros((1, 1)), np.zeros((1, 1, 1), np.int64), onef, one, one,
                 mask, *planes, np.empty((1, 1, 1)), np.empty((1, 1, 1, 3)),
                 np.empty((1, 1, 1)))
    k = 18
    flags = np.zeros(k, np.bool_)
    select_prep_kernel(np.ones((1, 1, 1, k)), np.zeros((1, 1, 1, k, 3)),
                       np.ones((1, 1, 1, k), np.bool_), np.ones((1, 1, 1, k), np.bool_), flags,
                       np.ones((1, 1, 3, 3)), one, one, np.ones((1, 1, 1, k)), True,
                       np.zeros(2), f8(0.0), np.empty((1, 1, 1, k), np.bool_),
                       np.empty((1, 1, 1, k)), np.empty((1, 1, 1, k)))
    grid_cost_kernel(np.ones((1, 2)), np.array([[4.5]]), np.zeros((1, 1)), anc, one, one, mask,
                     flags, flags, 1.0, 7.0, *planes, np.empty((1, 1, 1)))
    b4 = np.empty((1, 1, 1, k), np.bool_)
    all_paths_kernel(pos, anc, np.zeros((1, 1)), np.full((1, 1), 0.2), flags, *planes,
                     np.empty((1, 1, 1, k)), np.empty((1, 1, 1, k, 3)), b4, b4.copy(), b4.copy())
    x6, p3 = np.ones((1, 1, 6)), np.ones((1, 1, 3))
    iekf_terms_kernel(np.ones((1, 1, 6, 6)), x6, p3, p3, one, one, onef, np.ones((1, 1, 1, 3)),
                      onef, 1.0, one, np.empty((1, 1, 6, 6)), np.empty((1, 1, 1)),
                      np.empty((1, 1, 3)), np.empty((1, 1)), np.empty((1, 1, 3)))
    return time.perf_counter() - t0
