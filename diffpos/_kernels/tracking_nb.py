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

import numpy as np
from numba import njit

from .paths_nb import edge_axis, row_planes, slot_path

__all__ = ["model_kernel", "select_prep_kernel"]

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
                    else:
                        for i in range(3):
                            for j in range(3):
                                acc += 0.0 * pos_cov[n, h, i, j] * 0.0
                    s_var[n, h, m, k] = acc + var[n, m]
