"""Compiled (numba) Levenberg-Marquardt on the upper-edge diffraction model, one problem at a time.

A scalar port of :func:`diffpos.estimators.lm.levenberg_marquardt` (the numpy reference,
batched): the same iteration in ``v = (x, u = y^2, z)``, the same active bound at the wall
plane, the same step control, convergence tests and results. Differences are at the rounding
level only: sums over anchors in another order, and every 3x3 system solved by cofactors (the
reference uses LAPACK for batches of up to 64 problems and cofactors above).

Loss codes: 0 linear, 1 huber, 2 soft_l1 (:data:`LOSS_CODES`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

LOSS_CODES = {"linear": 0, "huber": 1, "soft_l1": 2}

_TINY = np.finfo(np.float64).tiny
_EPS = np.finfo(np.float64).eps


@njit(cache=True, error_model="numpy")
def evaluate(a, used, xn, yn2, zn, yn, in_u, h, elo, ehi, p, jac):
    """Path lengths ``p (M,)`` and Jacobian ``jac (M, 3)`` (in ``u`` if ``in_u``, else in ``y``)
    of the used anchors (the others are left as they are). ``h = 0.5 w - Delta`` [m]."""
    m = a.shape[0]
    r_o2 = yn2 + h * h
    r_o = math.sqrt(r_o2)
    for j in range(m):
        if not used[j]:
            continue
        xa, ya, za = a[j, 0], a[j, 1], a[j, 2]
        dz_out = (zn + h) - za
        r_s = math.sqrt(ya * ya + dz_out * dz_out)
        den = r_s + r_o
        if den > 0.0:
            qx = (xa * r_o + xn * r_s) / den
        else:
            qx = 0.5 * (xa + xn)
        if qx < elo:  # clipped to the edge ends (+-inf: unbounded; NaN stays NaN)
            qx = elo
        elif qx > ehi:
            qx = ehi
        dx_out = qx - xa
        dx_in = xn - qx
        opl = math.sqrt(dx_out * dx_out + r_s * r_s)
        ipl = math.sqrt(dx_in * dx_in + r_o2)
        inv_ipl = 1.0 / ipl
        jac[j, 0] = dx_in * inv_ipl
        jac[j, 1] = 0.5 * inv_ipl if in_u else yn * inv_ipl
        jac[j, 2] = dz_out / opl
        p[j] = opl + ipl


@njit(cache=True, error_model="numpy")
def rho_and_drho(z, loss):
    """``rho(z)`` and ``rho'(z)`` of the squared scaled residual (scipy convention)."""
    if loss == 1:
        if z > 1.0:
            sq = math.sqrt(z)
            return 2.0 * sq - 1.0, 1.0 / max(sq, 1.0)
        return z, 1.0
    if loss == 2:
        t = math.sqrt(1.0 + z)
        return 2.0 * (t - 1.0), 1.0 / t
    return z, 1.0


@njit(cache=True, error_model="numpy")
def cost_of(r, p, sw, used, loss, c):
    """``0.5 c^2 sum rho(((r - p) sw / c)^2)`` over the used anchors."""
    s = 0.0
    for j in range(r.shape[0]):
        if used[j]:
            u = (r[j] - p[j]) * sw[j]
            if loss == 0:
                s += u * u
            else:
                rho, _ = rho_and_drho((u / c) ** 2, loss)
                s += rho
    if loss == 0:
        return 0.5 * s
    return 0.5 * c * c * s


@njit(cache=True, error_model="numpy")
def solve3(a, b, out):
    """Solve the symmetric 3x3 system ``a x = b`` by cofactors (inf/NaN when singular)."""
    a00, a01, a02, a11, a12, a22 = a[0, 0], a[0, 1], a[0, 2], a[1, 1], a[1, 2], a[2, 2]
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    inv_det = 1.0 / det
    b0, b1, b2 = b[0], b[1], b[2]
    out[0] = (c00 * b0 + c01 * b1 + c02 * b2) * inv_det
    out[1] = (c01 * b0 + c11 * b1 + c12 * b2) * inv_det
    out[2] = (c02 * b0 + c12 * b1 + c22 * b2) * inv_det


