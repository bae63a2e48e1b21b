"""Compiled IEKF of the tracker (:func:`iekf_kernel`: the Gauss-Newton loop and Laplace
evidence per hypothesis) and the prior's information matrix (:func:`prior_info_kernel`), with
the 6 x 6 LU (partial pivoting) they share; moved verbatim from
:mod:`diffpos.tracking.model_nb`, whose per-row bodies of the link model and the normal
equations (``_model_row``, ``_terms_row``) they compile in. Held to
``diffpos.tracking.model._iekf_numpy`` / ``_prior_information_numpy`` within a tolerance
(tests/core/test_tracking_kernel.py). numba keys a kernel's cache on its own file: the
``CALLEES_SHA256`` stamp below changes with the code it compiles in.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from diffpos._kernels.npsum_nb import pairwise_sum as _pairwise_sum
from diffpos.paths.model_nb import edge_axis
from diffpos.tracking.model_nb import _OPTS, _model_row, _terms_row

__all__ = ["iekf_kernel", "prior_info_kernel", "warm_iekf"]

#: numba keys this file's on-disk cache on this file only, not on the ``*_nb`` code its
#: kernels compile in: a digest of that code (tests/core/test_kernel_stamps.py names the new
#: value after a callee's edit; writing it here is what invalidates a warm cache).
CALLEES_SHA256 = "77c779cd7459df0a"


#: The IEKF's state dimension (a compile-time constant: the 6 x 6 loops unroll).
_D = 6


@njit(**_OPTS)
def _lu(a, lu, piv):
    """LU factorisation with partial pivoting (as LAPACK's getrf) of the 6 x 6 ``a`` into
    ``lu`` (unit lower and upper triangle), row swaps in ``piv``."""
    d = _D
    for i in range(d):
        for j in range(d):
            lu[i, j] = a[i, j]
    for k in range(d):
        p = k
        big = abs(lu[k, k])
        for i in range(k + 1, d):
            v = abs(lu[i, k])
            if v > big:
                big = v
                p = i
        piv[k] = p
        if p != k:
            for j in range(d):
                t = lu[k, j]
                lu[k, j] = lu[p, j]
                lu[p, j] = t
        u = lu[k, k]
        if u == 0.0:
            continue
        for i in range(k + 1, d):
            f = lu[i, k] / u
            lu[i, k] = f
            for j in range(k + 1, d):
                lu[i, j] -= f * lu[k, j]


@njit(**_OPTS)
def _lu_logdet(lu):
    """``log |det|`` of :func:`_lu`'s factors (-inf if singular, as
    ``numpy.linalg.slogdet``): the log of the pivots' product (one log) unless it leaves
    the normal range, then the sum of their logs."""
    pr = 1.0
    for k in range(_D):
        pr *= abs(lu[k, k])
    if pr > 1e-290 and pr < 1e290:
        return math.log(pr)
    out = 0.0
    for k in range(_D):
        u = abs(lu[k, k])
        out += math.log(u) if u > 0.0 else -np.inf
    return out


@njit(**_OPTS)
def _lu_solve(lu, piv, b):
    """Solve ``a x = b`` in place in ``b`` (6,) from :func:`_lu`'s factors."""
    d = _D
    for k in range(d):
        p = piv[k]
        if p != k:
            t = b[k]
            b[k] = b[p]
            b[p] = t
    for i in range(d):
        acc = b[i]
        for j in range(i):
            acc -= lu[i, j] * b[j]
        b[i] = acc
    for i in range(d - 1, -1, -1):
        acc = b[i]
        for j in range(i + 1, d):
            acc -= lu[i, j] * b[j]
        b[i] = acc / lu[i, i]


@njit(**_OPTS)
def _lu_inv(lu, piv, out, col):
    """``out`` = the inverse of the factorised matrix (column by column; ``col`` (6,) work)."""
    d = _D
    for c in range(d):
        for i in range(d):
            col[i] = 1.0 if i == c else 0.0
        _lu_solve(lu, piv, col)
        for i in range(d):
            out[i, c] = col[i]


