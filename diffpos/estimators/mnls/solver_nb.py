"""Compiled M-NLS kernels: the link terms and the Levenberg-Marquardt steps.

:func:`link_terms_kernel` is :func:`diffpos.estimators.mnls.solver._link_terms_numpy` in one loop.
For every hypothesis row and link, the candidate mechanisms (existence, never later than the
shortest specular path or a path predicted surely detected, same-edge dominance, the
knife-edge SNR bound, an optional restriction), the max-mixture cost of every candidate
(Gaussian core or one-sided exponential tail, plus the SNR cost), the chosen slot and its
residual, Jacobian and IRLS weight: the same operations as the numpy reference, which stays
in :mod:`diffpos.estimators.mnls.solver` and is what the tests compare against
(tests/core/test_mnls.py: equal slots and flags, values to rounding). One link's choice is
:func:`link_choice`, shared with the LM kernel.

:func:`lm_kernel` is M-NLS's Levenberg-Marquardt (``mnls._lm``; the SNR terms held: the
caller refreshes them between calls every ``SNR_EVERY`` steps) for every row in one loop:
the path model per row and slot (:func:`diffpos.paths.model_nb.family_path_parts` on the
mechanism table and the building's partitions, the operations of ``paths_kernel``), the
link choice above, the cost summed in numpy's order (pairwise over >= 8 links), the damped
3x3 normal equations in einsum's order solved by LAPACK's ``gesv`` (numba's
``np.linalg.solve``: bitwise numpy's on the tested matrices), the box clamp, acceptance, the
damping update and the convergence test of ``mnls._lm``. Links outside the mask are not
evaluated (they add exact zeros to the reference's sums). Its reference is the numpy/numba
path in :mod:`diffpos.estimators.mnls.solver` (``mnls(..., kernel=False)``; tests/core/test_mnls.py).

Fixed compiled signatures (:data:`SIGNATURE`, :data:`LM_SIGNATURE`, C-contiguous inputs);
``cache=True``. numba's cache is keyed by this file only: :func:`lm_kernel` compiles
:func:`diffpos.paths.model_nb.family_path_parts` into itself, so a change of ``paths/model_nb.py``
changes the ``CALLEES_SHA256`` stamp below (tests/core/test_kernel_stamps.py), which
invalidates the stale cache.
Compile from an empty cache: ~12 s CPU (2-core VM, 2026-11-27).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types

from diffpos._kernels.npsum_nb import pairwise_sum as _pairwise_sum
from diffpos.paths.model_nb import edge_axis, family_path_parts, row_planes

__all__ = ["LM_SIGNATURE", "SIGNATURE", "link_choice", "link_terms_kernel", "lm_kernel",
           "worst_capped"]

_f8_1d = types.float64[::1]
_f8_2d = types.float64[:, ::1]
_f8_3d = types.float64[:, :, ::1]
_f8_4d = types.float64[:, :, :, ::1]
_b1_1d = types.boolean[::1]
_b1_2d = types.boolean[:, ::1]
_b1_3d = types.boolean[:, :, ::1]
_i8_1d = types.int64[::1]
_i8_2d = types.int64[:, ::1]
_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}  # nogil: pool.run_rows
#: numba keys this file's on-disk cache on this file only, not on the ``*_nb`` code its
#: kernels compile in: a digest of that code (tests/core/test_kernel_stamps.py names the new
#: value after a callee's edit; writing it here is what invalidates a warm cache).
CALLEES_SHA256 = "b407ab71c5258cbf"

#: The one compiled signature of :func:`link_terms_kernel`.
SIGNATURE = types.void(
    _f8_3d, _b1_3d, _f8_4d, _f8_3d, _f8_3d,  # length, valid, jacobian, deviation_cos, outside
    _f8_2d, _f8_2d, _b1_2d, _f8_2d, _f8_2d, _f8_2d,  # r, sig, mask, tail_a, cap, excess (N, M)
    types.float64, types.float64, types.float64,  # lam, wavelength, snr margin [dB]
    _f8_3d, _b1_3d, _b1_3d,  # snr_cost, strong, allowed (N, M, K) or (0, 0, 0)
    _b1_1d, _b1_1d, _i8_2d,  # specular slots, diffraction slots, same-edge pairs (P, 2)
    # outputs: cost (N, M), res, w (N, M), slot (N, M), tail, none (N, M), cand (N, M, K),
    # jac (N, M, 3)
    _f8_2d, _f8_2d, _f8_2d, _i8_2d, _b1_2d, _b1_2d, _b1_3d, _f8_3d,
)

#: The one compiled signature of :func:`lm_kernel`.
LM_SIGNATURE = types.void(
    _f8_3d, _f8_2d, _f8_2d, _b1_2d, _f8_2d, _f8_2d, _f8_2d,  # anchors, r, sig, mask, tail_a,
    # cap, excess
    _f8_1d, _f8_2d, _f8_2d, _f8_1d,  # floor index (float), lo, hi (N, 3), z_mid (N,)
    types.float64, types.float64, types.float64, types.float64,  # prior var, lam, wl, margin
    _f8_1d,  # building planes (first z, H, sill, window h, x0, x1, depth)
    _i8_2d,  # mechanism table (K, C) (diffpos.paths.model_nb.mechanism_table)
    _f8_2d,  # partitions (Q, 4) (diffpos.paths.model_nb.partition_array)
    _f8_3d, _b1_3d, _b1_3d,  # snr_cost, strong, allowed (N, M, K) or (0, 0, 0)
    _b1_1d, _b1_1d, _i8_2d,  # specular slots, diffraction slots, same-edge pairs
    types.int64, types.float64,  # LM steps, convergence step [m]
    # in/out: x (N, 3), damping (N,), live (N,); out: cost (N,), link evaluations (N,)
    _f8_2d, _f8_1d, _b1_1d, _f8_1d, _i8_1d,
)


@njit(**_OPTS)
def link_choice(length, valid, jac_all, dev, outm, r, sig, tail_a, excess, lam, wavelength,
                margin_db, snr_cost, has_snr, strong, has_strong, allowed, has_allowed, spec,
                diff, same_edge, cand, gauss, tail):
    """One link (K slots): candidates into ``cand``, then ``(cost, slot, residual, weight,
    is_tail, none, j0, j1, j2)`` (cost: ``tail_a + 10`` where no candidate; the caller
    applies the mask and the out-of-model cap, :func:`worst_capped`). ``gauss``, ``tail``:
    scratch (K,)."""
    k = length.shape[0]
    l_spec = math.inf
    for s in range(k):
        if valid[s] and length[s] < l_spec:
            if spec[s] or (has_strong and strong[s]):
                l_spec = length[s]
    for s in range(k):
        cand[s] = valid[s] and length[s] <= l_spec
    for p in range(same_edge.shape[0]):
        b, a = same_edge[p, 0], same_edge[p, 1]
        if valid[a] and dev[a] >= dev[b]:
            cand[b] = False
    for s in range(k):
        if diff[s] and cand[s]:
            d1 = outm[s]
            d2 = length[s] - d1
            theta = math.acos(min(max(dev[s], -1.0), 1.0))
            nu = theta * math.sqrt(2 * d1 * d2 / (wavelength * length[s]))
            jl = 0.0
            if nu > -0.78:
                jl = 6.9 + 20 * math.log10(math.sqrt((nu - 0.1) ** 2 + 1) + nu - 0.1)
            if excess < jl - margin_db:
                cand[s] = False
        if has_allowed and not allowed[s]:
            cand[s] = False
    best = math.inf
    slot = 0
    for s in range(k):
        e = r - length[s]
        z = e / sig
        gauss[s] = 0.5 * z * z
        tail[s] = tail_a + e / lam if e > 0 else math.inf
        c = min(gauss[s], tail[s])
        if has_snr:
            c += snr_cost[s]
        if not cand[s]:
            c = math.inf
        if c < best:
            best = c
            slot = s
    none = not (best < math.inf)
    is_tail = tail[slot] < gauss[slot]
    e = 0.0 if none else r - length[slot]
    w = 1.0
    if is_tail:
        w = sig ** 2 / (lam * max(e, 1e-9))
    if none:
        best = tail_a + 10.0
    j0 = 0.0 if none else jac_all[slot, 0]
    j1 = 0.0 if none else jac_all[slot, 1]
    j2 = 0.0 if none else jac_all[slot, 2]
    return best, slot, e, w, is_tail, none, j0, j1, j2


@njit(**_OPTS)
def worst_capped(cost, cap, mask):
    """The link whose cost exceeds its out-of-model cost ``cap`` the most (the first on a
    tie), ``-1`` if none does: M-NLS declares at most one link of a fix out of the model
    (its cost becomes ``cap``, its weight 0). ``cost``, ``cap``, ``mask``: one row (M,)."""
    worst = -1
    over = 0.0
    for j in range(cost.shape[0]):
        if mask[j] and cost[j] - cap[j] > over:
            over = cost[j] - cap[j]
            worst = j
    return worst


@njit(SIGNATURE, **_OPTS)
def link_terms_kernel(length, valid, jac_all, dev, outm, r, sig, mask, tail_a, cap, excess, lam,
                      wavelength, margin_db, snr_cost, strong, allowed, spec, diff, same_edge,
                      cost_out, res_out, w_out, slot_out, tail_out, none_out, cand, jac_out):
    n, m, k = length.shape
    has_snr = snr_cost.shape[0] > 0
    has_strong = strong.shape[0] > 0
    has_allowed = allowed.shape[0] > 0
    gauss = np.empty(k)
    tail = np.empty(k)
    no_f = np.zeros(k)
    no_b = np.zeros(k, dtype=np.bool_)
    for i in range(n):
        for j in range(m):
            best, slot, e, w, is_tail, none, j0, j1, j2 = link_choice(
                length[i, j], valid[i, j], jac_all[i, j], dev[i, j], outm[i, j], r[i, j],
                sig[i, j], tail_a[i, j], excess[i, j], lam, wavelength, margin_db,
                snr_cost[i, j] if has_snr else no_f, has_snr,
                strong[i, j] if has_strong else no_b, has_strong,
                allowed[i, j] if has_allowed else no_b, has_allowed, spec, diff, same_edge,
                cand[i, j], gauss, tail)
            jac_out[i, j, 0] = j0
            jac_out[i, j, 1] = j1
            jac_out[i, j, 2] = j2
            used = mask[i, j] and not none
            slot_out[i, j] = slot
            res_out[i, j] = e
            w_out[i, j] = w if used else 0.0
            cost_out[i, j] = best if mask[i, j] else 0.0
            tail_out[i, j] = is_tail and mask[i, j]
            none_out[i, j] = none and mask[i, j]
        jw = worst_capped(cost_out[i], cap[i], mask[i])
        if jw >= 0:  # out of the model: capped, no weight, excluded
            cost_out[i, jw] = cap[i, jw]
            w_out[i, jw] = 0.0
            tail_out[i, jw] = True


@njit(**_OPTS)
def _row_terms(i, x0, x1, x2, anchors, r, sig, mask, tail_a, cap, excess, floor, z_mid, prior_var,
               lam, wavelength, margin_db, planes, table, parts, edge, snr_cost, has_snr, strong,
               has_strong, allowed, has_allowed, spec, diff, same_edge, buf_len, buf_valid,
               buf_jac, buf_dev, buf_out, cand, gauss, tail, no_f, no_b, link_cost, lbuf, lskip,
               h, g):
    """Cost of row ``i`` at ``(x0, x1, x2)`` (``mnls._link_terms``: links + floor prior, the
    worst link above its out-of-model cost capped) and its normal equations ``h`` (3, 3),
    ``g`` (3,) without the prior (``mnls._lm``'s einsums; ``lbuf`` (M, 5), ``lskip`` (M,):
    every link's weighted terms, held until the capped link is known); returns ``(cost,
    links evaluated)``."""
    zf, zc, wlo, whi = row_planes(floor[i], planes[0], planes[1], planes[2], planes[3])
    ex0, ex1, depth = planes[4], planes[5], planes[6]
    for u in range(3):
        g[u] = 0.0
        for v in range(3):
            h[u, v] = 0.0
    m = r.shape[1]
    n_eval = 0
    for j in range(m):
        lskip[j] = True
        if not mask[i, j]:
            link_cost[j] = 0.0
            continue
        n_eval += 1
        a0, a1, a2 = anchors[i, j, 0], anchors[i, j, 1], anchors[i, j, 2]
        for s in range(table.shape[0]):
            ln, ok, j0, j1, j2, dv, om, _ = family_path_parts(
                table, s, a0, a1, a2, x0, x1, x2, zf, zc, wlo, whi, ex0, ex1, depth, edge,
                False, True, parts)
            buf_len[s] = ln
            buf_valid[s] = ok
            buf_jac[s, 0] = j0
            buf_jac[s, 1] = j1
            buf_jac[s, 2] = j2
            buf_dev[s] = dv
            buf_out[s] = om
        best, _slot, e, w, _tail, none, j0, j1, j2 = link_choice(
            buf_len, buf_valid, buf_jac, buf_dev, buf_out, r[i, j], sig[i, j], tail_a[i, j],
            excess[i, j], lam, wavelength, margin_db, snr_cost[i, j] if has_snr else no_f,
            has_snr, strong[i, j] if has_strong else no_b, has_strong,
            allowed[i, j] if has_allowed else no_b, has_allowed, spec, diff, same_edge, cand,
            gauss, tail)
        link_cost[j] = best
        if none:
            continue  # weight 0: adds exact zeros in the reference
        lskip[j] = False
        lbuf[j, 0] = w / sig[i, j] ** 2
        lbuf[j, 1] = e
        lbuf[j, 2] = j0
        lbuf[j, 3] = j1
        lbuf[j, 4] = j2
    jw = worst_capped(link_cost, cap[i], mask[i])
    if jw >= 0:  # weight 0: adds exact zeros in the reference
        link_cost[jw] = cap[i, jw]
        lskip[jw] = True
    for j in range(m):
        if lskip[j]:
            continue
        ws = lbuf[j, 0]
        e = lbuf[j, 1]
        for u in range(3):
            wu = ws * lbuf[j, 2 + u]
            for v in range(3):
                h[u, v] += wu * lbuf[j, 2 + v]
            g[u] += (ws * e) * lbuf[j, 2 + u]
    dz = x2 - z_mid[i]
    prior = 0.5 * dz ** 2 / prior_var
    return _pairwise_sum(link_cost, m) + prior, n_eval


@njit(**_OPTS)
def _trial_point(i, xo0, xo1, xo2, h, g, dmp, z_mid, prior_var, lo, hi, eye, hd, rhs, step, xn):
    """One damped step of :func:`lm_kernel` from ``(xo0, xo1, xo2)`` (row ``i``): the normal
    equations ``h``, ``g`` with the floor prior, damped by ``dmp`` as numpy evaluates
    ``h + lam * eye * (diag + 1e-9)``, solved by LAPACK (NaN where not finite) and clamped to
    the row's box; writes the trial point into ``xn`` (``hd``, ``rhs``, ``step``: work)."""
    for u in range(3):
        rhs[u] = g[u]
        for v in range(3):
            hd[u, v] = h[u, v]
    hd[2, 2] += 1.0 / prior_var
    rhs[2] -= (xo2 - z_mid[i]) / prior_var
    d0, d1, d2 = hd[0, 0], hd[1, 1], hd[2, 2]
    for u in range(3):  # h + lam * eye * (diag + 1e-9), as numpy evaluates it
        hd[u, 0] = hd[u, 0] + dmp * eye[u, 0] * (d0 + 1e-9)
        hd[u, 1] = hd[u, 1] + dmp * eye[u, 1] * (d1 + 1e-9)
        hd[u, 2] = hd[u, 2] + dmp * eye[u, 2] * (d2 + 1e-9)
    finite = True
    for u in range(3):
        finite = finite and math.isfinite(rhs[u])
        for v in range(3):
            finite = finite and math.isfinite(hd[u, v])
    if finite:
        step[:] = np.linalg.solve(hd, rhs)
    else:
        step[:] = np.nan
    for u in range(3):
        v = (xo0 if u == 0 else (xo1 if u == 1 else xo2)) + step[u]
        if v < lo[i, u]:  # np.clip: max then min, NaN stays NaN
            v = lo[i, u]
        if v > hi[i, u]:
            v = hi[i, u]
        xn[u] = v


