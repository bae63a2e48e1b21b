"""Positioning accuracy metrics: the one scorer of emulate, replay and the benchmarks.

Pure numpy/scipy. Everything works on arrays of *node-epochs* (one row per node and fusion
epoch, or per published fix): a row without a position (``NaN`` estimate) is a miss, so it
counts against availability and against the floor accuracy over all node-epochs, and is
left out of the error percentiles.

* :func:`percentiles` - the percentile summary of one error distribution
  (``p50 ... p99``, ``max``, ``mean``; ``None`` when empty).
* :func:`error_stats` - the per-group summary of ``diffpos replay``'s report.
* :func:`availability`, :func:`floor_accuracy`, :func:`ellipsoid_coverage` - the single
  quantities.
* :func:`score` - all of them at once from estimates, truth, floors and covariances.

Examples
--------
>>> import numpy as np
>>> est = np.array([[0.0, 0.0, 1.0], [np.nan, np.nan, np.nan]])
>>> s = score(est, np.zeros((2, 3)), estimate_floor=[0, -1], truth_floor=[0, 0])
>>> s.availability, s.floor_accuracy_all, s.floor_accuracy_fixes
(0.5, 0.5, 1.0)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.stats import chi2

__all__ = [
    "PERCENTILES",
    "Score",
    "availability",
    "ellipsoid_coverage",
    "error_stats",
    "floor_accuracy",
    "percentiles",
    "score",
]

#: percentiles reported for every error distribution (``diffpos replay``)
PERCENTILES: tuple[int, ...] = (50, 67, 90, 95, 99)


def percentiles(
    values: ArrayLike, q: Sequence[float] = PERCENTILES, *, max_mean: bool = True
) -> dict[str, float | None]:
    """Percentile summary of one distribution.

    Parameters
    ----------
    values : array_like, shape (K,)
        The samples (e.g. 3D errors [m]); must be finite.
    q : sequence of float
        Percentiles in [0, 100]; key ``p<q>`` each (numpy's default linear interpolation).
    max_mean : bool
        Also report ``max`` and ``mean``.

    Returns
    -------
    dict
        ``p<q>`` for each ``q`` (then ``max``, ``mean``); every value ``None`` when empty.
    """
    v = np.asarray(values, dtype=float).reshape(-1)
    keys = [f"p{p}" for p in q]
    if v.size == 0:
        out: dict[str, float | None] = dict.fromkeys(keys)
        if max_mean:
            out |= {"max": None, "mean": None}
        return out
    vals = np.percentile(v, list(q))
    out = {k: float(x) for k, x in zip(keys, vals, strict=True)}
    if max_mean:
        out["max"] = float(v.max())
        out["mean"] = float(v.mean())
    return out


def availability(has_position: ArrayLike) -> float | None:
    """Share of node-epochs with a position (a missing position is a miss).

    Parameters
    ----------
    has_position : array_like of bool, shape (N,)
        One entry per node-epoch.

    Returns
    -------
    float or None
        ``sum / N``; ``None`` when there are no node-epochs.
    """
    h = np.asarray(has_position, dtype=bool).reshape(-1)
    return float(h.mean()) if h.size else None


def floor_accuracy(
    estimate_floor: ArrayLike, truth_floor: ArrayLike, has_position: ArrayLike | None = None
) -> tuple[float | None, float | None]:
    """Floor accuracy over all node-epochs and over the fixes (node-epochs with a position).

    Parameters
    ----------
    estimate_floor, truth_floor : array_like of int, shape (N,)
        Estimated and true floor index per node-epoch (the estimate's value is ignored where
        there is no position).
    has_position : array_like of bool, shape (N,), optional
        Default: every node-epoch has a position.

    Returns
    -------
    over_all : float or None
        Right floor with a position / N (a miss counts as wrong); ``None`` when N = 0.
    over_fixes : float or None
        Right floor / fixes; ``None`` without fixes.
    """
    ef = np.asarray(estimate_floor).reshape(-1)
    tf = np.asarray(truth_floor).reshape(-1)
    h = (
        np.ones(ef.shape, bool)
        if has_position is None
        else np.asarray(has_position, bool).reshape(-1)
    )
    right = (ef == tf) & h
    n, k = int(h.size), int(h.sum())
    return (float(right.sum() / n) if n else None, float(right.sum() / k) if k else None)


def ellipsoid_coverage(
    error_m: ArrayLike, covariance_m2: ArrayLike, *, probability: float = 0.95
) -> float | None:
    """Share of fixes whose truth lies inside the reported ``probability`` error ellipsoid.

    Inside means ``d^T C^-1 d <= chi2_3^-1(probability)`` with ``d`` = estimate - truth and
    ``C`` the reported 3x3 covariance (a consistent estimator gives ~``probability``).
    Rows with a non-finite error or covariance are left out.

    Parameters
    ----------
    error_m : array_like, shape (K, 3) [m]
    covariance_m2 : array_like, shape (K, 3, 3) [m^2]
    probability : float
        Ellipsoid probability (0.95: the 95 % ellipsoid).

    Returns
    -------
    float or None
        ``None`` when no row has both.
    """
    d = np.asarray(error_m, dtype=float).reshape(-1, 3)
    c = np.asarray(covariance_m2, dtype=float).reshape(-1, 3, 3)
    ok = np.isfinite(d).all(axis=1) & np.isfinite(c).all(axis=(1, 2))
    if not ok.any():
        return None
    d, c = d[ok], c[ok]
    m2 = np.einsum("ki,kij,kj->k", d, np.linalg.pinv(c, hermitian=True), d)
    return float(np.mean(m2 <= chi2.ppf(probability, 3)))


def error_stats(
    err_3d_m: np.ndarray,
    err_z_m: np.ndarray,
    err_h_m: np.ndarray,
    floor_ok: np.ndarray,
    peb_m: np.ndarray,
    *,
    fixes: int,
) -> dict[str, Any]:
    """Summary of one error distribution (the groups of ``diffpos replay``'s report).

    Parameters
    ----------
    err_3d_m, err_z_m, err_h_m : ndarray, shape (K,) [m]
        3D, vertical (absolute) and horizontal errors of the fixes with a position and truth.
    floor_ok : ndarray of bool, shape (K,)
        Estimated floor index equals the true one.
    peb_m : ndarray, shape (K,) [m]
        PEB reported with each fix (NaN when absent).
    fixes : int
        All fixes of the group (with or without a position), for availability.

    Returns
    -------
    dict
        ``fixes``, ``evaluated``, ``availability`` (evaluated / fixes), ``error_3d_m``,
        ``error_z_m``, ``error_h_m`` (percentiles, max, mean), ``rmse_3d_m``,
        ``floor_accuracy`` (over the evaluated fixes), ``peb_m`` (percentiles of the reported
        PEB) and ``within_2peb`` (fraction of fixes with error <= 2 PEB).
    """
    k = int(err_3d_m.size)
    finite_peb = np.isfinite(peb_m)
    return {
        "fixes": int(fixes),
        "evaluated": k,
        "availability": (k / fixes) if fixes else None,
        "error_3d_m": percentiles(err_3d_m),
        "error_z_m": percentiles(err_z_m),
        "error_h_m": percentiles(err_h_m),
        "rmse_3d_m": float(np.sqrt(np.mean(err_3d_m**2))) if k else None,
        "floor_accuracy": float(np.mean(floor_ok)) if k else None,
        "peb_m": percentiles(peb_m[finite_peb]),
        "within_2peb": float(np.mean(err_3d_m[finite_peb] <= 2 * peb_m[finite_peb]))
        if finite_peb.any()
        else None,
    }


@dataclass(frozen=True)
class Score:
    """Accuracy of a set of node-epochs (see :func:`score`).

    Attributes
    ----------
    node_epochs : int
        Rows scored.
    fixes : int
        Rows with a position.
    availability : float or None
        ``fixes / node_epochs``.
    error_3d_m, error_z_m, error_h_m : dict
        :func:`percentiles` of the 3D, absolute vertical and horizontal errors of the fixes.
    rmse_3d_m : float or None
    floor_accuracy_all, floor_accuracy_fixes : float or None
        See :func:`floor_accuracy` (``None`` without floors).
    ellipsoid_coverage : float or None
        See :func:`ellipsoid_coverage` (``None`` without covariances).
    """

    node_epochs: int
    fixes: int
    availability: float | None
    error_3d_m: dict[str, float | None]
    error_z_m: dict[str, float | None]
    error_h_m: dict[str, float | None]
    rmse_3d_m: float | None
    floor_accuracy_all: float | None
    floor_accuracy_fixes: float | None
    ellipsoid_coverage: float | None

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (field order)."""
        return dict(self.__dict__)


def score(
    estimate_m: ArrayLike,
    truth_m: ArrayLike,
    *,
    estimate_floor: ArrayLike | None = None,
    truth_floor: ArrayLike | None = None,
    covariance_m2: ArrayLike | None = None,
    q: Sequence[float] = PERCENTILES,
    probability: float = 0.95,
) -> Score:
    """Score node-epochs against the truth.

    Parameters
    ----------
    estimate_m : array_like, shape (N, 3) [m]
        Estimated positions; a row with a NaN is a node-epoch without a position (a miss).
    truth_m : array_like, shape (N, 3) [m]
        True positions at the same times.
    estimate_floor, truth_floor : array_like of int, shape (N,), optional
        Floor indices (both needed for the floor accuracies).
    covariance_m2 : array_like, shape (N, 3, 3) [m^2], optional
        Reported covariances (NaN where absent), for the ellipsoid coverage.
    q : sequence of float
        Percentiles of the error summaries.
    probability : float
        Probability of the error ellipsoid (0.95).

    Returns
    -------
    Score
    """
    est = np.asarray(estimate_m, dtype=float).reshape(-1, 3)
    tru = np.asarray(truth_m, dtype=float).reshape(-1, 3)
    if est.shape != tru.shape:
        raise ValueError(f"estimate_m {est.shape} and truth_m {tru.shape} differ in shape")
    has = np.isfinite(est).all(axis=1)
    d = est[has] - tru[has]
    e3 = np.linalg.norm(d, axis=1)
    fl_all = fl_fix = None
    if estimate_floor is not None and truth_floor is not None:
        fl_all, fl_fix = floor_accuracy(estimate_floor, truth_floor, has)
    cover = None
    if covariance_m2 is not None:
        cov = np.asarray(covariance_m2, dtype=float).reshape(-1, 3, 3)
        cover = ellipsoid_coverage(d, cov[has], probability=probability)
    return Score(
        node_epochs=int(has.size),
        fixes=int(has.sum()),
        availability=availability(has),
        error_3d_m=percentiles(e3, q),
        error_z_m=percentiles(np.abs(d[:, 2]), q),
        error_h_m=percentiles(np.linalg.norm(d[:, :2], axis=1), q),
        rmse_3d_m=float(np.sqrt(np.mean(e3**2))) if e3.size else None,
        floor_accuracy_all=fl_all,
        floor_accuracy_fixes=fl_fix,
        ellipsoid_coverage=cover,
    )
