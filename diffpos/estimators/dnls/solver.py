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
  fix without ``sigmas_m``) are re-solved from all starts
  (:func:`diffpos.estimators.dnls.fit.multistart_fit`). This
  keeps the single-fix latency low; on 20,000 noisy random 4-anchor fixes it ended with a
  higher cost than running every start in 0.07 % of fixes (``keep_starts=None`` disables
  it).
* **Step control.** Levenberg-Marquardt damping ``(H + lambda diag H) dx = g`` with the cost
  deciding acceptance (``lambda / 3`` on success, ``x 8`` on failure), so every accepted
  step decreases the cost; pure Gauss-Newton is the limit ``lambda -> 0``.
* **Convergence tests** on the step size, relative cost decrease and gradient (see
  :func:`diffpos.estimators.lm.levenberg_marquardt`); ``converged`` reports them.
* **Mirror symmetry.** The model depends on ``y_n`` only through ``y_n^2``; a solution with
  ``y < 0`` is reflected to the inside (``y > 0``), which leaves the cost unchanged.

* **Exclusion search, bounded.** When the residual test fails, the gating solves every
  leave-one-out candidate again (:mod:`diffpos.estimators.gating`); on a realistic channel
  that is most fixes and ~90 % of the kernel's work. The candidates are solved only as far as
  ranking them needs (``exclusion_ftol``, the best one then to full convergence), the
  all-starts recheck runs only for fixes near consistency (``exclusion_recheck_ratio``), and
  candidates that a Gauss-Newton step shows cannot beat the one the linearised leave-one-out
  statistic ranks first are given up early (``exclusion_bound``). On the D-NLS replay of a
  30 s ``large`` recording: 0.48x the LM iterations, 0.54x the kernel's CPU, the same
  accuracy (``docs/dnls_cost.md``); ``None`` for all three is the exhaustive search.

After the fit, the covariance is the inverse FIM of the used measurements at the solution
(:func:`diffpos.bounds.fisher_information` and :func:`diffpos.bounds.bounds_from_fim`, the same
functions that give the PEB of the study), and the outlier gating of
:mod:`diffpos.estimators.gating` runs unless ``gating=None``.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.estimators.dnls.fit import (
    EXCLUSION_BOUND,
    EXCLUSION_BOUND_AFTER,
    EXCLUSION_FTOL,
    EXCLUSION_RECHECK_RATIO,
    RECHECK_PROBABILITY,
    FitSettings,
    solve_chunk,
)
from diffpos.estimators.gating import GatingConfig, chi2_threshold
from diffpos.estimators.lm import LOSSES, PathModel
from diffpos.estimators.lm_nb import LOSS_CODES
from diffpos.estimators.result import (
    ExclusionReason,
    FixResult,
    FixStatus,
    PreparedBatch,
    prepare_batch,
)
from diffpos.estimators.starts import DEFAULT_Z_STARTS_M, check_z_starts

__all__ = ["dnls"]

FloatArray = NDArray[np.float64]

_DEFAULT_GATING = GatingConfig()
#: The values of ``dnls(exclusion_starts=...)``.
EXCLUSION_STARTS = ("grid", "local")
_DEFAULT_ZS = np.asarray(DEFAULT_Z_STARTS_M, np.float64)
_PREGATE, _RAIM = int(ExclusionReason.PREGATE_SHORTER_THAN_LOS), int(ExclusionReason.RAIM)
_EXCLUSIONS = np.array([_PREGATE, _RAIM])
#: The two gating reasons are the highest codes: ``excluded`` is one comparison.
_EXCLUSIONS_LAST = sorted(int(c) for c in ExclusionReason)[-2:] == sorted((_PREGATE, _RAIM))