@njit(LM_SIGNATURE, **_OPTS)
def lm_kernel(anchors, r, sig, mask, tail_a, cap, excess, floor, lo, hi, z_mid, prior_var, lam,
              wavelength, margin_db, planes, table, parts, snr_cost, strong, allowed, spec, diff,
              same_edge, iters, conv_m, x, damp, live, cost_out, evals_out):
    """``iters`` projected LM steps of ``mnls._lm`` (SNR terms held) from ``x`` for every
    ``live`` row: ``x``, the damping ``damp`` and ``live`` (False once converged or the
    damping reaches 1e6) are updated in place; ``cost_out``: the cost at the returned point,
    ``evals_out``: links through the path model per row (module docstring)."""
    n, m = r.shape
    k = table.shape[0]
    has_snr = snr_cost.shape[0] > 0
    has_strong = strong.shape[0] > 0
    has_allowed = allowed.shape[0] > 0
    edge = edge_axis(planes[4], planes[5])
    buf_len = np.empty(k)
    buf_valid = np.empty(k, dtype=np.bool_)
    buf_jac = np.empty((k, 3))
    buf_dev = np.empty(k)
    buf_out = np.empty(k)
    cand = np.empty(k, dtype=np.bool_)
    gauss = np.empty(k)
    tail = np.empty(k)
    no_f = np.zeros(k)
    no_b = np.zeros(k, dtype=np.bool_)
    link_cost = np.empty(m)
    lbuf = np.empty((m, 5))
    lskip = np.empty(m, dtype=np.bool_)
    h = np.empty((3, 3))
    g = np.empty(3)
    h_new = np.empty((3, 3))
    g_new = np.empty(3)
    hd = np.empty((3, 3))
    rhs = np.empty(3)
    step = np.empty(3)
    xn = np.empty(3)
    eye = np.eye(3)
    for i in range(n):
        evals_out[i] = 0
        if not live[i]:
            cost_out[i] = np.nan
            continue
        xc0, xc1, xc2 = x[i, 0], x[i, 1], x[i, 2]
        cost, ne = _row_terms(i, xc0, xc1, xc2, anchors, r, sig, mask, tail_a, cap, excess,
                              floor,
                              z_mid, prior_var, lam, wavelength, margin_db, planes, table,
                              parts, edge, snr_cost, has_snr, strong, has_strong, allowed,
                              has_allowed, spec, diff, same_edge, buf_len, buf_valid, buf_jac, buf_dev,
                              buf_out, cand, gauss, tail, no_f, no_b, link_cost, lbuf, lskip,
                              h, g)
        evals = ne
        dmp = damp[i]
        for _ in range(iters):
            xo0, xo1, xo2 = xc0, xc1, xc2
            _trial_point(i, xo0, xo1, xo2, h, g, dmp, z_mid, prior_var, lo, hi, eye, hd, rhs,
                         step, xn)
            c_new, ne = _row_terms(i, xn[0], xn[1], xn[2], anchors, r, sig, mask, tail_a,
                                   cap, excess, floor, z_mid, prior_var, lam, wavelength,
                                   margin_db, planes, table, parts, edge, snr_cost, has_snr,
                                   strong, has_strong, allowed, has_allowed, spec, diff, same_edge,
                                   buf_len, buf_valid, buf_jac, buf_dev, buf_out, cand, gauss,
                                   tail, no_f, no_b, link_cost, lbuf, lskip, h_new, g_new)
            evals += ne
            ok = c_new < cost
            moved = max(abs(xn[0] - xo0), abs(xn[1] - xo1), abs(xn[2] - xo2))
            if math.isnan(xn[0] - xo0) or math.isnan(xn[1] - xo1) or math.isnan(xn[2] - xo2):
                moved = np.nan  # np.max propagates NaN
            if ok:
                xc0, xc1, xc2 = xn[0], xn[1], xn[2]
                cost = c_new
                for u in range(3):
                    g[u] = g_new[u]
                    for v in range(3):
                        h[u, v] = h_new[u, v]
                dmp = dmp / 3.0
            else:
                dmp = dmp * 4.0
            if (ok and moved < conv_m) or not (dmp < 1e6):
                live[i] = False
                break
        x[i, 0], x[i, 1], x[i, 2] = xc0, xc1, xc2
        damp[i] = dmp
        cost_out[i] = cost
        evals_out[i] = evals
