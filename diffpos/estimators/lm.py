"""Batched Levenberg-Marquardt core shared by D-NLS and its gating (internal).

All problems of a batch are iterated together: one model evaluation, one batch of 3x3
normal-equation solves per iteration (plus one for the few steps that reach the wall plane);
a problem that has converged (or failed) is frozen and dropped from the working set, so the
cost of an iteration falls as the batch converges. The depth is iterated as ``u = y^2 >= 0``
(see :func:`levenberg_marquardt`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from diffpos.sym3 import solve3

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

LOSSES = ("linear", "huber", "soft_l1")


@dataclass(frozen=True)
class PathModel:
    """Upper-edge diffraction path model parameters (scalars or per-problem ``(N,)``)."""

    window_height_m: FloatArray | float
    delta_m: FloatArray | float
    edge_x_m: tuple[float, float] | None

    @functools.cached_property
    def edge_offset_m(self) -> FloatArray | float:
        """Height of the upper edge above the node, ``0.5 w - Delta`` [m] (``(N, 1)`` or scalar)."""
        wh = self.window_height_m
        de = self.delta_m
        if isinstance(wh, np.ndarray) or isinstance(de, np.ndarray):
            return (0.5 * np.asarray(wh) - np.asarray(de)).reshape(-1, 1)
        return 0.5 * wh - de

    def take(self, idx: NDArray[np.int_]) -> PathModel:
        """The model restricted to problems ``idx`` (per-problem arrays are indexed)."""
        wh = self.window_height_m
        de = self.delta_m
        return PathModel(
            window_height_m=wh[idx] if isinstance(wh, np.ndarray) else wh,
            delta_m=de[idx] if isinstance(de, np.ndarray) else de,
            edge_x_m=self.edge_x_m,
        )

    def repeat(self, k: int) -> PathModel:
        """The model for ``np.repeat(problems, k)`` (each problem repeated ``k`` times)."""
        wh = self.window_height_m
        de = self.delta_m
        return PathModel(
            window_height_m=np.repeat(wh, k) if isinstance(wh, np.ndarray) else wh,
            delta_m=np.repeat(de, k) if isinstance(de, np.ndarray) else de,
            edge_x_m=self.edge_x_m,
        )

    def evaluate(self, anchors_m: FloatArray, x_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Path lengths ``(N, M)`` [m] and Jacobians ``(N, M, 3)`` for nodes ``x_m (N, 3)``.

        The same formulas as :func:`diffpos.geometry.window_edge_path` (upper edge), fused
        into the few operations the solver needs (no diffraction point, no edge flags).
        ``tests/test_dnls.py`` checks it against ``window_edge_path``. The Jacobian is with
        respect to ``(x, y, z)`` [m/m].
        """
        yn = x_m[:, 1:2]
        return self._evaluate(anchors_m, x_m[:, 0:1], yn * yn, x_m[:, 2:3], yn)

    def evaluate_u(self, anchors_m: FloatArray, v_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Path lengths ``(N, M)`` [m] and Jacobians ``(N, M, 3)`` in ``v = (x, u = y^2, z)``.

        The model depends on the depth ``y`` only through ``u = y^2``; in ``u`` it is smooth
        and non-degenerate at the wall plane ``u = 0``: ``dp/du = 1 / (2 ipl)`` [1/m] (the
        diffraction point is optimal, so its own dependence on ``u`` drops out, also when
        it is clipped to the edge ends). This is what the hot loop of
        :func:`levenberg_marquardt` calls, once per iteration.

        Parameters
        ----------
        anchors_m : ndarray, shape (N, M, 3) [m]
        v_m : ndarray, shape (N, 3)
            ``(x [m], u [m^2], z [m])`` with ``u >= 0``.
        """
        return self._evaluate(anchors_m, v_m[:, 0:1], v_m[:, 1:2], v_m[:, 2:3], None)

    def _evaluate(
        self,
        anchors_m: FloatArray,
        xn: FloatArray,
        yn2: FloatArray,
        zn: FloatArray,
        yn: FloatArray | None,
    ) -> tuple[FloatArray, FloatArray]:
        """Lengths and Jacobian in ``y`` (``yn`` given) or in ``u = y^2`` (``yn`` None)."""
        h = self.edge_offset_m
        xa = anchors_m[..., 0]
        ya = anchors_m[..., 1]
        za = anchors_m[..., 2]
        dz_out = (zn + h) - za
        r_s = np.sqrt(ya * ya + dz_out * dz_out)
        r_o2 = yn2 + h * h
        r_o = np.sqrt(r_o2)
        den = r_s + r_o
        if den.min(initial=1.0) > 0.0:
            qx = (xa * r_o + xn * r_s) / den
        else:  # node and anchor both on the edge line: any point between is optimal
            with np.errstate(invalid="ignore", divide="ignore"):
                qx = np.where(den > 0.0, (xa * r_o + xn * r_s) / den, 0.5 * (xa + xn))
        if self.edge_x_m is not None:
            qx = np.clip(qx, self.edge_x_m[0], self.edge_x_m[1])
        dx_out = qx - xa
        dx_in = xn - qx
        opl = np.sqrt(dx_out * dx_out + r_s * r_s)
        ipl = np.sqrt(dx_in * dx_in + r_o2)
        jac = np.empty((*ipl.shape, 3))
        with np.errstate(invalid="ignore", divide="ignore"):
            inv_ipl = 1.0 / ipl
            np.multiply(dx_in, inv_ipl, out=jac[..., 0])
            if yn is None:
                np.multiply(0.5, inv_ipl, out=jac[..., 1])
            else:
                np.multiply(yn, inv_ipl, out=jac[..., 1])
            np.divide(dz_out, opl, out=jac[..., 2])
        return opl + ipl, jac


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


@dataclass(frozen=True)
class LMResult:
    """Result of :func:`levenberg_marquardt`.

    Attributes
    ----------
    x_m : ndarray, shape (N, 3) [m]
        Solutions with ``y >= 0`` (rows with a non-finite initial cost: the start as given).
    cost : ndarray, shape (N,) [-]
        ``0.5 c^2 sum rho(...)`` at ``x_m``.
    iterations : ndarray of int, shape (N,)
        Iterations used (accepted and rejected steps).
    converged : ndarray of bool, shape (N,)
        A convergence test passed (see :func:`levenberg_marquardt`).
    lam : ndarray, shape (N,), optional
        The damping ``lambda`` where each problem stopped (``lambda0`` of another call
        continues the same iteration from ``x_m``).
    """

    x_m: FloatArray
    cost: FloatArray
    iterations: NDArray[np.int_]
    converged: BoolArray
    lam: FloatArray | None = None


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
    lambda0: float | FloatArray = 1e-4,
    cost_stop: FloatArray | None = None,
    stop_after: int = 0,
) -> LMResult:
    """Batched damped Gauss-Newton (Levenberg-Marquardt) on the path model.

    Minimises ``0.5 c^2 sum_j rho(((r_j - p_j(x)) sw_j / c)^2)`` for every problem, with
    Marquardt scaling ``H + lambda diag(H)``; robust losses via iteratively reweighted normal
    equations (weights ``rho'``), the true robust cost deciding step acceptance.

    **Depth parameter.** The model depends on the depth ``y`` only through ``u = y^2``, so
    the iteration runs in ``v = (x, u, z)`` with the bound ``u >= 0``
    (:meth:`PathModel.evaluate_u`). In ``y`` the Jacobian column ``y / ipl`` vanishes at the
    wall plane and fixes whose optimum is at ``y = 0`` (noise pushing a shallow node onto the
    wall) would crawl there sublinearly (and a row exactly at ``y = 0`` could never leave
    it); in ``u`` the model is regular at ``u = 0`` (``dp/du = 1 / (2 ipl)``) and the bound
    is handled with an active set: a step that would cross ``u = 0`` goes to ``u = 0`` with
    its ``(x, z)`` part re-solved for that ``du``, and a problem at ``u = 0`` whose gradient
    points to ``u < 0`` solves the reduced ``(x, z)`` system with ``u`` fixed. Away from the
    wall the linearised step is the one in ``y`` (Marquardt scaling makes it invariant to
    the change of variable ``du = 2 y dy``); ``u`` is updated linearly in an effective
    in-room path length ``s`` (``u + du + du^2 / (4 s^2)``, ``s^-2`` the weighted mean of
    ``ipl_j^-2``), which does not overshoot towards the wall on long steps. ``x0_m`` may
    have any sign of ``y``; the result has ``y = sqrt(u) >= 0`` (the model is even in ``y``).

    Convergence (per problem): an accepted step with ``|dx| <= xtol (xtol + |x|)`` (measured
    in ``(x, y, z)`` [m]) or a relative cost decrease ``<= ftol``; or a Gauss-Newton predicted
    decrease (half the Newton decrement ``g^T H^-1 g`` over the free parameters: at an active
    bound ``u = 0`` the reduced ``(x, z)`` system) below ``gtol`` times the cost (a
    stationary point, robust to rounding when steps can no longer lower the cost); or a zero
    cost. A problem whose damping exceeds ``1e12`` without an accepted step stops
    unconverged (unless its gradient test passes). "Zero cost" means residuals at the
    rounding level of the ranges (``64 eps |r_j|``). Problems with a non-finite initial
    cost are returned as given, unconverged, with 0 iterations.

    Parameters
    ----------
    anchors_m : ndarray, shape (N, M, 3) [m]
    ranges_m : ndarray, shape (N, M) [m]
    sw : ndarray, shape (N, M) [1/m]
        ``mask / sigma``: 0 drops a measurement.
    x0_m : ndarray, shape (N, 3) [m]
        Starts.
    model : PathModel
        Scalars or per-problem ``(N,)`` arrays.
    lambda0 : float or ndarray, shape (N,)
        Initial damping (``LMResult.lam`` of an earlier call continues its iteration).
    cost_stop : ndarray, shape (N,), optional
        A problem is given up (unconverged, where it is) once, after at least
        ``stop_after`` iterations, the cost a Gauss-Newton step predicts from its current
        point (``cost - g^T H^-1 g / 2``) is above its ``cost_stop`` (the D-NLS exclusion
        search: a candidate that cannot become the best; inf: never).
    stop_after : int
        Iterations before ``cost_stop`` applies.

    Returns
    -------
    LMResult
        ``x_m (N, 3)`` [m] with ``y >= 0``, ``cost (N,)``, ``iterations (N,)``,
        ``converged (N,)``.
    """
    x0 = np.asarray(x0_m, dtype=np.float64)
    out = _LMOutput.at_start(x0, anchors_m, ranges_m, sw, model, loss, loss_scale)
    out.lam = np.broadcast_to(np.asarray(lambda0, dtype=np.float64), out.cost.shape).copy()
    w = _WorkingSet.of_finite(out, anchors_m, ranges_m, sw, model, out.lam)
    # non-finite rows (e.g. a start on the edge line itself, where dp/du is infinite) are
    # handled explicitly (their steps are never accepted): no floating-point warnings
    with np.errstate(invalid="ignore"):
        n_it = 0
        while n_it < max_iter:
            if w.ids.size == 0:
                break
            h, g, inv4 = _normal_equations(w, loss, loss_scale)
            if w.at_wall:
                _hold_active_bound(w.v[:, 1], h, g)
            a2, dv, stationary, bad, dec = _damped_and_gauss_newton_steps(w, h, g, gtol)
            if cost_stop is not None:
                given_up = w.live & (w.it >= stop_after) & (w.cost - 0.5 * dec > cost_stop[w.ids])
                if given_up.any():  # retired where they are; the others' step again
                    if _retire(w, out, given_up, np.zeros_like(given_up)):
                        break
                    continue
            n_it += 1
            vt = _trial_point(w, dv, a2, g, inv4)
            accept, step2, c_old, costt = _evaluate_and_accept(w, vt, bad, loss, loss_scale)
            done_ok, failed = _convergence_tests(
                w, accept, step2, c_old, costt, stationary, xtol_m, ftol
            )
            finished = done_ok | failed
            if finished.any() and _retire(w, out, finished, done_ok):
                break
    if w.ids.size:  # iteration limit: write back the live rows, unconverged
        out.write_back(w, np.flatnonzero(w.live))
    # rows never iterated (non-finite cost) keep their start as given
    bad_rows = ~np.isfinite(out.cost)
    out.x[bad_rows] = x0[bad_rows]
    return LMResult(x_m=out.x, cost=out.cost, iterations=out.iterations, converged=out.converged,
                    lam=out.lam)


@dataclass
class _LMOutput:
    """Per-problem results of :func:`levenberg_marquardt`, filled as problems finish.

    ``v`` (the start in ``(x, u, z)``), ``res``, ``jac`` and ``floor`` (the zero-cost level)
    are the starting values the working set is built from.
    """

    x: FloatArray
    cost: FloatArray
    iterations: NDArray[np.int_]
    converged: BoolArray
    v: FloatArray
    res: FloatArray
    jac: FloatArray
    floor: FloatArray
    lam: FloatArray | None = None  # (N,) the damping where each problem stopped

    @classmethod
    def at_start(
        cls,
        x0: FloatArray,
        anchors_m: FloatArray,
        ranges_m: FloatArray,
        sw: FloatArray,
        model: PathModel,
        loss: str,
        loss_scale: float,
    ) -> _LMOutput:
        """Every problem at its start: ``y = |y0|``, ``u = y0^2``, cost of the start."""
        n = x0.shape[0]
        x_out = np.array(x0, copy=True)
        x_out[:, 1] = np.abs(x0[:, 1])
        v_out = np.array(x0, copy=True)  # (x, u, z)
        v_out[:, 1] = x0[:, 1] * x0[:, 1]
        p, jac = model.evaluate_u(anchors_m, v_out)
        res = ranges_m - p
        # cost at the level of floating-point rounding of the ranges: an exact fit
        eps_r = 64.0 * np.finfo(float).eps * np.abs(ranges_m) * sw
        return cls(
            x=x_out,
            cost=cost_of(res, sw, loss, loss_scale),
            iterations=np.zeros(n, dtype=np.int_),
            converged=np.zeros(n, dtype=bool),
            v=v_out,
            res=res,
            jac=jac,
            floor=0.5 * np.einsum("nm,nm->n", eps_r, eps_r),
        )

    def write_back(self, w: _WorkingSet, rows: NDArray[np.int_]) -> None:
        """Copy working rows ``rows`` to their problems (position, cost, iterations)."""
        gid = w.ids[rows]
        self.x[gid] = w.x[rows]
        self.cost[gid] = w.cost[rows]
        self.iterations[gid] = w.it[rows]
        self.lam[gid] = w.lam[rows]


@dataclass
class _WorkingSet:
    """The problems still iterating: batch rows ``ids`` and their per-row state.

    Each row is held both as ``v = (x, u, z)`` (the iteration) and as ``x = (x, y, z)``
    (step tests). It is compacted (rows gathered) only when fewer than half of its rows are
    live, so small batches pay no gather per iteration.
    """

    ids: NDArray[np.int_]
    a: FloatArray
    r: FloatArray
    sw: FloatArray
    v: FloatArray
    x: FloatArray
    res: FloatArray
    jac: FloatArray
    cost: FloatArray
    floor: FloatArray
    mdl: PathModel
    lam: FloatArray
    it: NDArray[np.int_]
    live: BoolArray
    wsum: FloatArray  # sum of weights (linear loss; recomputed per iteration otherwise)
    at_wall: bool  # some row may be on the wall plane u = 0

    @classmethod
    def of_finite(
        cls,
        out: _LMOutput,
        anchors_m: FloatArray,
        ranges_m: FloatArray,
        sw: FloatArray,
        model: PathModel,
        lam0: FloatArray,
    ) -> _WorkingSet:
        """The problems with a finite starting cost (all of them: no gather)."""
        ids = np.flatnonzero(np.isfinite(out.cost))
        if ids.size < out.cost.shape[0]:
            a_w, r_w, sw_w, v_w, x_w = anchors_m[ids], ranges_m[ids], sw[ids], out.v[ids], out.x[ids]
            res_w, jac_w, cost_w, floor_w = out.res[ids], out.jac[ids], out.cost[ids], out.floor[ids]
            mdl_w = model.take(ids)
        else:
            a_w, r_w, sw_w, v_w, x_w = anchors_m, ranges_m, sw, out.v.copy(), out.x.copy()
            res_w, jac_w, cost_w, floor_w = out.res, out.jac, out.cost.copy(), out.floor
            mdl_w = model
        tiny = np.finfo(float).tiny
        return cls(
            ids=ids, a=a_w, r=r_w, sw=sw_w, v=v_w, x=x_w, res=res_w, jac=jac_w, cost=cost_w,
            floor=floor_w, mdl=mdl_w,
            lam=lam0[ids].copy(),
            it=np.zeros(ids.size, dtype=np.int_),
            live=np.ones(ids.size, dtype=bool),
            wsum=np.maximum(np.einsum("nm,nm->n", sw_w, sw_w), tiny),
            at_wall=bool(np.any(v_w[:, 1] <= 0.0)),
        )

    def compact(self, keep: NDArray[np.int_]) -> None:
        """Keep only rows ``keep`` (all of them live)."""
        self.ids = self.ids[keep]
        self.a, self.r, self.sw, self.v = self.a[keep], self.r[keep], self.sw[keep], self.v[keep]
        self.x, self.res, self.jac = self.x[keep], self.res[keep], self.jac[keep]
        self.cost, self.floor, self.lam = self.cost[keep], self.floor[keep], self.lam[keep]
        self.it, self.wsum = self.it[keep], self.wsum[keep]
        self.mdl = self.mdl.take(keep)
        self.live = np.ones(self.ids.size, dtype=bool)


def _normal_equations(
    w: _WorkingSet, loss: str, loss_scale: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Weighted ``H = J^T W J`` ``(K, 3, 3)``, gradient ``g = J^T W r`` ``(K, 3)`` and
    ``1 / (4 ipl_eff^2)`` ``(K,)`` (robust losses: IRLS weights ``rho'``)."""
    if loss == "linear":
        ws = w.sw
    else:
        _, drho = robust_rho((w.res * w.sw / loss_scale) ** 2, loss)
        ws = w.sw * np.sqrt(drho)
    jw = w.jac * ws[..., None]
    rw = w.res * ws
    h = np.matmul(jw.transpose(0, 2, 1), jw)
    g = np.matmul(rw[:, None, :], jw)[:, 0, :]
    # 1 / (4 ipl_eff^2) = H_uu / sum_j w_j, the weighted mean of 1 / (4 ipl_j^2) (see the
    # update of u in _trial_point); 0 when no weight (then u + du)
    if loss != "linear":
        w.wsum = np.maximum(np.einsum("nm,nm->n", ws, ws), np.finfo(float).tiny)
    return h, g, h[:, 1, 1] / w.wsum


def _hold_active_bound(u_w: FloatArray, h: FloatArray, g: FloatArray) -> None:
    """Active bound, in place: at ``u = 0`` with the descent direction (+g) pointing to
    ``u < 0``, ``u`` is held: its row and column of ``h`` become the identity and ``g_u`` zero
    (the reduced ``(x, z)`` system)."""
    act = (u_w <= 0.0) & (g[:, 1] < 0.0)
    if act.any():
        free = (~act)[:, None]
        h[:, 1, :] *= free
        h[:, :, 1] *= free
        h[:, 1, 1] += act
        g[:, 1:2] *= free


def _damped_and_gauss_newton_steps(
    w: _WorkingSet, h: FloatArray, g: FloatArray, gtol: float
) -> tuple[FloatArray, FloatArray, BoolArray, BoolArray, FloatArray]:
    """One stacked solve: the damped LM step and the undamped Gauss-Newton step.

    The Gauss-Newton step's Newton decrement ``g^T H^-1 g`` (twice the decrease a full GN step
    would give) tests for a stationary point. Returns the damped matrices ``a2[:K]`` (with the
    undamped ones below), the LM step ``dv`` (0 where non-finite), ``stationary``, ``bad``
    (non-finite step) and the decrement ``dec``.
    """
    diag = np.arange(3)
    dh = h[:, diag, diag]
    dh = np.maximum(dh, 1e-12 * dh.max(axis=-1, keepdims=True) + np.finfo(float).tiny)
    k = w.ids.size
    a2 = np.concatenate([h, h])
    a2[:k, diag, diag] += w.lam[:, None] * dh
    sol = solve3(a2, np.concatenate([g, g]))
    dv = sol[:k]
    dec = np.einsum("ni,ni->n", g, sol[k:])
    stationary = np.isfinite(dec) & (dec <= 2.0 * gtol * w.cost + 2.0 * w.floor)
    bad = ~np.isfinite(dv).all(axis=-1)
    if bad.any():
        dv[bad] = 0.0
    return a2, dv, stationary, bad, dec


def _trial_point(
    w: _WorkingSet, dv: FloatArray, a2: FloatArray, g: FloatArray, inv4: FloatArray
) -> FloatArray:
    """The trial point ``v + dv`` in ``(x, u, z)``, with ``u`` updated along the path length.

    The linearised model changes ``p_j`` by ``du / (2 ipl_j)``, but the path
    ``sqrt(ipl_j^2 + du)`` is concave in ``u``, so ``u + du`` overshoots towards the wall when
    the step is large. The update is made linear in an effective in-room path length
    ``s = ipl_eff`` instead: ``s + du / (2 s)``, i.e. ``u + du + du^2 / (4 s^2)``. To first
    order this is the ``u`` step (local convergence is that of the ``u`` iteration); it is the
    ``y`` update ``y + du / (2 y)`` when ``ipl_eff = y`` and the plain ``u`` update when
    ``ipl_eff >> y``. Steps that would cross the wall go to it (:func:`_clamp_to_wall`).
    """
    u_w = w.v[:, 1]
    du = dv[:, 1]
    vt = w.v + dv
    fac = 1.0 + inv4 * du  # (u_t - u) / du: <= 0.5 past the vertex of the parabola
    np.add(u_w, du * fac, out=vt[:, 1])
    if np.fmin.reduce(vt[:, 1]) < 0.0 or np.fmin.reduce(fac) <= 0.5:  # NaN rows ignored
        _clamp_to_wall(w, vt, fac, a2, g, inv4)
    return vt


def _clamp_to_wall(
    w: _WorkingSet, vt: FloatArray, fac: FloatArray, a2: FloatArray, g: FloatArray, inv4: FloatArray
) -> None:
    """Steps past the wall, in place: ``s`` reaches the wall (``u = 0``) at
    ``s = sqrt(ipl_eff^2 - u)``, i.e. at a linear step ``du_b`` in ``[-2u, -u]``; a step beyond
    it (the parabola negative, or past its vertex) goes to ``u = 0`` exactly (``du = du_b``)
    and the damped ``(x, z)`` part of the same system is re-solved with that ``du`` fixed."""
    v_w = w.v
    ci = np.flatnonzero((vt[:, 1] < 0.0) | (fac <= 0.5))
    uc = v_w[ci, 1]
    dub = -2.0 * uc / (1.0 + np.sqrt(np.maximum(1.0 - 4.0 * uc * inv4[ci], 0.0)))
    hc = a2[ci]
    gc = g[ci] - hc[:, :, 1] * dub[:, None]
    hc[:, 1, :] = 0.0
    hc[:, :, 1] = 0.0
    hc[:, 1, 1] = 1.0
    gc[:, 1] = 0.0
    dvc = solve3(hc, gc)
    okc = np.isfinite(dvc).all(axis=-1)
    vt[ci[okc], 0] = v_w[ci[okc], 0] + dvc[okc, 0]
    vt[ci[okc], 2] = v_w[ci[okc], 2] + dvc[okc, 2]
    vt[ci, 1] = 0.0
    w.at_wall = True


def _evaluate_and_accept(
    w: _WorkingSet, vt: FloatArray, bad: BoolArray, loss: str, loss_scale: float
) -> tuple[BoolArray, FloatArray, FloatArray, FloatArray]:
    """Evaluate the trial points, move the rows whose cost falls and adapt the damping
    (``lambda / 3`` on success, ``x 8`` on failure); count the iteration.

    Returns ``accept``, the squared step ``|dx|^2`` in ``(x, y, z)`` [m^2], the old and the
    trial cost.
    """
    xt = vt.copy()
    np.sqrt(vt[:, 1], out=xt[:, 1])
    pt, jt = w.mdl.evaluate_u(w.a, vt)
    rest = w.r - pt
    costt = cost_of(rest, w.sw, loss, loss_scale)
    c_old = w.cost
    accept = (costt < c_old) & ~bad & w.live
    step = xt - w.x  # in (x, y, z) [m]
    step2 = np.einsum("ni,ni->n", step, step)
    if accept.all():  # the common case: every step accepted, no selection needed
        w.v, w.x, w.res, w.jac, w.cost = vt, xt, rest, jt, costt
        w.lam = np.maximum(w.lam / 3.0, 1e-12)
    else:
        w.v = np.where(accept[:, None], vt, w.v)
        w.x = np.where(accept[:, None], xt, w.x)
        w.res = np.where(accept[:, None], rest, w.res)
        w.jac = np.where(accept[:, None, None], jt, w.jac)
        w.cost = np.where(accept, costt, c_old)
        w.lam = np.where(accept, np.maximum(w.lam / 3.0, 1e-12), w.lam * 8.0)
    w.it += w.live
    return accept, step2, c_old, costt


def _convergence_tests(
    w: _WorkingSet,
    accept: BoolArray,
    step2: FloatArray,
    c_old: FloatArray,
    costt: FloatArray,
    stationary: BoolArray,
    xtol_m: float,
    ftol: float,
) -> tuple[BoolArray, BoolArray]:
    """``(done_ok, failed)`` per working row: converged (stationary, small step, small cost
    decrease or zero cost), or given up (damping above ``1e12``)."""
    xn2 = np.einsum("ni,ni->n", w.x, w.x)
    small_step = accept & (step2 <= (xtol_m * (xtol_m + np.sqrt(xn2))) ** 2)
    small_f = accept & (c_old - costt <= ftol * c_old)
    zero = c_old <= w.floor
    done_ok = w.live & (stationary | small_step | small_f | zero)
    failed = w.live & ~done_ok & (w.lam > 1e12)
    return done_ok, failed


def _retire(w: _WorkingSet, out: _LMOutput, finished: BoolArray, done_ok: BoolArray) -> bool:
    """Write the finished rows back and drop them; True when no row is left."""
    f_idx = np.flatnonzero(finished)
    out.write_back(w, f_idx)
    out.converged[w.ids[f_idx]] = done_ok[f_idx]
    w.live &= ~finished
    n_live = int(w.live.sum())
    if n_live == 0:
        w.ids = w.ids[:0]
        return True
    if n_live < 0.5 * w.ids.size:
        w.compact(np.flatnonzero(w.live))
    return False
