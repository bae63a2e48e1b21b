"""IPPA: iterative parallel projection for NLoS positioning (Jia & Buehrer 2010), batched.

Set-theoretic baseline of the paper. Each range defines a sphere (LoS) or a ball (NLoS: the
true distance is at most the range) around its anchor. An iteration projects the current
estimate onto the sphere of every **active** measurement and moves to the average of these
projections; an NLoS measurement is active only while the estimate lies *outside* its ball
(a point inside the ball already satisfies it).

Behaviour matched to the authors' published MATLAB (``ippa_floor.m`` and its driver
``Algo_comparisons.m`` in github.com/gauravduggal/Diffraction-based-positioning; read, not
copied):

* projection of ``theta`` onto the sphere of radius ``r_j - b_j`` about anchor ``a_j``, with
  ``b_j`` an optional mean NLoS bias subtracted from the range (their "NM(ID, mean/min)"
  variants; ``b_j = 0`` is their "NM(ID)");
* LoS measurements always active; NLoS ones only when ``|theta - a_j| > r_j - b_j``;
* the new estimate is the plain average of the active projections; when no measurement is
  active the iteration stops (the estimate is inside every ball);
* cost ``phi = (1/M) sum_j (r_j - b_j - |theta - a_j|)^2`` over all measurements;
  the iteration stops when ``|phi_k - phi_{k-1}| < tol_m2`` (their ``delta = 1e-4``, with
  ``phi_{-1} = 0``) or after ``max_iter = 20`` updates;
* the driver treats every measurement as NLoS (``nlos=True`` default here) and runs one start
  per floor hypothesis, keeping the estimate with the lowest ``phi``.

Deviations (documented): the starts are deterministic (``x`` = mean anchor ``x``, ``y`` =
``y_start_m``, ``z`` from ``z_starts_m``, the same floor grid as D-NLS) where the driver drew
the in-floor coordinates at random; the selection cost is ``phi`` evaluated at the *returned*
estimate (the MATLAB returns ``phi`` of the iterate before the last update); a zero-distance
projection (estimate on an anchor) keeps the estimate instead of dividing by zero.

IPPA has no noise model, so ``covariance_m2`` is NaN (``covariance_model="none"``). Status is
``OK_UNVERIFIED`` when the stopping rule fired, ``NOT_CONVERGED`` when ``max_iter`` was hit.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.estimators.result import (
    ExclusionReason,
    FixResult,
    FixStatus,
    PreparedBatch,
    prepare_batch,
)
from diffpos.estimators.starts import check_z_starts, grid_starts

__all__ = ["ippa"]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def ippa(
    anchors_m: ArrayLike,
    ranges_m: ArrayLike,
    sigmas_m: ArrayLike | None = None,
    *,
    mask: ArrayLike | None = None,
    nlos: bool | ArrayLike = True,
    nlos_bias_m: float | ArrayLike = 0.0,
    x0_m: ArrayLike | None = None,
    z_starts_m: ArrayLike | None = None,
    y_start_m: float = 3.0,
    max_iter: int = 20,
    tol_m2: float = 1e-4,
) -> FixResult:
    """Batched IPPA fixes, multi-start over floor hypotheses.

    Parameters
    ----------
    anchors_m : array_like, shape (B, M, 3) or (M, 3) [m]
    ranges_m : array_like, shape (B, M) or (M,) [m]
    sigmas_m : array_like, optional [m]
        Only used for the reported normalised test statistic (IPPA itself is unweighted).
    mask : array_like of bool, shape (B, M), optional
    nlos : bool or array_like of bool, shape (B, M)
        NLoS flags (True: ball constraint, False: sphere). Default all NLoS, as in the paper.
    nlos_bias_m : float or array_like, shape (B, M) [m]
        Mean NLoS bias subtracted from the ranges (0: none).
    x0_m : array_like, shape (B, 3) or (3,), optional [m]
        One start per fix instead of the floor grid.
    z_starts_m : array_like, shape (S,), optional [m]
        Floor hypotheses (default the D-NLS grid, every 3 m from 0 to 30 m).
    y_start_m : float [m]
        Start depth inside the wall.
    max_iter : int
        Most projection updates per start (authors: 20).
    tol_m2 : float [m^2]
        Stop when the mean squared sphere residual changes by less than this (authors: 1e-4).

    Returns
    -------
    FixResult
        ``method="ippa"``, ``covariance_model="none"``.
    """
    pb = prepare_batch(anchors_m, ranges_m, sigmas_m, mask)
    a, r, use = pb.anchors_m, pb.ranges_m, pb.mask
    b = r.shape[0]
    flags, rr = _nlos_flags_and_ranges(nlos, nlos_bias_m, r)
    starts = _starts(a, use, x0_m, z_starts_m, y_start_m)
    s = starts.shape[1]
    # every start of every fix iterated as one problem: rows b * s + start
    aa = np.repeat(a, s, axis=0)
    rrr = np.repeat(rr, s, axis=0)
    uu = np.repeat(use, s, axis=0)
    ff = np.repeat(flags, s, axis=0)
    theta, iters, stopped = _project_iterations(
        aa, rrr, uu, ff, starts.reshape(b * s, 3).copy(), max_iter=max_iter, tol_m2=tol_m2
    )
    return _best_start_result(pb, aa, rrr, uu, theta, iters, stopped, s)


def _nlos_flags_and_ranges(
    nlos: bool | ArrayLike, nlos_bias_m: float | ArrayLike, r: FloatArray
) -> tuple[BoolArray, FloatArray]:
    """NLoS flags ``(B, M)`` and the ranges minus the NLoS bias ``r - b`` ``(B, M)`` [m]."""
    b, m = r.shape
    flags = np.broadcast_to(np.asarray(nlos, dtype=bool), (b, m))
    bias = np.broadcast_to(np.asarray(nlos_bias_m, dtype=np.float64), (b, m))
    if not np.all(np.isfinite(bias)):
        raise ValueError("nlos_bias_m must be finite")
    return flags, r - bias


def _starts(
    a: FloatArray,
    use: BoolArray,
    x0_m: ArrayLike | None,
    z_starts_m: ArrayLike | None,
    y_start_m: float,
) -> FloatArray:
    """Starts ``(B, S, 3)``: the given one per fix, or the floor grid of
    :func:`diffpos.estimators.starts.grid_starts` (D-NLS's)."""
    if x0_m is not None:
        x0 = np.asarray(x0_m, dtype=np.float64)
        return np.broadcast_to(x0.reshape(-1, 3) if x0.ndim == 1 else x0, (a.shape[0], 3))[:, None]
    return grid_starts(a, use, check_z_starts(z_starts_m), y_start_m)


def _project_iterations(
    aa: FloatArray,
    rrr: FloatArray,
    uu: BoolArray,
    ff: BoolArray,
    theta: FloatArray,
    *,
    max_iter: int,
    tol_m2: float,
) -> tuple[FloatArray, NDArray[np.int_], BoolArray]:
    """The parallel projections from starts ``theta (N, 3)`` (updated in place).

    Returns the estimates, the updates made and whether the stopping rule fired (no active
    measurement, or ``|phi_k - phi_{k-1}| < tol_m2``); rows with fewer than 3 used
    measurements are not iterated.
    """
    n = theta.shape[0]
    cnt = np.maximum(uu.sum(axis=-1), 1)
    phi_old = np.zeros(n)
    iters = np.zeros(n, dtype=np.int_)
    stopped = np.zeros(n, dtype=bool)
    active = uu.sum(axis=-1) >= 3
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        d = theta[idx][:, None, :] - aa[idx]
        dist = np.sqrt(np.einsum("nmi,nmi->nm", d, d))
        u_i = uu[idx]
        phi = np.where(u_i, (rrr[idx] - dist) ** 2, 0.0).sum(axis=-1) / cnt[idx]
        on = u_i & (~ff[idx] | (dist > rrr[idx])) & (dist > 0)
        with np.errstate(divide="ignore", invalid="ignore"):
            proj = aa[idx] + (rrr[idx] / dist)[..., None] * d
        n_on = on.sum(axis=-1)
        mean_proj = np.where(on[..., None], proj, 0.0).sum(axis=1) / np.maximum(n_on, 1)[:, None]
        move = n_on > 0
        theta[idx[move]] = mean_proj[move]
        iters[idx[move]] += 1
        stop = ~move | (np.abs(phi - phi_old[idx]) < tol_m2)
        phi_old[idx] = phi
        stopped[idx[stop]] = True
        active[idx[stop]] = False
    return theta, iters, stopped


def _best_start_result(
    pb: PreparedBatch,
    aa: FloatArray,
    rrr: FloatArray,
    uu: BoolArray,
    theta: FloatArray,
    iters: NDArray[np.int_],
    stopped: BoolArray,
    s: int,
) -> FixResult:
    """The start with the lowest ``phi`` at its estimate, per fix, as a :class:`FixResult`."""
    r, use = pb.ranges_m, pb.mask
    b, m = r.shape
    cnt = np.maximum(uu.sum(axis=-1), 1)
    d = theta[:, None, :] - aa
    dist = np.sqrt(np.einsum("nmi,nmi->nm", d, d))
    phi_end = np.where(uu, (rrr - dist) ** 2, 0.0).sum(axis=-1) / cnt
    phi_end = np.where(np.isfinite(phi_end), phi_end, np.inf).reshape(b, s)
    best = np.argmin(phi_end, axis=-1)
    sel = np.arange(b) * s + best
    x = theta[sel]
    n_used = use.sum(axis=-1)
    solvable = n_used >= 3
    x[~solvable] = np.nan
    dist_b = dist[sel]
    res = np.where(use & solvable[:, None], r - dist_b, np.nan)
    conv = stopped[sel] & solvable
    status = np.where(conv, int(FixStatus.OK_UNVERIFIED), int(FixStatus.NOT_CONVERGED))
    status[~solvable] = FixStatus.TOO_FEW_ANCHORS
    status[pb.input_error != 0] = FixStatus.INVALID_INPUT
    reason = np.where(pb.present, ExclusionReason.NONE, ExclusionReason.MISSING).astype(np.int_)
    sw = use / pb.sigmas_m
    t_stat = np.where(solvable & pb.sigmas_given, np.nansum((res * sw) ** 2, axis=-1), np.nan)
    return FixResult(
        position_m=x,
        covariance_m2=np.full((b, 3, 3), np.nan),
        peb_m=np.full(b, np.nan),
        z_bound_m=np.full(b, np.nan),
        iterations=iters[sel],
        converged=conv,
        status=status.astype(np.int_),
        residuals_m=res,
        used=use.copy(),
        excluded=np.zeros((b, m), dtype=bool),
        exclusion_reason=reason,
        test_statistic=t_stat,
        test_threshold=np.full(b, np.nan),
        dof=np.maximum(n_used - 3, 0),
        cost=phi_end.reshape(-1)[sel] * n_used / 2.0,
        input_error=pb.input_error,
        method="ippa",
        covariance_model="none",
        sigmas_given=pb.sigmas_given,
    )
