"""Batched Levenberg-Marquardt core shared by D-NLS and its gating (internal).

All problems of a batch are iterated together: one model evaluation, one batch of 3x3
normal-equation solves per iteration; a problem that has converged (or failed) is frozen and
dropped from the working set, so the cost of an iteration falls as the batch converges.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..geometry import window_edge_path

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

LOSSES = ("linear", "huber", "soft_l1")


@dataclass(frozen=True)
class PathModel:
    """Upper-edge diffraction path model parameters (scalars or per-problem ``(N,)``)."""

    window_height_m: FloatArray | float
    delta_m: FloatArray | float
    edge_x_m: tuple[float, float] | None

    def take(self, idx: NDArray[np.int_]) -> PathModel:
        """The model restricted to problems ``idx`` (per-problem arrays are indexed)."""
        wh = self.window_height_m
        de = self.delta_m
        return PathModel(
            window_height_m=wh[idx] if np.ndim(wh) else wh,
            delta_m=de[idx] if np.ndim(de) else de,
            edge_x_m=self.edge_x_m,
        )

    def repeat(self, k: int) -> PathModel:
        """The model for ``np.repeat(problems, k)`` (each problem repeated ``k`` times)."""
        wh = self.window_height_m
        de = self.delta_m
        return PathModel(
            window_height_m=np.repeat(wh, k) if np.ndim(wh) else wh,
            delta_m=np.repeat(de, k) if np.ndim(de) else de,
            edge_x_m=self.edge_x_m,
        )

    def evaluate(self, anchors_m: FloatArray, x_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Path lengths ``(N, M)`` [m] and Jacobians ``(N, M, 3)`` for nodes ``x_m (N, 3)``."""
        wh = self.window_height_m
        de = self.delta_m
        ep = window_edge_path(
            anchors_m,
            x_m[:, None, :],
            window_height_m=wh[:, None] if np.ndim(wh) else wh,
            delta_m=de[:, None] if np.ndim(de) else de,
            edge_x_m=self.edge_x_m,
        )
        return ep.length_m, ep.jacobian


def robust_rho(z: FloatArray, loss: str) -> tuple[FloatArray, FloatArray]:
    """Loss ``rho(z)`` and ``rho'(z)`` of the squared scaled residual ``z`` (scipy convention).

    ``linear``: ``rho = z``; ``huber``: ``z`` for ``z <= 1`` else ``2 sqrt(z) - 1``;
    ``soft_l1``: ``2 (sqrt(1 + z) - 1)``.
    """
    if loss == "linear":
        return z, np.ones_like(z)
    if loss == "huber":
        big = z > 1.0
        sq = np.sqrt(z)
        with np.errstate(divide="ignore"):
            return np.where(big, 2.0 * sq - 1.0, z), np.where(big, 1.0 / np.maximum(sq, 1.0), 1.0)
    if loss == "soft_l1":
        t = np.sqrt(1.0 + z)
        return 2.0 * (t - 1.0), 1.0 / t
    raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")


def cost_of(residual_m: FloatArray, sw: FloatArray, loss: str, scale: float) -> FloatArray:
    """``0.5 c^2 sum rho((r sw / c)^2)`` per problem; ``sw`` is ``mask / sigma``."""
    u = residual_m * sw
    if loss == "linear":
        return 0.5 * np.einsum("nm,nm->n", u, u)
    z = (u / scale) ** 2
    rho, _ = robust_rho(z, loss)
    return 0.5 * scale * scale * rho.sum(axis=-1)


def solve3(a: FloatArray, b: FloatArray) -> FloatArray:
    """Batched solve of symmetric positive-definite 3x3 systems ``a x = b`` (cofactors).

    Parameters
    ----------
    a : ndarray, shape (N, 3, 3)
    b : ndarray, shape (N, 3)
    """
    a00, a01, a02 = a[:, 0, 0], a[:, 0, 1], a[:, 0, 2]
    a11, a12, a22 = a[:, 1, 1], a[:, 1, 2], a[:, 2, 2]
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = 1.0 / det
        x0 = (c00 * b0 + c01 * b1 + c02 * b2) * inv_det
        x1 = (c01 * b0 + c11 * b1 + c12 * b2) * inv_det
        x2 = (c02 * b0 + c12 * b1 + c22 * b2) * inv_det
    return np.stack([x0, x1, x2], axis=-1)


@dataclass(frozen=True)
class LMResult:
    x_m: FloatArray  # (N, 3)
    cost: FloatArray  # (N,)
    iterations: NDArray[np.int_]  # (N,)
    converged: BoolArray  # (N,)