@njit(**_OPTS)
def prior_info_kernel(p, y, logdet_y):
    """``tracking_model.prior_information`` per hypothesis: ``y`` (N, H, 6, 6) the inverse of
    ``p`` (LU with partial pivoting) and ``logdet_y`` (N, H) its log-determinant (of ``y``'s
    own LU factors, as the numpy reference's ``slogdet(inv(p))``). Not bit-identical to
    LAPACK (other operation order): the test holds it to numpy's within 1e-12."""
    n_n, n_h = p.shape[:2]
    lu = np.empty((_D, _D))
    piv = np.empty(_D, dtype=np.int64)
    col = np.empty(_D)
    for n in range(n_n):
        for h in range(n_h):
            _lu(p[n, h], lu, piv)
            _lu_inv(lu, piv, y[n, h], col)
            _lu(y[n, h], lu, piv)
            logdet_y[n, h] = _lu_logdet(lu)


@njit(**_OPTS)
def _lu_inv_sym(lu, piv, out, col):
    """:func:`_lu_inv` made symmetric (each off-diagonal pair replaced by its mean), as the
    numpy reference's ``0.5 * (P + P^T)``."""
    _lu_inv(lu, piv, out, col)
    for i in range(_D):
        for j in range(i + 1, _D):
            s = 0.5 * (out[i, j] + out[j, i])
            out[i, j] = s
            out[j, i] = s


@njit(**_OPTS)
def _laplace_log_ev(yy, d, w, e, eb, eh, wh, wb, log2pi, logdet, h_const, log_weight, tmp):
    """:func:`iekf_kernel`'s Laplace log-evidence of one hypothesis at its posterior:
    ``d`` (6,) the posterior minus the prior mean, ``yy`` (6, 6) the prior information,
    ``w``, ``e``, ``log_weight`` (M,) the links' weights, residuals and log-weights, ``eb``
    (3,) / ``eh`` the box and height residuals with weights ``wb`` / ``wh``, ``logdet`` the
    log-determinant of the posterior information minus the prior's, ``h_const`` the height
    mode's log-normaliser; ``tmp`` (M,) work."""
    n_m = w.shape[0]
    quad = 0.0
    for i in range(6):
        acc = 0.0
        for j in range(6):
            acc += yy[i, j] * d[j]
        quad += d[i] * acc
    for m in range(n_m):
        tmp[m] = w[m] * e[m] * e[m]
    quad += _pairwise_sum(tmp, n_m)
    quad += wb * ((eb[0] * eb[0] + eb[1] * eb[1]) + eb[2] * eb[2])
    quad += wh * eh * eh
    # sum of 0.5 (log w - log 2 pi) over the used links: one log of the weights' product
    # while it stays in the normal range, else one log per link
    pr = 1.0
    n_used = 0
    for m in range(n_m):
        if w[m] > 0:
            pr *= w[m]
            n_used += 1
    if pr > 1e-290 and pr < 1e290:
        norm = 0.5 * (math.log(pr) - n_used * log2pi)
    else:
        for m in range(n_m):
            tmp[m] = 0.5 * (math.log(w[m]) - log2pi) if w[m] > 0 else 0.0
        norm = _pairwise_sum(tmp, n_m)
    lw = _pairwise_sum(log_weight, n_m)
    return norm + h_const - 0.5 * quad - 0.5 * logdet + lw