def _per_fix(value: ArrayLike, batch: int, name: str) -> FloatArray | float:
    if isinstance(value, float | int) and not isinstance(value, bool):
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite, got {float(value)}")
        return float(value)
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
    exclusion_ftol: float | None = EXCLUSION_FTOL,
    exclusion_recheck_ratio: float | None = EXCLUSION_RECHECK_RATIO,
    exclusion_bound: float | None = EXCLUSION_BOUND,
    exclusion_starts: str = "grid",
    chunk_size: int = 1024,
    kernel: bool = True,
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
        Start heights (default :data:`diffpos.estimators.starts.DEFAULT_Z_STARTS_M`).
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
    exclusion_ftol : float or None [-]
        The RAIM exclusion search (``GatingConfig.multistart_exclusion``) solves each
        leave-one-out candidate to this relative cost decrease only (enough to rank them),
        then iterates the best one on to the full convergence test, whose answer is the fix.
        ``None``: every candidate to the full test (the exhaustive search before 2026-12-06;
        ``docs/dnls_cost.md``). Default :data:`~diffpos.estimators.dnls.fit.EXCLUSION_FTOL`.
    exclusion_recheck_ratio : float or None [-]
        The exclusion search re-solves every candidate of a fix from all starts without
        screening when none passes the residual test; only if the best one's statistic is
        within this factor of its threshold (a fix further off has more than one bad range
        and screening is not what failed it). ``None``: always (before 2026-12-06). Default
        :data:`~diffpos.estimators.dnls.fit.EXCLUSION_RECHECK_RATIO`.
    exclusion_bound : float or None [-]
        With the linear loss, the exclusion search solves first the candidate that the
        linearised leave-one-out statistic ranks best, and gives up another candidate's start
        (after :data:`~diffpos.estimators.dnls.fit.EXCLUSION_BOUND_AFTER` iterations) once a
        Gauss-Newton step from where it is would leave its cost above this factor times the
        first candidate's cost: it cannot become the fix's best. ``None``: every candidate to
        convergence (before 2026-12-06). Default
        :data:`~diffpos.estimators.dnls.fit.EXCLUSION_BOUND`.
    exclusion_starts : {"grid", "local"}
        The starts of a cold fix's (no ``x0_m``) exclusion candidates: ``"grid"`` (default)
        every start of the first fit (the height grid and the LLS position, screened) plus
        the current solution; ``"local"`` the candidate's own LLS position and the current
        solution only (two starts, nothing screened, nothing rechecked: ~0.4x the cold
        fixes' CPU on the D-NLS replay of a 30 s ``large`` recording, the candidate's floor
        search left to the first fit's multi-start; accuracy side by side in
        ``docs/performance.md``, "Session 23: D-NLS replay"). Fixes with ``x0_m`` are
        unaffected.
    chunk_size : int
        Fixes solved together per chunk by the numpy reference (bounds memory; results depend
        on it only at the rounding level).
    kernel : bool
        Solve with the compiled kernel (:mod:`diffpos.estimators.dnls.fit_nb`, the default: same
        statuses, used anchors and exclusions; positions equal at the rounding level) or with
        the numpy reference implementation (``False``).

    Returns
    -------
    FixResult
        ``method="dnls"``, ``covariance_model="diffraction FIM"``.

    Examples
    --------
    >>> import numpy as np
    >>> from diffpos.estimators.dnls.solver import dnls
    >>> from diffpos.geometry import window_edge_path
    >>> anchors = np.array([[-15, -20, 1], [0, -15, 0], [0, -7, 4], [15, -20, 1.0]])
    >>> node = np.array([2.0, 5.0, 10.5])
    >>> r = window_edge_path(anchors, node, window_height_m=1.0).length_m
    >>> fix = dnls(anchors, r, 0.1, window_height_m=1.0)
    >>> bool(np.allclose(fix.position_m[0], node, atol=1e-6))
    True
    """
    _check_options(loss, loss_scale, gating)
    _check_search(exclusion_ftol, exclusion_recheck_ratio, exclusion_bound, exclusion_starts)
    batch_in = prepare_batch(anchors_m, ranges_m, sigmas_m, mask)
    bsz, m = batch_in.ranges_m.shape
    model = _path_model(window_height_m, delta_m, edge_x_m, bsz)
    x0, starts = _start_option(x0_m, z_starts_m, bsz)
    if kernel:
        out = _solve_compiled(batch_in, model, x0, starts, gating, loss, loss_scale, max_iter,
                              xtol_m, lls_start, keep_starts, screen_iter, y_start_m,
                              (exclusion_ftol, exclusion_recheck_ratio, exclusion_bound,
                               exclusion_starts))
        return _fix_result(out, batch_in)
    cfg = FitSettings(
        z_starts=starts,
        y_start=y_start_m,
        lls_start=lls_start,
        gating=gating,
        loss=loss,
        loss_scale=loss_scale,
        max_iter=max_iter,
        xtol=xtol_m,
        sigmas_given=batch_in.sigmas_given,
        keep_starts=keep_starts,
        screen_iter=screen_iter,
        exclusion_ftol=exclusion_ftol,
        exclusion_recheck_ratio=exclusion_recheck_ratio,
        exclusion_bound=exclusion_bound,
        exclusion_starts=exclusion_starts,
    )
    out = _alloc(bsz, m)
    for lo in range(0, bsz, max(int(chunk_size), 1)):
        sl = slice(lo, min(lo + max(int(chunk_size), 1), bsz))
        solve_chunk(
            out,
            sl,
            batch_in.anchors_m[sl],
            batch_in.ranges_m[sl],
            batch_in.sigmas_m[sl],
            batch_in.mask[sl],
            model.take(np.arange(sl.start, sl.stop)),
            None if x0 is None else x0[sl],
            cfg,
        )
    return _fix_result(out, batch_in)


@functools.lru_cache(maxsize=64)
def _thresholds(m: int, false_alarm_probability: float) -> FloatArray:
    """Chi-square thresholds by dof ``0..m`` (NaN below 1 dof; shared: never written)."""
    return chi2_threshold(np.arange(m + 1), false_alarm_probability)


def _solve_compiled(batch_in: PreparedBatch, model: PathModel, x0: FloatArray | None,
                    starts: FloatArray | None, gating: GatingConfig | None, loss: str,
                    loss_scale: float, max_iter: int, xtol: float, lls_start: bool,
                    keep_starts: int | None, screen_iter: int, y_start: float,
                    search: tuple[float | str | None, ...]) -> dict[str, np.ndarray]:
    """The whole batch through the compiled kernel; the output arrays of :func:`_alloc`
    (``search``: ``(exclusion_ftol, exclusion_recheck_ratio, exclusion_bound,
    exclusion_starts)``)."""
    bsz, m = batch_in.ranges_m.shape
    ipar, fpar = _kernel_options(LOSS_CODES[loss], float(loss_scale), int(max_iter), float(xtol),
                                 keep_starts, int(screen_iter), bool(lls_start),
                                 batch_in.sigmas_given, float(y_start), model.edge_x_m, gating,
                                 search)
    h_m = model.edge_offset_m
    if isinstance(h_m, float):
        h = np.empty(bsz)
        h.fill(h_m)
    else:
        h = np.array(np.broadcast_to(h_m, (bsz, 1))[:, 0], np.float64)  # writable
    if x0 is None:
        x0_c, has_x0 = np.zeros((bsz, 3)), np.zeros(bsz, bool)
    else:
        x0_c, has_x0 = np.array(x0, np.float64, order="C"), np.ones(bsz, bool)
    zs = np.zeros(1) if starts is None else np.ascontiguousarray(starts, np.float64)
    pfa = gating.false_alarm_probability if gating is not None else 0.5
    out = _kernel_outputs(bsz, m)
    # imported here: importing fit_nb compiles D-NLS (explicit signatures, ~44 s of CPU on a
    # fresh machine), which a fusion running M-NLS must not pay for
    from diffpos.estimators.dnls import fit_nb as dnls_nb

    dnls_nb.dnls_batch(batch_in.anchors_m, batch_in.ranges_m, batch_in.sigmas_m, batch_in.mask,
                       h, x0_c, has_x0, zs, ipar, fpar, _thresholds(m, pfa),
                       _thresholds(m, RECHECK_PROBABILITY), *out)
    pos, cov, out_i, out_f, resid, used, reason = out
    return {
        "position_m": pos, "covariance_m2": cov, "peb_m": out_f[:, 0], "z_bound_m": out_f[:, 1],
        "iterations": out_i[:, 0], "converged": out_i[:, 1] != 0, "status": out_i[:, 2],
        "residuals_m": resid, "used": used, "exclusion_reason": reason,
        "test_statistic": out_f[:, 2], "test_threshold": out_f[:, 3], "dof": out_i[:, 3],
        "cost": out_f[:, 4],
    }


@functools.lru_cache(maxsize=256)
def _kernel_options(loss: int, loss_scale: float, max_iter: int, xtol: float,
                    keep_starts: int | None, screen_iter: int, lls_start: bool,
                    sigmas_given: bool, y_start: float, edge_x_m: tuple[float, float] | None,
                    gating: GatingConfig | None, search: tuple[float | str | None, ...]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`diffpos.estimators.dnls.fit_nb.options`, once per distinct option set (the kernel only
    reads ``ipar``/``fpar``; shared arrays, never written)."""
    from diffpos.estimators.dnls import fit_nb as dnls_nb  # compiles on import: when used

    return dnls_nb.options(loss=loss, loss_scale=loss_scale, max_iter=max_iter, xtol=xtol,
                           keep_starts=keep_starts, screen_iter=screen_iter, lls_start=lls_start,
                           sigmas_given=sigmas_given, y_start=y_start, edge_x_m=edge_x_m,
                           gating=gating, exclusion_ftol=search[0], recheck_ratio=search[1],
                           bound=search[2], bound_after=EXCLUSION_BOUND_AFTER,
                           local_starts=search[3] == "local")