def levenberg_marquardt(
    anchors_m: FloatArray,
    ranges_m: FloatArray,
    sw: FloatArray,
    x0_m: FloatArray,
    model: PathModel,
    *,
    loss: str = "linear",
    loss_scale: float = 1.0,
    max_iter: int = 50,
    xtol_m: float = 1e-10,
    ftol: float = 1e-12,
    gtol: float = 1e-10,
    lambda0: float = 1e-4,
) -> LMResult:
    """Batched damped Gauss-Newton (Levenberg-Marquardt) on the path model.

    Minimises ``0.5 c^2 sum_j rho(((r_j - p_j(x)) sw_j / c)^2)`` for every problem, with
    Marquardt scaling ``H + lambda diag(H)``; robust losses via iteratively reweighted normal
    equations (weights ``rho'``), the true robust cost deciding step acceptance.

    Convergence (per problem): an accepted step with ``|dx| <= xtol (xtol + |x|)`` or a relative
    cost decrease ``<= ftol``; or a Gauss-Newton predicted decrease (half the Newton decrement
    ``g^T H^-1 g``) below ``gtol`` times the cost (a stationary point, robust to rounding when
    steps can no longer lower the cost); or a zero cost. A problem whose damping exceeds
    ``1e12`` without an accepted step stops unconverged (unless its gradient test passes).
    "Zero cost" means residuals at the rounding level of the ranges (``64 eps |r_j|``).
    """
    n = x0_m.shape[0]
    x = np.array(x0_m, dtype=np.float64, copy=True)
    p, jac = model.evaluate(anchors_m, x)
    res = ranges_m - p
    cost = cost_of(res, sw, loss, loss_scale)
    lam = np.full(n, lambda0)
    iters = np.zeros(n, dtype=np.int_)
    conv = np.zeros(n, dtype=bool)
    active = np.isfinite(cost)
    # cost at the level of floating-point rounding of the ranges: an exact fit
    eps_r = 64.0 * np.finfo(float).eps * np.abs(ranges_m) * sw
    cost_floor = 0.5 * np.einsum("nm,nm->n", eps_r, eps_r)
    tiny = np.finfo(float).tiny
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        a_i = anchors_m[idx]
        r_i = ranges_m[idx]
        sw_i = sw[idx]
        x_i = x[idx]
        res_i = res[idx]
        if loss == "linear":
            ws = sw_i
        else:
            _, drho = robust_rho((res_i * sw_i / loss_scale) ** 2, loss)
            ws = sw_i * np.sqrt(drho)
        jw = jac[idx] * ws[..., None]
        rw = res_i * ws
        h = np.einsum("nmi,nmj->nij", jw, jw)
        g = np.einsum("nmi,nm->ni", jw, rw)
        dh = np.einsum("nii->ni", h)
        dh = np.maximum(dh, 1e-12 * dh.max(axis=-1, keepdims=True) + tiny)
        # Newton decrement of the undamped Gauss-Newton model: twice the cost decrease a full
        # GN step would give. Tiny relative to the cost => stationary point.
        dgn = solve3(h, g)
        dec = np.einsum("ni,ni->n", g, dgn)
        stationary = np.isfinite(dec) & (dec <= 2.0 * gtol * cost[idx] + 2.0 * cost_floor[idx])
        a_mat = h.copy()
        a_mat[:, [0, 1, 2], [0, 1, 2]] += lam[idx, None] * dh
        dx = solve3(a_mat, g)
        bad = ~np.all(np.isfinite(dx), axis=-1)
        dx[bad] = 0.0
        xt = x_i + dx
        pt, jt = model.take(idx).evaluate(a_i, xt)
        rest = r_i - pt
        costt = cost_of(rest, sw_i, loss, loss_scale)
        c_old = cost[idx]
        accept = (costt < c_old) & ~bad & np.isfinite(costt)
        acc_idx = idx[accept]
        x[acc_idx] = xt[accept]
        res[acc_idx] = rest[accept]
        jac[acc_idx] = jt[accept]
        cost[acc_idx] = costt[accept]
        lam[acc_idx] = np.maximum(lam[acc_idx] / 3.0, 1e-12)
        rej_idx = idx[~accept]
        lam[rej_idx] = lam[rej_idx] * 8.0
        iters[idx] += 1
        step = np.sqrt(np.einsum("ni,ni->n", dx, dx))
        xn = np.sqrt(np.einsum("ni,ni->n", x_i, x_i))
        small_step = accept & (step <= xtol_m * (xtol_m + xn))
        small_f = accept & (c_old - costt <= ftol * c_old)
        zero = cost[idx] <= cost_floor[idx]
        done_ok = stationary | small_step | small_f | zero
        failed = ~done_ok & (lam[idx] > 1e12)
        conv[idx] = done_ok
        active[idx[done_ok | failed]] = False
    return LMResult(x_m=x, cost=cost, iterations=iters, converged=conv)