@njit(**_OPTS)
def iekf_kernel(x_prior, y, logdet_y, lo, hi, z_nom, wh, h_const, anchors, floor, slot,
                extra_var, log_weight, rho, var, mask, n_iter, wb, log2pi, first_z, floor_h,
                sill, win_h, x0, x1, depth, x_out, p_out, log_ev, residual):
    """``tracking_model.iekf``'s Gauss-Newton loop and Laplace evidence, one pass per
    hypothesis without temporaries.

    ``x_prior`` (N, H, 6), ``y``/``logdet_y`` its prior information and log-determinant
    (:func:`prior_info_kernel`), ``lo``/``hi`` (N, H, 3) the floor box, ``z_nom``, ``wh``,
    ``h_const`` (N, H) the height prior (nominal height, weight, log-normaliser of the mode),
    ``anchors`` (N, M, 3), ``floor`` (N, H) float64, ``slot``/``extra_var``/``log_weight``
    (N, H, M) the selection, ``rho``/``var``/``mask`` (N, M), ``n_iter`` Gauss-Newton
    iterations, ``wb`` the box weight; writes the posterior ``x_out`` (N, H, 6), ``p_out``
    (N, H, 6, 6), ``log_ev`` (N, H) and ``residual`` (N, H, M) (NaN where no slot).

    The link model and the iteration's terms are :func:`model_kernel`'s and
    :func:`iekf_terms_kernel`'s bodies (bit-identical to the numpy reference); the 6 x 6
    solve, inverse and log-determinant are LU with partial pivoting here, LAPACK's there, and
    the small sums are in another order: the test holds the result to numpy's
    (``tracking_model._iekf_numpy``) within a stated tolerance.
    """
    edge = edge_axis(x0, x1)
    n_n, n_h, n_m = slot.shape
    model = np.empty(n_m)
    jm = np.empty((n_m, 3))
    w = np.empty(n_m)
    e = np.empty(n_m)
    tmp = np.empty(n_m)
    a = np.empty((6, 6))
    lu = np.empty((6, 6))
    piv = np.empty(6, dtype=np.int64)
    col = np.empty(6)
    eb = np.empty(3)
    gpart = np.empty(3)
    xl = np.empty(6)
    g = np.empty(6)
    d = np.empty(6)
    for n in range(n_n):
        for h in range(n_h):
            xp = x_prior[n, h]
            yy = y[n, h]
            for i in range(6):
                xl[i] = xp[i]
            eh = 0.0
            for it in range(n_iter + 1):
                _model_row(xl[0], xl[1], xl[2], anchors[n], floor[n, h], slot[n, h],
                           extra_var[n, h], rho[n], var[n], mask[n], first_z, floor_h, sill,
                           win_h, x0, x1, depth, edge, model, jm, w)
                eh = _terms_row(yy, xl, lo[n, h], hi[n, h], z_nom[n, h], rho[n], model, jm,
                                w, wb, wh[n, h], a, e, eb, gpart)
                if it == n_iter:
                    break
                for i in range(6):
                    d[i] = xl[i] - xp[i]
                for i in range(6):
                    acc = 0.0
                    for j in range(6):
                        acc += yy[i, j] * d[j]
                    g[i] = -acc
                for i in range(3):
                    g[i] += gpart[i]
                g[2] += wh[n, h] * eh
                _lu(a, lu, piv)
                _lu_solve(lu, piv, g)
                for i in range(6):
                    xl[i] = xl[i] + g[i]
            _lu(a, lu, piv)
            logdet_a = _lu_logdet(lu)
            _lu_inv_sym(lu, piv, p_out[n, h], col)
            for i in range(6):
                d[i] = xl[i] - xp[i]
                x_out[n, h, i] = xl[i]
            log_ev[n, h] = _laplace_log_ev(yy, d, w, e, eb, eh, wh[n, h], wb, log2pi,
                                           logdet_a - logdet_y[n, h], h_const[n, h],
                                           log_weight[n, h], tmp)
            for m in range(n_m):
                residual[n, h, m] = e[m] if slot[n, h, m] >= 0 else np.nan


def warm_iekf(planes: tuple, anc: np.ndarray) -> None:
    """Compile (or load from numba's cache) :func:`prior_info_kernel` and :func:`iekf_kernel`
    on tiny inputs (called by :func:`diffpos.tracking.tracker.warm_tracking`)."""
    one, onef = np.ones((1, 1)), np.ones((1, 1, 1))
    mask = np.ones((1, 1), np.bool_)
    i3 = np.zeros((1, 1, 1), np.int64)
    y6 = np.empty((1, 1, 6, 6))
    prior_info_kernel(np.broadcast_to(np.eye(6), (1, 1, 6, 6)).copy(), y6, np.empty((1, 1)))
    x6, p3 = np.ones((1, 1, 6)), np.ones((1, 1, 3))
    iekf_kernel(x6, y6, one, p3, p3, one, one, one, anc, np.zeros((1, 1)), i3, onef, onef, one,
                one, mask, 3, 2500.0, 1.8, *planes, np.empty((1, 1, 6)), np.empty((1, 1, 6, 6)),
                np.empty((1, 1)), np.empty((1, 1, 1)))
