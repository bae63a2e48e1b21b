"""Result type shared by the batched estimators, status codes and input preparation.

Every estimator (:func:`~diffpos.estimators.dnls.solver`, :func:`~diffpos.estimators.lls`,
:func:`~diffpos.estimators.ippa`) returns one :class:`FixResult` holding batched arrays: row
``i`` is the fix of problem ``i``. Per-fix human-readable messages are built lazily by
:meth:`FixResult.message` so that a batch of 100,000 fixes costs no string formatting.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["ExclusionReason", "FixResult", "FixStatus", "InputError", "PreparedBatch"]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int_]


class FixStatus(enum.IntEnum):
    """Outcome of one fix (stored as small integers in :attr:`FixResult.status`)."""

    OK = 0
    """Converged, identifiable, and the residual test (RAIM) passed."""
    OK_UNVERIFIED = 1
    """Converged and identifiable, but the residuals could not be tested: too few anchors
    (``|S| <= 3`` leaves no redundancy), no noise model (``sigmas_m`` not given), or gating
    disabled."""
    NOT_CONVERGED = 2
    """The iteration limit was reached or the step control failed before convergence."""
    NOT_IDENTIFIABLE = 3
    """The FIM at the solution is singular or ill-conditioned (paper Theorem 2); the
    covariance is infinite in the weak direction."""
    TOO_FEW_ANCHORS = 4
    """Fewer than 3 usable measurements (paper Corollary 3: ``M >= 3`` is necessary)."""
    GATING_FAILED = 5
    """The residual test failed and no exclusion could make it pass (or too few anchors
    remained to try), or the test passed but the position lies outside the plausible heights
    (``GatingConfig.z_range_m``, default below ground; the message says which). The position
    is returned but should not be trusted."""
    INVALID_INPUT = 6
    """A field of the problem is malformed (non-finite, negative range, bad sigma)."""


class ExclusionReason(enum.IntEnum):
    """Why a measurement was not used (stored in :attr:`FixResult.exclusion_reason`)."""

    NONE = 0
    """Used in the fix."""
    MISSING = 1
    """Not present (``mask`` False, padding of a ragged anchor set)."""
    PREGATE_SHORTER_THAN_LOS = 2
    """The range is shorter than the straight line anchor-node at the fitted position by more
    than the tolerance: no diffraction path can be that short."""
    RAIM = 3
    """Excluded by the chi-square residual test (fault detection and exclusion)."""


class InputError(enum.IntEnum):
    """Which input field made a fix invalid (``0`` = none)."""

    NONE = 0
    ANCHORS = 1
    RANGES_NONFINITE = 2
    RANGES_NEGATIVE = 3
    SIGMAS = 4


_INPUT_ERROR_TEXT = {
    InputError.ANCHORS: "anchors_m contains NaN or inf for a present measurement",
    InputError.RANGES_NONFINITE: "ranges_m contains NaN or inf for a present measurement",
    InputError.RANGES_NEGATIVE: "ranges_m contains a negative range",
    InputError.SIGMAS: "sigmas_m must be finite and > 0",
}

_REASON_TEXT = {
    ExclusionReason.MISSING: "missing",
    ExclusionReason.PREGATE_SHORTER_THAN_LOS: "shorter than the straight line (pre-gate)",
    ExclusionReason.RAIM: "failed the residual test (RAIM)",
}


@dataclass(frozen=True)
class FixResult:
    """Batched position fixes (one row per problem), ``scipy.optimize.OptimizeResult`` style.

    Attributes
    ----------
    position_m : ndarray, shape (B, 3) [m]
        Estimated node positions in building coordinates (NaN where no estimate exists).
    covariance_m2 : ndarray, shape (B, 3, 3) [m^2]
        Inverse FIM at the solution over the used measurements (see ``covariance_model``);
        ``inf`` where not identifiable, NaN where the method has no noise model.
    peb_m : ndarray, shape (B,) [m]
        ``sqrt(trace(covariance_m2))``, the position error bound at the estimate.
    z_bound_m : ndarray, shape (B,) [m]
        ``sqrt(covariance_m2[2, 2])``.
    iterations : ndarray of int, shape (B,)
        Iterations of the final fit (the best start, after the last exclusion).
    converged : ndarray of bool, shape (B,)
        Convergence test passed for the final fit.
    status : ndarray of int, shape (B,)
        :class:`FixStatus` codes.
    residuals_m : ndarray, shape (B, M) [m]
        Measured minus modelled range at the solution, NaN for unused measurements.
    used : ndarray of bool, shape (B, M)
        Measurements used in the final fit.
    excluded : ndarray of bool, shape (B, M)
        Measurements present in the input but excluded by gating.
    exclusion_reason : ndarray of int, shape (B, M)
        :class:`ExclusionReason` codes.
    test_statistic : ndarray, shape (B,) [-]
        Sum of squared normalised residuals ``sum (r_j / sigma_j)^2`` over the used set (NaN
        if not computed).
    test_threshold : ndarray, shape (B,) [-]
        Chi-square threshold for ``dof`` at the false-alarm probability (NaN if no test).
    dof : ndarray of int, shape (B,)
        Degrees of freedom ``|S| - 3`` of the final test.
    cost : ndarray, shape (B,) [-]
        Final value of the minimised cost ``0.5 sum rho((r_j / sigma_j)^2)``.
    input_error : ndarray of int, shape (B,)
        :class:`InputError` code of invalid problems.
    method : str
        ``"dnls"``, ``"lls"`` or ``"ippa"``.
    covariance_model : str
        What ``covariance_m2`` is: ``"diffraction FIM"``, ``"LoS FIM"`` or ``"none"``.
    sigmas_given : bool
        Whether the caller gave ``sigmas_m`` (otherwise 1 m was assumed and the covariance
        was scaled by the a-posteriori variance factor).
    condition : ndarray, shape (B,), optional [-]
        Condition number of the linear system (LLS only).
    """

    position_m: FloatArray
    covariance_m2: FloatArray
    peb_m: FloatArray
    z_bound_m: FloatArray
    iterations: IntArray
    converged: BoolArray
    status: IntArray
    residuals_m: FloatArray
    used: BoolArray
    excluded: BoolArray
    exclusion_reason: IntArray
    test_statistic: FloatArray
    test_threshold: FloatArray
    dof: IntArray
    cost: FloatArray
    input_error: IntArray
    method: str
    covariance_model: str
    sigmas_given: bool = True
    condition: FloatArray | None = None

    def __len__(self) -> int:
        return int(self.position_m.shape[0])

    @classmethod
    def from_fields(cls, fields: dict[str, Any]) -> FixResult:
        """The result with exactly the dataclass's fields from ``fields`` (every field without
        a default must be there), without the frozen ``__init__``'s per-field
        ``object.__setattr__`` (~3 us of a single fix's ~50 us); same object otherwise."""
        missing = _FIX_REQUIRED.difference(fields)
        if missing or not _FIX_FIELDS.issuperset(fields):
            raise TypeError(f"FixResult fields: missing {sorted(missing)}, unknown "
                            f"{sorted(set(fields) - _FIX_FIELDS)}")
        obj = object.__new__(cls)
        obj.__dict__.update(_FIX_DEFAULTS)
        obj.__dict__.update(fields)
        return obj

    @property
    def ok(self) -> BoolArray:
        """True where the status is ``OK`` or ``OK_UNVERIFIED``."""
        return (self.status == FixStatus.OK) | (self.status == FixStatus.OK_UNVERIFIED)

    def excluded_list(self, i: int) -> list[dict[str, Any]]:
        """Excluded measurements of fix ``i`` as ``[{"index": j, "reason": name}]``."""
        out = []
        for j in np.flatnonzero(self.excluded[i]):
            reason = ExclusionReason(int(self.exclusion_reason[i, j]))
            out.append({"index": int(j), "reason": reason.name.lower()})
        return out

    def message(self, i: int) -> str:
        """Human-readable verdict of fix ``i``."""
        return self.messages(np.array([i]))[0]

    def messages(self, rows: ArrayLike | None = None) -> list[str]:
        """Human-readable verdicts of fixes ``rows`` (default: all), like :meth:`message`.

        The arrays are converted to Python values once for the whole selection (the fusion
        builds one verdict per fix: ~1-2 us each here instead of ~15 us through
        :meth:`message` per row).
        """
        idx = np.arange(len(self)) if rows is None else np.asarray(rows, dtype=np.intp)
        ex = self.excluded[idx]
        reasons = self.exclusion_reason[idx]
        excl_txt = [""] * idx.size
        for k, j in zip(*np.nonzero(ex), strict=True):  # exclusions are rare: loop over them only
            reason = _REASON_TEXT[ExclusionReason(int(reasons[k, j]))]
            excl_txt[k] += (", " if excl_txt[k] else "; excluded ") + f"anchor {j} ({reason})"
        cond = self.condition[idx].tolist() if self.condition is not None else None
        cols = zip(
            self.status[idx].tolist(), self.used[idx].sum(axis=-1).tolist(), excl_txt,
            self.test_statistic[idx].tolist(), self.test_threshold[idx].tolist(),
            self.dof[idx].tolist(), self.iterations[idx].tolist(),
            self.input_error[idx].tolist(), self.position_m[idx, 2].tolist(),
            cond if cond is not None else [None] * idx.size,
            strict=True,
        )
        return [self._verdict(*c) for c in cols]

    def _verdict(self, st: int, n_used: int, excl_txt: str, stat: float, thr: float,
                 dof: int, it: int, input_error: int, z_m: float, cond: float | None) -> str:
        test_txt = ""
        if math.isfinite(thr):
            test_txt = f"; residual test {stat:.3g} vs threshold {thr:.3g} (chi2, {dof} dof)"
        if st == FixStatus.INVALID_INPUT:
            return "invalid input: " + _INPUT_ERROR_TEXT.get(
                InputError(input_error), "malformed problem"
            )
        if st == FixStatus.TOO_FEW_ANCHORS:
            return (
                f"too few anchors: {n_used} usable measurement(s) after gating, at least 3 are "
                "needed for a 3D fix" + excl_txt
            )
        if st == FixStatus.NOT_IDENTIFIABLE and self.method == "lls":
            c = float(cond) if cond is not None else float("inf")
            return (
                f"not identifiable: the LLS system of {n_used} anchors is rank deficient or "
                f"ill-conditioned (condition {c:.3g}); differencing needs >= 4 anchors not "
                "in one plane. No minimum-norm answer is returned"
            )
        if st == FixStatus.NOT_IDENTIFIABLE:
            return (
                f"not identifiable: the FIM at the solution ({n_used} anchors) is singular or "
                "ill-conditioned; the anchors do not constrain every direction (e.g. all "
                "anchors and the node in one vertical plane x = const)" + excl_txt
            )
        if st == FixStatus.NOT_CONVERGED and self.method != "ippa":
            return f"not converged after {it} iterations ({n_used} anchors)" + excl_txt + test_txt
        if st == FixStatus.GATING_FAILED and stat <= thr:
            # the test passed: only the plausibility check (GatingConfig.z_range_m) fails a fix
            return (
                f"residual test passed with {n_used} anchors, but the height "
                f"z = {z_m:.3g} m is outside the plausible range "
                "(GatingConfig.z_range_m, default above ground): likely a mirror solution, "
                "the position is unreliable" + excl_txt + test_txt
            )
        if st == FixStatus.GATING_FAILED:
            return (
                f"residual test failed and exclusion could not fix it ({n_used} anchors left); "
                "the position is unreliable" + excl_txt + test_txt
            )
        if st == FixStatus.OK_UNVERIFIED:
            if self.method == "lls":
                return (
                    f"solved in closed form with {n_used} anchors assuming LoS, unverified "
                    "(LLS does not test its residuals)"
                )
            if self.method == "ippa":
                return (
                    f"stopped after {it} projection updates with {n_used} anchors, unverified "
                    "(IPPA has no residual test)"
                )
            if not self.sigmas_given:
                why = "no sigmas_m given, residuals cannot be tested"
            elif n_used <= 3:
                why = f"only {n_used} anchors, no redundancy to test the residuals"
            else:
                why = "gating disabled"
            return f"converged in {it} iterations, unverified ({why})" + excl_txt
        if st == FixStatus.NOT_CONVERGED:  # ippa
            return f"IPPA hit its limit of {it} projection updates ({n_used} anchors)"
        return f"converged in {it} iterations with {n_used} anchors" + excl_txt + test_txt

    def to_records(self) -> list[dict[str, Any]]:
        """JSON-ready dicts, one per fix (the ``diffpos solve`` output fields).

        Non-finite numbers become ``None`` (JSON ``null``). Built column by column: every
        array is converted to Python values once for the whole batch, and only the rows that
        hold a non-finite number are cleaned element by element.
        """
        b = len(self)
        names = [_STATUS_NAMES[s] for s in self.status.tolist()]
        messages = self.messages()  # all verdicts at once (message(i) converts per call)
        pos, cov, res = (_clean_rows(self.position_m), _clean_rows(self.covariance_m2),
                         _clean_rows(self.residuals_m))
        peb, zb = _clean_scalars(self.peb_m), _clean_scalars(self.z_bound_m)
        stat, thr = _clean_scalars(self.test_statistic), _clean_scalars(self.test_threshold)
        iters, conv = self.iterations.tolist(), self.converged.tolist()
        m = self.used.shape[1]
        all_used = list(range(m))
        used_rows = self.used.tolist()
        any_excl = self.excluded.any(axis=1).tolist()
        out = []
        for i in range(b):
            u = used_rows[i]
            out.append({
                "status": names[i], "message": messages[i], "method": self.method,
                "position_m": pos[i], "covariance_m2": cov[i],
                "covariance_model": self.covariance_model, "peb_m": peb[i], "z_bound_m": zb[i],
                "iterations": iters[i], "converged": conv[i],
                "used_anchors": all_used.copy() if all(u) else [j for j in range(m) if u[j]],
                "excluded_anchors": self.excluded_list(i) if any_excl[i] else [],
                "residuals_m": res[i], "test_statistic": stat[i], "test_threshold": thr[i],
            })
        return out


_STATUS_NAMES = {int(s): s.name.lower() for s in FixStatus}
_FIX_FIELDS = frozenset(f.name for f in dataclasses.fields(FixResult))
_FIX_DEFAULTS = {f.name: f.default for f in dataclasses.fields(FixResult)
                 if f.default is not dataclasses.MISSING}
_FIX_REQUIRED = _FIX_FIELDS - set(_FIX_DEFAULTS)


def _clean_rows(a: np.ndarray) -> list[Any]:
    """Rows of ``a`` as nested lists, non-finite numbers as ``None``."""
    arr = np.asarray(a, dtype=np.float64)
    rows = arr.tolist()
    fin = np.isfinite(arr).reshape(arr.shape[0], -1).all(axis=1)
    for i in np.flatnonzero(~fin).tolist():
        rows[i] = _nan_to_none(np.where(np.isfinite(arr[i]), arr[i], np.nan).tolist())
    return rows


def _clean_scalars(a: np.ndarray) -> list[float | None]:
    """``a (B,)`` as floats, non-finite as ``None``."""
    arr = np.asarray(a, dtype=np.float64)
    return [v if math.isfinite(v) else None for v in arr.tolist()]


def _nan_to_none(x: Any) -> Any:
    if isinstance(x, list):
        return [_nan_to_none(v) for v in x]
    if isinstance(x, float) and x != x:
        return None
    return x


@dataclass(frozen=True)
class PreparedBatch:
    """Validated, broadcast inputs (internal)."""

    anchors_m: FloatArray  # (B, M, 3), finite everywhere (placeholders where masked)
    ranges_m: FloatArray  # (B, M), finite everywhere
    sigmas_m: FloatArray  # (B, M), finite > 0 everywhere
    mask: BoolArray  # (B, M) present and valid
    present: BoolArray  # (B, M) as given by the caller
    input_error: IntArray  # (B,)
    sigmas_given: bool
    all_valid: bool = False  # True: every value present and valid (no masking to apply)


def prepare_batch(
    anchors_m: ArrayLike,
    ranges_m: ArrayLike,
    sigmas_m: ArrayLike | None,
    mask: ArrayLike | None,
) -> PreparedBatch:
    """Broadcast and validate estimator inputs.

    Shape errors raise ``ValueError`` naming the field. Value errors (NaN/inf, negative
    ranges, non-positive sigmas) are reported per fix through ``input_error`` so that one bad
    problem does not abort a batch.
    """
    a = np.asarray(anchors_m, dtype=np.float64)
    r = np.asarray(ranges_m, dtype=np.float64)
    if mask is None and a.ndim == 2 and r.ndim == 1:
        fast = _single_fix(a, r, sigmas_m)
        if fast is not None:
            return fast
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3 or a.shape[-1] != 3:
        raise ValueError(f"anchors_m must have shape (B, M, 3) or (M, 3), got {a.shape}")
    if r.ndim == 1:
        r = r[None]
    if r.ndim != 2:
        raise ValueError(f"ranges_m must have shape (B, M) or (M,), got {r.shape}")
    batch = max(a.shape[0], r.shape[0])
    m = a.shape[1]
    if r.shape[1] != m:
        raise ValueError(
            f"ranges_m has {r.shape[1]} measurements per fix but anchors_m has {m} anchors"
        )
    for name, arr in (("anchors_m", a), ("ranges_m", r)):
        if arr.shape[0] not in (1, batch):
            raise ValueError(f"{name} batch size {arr.shape[0]} does not match {batch}")
    if a.shape[0] != batch:
        a = np.broadcast_to(a, (batch, m, 3))
    if r.shape[0] != batch:
        r = np.broadcast_to(r, (batch, m))
    sigmas_given = sigmas_m is not None
    if sigmas_m is None:
        s = np.ones((batch, m))
    elif isinstance(sigmas_m, float | int) and not isinstance(sigmas_m, bool):
        s = np.full((batch, m), float(sigmas_m))
    else:
        s = np.asarray(sigmas_m, dtype=np.float64)
        try:
            s = s if s.shape == (batch, m) else np.broadcast_to(s, (batch, m))
        except ValueError:
            raise ValueError(
                f"sigmas_m must be a scalar or broadcast to (B, M) = {(batch, m)}, got {s.shape}"
            ) from None
    if mask is None:
        present = np.ones((batch, m), dtype=bool)
    else:
        pm = np.asarray(mask)
        if pm.dtype != bool:
            raise ValueError(f"mask must be a bool array, got dtype {pm.dtype}")
        try:
            present = np.broadcast_to(pm, (batch, m)).copy()
        except ValueError:
            raise ValueError(
                f"mask must broadcast to (B, M) = {(batch, m)}, got {pm.shape}"
            ) from None
    if (
        present.all() and np.isfinite(a).all() and np.isfinite(r).all() and (r >= 0).all()
        and (s > 0).all() and np.isfinite(s).all()
    ):  # the common case: every value valid and present, nothing to mask (same result)
        return _as_given(a, r, s, present, sigmas_given)
    err = _input_errors(a, r, s, present)
    valid_fix = err == 0
    use = present & valid_fix[:, None]
    # Masked anchors get a harmless finite placeholder (never enters a sum: weight 0).
    a_safe = np.where(use[..., None], a, np.array([0.0, -1.0, 0.0]))
    r_safe = np.where(use, r, 0.0)
    s_safe = np.where(use, s, 1.0)
    return PreparedBatch(
        anchors_m=np.ascontiguousarray(a_safe),
        ranges_m=np.ascontiguousarray(r_safe),
        sigmas_m=np.ascontiguousarray(s_safe),
        mask=use,
        present=present,
        input_error=err,
        sigmas_given=sigmas_given,
    )


def _input_errors(a: np.ndarray, r: np.ndarray, s: np.ndarray, present: np.ndarray
                  ) -> IntArray:
    """Per fix the first offending field (:class:`InputError`), 0 where valid."""
    err = np.zeros(r.shape[0], dtype=np.int_)
    bad_r_neg = present & (r < 0)
    bad_r_nf = present & ~np.isfinite(r)
    bad_a = present & ~np.all(np.isfinite(a), axis=-1)
    bad_s = present & ~(np.isfinite(s) & (s > 0))
    # Report the first offending field in order anchors, ranges, sigmas.
    for code, bad in (
        (InputError.SIGMAS, bad_s),
        (InputError.RANGES_NEGATIVE, bad_r_neg),
        (InputError.RANGES_NONFINITE, bad_r_nf),
        (InputError.ANCHORS, bad_a),
    ):
        err = np.where(np.any(bad, axis=-1), int(code), err)
    return err


def _single_fix(a: np.ndarray, r: np.ndarray, sigmas_m: ArrayLike | None
                ) -> PreparedBatch | None:
    """The common single-fix call (anchors ``(M, 3)``, ranges ``(M,)``, sigma scalar or None,
    no mask) when every value is valid, else None (the general path then gives the same
    batch or the per-fix input errors). Finite minimum and maximum = every value finite
    (NaN propagates through both)."""
    m = r.shape[0]
    if a.shape != (m, 3) or m == 0:
        return None
    if sigmas_m is None:
        sig = 1.0
    elif isinstance(sigmas_m, float | int) and not isinstance(sigmas_m, bool):
        sig = float(sigmas_m)
        if not (sig > 0 and math.isfinite(sig)):
            return None
    else:
        return None
    r_lo, r_hi = float(np.minimum.reduce(r)), float(np.maximum.reduce(r))
    if not (math.isfinite(float(np.minimum.reduce(a, None)))
            and math.isfinite(float(np.maximum.reduce(a, None)))
            and r_lo >= 0 and math.isfinite(r_hi)):  # min/max propagate NaN
        return None
    s = np.empty((1, m))
    s.fill(sig)
    present = np.ones((1, m), dtype=bool)
    return PreparedBatch(
        anchors_m=np.array(a.reshape(1, m, 3), np.float64, order="C"),
        ranges_m=np.array(r.reshape(1, m), np.float64, order="C"),
        sigmas_m=s,
        mask=present,
        present=present.copy(),
        input_error=np.zeros(1, dtype=np.int_),
        sigmas_given=sigmas_m is not None,
        all_valid=True,
    )


def _as_given(a: np.ndarray, r: np.ndarray, s: np.ndarray, present: np.ndarray,
              sigmas_given: bool) -> PreparedBatch:
    """The batch of valid, all-present inputs (contiguous copies)."""
    return PreparedBatch(
        anchors_m=np.array(a, np.float64, order="C"),
        ranges_m=np.array(r, np.float64, order="C"),
        sigmas_m=np.array(s, np.float64, order="C"),
        mask=present,
        present=present.copy(),
        input_error=np.zeros(r.shape[0], dtype=np.int_),
        sigmas_given=sigmas_given,
        all_valid=True,
    )