def _kernel_outputs(bsz: int, m: int) -> tuple[np.ndarray, ...]:
    """The output arrays of :func:`dnls_nb.dnls_batch` filled with an unsolved fix's values
    (as ``dnls_nb.run``): pos, cov, out_i (iterations, converged, status, dof), out_f (peb,
    z bound, statistic, threshold, cost), residuals, used, exclusion reason."""
    fl = np.empty(bsz * (3 + 9 + 5 + m))
    fl.fill(np.nan)
    pos = fl[: 3 * bsz].reshape(bsz, 3)
    cov = fl[3 * bsz: 12 * bsz].reshape(bsz, 3, 3)
    out_f = fl[12 * bsz: 17 * bsz].reshape(bsz, 5)
    resid = fl[17 * bsz:].reshape(bsz, m)
    out_i = np.zeros((bsz, 4), np.int64)
    out_i[:, 2] = FixStatus.TOO_FEW_ANCHORS
    return (pos, cov, out_i, out_f, resid, np.zeros((bsz, m), np.bool_),
            np.zeros((bsz, m), np.int64))


def _check_options(loss: str, loss_scale: float, gating: GatingConfig | None) -> None:
    """Validate the loss and the gating settings."""
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    if not loss_scale > 0:
        raise ValueError("loss_scale must be > 0")
    if gating is not None and not isinstance(gating, GatingConfig):
        raise TypeError("gating must be a GatingConfig or None")