@njit(cache=True, error_model="numpy")
def _normal_equations(jac, res, sw, used, loss, c, hm, g):
    """``H = J^T W J`` into ``hm``, ``g = J^T W r`` into ``g``; returns ``sum w`` (robust
    losses: IRLS weights ``rho'``)."""
    hm[:, :] = 0.0
    g[:] = 0.0
    wsum = 0.0
    for j in range(res.shape[0]):
        if not used[j]:
            continue
        ws = sw[j]
        if loss != 0:
            _, drho = rho_and_drho((res[j] * sw[j] / c) ** 2, loss)
            ws = sw[j] * math.sqrt(drho)
        wsum += ws * ws
        rw = res[j] * ws
        for i in range(3):
            ji = jac[j, i] * ws
            g[i] += rw * ji
            for k in range(i, 3):
                hm[i, k] += ji * jac[j, k] * ws
    hm[1, 0], hm[2, 0], hm[2, 1] = hm[0, 1], hm[0, 2], hm[1, 2]
    return wsum


@njit(cache=True, error_model="numpy")
def _clamp_to_wall(v, vt, hd, g, inv4, hc, gc, dvc):
    """A step past the wall goes to ``u = 0`` exactly with the damped ``(x, z)`` part re-solved
    for that ``du`` (see ``_core._clamp_to_wall``)."""
    uc = v[1]
    dub = -2.0 * uc / (1.0 + math.sqrt(max(1.0 - 4.0 * uc * inv4, 0.0)))
    for i in range(3):
        gc[i] = g[i] - hd[i, 1] * dub
        for k in range(3):
            hc[i, k] = hd[i, k]
    for i in range(3):
        hc[1, i] = 0.0
        hc[i, 1] = 0.0
    hc[1, 1] = 1.0
    gc[1] = 0.0
    solve3(hc, gc, dvc)
    if np.isfinite(dvc[0]) and np.isfinite(dvc[1]) and np.isfinite(dvc[2]):
        vt[0] = v[0] + dvc[0]
        vt[2] = v[2] + dvc[2]
    vt[1] = 0.0


@njit(cache=True, error_model="numpy")
def _step(v, hm, g, lam, at_wall, inv4, cost, floor, gtol, ws3, vt):
    """Damped LM step and trial point ``vt``; returns ``(stationary, bad, at_wall, dec)``
    (``dec``: the Newton decrement ``g^T H^-1 g``, twice the decrease a Gauss-Newton step
    predicts)."""
    hd, hc, gc, dv, gn = ws3[0], ws3[1], ws3[2, 0], ws3[2, 1], ws3[2, 2]
    if at_wall and v[1] <= 0.0 and g[1] < 0.0:  # active bound: hold u
        for i in range(3):
            hm[1, i] = 0.0
            hm[i, 1] = 0.0
        hm[1, 1] = 1.0
        g[1] = 0.0
    dmax = max(hm[0, 0], hm[1, 1], hm[2, 2])
    for i in range(3):
        for k in range(3):
            hd[i, k] = hm[i, k]
    for i in range(3):
        dh = max(hm[i, i], 1e-12 * dmax + _TINY)
        hd[i, i] += lam * dh
    solve3(hd, g, dv)
    solve3(hm, g, gn)
    dec = g[0] * gn[0] + g[1] * gn[1] + g[2] * gn[2]
    stationary = np.isfinite(dec) and dec <= 2.0 * gtol * cost + 2.0 * floor
    bad = not (np.isfinite(dv[0]) and np.isfinite(dv[1]) and np.isfinite(dv[2]))
    if bad:
        dv[:] = 0.0
    du = dv[1]
    fac = 1.0 + inv4 * du
    vt[0] = v[0] + dv[0]
    vt[1] = v[1] + du * fac
    vt[2] = v[2] + dv[2]
    if vt[1] < 0.0 or fac <= 0.5:
        _clamp_to_wall(v, vt, hd, g, inv4, hc, gc, gn)  # gn is free again
        at_wall = True
    return stationary, bad, at_wall, dec


#: Relative cost decrease of the convergence test (``levenberg_marquardt``'s default ``ftol``).
FTOL = 1e-12
#: Initial damping (``levenberg_marquardt``'s default ``lambda0``).
LAMBDA0 = 1e-4


