"""Compiled (numba) D-NLS: the whole fix (pre-gate, starts, screened multi-start LM, RAIM
exclusion, FIM covariance, status) one problem at a time.

The numpy implementation (:mod:`diffpos.estimators.dnls.fit`, :mod:`~diffpos.estimators.gating`,
:mod:`~diffpos.estimators.lm`) is the reference: this is a scalar port of the same steps in
the same order, with the same statuses, used anchors and exclusion reasons
(``tests/core/test_dnls_kernel.py`` compares them on thousands of problems). Results differ at
the rounding level (sums in another order, 3x3 systems by cofactors), which moves positions by
far less than the convergence tolerance.

Entry point: :func:`dnls_batch` (one explicit signature, compiled once and cached on disk by
``cache=True``); :func:`warm_dnls` compiles or loads it. Options travel as two small arrays
(``ipar``, ``fpar``; indices ``I_*`` and ``F_*`` below) so that one signature serves every call.
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit

from diffpos.estimators.lm_nb import (
    FTOL,
    LAMBDA0,
    cost_of,
    evaluate,
    lm_fit,
    lm_fit_ftol,
    solve3,
)

# integer options (ipar)
I_LOSS, I_MAXIT, I_KEEP, I_SCREEN, I_LLS, I_SIGG, I_GATE = 0, 1, 2, 3, 4, 5, 6
I_MAXEXCL, I_MINAFTER, I_PREGATE, I_REFIT, I_MSEXCL, I_ZRANGE, I_POLISH = 7, 8, 9, 10, 11, 12, 13
I_PRUNE_AFTER = 14  # iterations before a candidate's start may be given up
I_LOCAL = 15  # a cold fix's exclusion candidates from their LLS position and the solution only
N_IPAR = 16
# float options (fpar)
F_SCALE, F_XTOL, F_YSTART, F_PGSIG, F_PGMARGIN, F_ZLO, F_ZHI, F_ELO, F_EHI = range(9)
F_CFTOL, F_RECHK, F_PRUNE = 9, 10, 11  # the exclusion candidates' ftol, recheck ratio, bound
N_FPAR = 12

# statuses and exclusion reasons (the values of diffpos.estimators.result's enums)
_OK, _OK_UNVERIFIED, _NOT_CONVERGED, _NOT_IDENTIFIABLE = 0, 1, 2, 3
_TOO_FEW, _GATING_FAILED = 4, 5
_R_NONE, _R_PREGATE, _R_RAIM = 0, 2, 3
_REFIT_XTOL = 1e-10  # the reference's refits use the LM default, not the caller's xtol
_MAX_LLS_CONDITION = 1e8

_JIT = {"cache": True, "error_model": "numpy"}
#: numba keys this file's on-disk cache on this file only, not on the ``*_nb`` code its
#: kernels compile in: a digest of that code (tests/core/test_kernel_stamps.py names the new
#: value after a callee's edit; writing it here is what invalidates a warm cache).
CALLEES_SHA256 = "af625205587de6f6"


@njit(**_JIT)
def _count(used):
    n = 0
    for j in range(used.shape[0]):
        n += used[j]
    return n


@njit(**_JIT)
def _lls_start(a, r, used, fallback, out):
    """The LoS linear least-squares position (first used anchor as reference), ``y`` reflected
    inside and at least 0.5 m deep; ``fallback`` where it is not identifiable."""
    m = r.shape[0]
    n = _count(used)
    ok = False
    if m >= 3 and n >= 3:
        k = 0
        while not used[k]:
            k += 1
        qk = a[k, 0] ** 2 + a[k, 1] ** 2 + a[k, 2] ** 2 - r[k] * r[k]
        amat = np.zeros((m, 3))
        bvec = np.zeros(m)
        for j in range(m):
            if used[j] and j != k:
                for i in range(3):
                    amat[j, i] = 2.0 * (a[j, i] - a[k, i])
                bvec[j] = (a[j, 0] ** 2 + a[j, 1] ** 2 + a[j, 2] ** 2 - r[j] * r[j]) - qk
        u, sv, vt = np.linalg.svd(amat, full_matrices=False)
        cond = sv[0] / sv[2] if sv[2] > 0 else math.inf
        if np.isfinite(cond) and cond < _MAX_LLS_CONDITION:
            ub = (u.T @ bvec) / sv
            for i in range(3):
                out[i] = vt[0, i] * ub[0] + vt[1, i] * ub[1] + vt[2, i] * ub[2]
            ok = True
    if not ok:
        out[:] = fallback
    out[1] = max(abs(out[1]), 0.5)


@njit(**_JIT)
def _starts(a, r, used, x0, has_x0, zs, ipar, fpar, warm, has_warm):
    """Starts ``(S', 3)``: the given ``x0``, or the height grid (x = mean anchor x, y = y_start)
    plus the LLS position; then the warm start if ``has_warm``."""
    if has_x0:
        st = np.empty((1 + has_warm, 3))
        st[0] = x0
    else:
        s = zs.shape[0]
        st = np.empty((s + ipar[I_LLS] + has_warm, 3))
        xm, cnt = 0.0, 0
        for j in range(r.shape[0]):
            if used[j]:
                xm += a[j, 0]
                cnt += 1
        xm /= max(cnt, 1)
        for i in range(s):
            st[i, 0], st[i, 1], st[i, 2] = xm, fpar[F_YSTART], zs[i]
        if ipar[I_LLS]:
            _lls_start(a, r, used, st[s // 2], st[s])
    if has_warm:
        st[st.shape[0] - 1] = warm
    return st


@njit(**_JIT)
def _full(a, r, sw, used, st, h, ipar, fpar, ftol, stop, out_x, out_lam):
    """Every start to convergence (relative cost decrease ``ftol``; given up above ``stop``,
    see ``lm_fit_ftol``), the lowest finite cost kept: ``(cost, iterations, conv)``, its
    solution in ``out_x`` and its final damping in ``out_lam[0]``."""
    best_c, best = math.inf, (math.nan, 0, False)
    xi = np.empty(3)
    lam = np.empty(1)
    for i in range(st.shape[0]):
        lam[0] = LAMBDA0
        res = lm_fit_ftol(a, r, sw, used, st[i], h, fpar[F_ELO], fpar[F_EHI], ipar[I_LOSS],
                          fpar[F_SCALE], ipar[I_MAXIT], fpar[F_XTOL], ftol, stop,
                          ipar[I_PRUNE_AFTER], lam, xi)
        c = res[0] if np.isfinite(res[0]) else math.inf
        if i == 0 or c < best_c:
            best_c, best = c, res
            out_x[:] = xi
            out_lam[0] = lam[0]
    return best


@njit(**_JIT)
def multistart(a, r, sw, used, st, h, ipar, fpar, recheck_dof, thr_re, ftol, stop, out_x,
               out_lam):
    """Screened multi-start as ``_dnls_fit.multistart_fit`` for one problem (the starts
    iterated to a relative cost decrease ``ftol``; after the screening, given up above the
    cost ``stop``: ``lm_fit_ftol``).

    ``recheck_dof < 0``: no noise model, every screened fix is re-solved from all starts.
    ``out_lam[0]``: the final damping of the start kept.
    """
    s, keep, screen, maxit = st.shape[0], ipar[I_KEEP], ipar[I_SCREEN], ipar[I_MAXIT]
    if keep < 0 or s <= keep or maxit <= screen:
        return _full(a, r, sw, used, st, h, ipar, fpar, ftol, stop, out_x, out_lam)
    elo, ehi, loss, sc, xtol = fpar[F_ELO], fpar[F_EHI], ipar[I_LOSS], fpar[F_SCALE], fpar[F_XTOL]
    scr_x = np.empty((s, 3))
    scr_c = np.empty(s)
    scr_it = np.empty(s, np.int64)
    lam = np.empty(1)
    for i in range(s):
        lam[0] = LAMBDA0
        c, it, _ = lm_fit_ftol(a, r, sw, used, st[i], h, elo, ehi, loss, sc, screen, xtol, ftol,
                               math.inf, 0, lam, scr_x[i])
        scr_c[i] = c if np.isfinite(c) else math.inf
        scr_it[i] = it
    order = np.argsort(scr_c, kind="mergesort")[:keep]
    best_c, best = math.inf, (math.nan, 0, False)
    xi = np.empty(3)
    for kk in range(keep):
        i = order[kk]
        lam[0] = LAMBDA0  # the continuation starts afresh (as the reference's second call)
        c, it, cv = lm_fit_ftol(a, r, sw, used, scr_x[i], h, elo, ehi, loss, sc, maxit - screen,
                                xtol, ftol, stop, ipar[I_PRUNE_AFTER], lam, xi)
        cf = c if np.isfinite(c) else math.inf
        if kk == 0 or cf < best_c:
            best_c, best = cf, (c, scr_it[i] + it, cv)
            out_x[:] = xi
            out_lam[0] = lam[0]
    cost = best[0]
    if recheck_dof < 0:
        redo = True
    else:
        thr = thr_re[max(recheck_dof, 0)]
        redo = (not np.isfinite(cost)) or (recheck_dof >= 1 and 2.0 * cost > thr)
    if redo:
        x2, lam2 = np.empty(3), np.empty(1)
        full = _full(a, r, sw, used, st, h, ipar, fpar, ftol, stop, x2, lam2)
        if full[0] < cost:
            out_x[:] = x2
            out_lam[0] = lam2[0]
            return full
    return best


@njit(**_JIT)
def _t_stat(a, r, sw, used, x, h, elo, ehi, p, jac):
    """``sum ((r - p(x)) sw)^2`` over ``used`` at ``x = (x, y, z)``."""
    evaluate(a, used, x[0], x[1] * x[1], x[2], x[1], False, h, elo, ehi, p, jac)
    t = 0.0
    for j in range(r.shape[0]):
        if used[j]:
            e = (r[j] - p[j]) * sw[j]
            t += e * e
    return t


@njit(**_JIT)
def _los(a, j, x):
    return math.sqrt((x[0] - a[j, 0]) ** 2 + (x[1] - a[j, 1]) ** 2 + (x[2] - a[j, 2]) ** 2)


@njit(**_JIT)
def _pregate_tol(ipar, fpar, sig_j):
    """``k sigma_j + margin`` [m], or -1 when the pre-gate is off."""
    if not ipar[I_PREGATE] or not (ipar[I_SIGG] or fpar[F_PGMARGIN] > 0):
        return -1.0
    return fpar[F_PGSIG] * (sig_j if ipar[I_SIGG] else 0.0) + fpar[F_PGMARGIN]


@njit(**_JIT)
def _candidates(a, r, sig, sw, used, x, h, x0, has_x0, zs, ipar, fpar, thr_fa, thr_re, xc, ic, vc):
    """Every leave-one-out candidate of a failing fix solved (multi-start plus the warm start
    ``x``, or warm refits only); returns each candidate's test statistic (inf: not a candidate).

    ``I_POLISH`` (``dnls(exclusion_ftol=...)``): the multi-start candidates are solved to the
    loose relative cost decrease ``F_CFTOL``, which is enough to rank them, and the best one
    is then iterated on to the full convergence test. ``F_PRUNE`` finite
    (``dnls(exclusion_bound=...)``, linear loss): the candidate the linearised leave-one-out
    statistic (:func:`_loo_order`) ranks first is solved first, and the others' starts are
    given up once a Gauss-Newton step from where they are would leave their cost above
    ``F_PRUNE`` times its cost (``_dnls_fit._solve_candidates``). ``I_LOCAL``: a cold fix's
    candidates from their own LLS position and ``x`` only (:func:`_candidate_starts`; with
    fewer starts than ``I_KEEP`` nothing is screened, so nothing is rechecked)."""
    m = r.shape[0]
    tc = np.full(m, math.inf)
    cu = used.copy()
    cc = np.full(m, math.inf)
    p, jac = np.zeros(m), np.zeros((m, 3))
    ms = ipar[I_MSEXCL] != 0
    prune = ms and ipar[I_LOSS] == 0 and np.isfinite(fpar[F_PRUNE])
    order = _loo_order(a, r, sw, used, x, h, fpar, p, jac) if prune else np.arange(m)
    stop = math.inf
    lc = np.full(m, LAMBDA0)  # each candidate's final damping (the polish continues it)
    n_st = 0
    for jj in range(m):
        j = order[jj]
        xc[j] = x
        ic[j], vc[j] = 0, False
        if ms and not used[j]:
            continue
        cu[:] = used
        cu[j] = False
        if ms:
            st = _candidate_starts(a, r, cu, x0, has_x0, zs, ipar, fpar, x)
            n_st = st.shape[0]
            cc[j], ic[j], vc[j] = multistart(a, r, sw, cu, st, h, ipar, fpar, 0, thr_re,
                                             fpar[F_CFTOL], stop, xc[j], lc[j:j + 1])
            if prune and jj == 0 and np.isfinite(cc[j]):
                stop = fpar[F_PRUNE] * cc[j]
        else:
            _, ic[j], vc[j] = lm_fit(a, r, sw, cu, x, h, fpar[F_ELO], fpar[F_EHI], ipar[I_LOSS],
                                     fpar[F_SCALE], ipar[I_REFIT], _REFIT_XTOL, xc[j])
    if ms and ipar[I_KEEP] >= 0 and n_st > ipar[I_KEEP]:
        _recheck_candidates(a, r, sw, used, h, x0, has_x0, zs, ipar, fpar, thr_fa, x, cc, xc, ic, vc,
                            lc)
    for j in range(m):
        if used[j]:
            xc[j, 1] = abs(xc[j, 1])
            cu[:] = used
            cu[j] = False
            tc[j] = _t_stat(a, r, sw, cu, xc[j], h, fpar[F_ELO], fpar[F_EHI], p, jac)
    if ms and ipar[I_POLISH]:
        _polish_best(a, r, sw, used, h, ipar, fpar, tc, xc, ic, vc, lc, p, jac)
    return tc


@njit(**_JIT)
def _candidate_starts(a, r, cu, x0, has_x0, zs, ipar, fpar, x):
    """The starts of the candidate on anchors ``cu``: those of the first fit (the given
    start, or the height grid and the LLS position) plus the current solution ``x``. With
    ``I_LOCAL`` (``dnls(exclusion_starts="local")``) and no given start: the candidate's own
    LLS position (if ``I_LLS``; ``x`` where it is not identifiable) and ``x`` only."""
    if has_x0 or not ipar[I_LOCAL]:
        return _starts(a, r, cu, x0, has_x0, zs, ipar, fpar, x, True)
    st = np.empty((1 + ipar[I_LLS], 3))
    if ipar[I_LLS]:
        _lls_start(a, r, cu, x, st[0])
    st[st.shape[0] - 1] = x
    return st


@njit(**_JIT)
def _loo_order(a, r, sw, used, x, h, fpar, p, jac):
    """The anchors by the linearised leave-one-out statistic at ``x`` (ascending; stable,
    unused anchors last): ``T - w_j e_j^2 / (1 - h_jj)`` with ``T`` the statistic of ``used``
    and ``h_jj`` the leverage of anchor ``j`` (-inf where ``1 - h_jj <= 1e-12``)."""
    m = r.shape[0]
    evaluate(a, used, x[0], x[1] * x[1], x[2], x[1], False, h, fpar[F_ELO], fpar[F_EHI], p, jac)
    hm = np.zeros((3, 3))
    t = 0.0
    for j in range(m):
        if used[j]:
            e = (r[j] - p[j]) * sw[j]
            t += e * e
            for i in range(3):
                for k in range(3):
                    hm[i, k] += jac[j, i] * jac[j, k] * sw[j] * sw[j]
    pred = np.full(m, math.inf)
    q, ji = np.empty(3), np.empty(3)
    for j in range(m):
        if used[j]:
            for i in range(3):
                ji[i] = jac[j, i] * sw[j]
            solve3(hm, ji, q)
            one_minus = 1.0 - (ji[0] * q[0] + ji[1] * q[1] + ji[2] * q[2])
            e = (r[j] - p[j]) * sw[j]
            pred[j] = t - e * e / one_minus if one_minus > 1e-12 else -math.inf
    return np.argsort(pred, kind="mergesort")


@njit(**_JIT)
def _polish_best(a, r, sw, used, h, ipar, fpar, tc, xc, ic, vc, lc, p, jac):
    """The candidate with the smallest statistic iterated on from its loose solution to the
    full convergence test: the same iteration continued (its damping ``lc``, the iterations
    its start had left of ``I_MAXIT``); its statistic updated."""
    j = np.argmin(tc)
    if not np.isfinite(tc[j]):
        return
    cu = used.copy()
    cu[j] = False
    xi = np.empty(3)
    budget = max(ipar[I_MAXIT] - ic[j], 0)  # the iterations its start had left
    _, it, cv = lm_fit_ftol(a, r, sw, cu, xc[j], h, fpar[F_ELO], fpar[F_EHI], ipar[I_LOSS],
                            fpar[F_SCALE], budget, fpar[F_XTOL], FTOL, math.inf, 0, lc[j:j + 1],
                            xi)
    xc[j] = xi
    xc[j, 1] = abs(xc[j, 1])
    ic[j] += it
    vc[j] = cv
    tc[j] = _t_stat(a, r, sw, cu, xc[j], h, fpar[F_ELO], fpar[F_EHI], p, jac)


@njit(**_JIT)
def _recheck_candidates(a, r, sw, used, h, x0, has_x0, zs, ipar, fpar, thr_fa, x, cc, xc, ic, vc,
                        lc):
    """If no screened candidate passes the residual test, but one comes within ``F_RECHK``
    times its threshold (inf: always), re-solve every candidate from all starts (no
    screening) and keep the better answers."""
    m = r.shape[0]
    dof_c = _count(used) - 1 - 3
    if dof_c >= 1:
        near = not np.isfinite(fpar[F_RECHK])  # inf: the exhaustive search
        for j in range(m):
            if used[j] and 2.0 * cc[j] <= thr_fa[dof_c]:
                return
            if used[j] and 2.0 * cc[j] <= fpar[F_RECHK] * thr_fa[dof_c]:
                near = True
        if not near:
            return
    elif np.isfinite(fpar[F_RECHK]):  # no threshold to come near
        return
    cu = used.copy()
    x2, lam2 = np.empty(3), np.empty(1)
    for j in range(m):
        if not used[j]:
            continue
        cu[:] = used
        cu[j] = False
        st = _starts(a, r, cu, x0, has_x0, zs, ipar, fpar, x, True)
        c2, i2, v2 = _full(a, r, sw, cu, st, h, ipar, fpar, fpar[F_CFTOL], math.inf, x2, lam2)
        if c2 < cc[j]:
            xc[j] = x2
            ic[j], vc[j] = i2, v2
            lc[j] = lam2[0]


@njit(**_JIT)
def _check(a, r, sig, sw, used, x, h, ipar, fpar, thr_fa, can_exclude, p, jac):
    """Post-fit pre-gate and chi-square test: ``(fail, testable, raim, pg_excl, pg_j)``."""
    m, n = r.shape[0], _count(used)
    t = _t_stat(a, r, sw, used, x, h, fpar[F_ELO], fpar[F_EHI], p, jac)
    pg_j, worst_max = 0, -math.inf
    for j in range(m):
        tol = _pregate_tol(ipar, fpar, sig[j])
        if used[j] and tol >= 0.0:
            d = _los(a, j, x) - r[j]
            if d - tol > 0:
                wv = d / (sig[j] if ipar[I_SIGG] else 1.0)
                if wv > worst_max:
                    worst_max, pg_j = wv, j
    pg_excl = np.isfinite(worst_max) and n - 1 >= 3 and can_exclude
    dof = n - 3
    testable = dof >= 1 and ipar[I_SIGG] != 0
    fail = testable and t > thr_fa[max(dof, 0)]
    raim = fail and n - 1 >= ipar[I_MINAFTER] and can_exclude
    return fail, testable, raim, pg_excl and not fail, pg_j


@njit(**_JIT)
def _confirm_pregate(a, r, sig, sw, used, reason, x, it_cv, h, ipar, fpar, j):
    """Refit without anchor ``j``; keep the exclusion only if its range is also impossible at
    the new solution. Returns whether it was confirmed (``used``/``reason`` updated)."""
    used[j] = False
    xf = np.empty(3)
    _, it, cv = lm_fit(a, r, sw, used, x, h, fpar[F_ELO], fpar[F_EHI], ipar[I_LOSS],
                       fpar[F_SCALE], ipar[I_REFIT], _REFIT_XTOL, xf)
    tol_j = fpar[F_PGSIG] * (sig[j] if ipar[I_SIGG] else 0.0)
    if r[j] < _los(a, j, xf) - tol_j - fpar[F_PGMARGIN]:
        x[:] = xf
        it_cv[0], it_cv[1] = it, cv
        reason[j] = _R_PREGATE
        return True
    used[j] = True
    return False


@njit(**_JIT)
def gate_fix(a, r, sig, sw, used, reason, x, it_cv, h, x0, has_x0, zs, ipar, fpar, thr_fa,
             thr_re):
    """Pre-gate and RAIM rounds of one fix (``gating.run_gating``); updates ``used``,
    ``reason``, ``x`` and ``it_cv``; returns ``(gating_failed, tested)``."""
    m = r.shape[0]
    p, jac = np.zeros(m), np.zeros((m, 3))
    xc, ic, vc = np.empty((m, 3)), np.zeros(m, np.int64), np.zeros(m, np.bool_)
    n_excl, failed, tested = 0, False, False
    for _ in range(ipar[I_MAXEXCL] + 1):
        can = n_excl < ipar[I_MAXEXCL]
        fail, tested, raim, pg, pg_j = _check(a, r, sig, sw, used, x, h, ipar, fpar, thr_fa,
                                              can, p, jac)
        if not pg and not raim:
            return fail, tested
        if raim:
            tc = _candidates(a, r, sig, sw, used, x, h, x0, has_x0, zs, ipar, fpar, thr_fa,
                             thr_re, xc, ic, vc)
            best = np.argmin(tc)
            x[:] = xc[best]
            it_cv[0], it_cv[1] = ic[best], vc[best]
            used[best] = False
            reason[best] = _R_RAIM
        elif not _confirm_pregate(a, r, sig, sw, used, reason, x, it_cv, h, ipar, fpar, pg_j):
            return fail, tested
        n_excl += 1
    # the exclusion limit is reached: the final test on the final anchor set decides
    n = _count(used)
    t = _t_stat(a, r, sw, used, x, h, fpar[F_ELO], fpar[F_EHI], p, jac)
    tested = n - 3 >= 1 and ipar[I_SIGG] != 0
    failed = tested and t > thr_fa[max(n - 3, 0)]
    return failed, tested


@njit(**_JIT)
def _covariance(jac, sig, used, cov):
    """Inverse FIM of the used anchors into ``cov``; returns identifiable
    (``bounds.bounds_from_fim``: closed form when safely conditioned, else eigenvalues)."""
    f = np.zeros((3, 3))
    for j in range(sig.shape[0]):
        if used[j]:
            w = 1.0 / (sig[j] * sig[j])
            for i in range(3):
                for k in range(3):
                    f[i, k] += jac[j, i] * w * jac[j, k]
    a, d, g = f[0, 0], f[1, 1], f[2, 2]
    b, c, e = 0.5 * (f[0, 1] + f[1, 0]), 0.5 * (f[0, 2] + f[2, 0]), 0.5 * (f[1, 2] + f[2, 1])
    c00, c01, c02 = d * g - e * e, c * e - b * g, b * e - c * d
    c11, c12, c22 = a * g - c * c, b * c - a * e, a * d - b * b
    det = a * c00 + b * c01 + c * c02
    fro = math.sqrt(a * a + d * d + g * g + 2.0 * (b * b + c * c + e * e))
    if det > 1e-6 * fro**3:
        adj = np.array([[c00, c01, c02], [c01, c11, c12], [c02, c12, c22]])
        cov[:, :] = adj / det
        return True
    if not np.all(np.isfinite(f)):
        cov[:, :] = math.inf
        return False
    eig = np.linalg.eigvalsh(f)
    if eig[2] > 0.0 and eig[0] > eig[2] / 1e12:
        cov[:, :] = np.linalg.inv(f)
        return True
    cov[:, :] = math.inf
    return False


@njit(**_JIT)
def _status(x, tested, failed, converged, identifiable, n_used, ipar, fpar):
    """Status of a solved fix; later rules override earlier ones (``_dnls_fit._fix_status``)."""
    st = _OK if tested else _OK_UNVERIFIED
    if failed:
        st = _GATING_FAILED
    if ipar[I_GATE] and ipar[I_ZRANGE] and st == _OK:
        if x[2] < fpar[F_ZLO] or x[2] > fpar[F_ZHI]:
            st = _GATING_FAILED
    if not converged:
        st = _NOT_CONVERGED
    if not identifiable:
        st = _NOT_IDENTIFIABLE
    if n_used < 3:
        st = _TOO_FEW
    return st


@njit(**_JIT)
def _final(b, a, r, sig, sw, used, x, h, ipar, fpar, thr_fa, out_f, cov, resid):
    """Residuals, FIM covariance (scaled by the a-posteriori variance factor without sigmas),
    test statistic and cost of fix ``b``: ``out_f[b] = (peb, z bound, statistic, threshold,
    cost)``; returns identifiable."""
    m = r.shape[0]
    p, jac = np.zeros(m), np.zeros((m, 3))
    evaluate(a, used, x[0], x[1] * x[1], x[2], x[1], False, h, fpar[F_ELO], fpar[F_EHI], p, jac)
    ident = _covariance(jac, sig, used, cov[b])
    n = _count(used)
    t, ssr = 0.0, 0.0
    for j in range(m):
        if used[j]:
            e = r[j] - p[j]
            resid[b, j] = e
            t += (e * sw[j]) ** 2
            ssr += e * e
    if not ipar[I_SIGG]:
        cov[b] *= ssr / (n - 3) if n > 3 else 1.0
    out_f[b, 0] = math.sqrt(cov[b, 0, 0] + cov[b, 1, 1] + cov[b, 2, 2])
    out_f[b, 1] = math.sqrt(cov[b, 2, 2])
    out_f[b, 2] = t if ipar[I_SIGG] else math.nan
    out_f[b, 3] = thr_fa[max(n - 3, 0)] if ipar[I_GATE] and ipar[I_SIGG] else math.nan
    out_f[b, 4] = cost_of(r, p, sw, used, ipar[I_LOSS], fpar[F_SCALE])
    return ident


@njit(**_JIT)
def _wall_pregate(a, r, sig, used, reason, ipar, fpar):
    """Before the fit: drop ranges shorter than the anchor's distance to the wall."""
    if not ipar[I_GATE]:
        return
    for j in range(r.shape[0]):
        tol = _pregate_tol(ipar, fpar, sig[j])
        if used[j] and tol >= 0.0 and r[j] < abs(a[j, 1]) - tol:
            used[j] = False
            reason[j] = _R_PREGATE


@njit(**_JIT)
def solve_fix(b, a, r, sig, mask, h, x0, has_x0, zs, ipar, fpar, thr_fa, thr_re, pos, cov,
              out_i, out_f, resid, used_out, reason_out):
    """Fix ``b``: wall pre-gate, multi-start fit, gating, final fields (``_dnls_fit.solve_chunk``).
    ``out_i[b] = (iterations, converged, status, dof)``."""
    used = mask.copy()
    reason = reason_out[b]
    _wall_pregate(a, r, sig, used, reason, ipar, fpar)
    n = _count(used)
    if n < 3:
        return
    sw = 1.0 / sig
    x = np.empty(3)
    st = _starts(a, r, used, x0, has_x0, zs, ipar, fpar, x0, False)
    _, it, cv = multistart(a, r, sw, used, st, h, ipar, fpar, n - 3 if ipar[I_SIGG] else -1,
                           thr_re, FTOL, math.inf, x, np.empty(1))
    x[1] = abs(x[1])
    it_cv = np.array([it, cv], np.int64)
    failed, tested = False, False
    if ipar[I_GATE]:
        failed, tested = gate_fix(a, r, sig, sw, used, reason, x, it_cv, h, x0, has_x0, zs,
                                  ipar, fpar, thr_fa, thr_re)
        x[1] = abs(x[1])
    ident = _final(b, a, r, sig, sw, used, x, h, ipar, fpar, thr_fa, out_f, cov, resid)
    n = _count(used)
    pos[b] = x
    used_out[b] = used
    out_i[b, 0], out_i[b, 1] = it_cv[0], it_cv[1]
    out_i[b, 2] = _status(x, tested, failed, it_cv[1] != 0, ident, n, ipar, fpar)
    out_i[b, 3] = n - 3


_SIG = (
    "void(f8[:, :, ::1], f8[:, ::1], f8[:, ::1], b1[:, ::1], f8[::1], f8[:, ::1], b1[::1], "
    "f8[::1], i8[::1], f8[::1], f8[::1], f8[::1], f8[:, ::1], f8[:, :, ::1], i8[:, ::1], "
    "f8[:, ::1], f8[:, ::1], b1[:, ::1], i8[:, ::1])"
)


@njit(_SIG, **_JIT)
def dnls_batch(a, r, sig, mask, h, x0, has_x0, zs, ipar, fpar, thr_fa, thr_re, pos, cov, out_i,
               out_f, resid, used_out, reason_out):
    """Every fix of a batch (see :func:`solve_fix`); outputs pre-filled by the caller with the
    values of an unsolved fix (NaN, 0, ``TOO_FEW_ANCHORS``)."""
    for b in range(r.shape[0]):
        solve_fix(b, a[b], r[b], sig[b], mask[b], h[b], x0[b], has_x0[b], zs, ipar, fpar,
                  thr_fa, thr_re, pos, cov, out_i, out_f, resid, used_out, reason_out)


def options(*, loss: int, loss_scale: float, max_iter: int, xtol: float, keep_starts: int | None,
            screen_iter: int, lls_start: bool, sigmas_given: bool, y_start: float,
            edge_x_m: tuple[float, float] | None, gating, exclusion_ftol: float | None = None,
            recheck_ratio: float | None = None, bound: float | None = None,
            bound_after: int = 0, local_starts: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(ipar, fpar)`` of :func:`dnls_batch` from the validated options of ``dnls``
    (``gating``: a ``GatingConfig`` or None; ``exclusion_ftol``, ``recheck_ratio``: ``dnls``'s
    ``exclusion_ftol``, ``exclusion_recheck_ratio`` and ``exclusion_bound`` with
    ``EXCLUSION_BOUND_AFTER``, None: the exhaustive search; ``local_starts``:
    ``exclusion_starts="local"``)."""
    ipar = np.zeros(N_IPAR, np.int64)
    fpar = np.zeros(N_FPAR)
    ipar[I_POLISH] = exclusion_ftol is not None
    fpar[F_CFTOL] = FTOL if exclusion_ftol is None else exclusion_ftol
    fpar[F_RECHK] = math.inf if recheck_ratio is None else recheck_ratio
    fpar[F_PRUNE] = math.inf if bound is None else bound
    ipar[I_PRUNE_AFTER] = bound_after
    ipar[I_LOCAL] = bool(local_starts)
    ipar[I_LOSS], ipar[I_MAXIT], ipar[I_SCREEN] = loss, max_iter, screen_iter
    ipar[I_KEEP] = -1 if keep_starts is None else keep_starts
    ipar[I_LLS], ipar[I_SIGG] = bool(lls_start), bool(sigmas_given)
    fpar[F_SCALE], fpar[F_XTOL], fpar[F_YSTART] = loss_scale, xtol, y_start
    fpar[F_ELO], fpar[F_EHI] = (-math.inf, math.inf) if edge_x_m is None else edge_x_m
    if gating is not None:
        ipar[I_GATE], ipar[I_MAXEXCL] = 1, gating.max_exclusions
        ipar[I_MINAFTER], ipar[I_PREGATE] = gating.min_anchors_after_exclusion, gating.pregate
        ipar[I_REFIT], ipar[I_MSEXCL] = gating.refit_max_iter, gating.multistart_exclusion
        fpar[F_PGSIG], fpar[F_PGMARGIN] = gating.pregate_sigmas, gating.pregate_margin_m
        if gating.z_range_m is not None:
            ipar[I_ZRANGE] = 1
            fpar[F_ZLO], fpar[F_ZHI] = gating.z_range_m
    return ipar, fpar


def run(a, r, sig, mask, h, x0, has_x0, zs, ipar, fpar, thr_fa, thr_re) -> dict[str, np.ndarray]:
    """Solve a prepared batch (C-contiguous arrays of the signature's types) with
    :func:`dnls_batch`; returns the output arrays by the names of ``dnls``'s ``_alloc``."""
    bsz, m = r.shape
    pos = np.full((bsz, 3), np.nan)
    cov = np.full((bsz, 3, 3), np.nan)
    out_i = np.zeros((bsz, 4), np.int64)
    out_i[:, 2] = _TOO_FEW
    out_f = np.full((bsz, 5), np.nan)
    resid = np.full((bsz, m), np.nan)
    used = np.zeros((bsz, m), np.bool_)
    reason = np.zeros((bsz, m), np.int64)
    dnls_batch(a, r, sig, mask, h, x0, has_x0, zs, ipar, fpar, thr_fa, thr_re, pos, cov, out_i,
               out_f, resid, used, reason)
    return {
        "position_m": pos, "covariance_m2": cov, "peb_m": out_f[:, 0], "z_bound_m": out_f[:, 1],
        "iterations": out_i[:, 0], "converged": out_i[:, 1].astype(bool), "status": out_i[:, 2],
        "residuals_m": resid, "used": used, "exclusion_reason": reason,
        "test_statistic": out_f[:, 2], "test_threshold": out_f[:, 3], "dof": out_i[:, 3],
        "cost": out_f[:, 4],
    }


def warm_dnls() -> float:
    """Compile :func:`dnls_batch` (or load it from numba's on-disk cache) and run it once on
    a tiny problem, so that the first real fix pays no compilation. Returns the seconds it took
    (first time on a machine: tens of seconds of CPU; from the cache: under a second)."""
    t0 = time.perf_counter()
    a = np.array([[[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0],
                   [15.0, -20.0, 1.0], [5.0, -10.0, 12.0]]])
    r = np.array([[23.0, 17.0, 13.0, 24.0, 14.0]])
    ipar, fpar = options(loss=0, loss_scale=1.5, max_iter=50, xtol=1e-10, keep_starts=3,
                         screen_iter=4, lls_start=True, sigmas_given=True, y_start=3.0,
                         edge_x_m=None, gating=None)
    ipar[I_GATE] = 1
    thr = np.full(6, 10.0)
    run(a, r, np.full((1, 5), 0.1), np.ones((1, 5), bool), np.array([0.5]), np.zeros((1, 3)),
        np.zeros(1, bool), np.arange(0.0, 31.0, 3.0), ipar, fpar, thr, thr)
    return time.perf_counter() - t0