def _check_search(exclusion_ftol: float | None, exclusion_recheck_ratio: float | None,
                  exclusion_bound: float | None, exclusion_starts: str = "grid") -> None:
    """Validate the exclusion search's bounds and starts."""
    if exclusion_starts not in EXCLUSION_STARTS:
        raise ValueError(f"exclusion_starts must be one of {EXCLUSION_STARTS}, got "
                         f"{exclusion_starts!r}")
    if exclusion_bound is not None and not exclusion_bound >= 1.0:
        raise ValueError("exclusion_bound must be None or >= 1 (a multiple of the first "
                         f"candidate's cost), got {exclusion_bound}")
    if exclusion_ftol is not None and not 0.0 < exclusion_ftol < 1.0:
        raise ValueError(f"exclusion_ftol must be None or in (0, 1), got {exclusion_ftol}")
    if exclusion_recheck_ratio is not None and not exclusion_recheck_ratio >= 1.0:
        raise ValueError("exclusion_recheck_ratio must be None or >= 1 (a multiple of the "
                         f"chi-square threshold), got {exclusion_recheck_ratio}")


def _path_model(
    window_height_m: float | ArrayLike,
    delta_m: float | ArrayLike,
    edge_x_m: ArrayLike | None,
    bsz: int,
) -> PathModel:
    """The validated path model (scalars or per-fix ``(B,)`` arrays)."""
    wh = _per_fix(window_height_m, bsz, "window_height_m")
    if (wh <= 0) if isinstance(wh, float) else np.any(wh <= 0):
        raise ValueError("window_height_m must be > 0")
    de = _per_fix(delta_m, bsz, "delta_m")
    edge = check_edge_x(edge_x_m)
    return PathModel(window_height_m=wh, delta_m=de, edge_x_m=edge)


def _start_option(
    x0_m: ArrayLike | None, z_starts_m: ArrayLike | None, bsz: int
) -> tuple[FloatArray | None, FloatArray | None]:
    """``(x0 (B, 3), None)`` for one given start per fix, else ``(None, start heights)``."""
    if x0_m is not None:
        x0 = np.asarray(x0_m, dtype=np.float64)
        x0 = x0.reshape(-1, 3) if x0.ndim == 1 else x0
        x0 = x0 if x0.shape == (bsz, 3) else np.broadcast_to(x0, (bsz, 3))
        if not np.all(np.isfinite(x0)):
            raise ValueError("x0_m must be finite")
        return x0, None
    if z_starts_m is None:
        return None, _DEFAULT_ZS  # validated once; the solvers only read it
    return None, check_z_starts(z_starts_m)


def _fix_result(out: dict[str, np.ndarray], batch_in: PreparedBatch) -> FixResult:
    """The :class:`FixResult` of the filled output arrays (invalid and missing marked)."""
    reason = out["exclusion_reason"]
    if not batch_in.all_valid:
        invalid = batch_in.input_error != 0
        if invalid.any():
            out["status"][invalid] = FixStatus.INVALID_INPUT
            reason[invalid[:, None] & batch_in.present] = ExclusionReason.NONE
        if not batch_in.present.all():
            reason[~batch_in.present] = ExclusionReason.MISSING
    out["excluded"] = (reason >= _PREGATE) if _EXCLUSIONS_LAST else np.isin(reason, _EXCLUSIONS)
    out["input_error"] = batch_in.input_error
    out["sigmas_given"] = batch_in.sigmas_given
    out["method"], out["covariance_model"] = "dnls", "diffraction FIM"
    return FixResult.from_fields(out)


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
