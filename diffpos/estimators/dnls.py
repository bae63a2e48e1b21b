"""D-NLS: batched non-linear least squares on the diffraction path model (paper Sec. V-A).

The measurement model is ``r_j = p_j(alpha) + n_j`` with ``p_j`` the upper-edge diffraction
path length of Corollary 1 (:func:`diffpos.geometry.window_edge_path`), optionally with the
Case-2 offset ``Delta`` (``delta_m``): the edge is ``0.5 w - Delta`` above the node. The paper
iterates plain Gauss-Newton from one start and notes that it falls into local minima; here:

* **Multi-start over floor hypotheses.** Without building knowledge the node height is
  unknown, so each fix is started from a grid of heights (``z_starts_m``, default every 3 m
  from 0 to 30 m: one start per plausible floor), with ``x`` at the mean ``x`` of its anchors
  and ``y`` ``y_start_m`` (default 3 m) inside the wall. All starts of all fixes are iterated
  together and the start with the lowest final cost is kept. One more start is the LoS
  linear least-squares (LLS) position, which rescues fixes deep inside the building whose
  grid starts all fall into a local minimum. Measured on 20,000 noise-free random fixes
  (anchors at y in [-40, -5] m, z in [0, 40] m; nodes up to 15 m deep on 9 floors): with 4
  anchors, 18 ended in a wrong local minimum with the grid alone and 5 with the LLS start
  added (all starts run to convergence); with the default screening 10 (Case-1) and 8
  (Case-2); with 5, 6 or 8 anchors none. ``x0_m`` replaces all of this by one given start.
* **Screening.** By default every start gets 4 iterations and only the 3 best go on; fixes
  whose residual statistic is then suspicious (above the 90 % chi-square quantile, or any
  fix without ``sigmas_m``) are re-solved from all starts (:func:`multistart_fit`). This
  keeps the single-fix latency low; on 20,000 noisy random 4-anchor fixes it ended with a
  higher cost than running every start in 0.07 % of fixes (``keep_starts=None`` disables
  it).
* **Step control.** Levenberg-Marquardt damping ``(H + lambda diag H) dx = g`` with the cost
  deciding acceptance (``lambda / 3`` on success, ``x 8`` on failure), so every accepted
  step decreases the cost; pure Gauss-Newton is the limit ``lambda -> 0``.
* **Convergence tests** on the step size, relative cost decrease and gradient (see
  :func:`diffpos.estimators._core.levenberg_marquardt`); ``converged`` reports them.
* **Mirror symmetry.** The model depends on ``y_n`` only through ``y_n^2``; a solution with
  ``y < 0`` is reflected to the inside (``y > 0``), which leaves the cost unchanged.

After the fit, the covariance is the inverse FIM of the used measurements at the solution
(:func:`diffpos.bounds.fisher_information` and :func:`diffpos.bounds.bounds_from_fim`, the same
functions that give the PEB of the study), and the outlier gating of
:mod:`diffpos.estimators.gating` runs unless ``gating=None``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..bounds import bounds_from_fim, fisher_information
from ._core import LOSSES, PathModel, cost_of, levenberg_marquardt
from .gating import GateState, GatingConfig, chi2_threshold, run_gating, wall_pregate
from .result import ExclusionReason, FixResult, FixStatus, prepare_batch

__all__ = ["DEFAULT_Z_STARTS_M", "dnls"]

FloatArray = NDArray[np.float64]

#: Default start heights [m]: one per 3 m floor from the ground to 30 m.
DEFAULT_Z_STARTS_M = tuple(float(z) for z in np.arange(0.0, 30.0 + 1e-9, 3.0))

_DEFAULT_GATING = GatingConfig()


def _per_fix(value: ArrayLike, batch: int, name: str) -> FloatArray | float:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        if not np.isfinite(arr):
            raise ValueError(f"{name} must be finite, got {float(arr)}")
        return float(arr)
    if arr.shape != (batch,):
        raise ValueError(f"{name} must be a scalar or have shape (B,) = ({batch},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr


def check_edge_x(edge_x_m: ArrayLike | None) -> tuple[float, float] | None:
    """Validate ``edge_x_m`` (``None`` or two finite, different numbers) [m]."""
    if edge_x_m is None:
        return None
    e = np.asarray(edge_x_m, dtype=np.float64)
    if e.shape != (2,) or not np.all(np.isfinite(e)) or e[0] == e[1]:
        raise ValueError(f"edge_x_m must be two different finite numbers [x1, x2], got {edge_x_m}")
    return (float(min(e)), float(max(e)))


def _check_z_starts(z_starts_m: ArrayLike | None) -> FloatArray:
    """The start heights (default :data:`DEFAULT_Z_STARTS_M`), validated, shape (S,) [m]."""
    zs = np.asarray(DEFAULT_Z_STARTS_M if z_starts_m is None else z_starts_m, float)
    if zs.ndim != 1 or zs.size == 0 or not np.all(np.isfinite(zs)):
        raise ValueError("z_starts_m must be a non-empty 1-D array of finite heights [m]")
    return zs


def dnls(
    anchors_m: ArrayLike,
    ranges_m: ArrayLike,
    sigmas_m: ArrayLike | None = None,
    *,
    mask: ArrayLike | None = None,
    window_height_m: float | ArrayLike,
    delta_m: float | ArrayLike = 0.0,
    edge_x_m: tuple[float, float] | None = None,
    gating: GatingConfig | None = _DEFAULT_GATING,
    loss: str = "linear",
    loss_scale: float = 1.5,
    x0_m: ArrayLike | None = None,
    z_starts_m: ArrayLike | None = None,
    y_start_m: float = 3.0,
    max_iter: int = 50,
    xtol_m: float = 1e-10,
    lls_start: bool = True,
    keep_starts: int | None = 3,
    screen_iter: int = 4,
    chunk_size: int = 1024,
) -> FixResult:
    """Batched D-NLS position fixes with optional outlier gating.

    Parameters
    ----------
    anchors_m : array_like, shape (B, M, 3) or (M, 3) [m]
        Anchor positions in building coordinates (front wall ``y = 0``, inside ``y > 0``).
    ranges_m : array_like, shape (B, M) or (M,) [m]
        Measured ranges (first-arrival path lengths).
    sigmas_m : array_like, shape (B, M), scalar or None [m]
        Ranging standard deviations. ``None``: unit weights, the covariance is scaled by the
        a-posteriori variance factor ``2 cost / (|S| - 3)`` (if ``|S| > 3``) and the residual
        test is skipped (``OK_UNVERIFIED``).
    mask : array_like of bool, shape (B, M), optional
        Which measurements exist (False = padding of a ragged anchor set).
    window_height_m : float or array_like, shape (B,) [m]
        Window height ``w``.
    delta_m : float or array_like, shape (B,) [m]
        Offset ``Delta`` used in the model (0: Case-1; e.g. 1.5: Case-2).
    edge_x_m : (float, float), optional
        Extent of the window edges along x [m]; default unbounded.
    gating : GatingConfig or None
        Outlier gating settings; ``None`` disables pre-gate and RAIM.
    loss : {"linear", "huber", "soft_l1"}
        Loss on the normalised residuals ``r_j / sigma_j`` (robust alternative to gating).
    loss_scale : float [sigma]
        Soft threshold ``c`` of the robust loss in units of ``sigma_j``.
    x0_m : array_like, shape (B, 3) or (3,), optional [m]
        One start per fix instead of the multi-start grid.
    z_starts_m : array_like, shape (S,), optional [m]
        Start heights (default :data:`DEFAULT_Z_STARTS_M`).
    y_start_m : float [m]
        Start depth inside the wall for the grid starts.
    max_iter : int
        Iteration limit per start.
    xtol_m : float [-]
        Relative step tolerance of the convergence test.
    lls_start : bool
        Add the LoS linear least-squares position (``y`` reflected inside) as one more
        start (ignored where LLS is not identifiable, e.g. fewer than 4 anchors).
    keep_starts : int or None
        Screening: after ``screen_iter`` iterations from every start, only the
        ``keep_starts`` starts with the lowest cost of each fix are iterated to convergence
        (``None``: all starts to convergence).
    screen_iter : int
        Iterations of the screening phase.
    chunk_size : int
        Fixes solved together per chunk (bounds memory; results depend on it only at the
        rounding level).

    Returns
    -------
    FixResult
        ``method="dnls"``, ``covariance_model="diffraction FIM"``.

    Examples
    --------
    >>> import numpy as np
    >>> from diffpos.estimators import dnls
    >>> from diffpos.geometry import window_edge_path
    >>> anchors = np.array([[-15, -20, 1], [0, -15, 0], [0, -7, 4], [15, -20, 1.0]])
    >>> node = np.array([2.0, 5.0, 10.5])
    >>> r = window_edge_path(anchors, node, window_height_m=1.0).length_m
    >>> fix = dnls(anchors, r, 0.1, window_height_m=1.0)
    >>> bool(np.allclose(fix.position_m[0], node, atol=1e-6))
    True
    """
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    if not loss_scale > 0:
        raise ValueError("loss_scale must be > 0")
    if gating is not None and not isinstance(gating, GatingConfig):
        raise TypeError("gating must be a GatingConfig or None")
    batch_in = prepare_batch(anchors_m, ranges_m, sigmas_m, mask)
    bsz, m = batch_in.ranges_m.shape
    wh = _per_fix(window_height_m, bsz, "window_height_m")
    if np.any(np.asarray(wh) <= 0):
        raise ValueError("window_height_m must be > 0")
    de = _per_fix(delta_m, bsz, "delta_m")
    edge = check_edge_x(edge_x_m)
    model = PathModel(window_height_m=wh, delta_m=de, edge_x_m=edge)
    if x0_m is not None:
        x0 = np.asarray(x0_m, dtype=np.float64)
        x0 = np.broadcast_to(x0.reshape(-1, 3) if x0.ndim == 1 else x0, (bsz, 3))
        if not np.all(np.isfinite(x0)):
            raise ValueError("x0_m must be finite")
        starts = None
    else:
        x0 = None
        starts = _check_z_starts(z_starts_m)

    out = _alloc(bsz, m)
    for lo in range(0, bsz, max(int(chunk_size), 1)):
        sl = slice(lo, min(lo + max(int(chunk_size), 1), bsz))
        _solve_chunk(
            out,
            sl,
            batch_in.anchors_m[sl],
            batch_in.ranges_m[sl],
            batch_in.sigmas_m[sl],
            batch_in.mask[sl],
            model.take(np.arange(sl.start, sl.stop)),
            x0=None if x0 is None else x0[sl],
            z_starts=starts,
            y_start=y_start_m,
            gating=gating,
            loss=loss,
            loss_scale=loss_scale,
            max_iter=max_iter,
            xtol=xtol_m,
            sigmas_given=batch_in.sigmas_given,
            keep_starts=keep_starts,
            screen_iter=screen_iter,
            lls_start=lls_start,
        )
    invalid = batch_in.input_error != 0
    out["status"][invalid] = FixStatus.INVALID_INPUT
    reason = out["exclusion_reason"]
    reason[~batch_in.present] = ExclusionReason.MISSING
    reason[invalid[:, None] & batch_in.present] = ExclusionReason.NONE
    return FixResult(
        position_m=out["position_m"],
        covariance_m2=out["covariance_m2"],
        peb_m=out["peb_m"],
        z_bound_m=out["z_bound_m"],
        iterations=out["iterations"],
        converged=out["converged"],
        status=out["status"],
        residuals_m=out["residuals_m"],
        used=out["used"],
        excluded=(reason == ExclusionReason.PREGATE_SHORTER_THAN_LOS)
        | (reason == ExclusionReason.RAIM),
        exclusion_reason=reason,
        test_statistic=out["test_statistic"],
        test_threshold=out["test_threshold"],
        dof=out["dof"],
        cost=out["cost"],
        input_error=batch_in.input_error,
        method="dnls",
        covariance_model="diffraction FIM",
        sigmas_given=batch_in.sigmas_given,
    )


def _alloc(b: int, m: int) -> dict[str, np.ndarray]:
    return {
        "position_m": np.full((b, 3), np.nan),
        "covariance_m2": np.full((b, 3, 3), np.nan),
        "peb_m": np.full(b, np.nan),
        "z_bound_m": np.full(b, np.nan),
        "iterations": np.zeros(b, dtype=np.int_),
        "converged": np.zeros(b, dtype=bool),
        "status": np.full(b, int(FixStatus.TOO_FEW_ANCHORS), dtype=np.int_),
        "residuals_m": np.full((b, m), np.nan),
        "used": np.zeros((b, m), dtype=bool),
        "exclusion_reason": np.zeros((b, m), dtype=np.int_),
        "test_statistic": np.full(b, np.nan),
        "test_threshold": np.full(b, np.nan),
        "dof": np.zeros(b, dtype=np.int_),
        "cost": np.full(b, np.nan),
    }


def _lls_starts(
    a: FloatArray, r: FloatArray, mask: NDArray[np.bool_], grid: FloatArray
) -> FloatArray:
    """One extra start per fix from LLS; falls back to the middle grid start."""
    from .lls import lls_positions

    x, _, ok = lls_positions(a, r, mask)
    fallback = grid[:, grid.shape[1] // 2]
    x = np.where(ok[:, None], x, fallback)
    x[:, 1] = np.maximum(np.abs(x[:, 1]), 0.5)
    return x[:, None, :]


def grid_starts(
    anchors_m: FloatArray, mask: NDArray[np.bool_], z_starts: FloatArray, y_start: float
) -> FloatArray:
    """Multi-start points ``(B, S, 3)``: x = mean anchor x, y = ``y_start``, z from the grid."""
    cnt = np.maximum(mask.sum(axis=-1), 1)
    xm = np.where(mask, anchors_m[..., 0], 0.0).sum(axis=-1) / cnt
    b, s = xm.shape[0], z_starts.size
    st = np.empty((b, s, 3))
    st[..., 0] = xm[:, None]
    st[..., 1] = y_start
    st[..., 2] = z_starts[None, :]
    return st


def _solve_chunk(
    out: dict[str, np.ndarray],
    sl: slice,
    anchors: FloatArray,
    ranges: FloatArray,
    sigmas: FloatArray,
    mask: NDArray[np.bool_],
    model: PathModel,
    *,
    x0: FloatArray | None,
    z_starts: FloatArray | None,
    y_start: float,
    gating: GatingConfig | None,
    loss: str,
    loss_scale: float,
    max_iter: int,
    xtol: float,
    sigmas_given: bool,
    keep_starts: int | None,
    screen_iter: int,
    lls_start: bool,
) -> None:
    m = ranges.shape[1]
    reason0 = np.zeros((ranges.shape[0], m), dtype=np.int_)
    if gating is not None:
        wall = wall_pregate(anchors, ranges, sigmas, mask, gating, sigmas_given=sigmas_given)
        if np.any(wall):
            mask = mask & ~wall
            reason0[wall] = ExclusionReason.PREGATE_SHORTER_THAN_LOS
            out["exclusion_reason"][sl] = reason0
            out["used"][sl] = mask
    solvable = mask.sum(axis=-1) >= 3
    idx = np.flatnonzero(solvable)
    if idx.size == 0:
        return
    a = anchors[idx]
    r = ranges[idx]
    sig_i = sigmas[idx]
    sw = mask[idx] / sig_i
    mdl = model.take(idx)
    x0_i = None if x0 is None else x0[idx]

    def make_starts(aa, rr, cu, rows):
        # the given start, or the z grid (plus the LLS fix): (len(rows), S, 3)
        if x0_i is not None:
            return x0_i[rows][:, None, :]
        st = grid_starts(aa, cu, z_starts, y_start)
        if lls_start:
            st = np.concatenate([st, _lls_starts(aa, rr, cu, st)], axis=1)
        return st

    starts = make_starts(a, r, mask[idx], slice(None))
    n = starts.shape[0]
    x, cost_best, iters_best, conv_best = multistart_fit(
        a, r, sw, starts, mdl, loss=loss, loss_scale=loss_scale, max_iter=max_iter, xtol=xtol,
        keep_starts=keep_starts, screen_iter=screen_iter,
        recheck=mask[idx].sum(axis=-1) - 3 if sigmas_given else None,
    )
    x[:, 1] = np.abs(x[:, 1])  # mirror symmetry y -> -y of the model
    state = GateState(
        x_m=x,
        cost=cost_best,
        iterations=iters_best,
        converged=conv_best,
        used=mask[idx].copy(),
        reason=reason0[idx].copy(),
        gating_failed=np.zeros(n, dtype=bool),
        tested=np.zeros(n, dtype=bool),
    )

    def solve_candidates(pi, cu, warm):
        # The first fit's multi-start on each candidate subset, plus the warm start. The
        # screening recheck is done per fix, not per candidate: the candidates that keep
        # the faulty anchor all fail, and re-solving each of them from every start would
        # only confirm it. A fix is re-solved from all starts (every candidate) only if
        # none of its screened candidates passes the residual test itself.
        aa, rr, swc, mc = a[pi], r[pi], cu / sig_i[pi], mdl.take(pi)
        # one given start (or the grid) plus the warm start (the current solution)
        st = np.concatenate([make_starts(aa, rr, cu, pi), warm[:, None, :]], axis=1)
        common = {"loss": loss, "loss_scale": loss_scale, "max_iter": max_iter,
                  "xtol": xtol, "screen_iter": screen_iter}
        dof_c = cu.sum(axis=-1) - 3
        xc, cc, ic, vc = multistart_fit(aa, rr, swc, st, mc, keep_starts=keep_starts,
                                        recheck=np.zeros_like(dof_c), **common)
        if keep_starts is not None and st.shape[1] > keep_starts:
            thr_c = chi2_threshold(dof_c, gating.false_alarm_probability)
            good = (dof_c >= 1) & (2.0 * cc <= thr_c)
            _, grp = np.unique(pi, return_inverse=True)
            fix_good = np.zeros(grp.max(initial=-1) + 1, dtype=bool)
            np.logical_or.at(fix_good, grp, good)
            rows = np.flatnonzero(~fix_good[grp])
            if rows.size:
                x2, c2, i2, v2 = multistart_fit(
                    aa[rows], rr[rows], swc[rows], st[rows], mc.take(rows),
                    keep_starts=None, recheck=None, **common)
                b = c2 < cc[rows]
                rb = rows[b]
                xc[rb], ic[rb], vc[rb] = x2[b], i2[b], v2[b]
        xc[:, 1] = np.abs(xc[:, 1])
        return xc, ic, vc

    if gating is not None:
        run_gating(
            state,
            a,
            r,
            sig_i,
            mdl,
            gating,
            active=np.ones(n, dtype=bool),
            sigmas_given=sigmas_given,
            loss=loss,
            loss_scale=loss_scale,
            solve_candidates=solve_candidates,
        )
        state.x_m[:, 1] = np.abs(state.x_m[:, 1])
    used = state.used
    p, jac = mdl.evaluate(a, state.x_m)
    res = r - p
    n_used = used.sum(axis=-1)
    fim = fisher_information(jac, sig_i, used)
    bnd = bounds_from_fim(fim)
    cov = bnd.crlb_m2
    cost_final = cost_of(res, used / sig_i, loss, loss_scale)
    if not sigmas_given:
        # a-posteriori variance factor (unit weights were used)
        ssr = np.einsum("nm,nm->n", res * used, res * used)
        with np.errstate(divide="ignore", invalid="ignore"):
            s2 = np.where(n_used > 3, ssr / (n_used - 3), 1.0)
        cov = cov * s2[:, None, None]
    peb = np.sqrt(np.trace(cov, axis1=-2, axis2=-1))
    zb = np.sqrt(cov[:, 2, 2])
    sw_used = used / sig_i
    t_stat = np.einsum("nm,nm->n", res * sw_used, res * sw_used)
    dof = n_used - 3
    thr = (
        chi2_threshold(dof, gating.false_alarm_probability)
        if gating is not None and sigmas_given
        else np.full(n, np.nan)
    )
    status = np.full(n, int(FixStatus.OK), dtype=np.int_)
    status[~state.tested] = FixStatus.OK_UNVERIFIED
    status[state.gating_failed] = FixStatus.GATING_FAILED
    if gating is not None and gating.z_range_m is not None:
        z_lo, z_hi = gating.z_range_m
        z = state.x_m[:, 2]
        status[(status == FixStatus.OK) & ((z < z_lo) | (z > z_hi))] = FixStatus.GATING_FAILED
    status[~state.converged] = FixStatus.NOT_CONVERGED
    status[~bnd.identifiable] = FixStatus.NOT_IDENTIFIABLE
    status[n_used < 3] = FixStatus.TOO_FEW_ANCHORS
    gi = sl.start + idx
    out["position_m"][gi] = state.x_m
    out["covariance_m2"][gi] = cov
    out["peb_m"][gi] = peb
    out["z_bound_m"][gi] = zb
    out["iterations"][gi] = state.iterations
    out["converged"][gi] = state.converged
    out["status"][gi] = status
    out["residuals_m"][gi] = np.where(used, res, np.nan)
    out["used"][gi] = used
    out["exclusion_reason"][gi] = state.reason
    out["test_statistic"][gi] = np.where(sigmas_given, t_stat, np.nan)
    out["test_threshold"][gi] = thr
    out["dof"][gi] = dof
    out["cost"][gi] = cost_final


#: Screened fixes whose residual statistic exceeds this quantile are re-solved from all starts.
RECHECK_PROBABILITY = 0.1


def multistart_fit(
    a: FloatArray,
    r: FloatArray,
    sw: FloatArray,
    starts: FloatArray,
    mdl: PathModel,
    *,
    loss: str,
    loss_scale: float,
    max_iter: int,
    xtol: float,
    keep_starts: int | None,
    screen_iter: int,
    recheck: NDArray[np.int_] | None,
) -> tuple[FloatArray, FloatArray, NDArray[np.int_], NDArray[np.bool_]]:
    """Best-of-starts LM fit per problem: ``starts (N, S, 3)`` -> x, cost, iterations, converged.

    With screening (``keep_starts``), every start gets ``screen_iter`` iterations and only the
    ``keep_starts`` lowest-cost ones go on. Screening can drop the start that would have
    reached the global minimum (measured: 0.3 % of random 4-anchor fixes), which then shows
    up as a large residual; so fixes whose statistic ``2 cost`` exceeds the
    ``1 - RECHECK_PROBABILITY`` chi-square quantile for ``recheck`` dof (or all fixes, if
    ``recheck`` is None: no noise model to judge) are re-solved from all starts and the
    better answer kept.
    """
    n, s = starts.shape[0], starts.shape[1]
    common = {"loss": loss, "loss_scale": loss_scale, "xtol_m": xtol}

    def full(rows: NDArray[np.int_]):
        k = rows.size
        fit = levenberg_marquardt(
            np.repeat(a[rows], s, axis=0), np.repeat(r[rows], s, axis=0),
            np.repeat(sw[rows], s, axis=0), starts[rows].reshape(k * s, 3),
            mdl.take(rows).repeat(s), max_iter=max_iter, **common,
        )
        return _pick_best(fit.x_m, fit.cost, fit.iterations, fit.converged, k, s)

    if keep_starts is None or s <= keep_starts or max_iter <= screen_iter:
        return full(np.arange(n))
    scr = levenberg_marquardt(
        np.repeat(a, s, axis=0), np.repeat(r, s, axis=0), np.repeat(sw, s, axis=0),
        starts.reshape(n * s, 3), mdl.repeat(s), max_iter=screen_iter, **common,
    )
    c_scr = np.where(np.isfinite(scr.cost), scr.cost, np.inf).reshape(n, s)
    k = keep_starts
    order = np.argsort(c_scr, axis=-1, kind="stable")[:, :k]
    pick = (np.arange(n)[:, None] * s + order).ravel()
    fit = levenberg_marquardt(
        np.repeat(a, k, axis=0), np.repeat(r, k, axis=0), np.repeat(sw, k, axis=0),
        scr.x_m[pick], mdl.repeat(k), max_iter=max_iter - screen_iter, **common,
    )
    x, cost, iters, conv = _pick_best(
        fit.x_m, fit.cost, scr.iterations[pick] + fit.iterations, fit.converged, n, k
    )
    if recheck is None:
        redo = np.ones(n, dtype=bool)
    else:
        thr = chi2_threshold(recheck, RECHECK_PROBABILITY)
        redo = ~np.isfinite(cost) | ((recheck >= 1) & (2.0 * cost > thr))
    rows = np.flatnonzero(redo)
    if rows.size:
        x2, c2, i2, v2 = full(rows)
        better = c2 < cost[rows]
        rb = rows[better]
        x[rb], cost[rb], iters[rb], conv[rb] = x2[better], c2[better], i2[better], v2[better]
    return x, cost, iters, conv


def _pick_best(x_m, cost, iters, conv, n, s):
    c = np.where(np.isfinite(cost), cost, np.inf).reshape(n, s)
    best = np.argmin(c, axis=-1)
    sel = np.arange(n) * s + best
    return x_m[sel].copy(), cost[sel].copy(), iters[sel].copy(), conv[sel].copy()