@njit(cache=True, error_model="numpy")
def lm_fit(a, r, sw, used, x0, h, elo, ehi, loss, c, max_iter, xtol, out_x):
    """One problem: LM from ``x0 (3,)``; writes the solution (``y >= 0``) into ``out_x`` and
    returns ``(cost, iterations, converged)``. A non-finite starting cost returns the start as
    given, unconverged, with 0 iterations (as the reference)."""
    return lm_fit_ftol(a, r, sw, used, x0, h, elo, ehi, loss, c, max_iter, xtol, FTOL, math.inf,
                       0, np.full(1, LAMBDA0), out_x)


@njit(cache=True, error_model="numpy")
def lm_fit_ftol(a, r, sw, used, x0, h, elo, ehi, loss, c, max_iter, xtol, ftol, cost_stop,
                stop_after, lam_io, out_x):
    """:func:`lm_fit` with the relative cost decrease ``ftol`` of its convergence test given
    (``levenberg_marquardt(ftol=...)``; :data:`FTOL` in :func:`lm_fit`), and given up
    (unconverged, where it is) once, after at least ``stop_after`` iterations, the cost a
    Gauss-Newton step predicts from the current point (``cost - dec / 2``) is above
    ``cost_stop`` (``levenberg_marquardt(cost_stop=...)``; inf: never). ``lam_io`` (1,):
    the initial damping on entry (:data:`LAMBDA0`), the damping where it stopped on return
    (given again with ``x0 = out_x``, it continues the same iteration)."""
    gtol, m = 1e-10, r.shape[0]
    bm, bj, b3, bv = np.zeros((3, m)), np.zeros((2, m, 3)), np.zeros((4, 3, 3)), np.zeros((5, 3))
    p, pt, res, jac, jt = bm[0], bm[1], bm[2], bj[0], bj[1]  # 4 allocations, not 11
    ws3, hm = b3[:3], b3[3]
    g, v, vt, x, xt = bv[0], bv[1], bv[2], bv[3], bv[4]
    v[0], v[1], v[2] = x0[0], x0[1] * x0[1], x0[2]
    x[0], x[1], x[2] = x0[0], abs(x0[1]), x0[2]
    evaluate(a, used, v[0], v[1], v[2], 0.0, True, h, elo, ehi, p, jac)
    cost = cost_of(r, p, sw, used, loss, c)
    if not np.isfinite(cost):
        out_x[:] = x0
        return cost, 0, False
    floor = 0.0
    for j in range(m):
        if used[j]:
            e = 64.0 * _EPS * abs(r[j]) * sw[j]
            floor += e * e
            res[j] = r[j] - p[j]
    floor *= 0.5
    lam, at_wall, it = lam_io[0], v[1] <= 0.0, 0
    for _ in range(max_iter):
        wsum = _normal_equations(jac, res, sw, used, loss, c, hm, g)
        inv4 = hm[1, 1] / max(wsum, _TINY)
        stationary, bad, at_wall, dec = _step(v, hm, g, lam, at_wall, inv4, cost, floor, gtol,
                                              ws3, vt)
        if it >= stop_after and cost - 0.5 * dec > cost_stop:
            out_x[:] = x
            lam_io[0] = lam
            return cost, it, False
        xt[0], xt[1], xt[2] = vt[0], math.sqrt(vt[1]), vt[2]
        evaluate(a, used, vt[0], vt[1], vt[2], 0.0, True, h, elo, ehi, pt, jt)
        costt = cost_of(r, pt, sw, used, loss, c)
        c_old = cost
        accept = costt < c_old and not bad
        step2 = (xt[0] - x[0]) ** 2 + (xt[1] - x[1]) ** 2 + (xt[2] - x[2]) ** 2
        if accept:
            v[:], x[:], cost = vt, xt, costt
            p, pt, jac, jt = pt, p, jt, jac
            for j in range(m):
                if used[j]:
                    res[j] = r[j] - p[j]
            lam = max(lam / 3.0, 1e-12)
        else:
            lam = lam * 8.0
        it += 1
        xn = math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2])
        done = stationary or c_old <= floor
        if accept:
            done = done or step2 <= (xtol * (xtol + xn)) ** 2 or c_old - costt <= ftol * c_old
        if done or lam > 1e12:
            out_x[:] = x
            lam_io[0] = lam
            return cost, it, done
    out_x[:] = x
    lam_io[0] = lam
    return cost, it, False
