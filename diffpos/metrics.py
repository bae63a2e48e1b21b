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
* :func:`score` - all of them at once from estimates, truth, floors and covariances, and
  the calibration of the reported floor probabilities (:mod:`diffpos.floor_calibration`).
* :class:`QuantileSketch`, :class:`StreamingErrorStats`, :class:`StreamingScore` - the same
  summaries over a stream in bounded memory (replay of recordings of any length): exact
  (identical to the functions above) up to ``exact_limit`` values per distribution, then a
  log-bucket histogram whose percentiles are within ``relative_accuracy`` (0.5 %) of the exact
  ones, or 1 um for values below 1 um; counts, availability, floor accuracy, ``within_2peb``,
  ``max`` stay exact, ``mean`` and ``rmse`` are running sums (rounding only).

Examples
--------
>>> import numpy as np
>>> est = np.array([[0.0, 0.0, 1.0], [np.nan, np.nan, np.nan]])
>>> s = score(est, np.zeros((2, 3)), estimate_floor=[0, -1], truth_floor=[0, 0])
>>> s.availability, s.floor_accuracy_all, s.floor_accuracy_fixes
(0.5, 0.5, 1.0)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from diffpos.chi_square import chi2_3_quantile
from diffpos.floor_calibration import FloorCalibration, floor_calibration

__all__ = [
    "PERCENTILES",
    "QuantileSketch",
    "Score",
    "StreamingErrorStats",
    "StreamingScore",
    "availability",
    "ellipsoid_coverage",
    "error_stats",
    "floor_accuracy",
    "percentiles",
    "score",
    "truth_at",
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
    return float(np.mean(m2 <= chi2_3_quantile(probability)))


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
    floor_calibration : dict or None
        :func:`diffpos.floor_calibration.floor_calibration` (``None`` without floor
        probabilities, e.g. estimate v1).
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
    floor_calibration: dict[str, Any] | None = None

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (field order)."""
        return dict(self.__dict__)


def truth_at(t_ns: ArrayLike, truth_t_ns: ArrayLike, truth_position_m: ArrayLike,
             truth_floor: ArrayLike | None = None, *,
             floor_of: Callable[[np.ndarray], ArrayLike] | None = None
             ) -> tuple[np.ndarray, np.ndarray | None]:
    """One node's truth at the times ``t_ns`` (K,) of its estimates: the position linearly
    interpolated between its samples (``truth_t_ns`` (S,) ascending, ``truth_position_m``
    (S, 3); held at the first/last sample outside them) and its floor.

    The floor is ``floor_of(z)`` of the interpolated height ``z`` (K,) when ``floor_of`` is
    given (the building's :meth:`~diffpos.scenario.Building.floor_index`: the floor of the
    true position at that time, as ``emulate``'s live summary takes it); else, where no
    building is known, the recorded ``truth_floor`` (S,) of the nearest sample (wrong for up to
    half a sample period at a slab crossing); ``None`` without either.

    An estimate states the time its position refers to (the fusion: the mean time of the
    ranges it used, up to a period after the epoch's truth sample); every scorer compares it
    with the truth at that time. At 1.2 m/s walking speed the epoch-start sample is up to
    ~12 cm away from it, as large as a tracker's horizontal standard deviation.
    """
    t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
    tt = np.asarray(truth_t_ns, dtype=np.int64).reshape(-1)
    tp = np.asarray(truth_position_m, dtype=float).reshape(-1, 3)
    if tt.size == 0 or tt.size != tp.shape[0]:
        raise ValueError("truth_t_ns and truth_position_m must be non-empty and of equal length")
    q, grid = (t - tt[0]).astype(float), (tt - tt[0]).astype(float)
    pos = np.stack([np.interp(q, grid, tp[:, k]) for k in range(3)], axis=-1)
    if floor_of is not None:
        return pos, np.asarray(floor_of(pos[:, 2]), np.int64).reshape(-1)
    if truth_floor is None:
        return pos, None
    j = np.searchsorted(tt, t)
    left, right = np.clip(j - 1, 0, tt.size - 1), np.clip(j, 0, tt.size - 1)
    nearest = np.where(np.abs(t - tt[left]) <= np.abs(t - tt[right]), left, right)
    return pos, np.asarray(truth_floor).reshape(-1)[nearest]


def score(
    estimate_m: ArrayLike,
    truth_m: ArrayLike,
    *,
    estimate_floor: ArrayLike | None = None,
    truth_floor: ArrayLike | None = None,
    covariance_m2: ArrayLike | None = None,
    floor_probabilities: ArrayLike | None = None,
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
    floor_probabilities : array_like, shape (N, F), optional
        Reported probability of every floor (NaN rows where absent), for the calibration
        (with both floors; :mod:`diffpos.floor_calibration`).
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
    calib = None
    if floor_probabilities is not None and fl_all is not None:
        calib = floor_calibration(estimate_floor, truth_floor, floor_probabilities,
                                  has_position=has)
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
        floor_calibration=calib,
    )


# ----------------------------------------------------------------------------------------
# the same summaries over a stream, in bounded memory
# ----------------------------------------------------------------------------------------

#: values kept exactly per distribution before a sketch switches to its histogram
EXACT_LIMIT = 4096
#: smallest and largest value the histogram resolves [m]; below: counted as 0, above: clamped
_SKETCH_LO, _SKETCH_HI = 1e-6, 1e6


class QuantileSketch:
    """A stream of non-negative values summarised like :func:`percentiles`, in bounded memory.

    Up to ``exact_limit`` values are kept as they are and the summary is :func:`percentiles`'
    (identical). Beyond, every value goes into a log-spaced histogram (bucket ``i`` holds
    ``(lo g^(i-1), lo g^i]``, ``g = (1 + a) / (1 - a)``; DDSketch's mapping): each order
    statistic is estimated by its bucket's centre ``2 lo g^i / (g + 1)``, within a relative
    ``a`` of the true one (values below ``lo`` = 1 um count as 0: absolute error < 1 um;
    above 1e6 they are clamped); percentiles interpolate two order statistics as numpy's
    linear method does (so they keep the bound); ``max`` is exact, ``mean`` a running sum.
    Memory: ``exact_limit`` floats, then ``log(1e12) / log(g)`` counters (2,764 int32 at
    ``a`` = 0.5 %: 11 KB), whatever the stream's length.

    Parameters
    ----------
    exact_limit : int
    relative_accuracy : float
    """

    def __init__(self, *, exact_limit: int = EXACT_LIMIT, relative_accuracy: float = 0.005):
        if not 0 < relative_accuracy < 1:
            raise ValueError(f"relative_accuracy {relative_accuracy} is not in (0, 1)")
        self.exact_limit = int(exact_limit)
        self.relative_accuracy = float(relative_accuracy)
        self._gamma = (1 + relative_accuracy) / (1 - relative_accuracy)
        self._exact: list[np.ndarray] = []
        self._n_exact = 0
        self._hist: np.ndarray | None = None
        self._zeros = 0
        self.count = 0
        self._sum = 0.0
        self._max = -np.inf

    @property
    def exact(self) -> bool:
        """Still every value kept (the summary is :func:`percentiles`')."""
        return self._hist is None

    def add(self, values: ArrayLike) -> None:
        """Add values (finite, >= 0)."""
        v = np.asarray(values, dtype=float).reshape(-1)
        if v.size == 0:
            return
        self.count += int(v.size)
        self._sum += float(v.sum())
        self._max = max(self._max, float(v.max()))
        if self._hist is None:
            if self._n_exact + v.size <= self.exact_limit:
                self._exact.append(v.copy())
                self._n_exact += int(v.size)
                return
            nb = int(np.ceil(np.log(_SKETCH_HI / _SKETCH_LO) / np.log(self._gamma))) + 1
            self._hist = np.zeros(nb, np.int32)
            for old in self._exact:
                self._bin(old)
            self._exact, self._n_exact = [], 0
        self._bin(v)

    def _bin(self, v: np.ndarray) -> None:
        small = v < _SKETCH_LO
        self._zeros += int(small.sum())
        big = v[~small]
        if big.size:
            i = np.ceil(np.log(big / _SKETCH_LO) / np.log(self._gamma)).astype(np.int64)
            np.clip(i, 0, self._hist.size - 1, out=i)
            self._hist += np.bincount(i, minlength=self._hist.size).astype(np.int32)

    def values(self) -> np.ndarray:
        """Every value (exact), or each bucket's centre repeated by its count (O(count)
        memory: for plots, not for the summary)."""
        if self._hist is None:
            return np.concatenate(self._exact) if self._exact else np.empty(0)
        return np.concatenate([np.zeros(self._zeros), np.repeat(self._centres(), self._hist)])

    def sorted_values(self) -> np.ndarray:
        """:meth:`values` sorted."""
        return np.sort(self.values())

    def _centres(self) -> np.ndarray:
        g = self._gamma
        return np.minimum(2 * _SKETCH_LO * g ** np.arange(self._hist.size) / (g + 1), self._max)

    def summary(self, q: Sequence[float] = PERCENTILES, *,
                max_mean: bool = True) -> dict[str, float | None]:
        """:func:`percentiles` of everything added (see the class for the error bound; while
        exact, of the sorted values: the same result whatever the order they came in)."""
        if self._hist is None or self.count == 0:
            return percentiles(self.sorted_values(), q, max_mean=max_mean)
        cum = np.cumsum(self._hist, dtype=np.int64) + self._zeros
        centres = self._centres()

        def order_stat(k: int) -> float:
            if k >= self.count - 1:
                return self._max
            if k < self._zeros:
                return 0.0
            return float(centres[np.searchsorted(cum, k, side="right")])

        out: dict[str, float | None] = {}
        for p in q:
            r = p / 100 * (self.count - 1)
            lo = int(np.floor(r))
            a = order_stat(lo)
            b = order_stat(min(lo + 1, self.count - 1))
            out[f"p{p}"] = a + (r - lo) * (b - a)
        if max_mean:
            out["max"] = self._max
            out["mean"] = self._sum / self.count
        return out


class StreamingErrorStats:
    """:func:`error_stats` over batches of fixes, in bounded memory (:class:`QuantileSketch`
    per distribution: identical to :func:`error_stats` while exact)."""

    def __init__(self, *, exact_limit: int = EXACT_LIMIT) -> None:
        kw = {"exact_limit": exact_limit}
        self.e3, self.ez, self.eh, self.peb = (QuantileSketch(**kw) for _ in range(4))
        self.evaluated = self.floor_ok = self.with_peb = self.within_2peb = 0
        self._sumsq = 0.0

    def add(self, err_3d_m: ArrayLike, err_z_m: ArrayLike, err_h_m: ArrayLike,
            floor_ok: ArrayLike, peb_m: ArrayLike) -> None:
        """A batch (arguments as :func:`error_stats`')."""
        e3 = np.asarray(err_3d_m, float).reshape(-1)
        peb = np.asarray(peb_m, float).reshape(-1)
        fok = np.asarray(floor_ok, bool).reshape(-1)
        fin = np.isfinite(peb)
        self.e3.add(e3)
        self.ez.add(err_z_m)
        self.eh.add(err_h_m)
        self.peb.add(peb[fin])
        self.evaluated += int(e3.size)
        self.floor_ok += int(fok.sum())
        self.with_peb += int(fin.sum())
        self.within_2peb += int((e3[fin] <= 2 * peb[fin]).sum())
        self._sumsq += float(np.dot(e3, e3))

    def result(self, *, fixes: int) -> dict[str, Any]:
        """:func:`error_stats`' dict (identical to it while the sketches are exact)."""
        k = self.evaluated
        if k and self.e3.exact:
            e3 = self.e3.sorted_values()
            rmse = float(np.sqrt(np.mean(e3**2)))
        else:
            rmse = float(np.sqrt(self._sumsq / k)) if k else None
        return {
            "fixes": int(fixes),
            "evaluated": k,
            "availability": (k / fixes) if fixes else None,
            "error_3d_m": self.e3.summary(),
            "error_z_m": self.ez.summary(),
            "error_h_m": self.eh.summary(),
            "rmse_3d_m": rmse,
            "floor_accuracy": (self.floor_ok / k) if k else None,
            "peb_m": self.peb.summary(),
            "within_2peb": (self.within_2peb / self.with_peb) if self.with_peb else None,
        }


class StreamingScore:
    """:func:`score` over batches of node-epochs (without covariances: the coverage is a
    count, see :func:`ellipsoid_coverage`), in bounded memory: identical to :func:`score`
    while the error distributions are exact (:class:`QuantileSketch`); the floor calibration
    up to rounding (its sums per bin)."""

    def __init__(self, *, exact_limit: int = EXACT_LIMIT) -> None:
        kw = {"exact_limit": exact_limit}
        self.e3, self.ez, self.eh = (QuantileSketch(**kw) for _ in range(3))
        self.node_epochs = self.fixes = 0
        self._right = 0
        self._floors = True
        self._sumsq = 0.0
        self._calib = FloorCalibration()

    def add(self, error_m: ArrayLike, *, estimate_floor: ArrayLike | None = None,
            truth_floor: ArrayLike | None = None,
            floor_probabilities: ArrayLike | None = None) -> None:
        """A batch of node-epochs: ``error_m`` (N, 3) = estimate - truth, a NaN row a miss;
        ``floor_probabilities`` (N, F) as :func:`score`'s (a batch without: none reported)."""
        d = np.asarray(error_m, float).reshape(-1, 3)
        self._add(d)
        if estimate_floor is None or truth_floor is None:
            self._floors = False
        elif self._floors:
            ef = np.asarray(estimate_floor).reshape(-1)
            tf = np.asarray(truth_floor).reshape(-1)
            has = np.isfinite(d).all(axis=1)
            self._right += int(((ef == tf) & has).sum())
            p = np.empty((d.shape[0], 0)) if floor_probabilities is None else floor_probabilities
            self._calib.add(ef, tf, p, has_position=has)

    def _add(self, d: np.ndarray) -> None:
        has = np.isfinite(d).all(axis=1)
        dh = d[has]
        e3 = np.linalg.norm(dh, axis=1)
        self.e3.add(e3)
        self.ez.add(np.abs(dh[:, 2]))
        self.eh.add(np.linalg.norm(dh[:, :2], axis=1))
        self.node_epochs += int(has.size)
        self.fixes += int(has.sum())
        self._sumsq += float(np.dot(e3, e3))

    def result(self, q: Sequence[float] = PERCENTILES, *,
               ellipsoid_coverage: float | None = None) -> Score:
        n, k = self.node_epochs, self.fixes
        exact = self.e3.exact
        e3 = self.e3.sorted_values() if exact else None
        fl = (None, None)
        if self._floors and n:
            fl = (self._right / n, (self._right / k) if k else None)
        return Score(
            node_epochs=n,
            fixes=k,
            availability=(k / n) if n else None,
            error_3d_m=self.e3.summary(q),
            error_z_m=self.ez.summary(q),
            error_h_m=self.eh.summary(q),
            rmse_3d_m=(float(np.sqrt(np.mean(e3**2))) if exact else
                       float(np.sqrt(self._sumsq / k))) if k else None,
            floor_accuracy_all=fl[0],
            floor_accuracy_fixes=fl[1],
            ellipsoid_coverage=ellipsoid_coverage,
            floor_calibration=self._calib.result() if self._floors else None,
        )
