"""The paper's positioning study as pure functions of per-link first-arrival data.

Nothing here knows where the first arrivals came from: :class:`FirstArrivalData` holds, per
node x anchor link, the measured range, its SNR and ranging sigma, the MPC group of the
first-arriving path and its arrival angle. :meth:`FirstArrivalData.from_channel` builds it
from the emulator (:mod:`diffpos.channel.emulator`); a ray-traced dataset (e.g. Sionna RT) only has to
fill the same arrays to replace the emulator.

:func:`positioning_study` runs the estimators of the paper's Fig. "positioning results" on
every receiver (batched, chunked so a caller can show progress):

=================  ==========================================================================
key                method
=================  ==========================================================================
``lls``            linear least squares assuming LoS (baseline)
``ippa``           iterative parallel projection; ranges whose first arrival is the direct
                   path (MPC-1) are LoS spheres, the others NLoS balls (ideal LoS/NLoS
                   identification, as the paper assumes)
``dnls_case1``     D-NLS with the upper-edge diffraction model, ``Delta = 0`` (Assumption 1)
``dnls_case2``     D-NLS with the model offset ``Delta`` (default 1.5 m, half a floor)
``dnls_lower``     (extra) D-NLS modelling the *lower* window edge (``Delta = w``)
``mnls``           M-NLS: mechanism-aware NLS on the first-arrival path model
                   (:func:`diffpos.estimators.mnls.solver`; needs the ``building``, uses the SNR
                   with the ``radio``)
=================  ==========================================================================

With the ``building`` given, the study also reports each method's *floor accuracy*: the share
of all receivers whose estimate lies on the receiver's floor (a failed fix is a miss), and for
``mnls`` the share of fixes whose reported 95 % ellipsoid holds the truth
(:meth:`PositioningStudy.ellipsoid_coverage`).

All estimators are unweighted, like the paper's (their least-squares costs have no
``1/sigma^2``); D-NLS runs without outlier gating (the paper's plain Gauss-Newton) over the
estimator's default multi-start grid. The position error bound (PEB) and z bound use the
diffraction-model FIM at the true node with the ranging CRLB of every detected link.

A fix that fails (no estimate) counts as an infinite error: it is never "within x metres" in
the CDFs, and percentiles above the success rate are reported as ``inf``.

Reproduction (``diffpos reproduce``'s computation)
--------------------------------------------------
The paper's study end to end on a scenario (:func:`reproduce`). Channels (the O2I emulator, or first arrivals from elsewhere: a ray trace or a saved array
file, loaded by the caller) -> first arrivals -> the MPC table and first-arrival statistics ->
the positioning study (:func:`diffpos.study.positioning_study`: the paper's four estimators
and M-NLS by default, each method's floor accuracy over all receivers, M-NLS's 95 % ellipsoid
coverage, the wall time of every method) -> the summary dict the writers and the terminal
report use. Pure numerics: the caller reads files and draws.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.bounds import position_error_bound
from diffpos.channel.emulator import Channel, emulate_channel, first_arrival, mpc_statistics
from diffpos.channel.linkbudget import db_to_linear, ranging_crlb_m
from diffpos.chi_square import chi2_3_quantile
from diffpos.estimators.dnls.solver import dnls
from diffpos.estimators.ippa import ippa
from diffpos.estimators.lls import lls
from diffpos.estimators.mnls.rules import DEFAULT_SNR_RULE, SnrRule
from diffpos.estimators.mnls.solver import mnls
from diffpos.scenario import Scenario
from diffpos.study_methods import DEFAULT_QUICK_NODES, METHOD_LABELS, REPRODUCE_METHODS

__all__ = [
    "DEFAULT_METHODS",
    "PAPER_TABLE",
    "Arrivals",
    "FirstArrivalData",
    "PositioningStudy",
    "Progress",
    "ReproduceConfig",
    "Reproduction",
    "build_summary",
    "empirical_cdf",
    "emulator_arrivals",
    "first_arrival_statistics",
    "floor_accuracy",
    "floor_starts_m",
    "percentile_summary",
    "positioning_study",
    "reproduce",
    "study_rngs",
]

FloatArray = NDArray[np.float64]

DEFAULT_METHODS: tuple[str, ...] = ("lls", "ippa", "dnls_case1", "dnls_case2")
PERCENTILES: tuple[tuple[str, float], ...] = (("median", 50.0), ("p80", 80.0), ("p95", 95.0))


@dataclass(frozen=True)
class FirstArrivalData:
    """First-arrival measurements of N receivers from M anchors (the study's only input).

    Attributes
    ----------
    anchors_m : ndarray, shape (M, 3) [m]
    nodes_m : ndarray, shape (N, 3) [m]
        True receiver positions (ground truth).
    range_m : ndarray, shape (N, M) [m]
        Measured range of the first-arriving path (NaN where not detected).
    snr_db : ndarray, shape (N, M) [dB]
        SNR of the first-arriving path.
    sigma_m : ndarray, shape (N, M) [m]
        Ranging standard deviation (CRLB at ``snr_db``; ``inf`` where not detected).
    detected : ndarray of bool, shape (N, M)
    mpc_class : ndarray of int8, shape (N, M)
        MPC group 1..4 of the first-arriving path (0: not detected or unknown).
    aoa_deg : ndarray, shape (N, M) [deg]
        Arrival zenith angle of the first-arriving path (NaN if unknown).
    """

    anchors_m: FloatArray
    nodes_m: FloatArray
    range_m: FloatArray
    snr_db: FloatArray
    sigma_m: FloatArray
    detected: NDArray[np.bool_]
    mpc_class: NDArray[np.int8]
    aoa_deg: FloatArray

    def __post_init__(self) -> None:
        a = np.asarray(self.anchors_m)
        n = np.asarray(self.nodes_m)
        if a.ndim != 2 or a.shape[1] != 3:
            raise ValueError(f"anchors_m: expected shape (M, 3), got {a.shape}")
        if n.ndim != 2 or n.shape[1] != 3:
            raise ValueError(f"nodes_m: expected shape (N, 3), got {n.shape}")
        want = (n.shape[0], a.shape[0])
        for name in ("range_m", "snr_db", "sigma_m", "detected", "mpc_class", "aoa_deg"):
            shp = np.shape(getattr(self, name))
            if shp != want:
                raise ValueError(f"{name}: expected shape (N, M) = {want}, got {shp}")
        det = np.asarray(self.detected, dtype=bool)
        if np.any(det & ~np.isfinite(np.asarray(self.range_m, dtype=float))):
            raise ValueError("range_m: must be finite wherever detected is True")

    @property
    def n_nodes(self) -> int:
        return int(np.shape(self.nodes_m)[0])

    @classmethod
    def from_channel(cls, fap: Any, anchors_m: ArrayLike, nodes_m: ArrayLike) -> FirstArrivalData:
        """From a :class:`diffpos.channel.emulator.FirstArrival` and the positions it was computed at."""
        return cls(
            anchors_m=np.asarray(anchors_m, dtype=np.float64),
            nodes_m=np.asarray(nodes_m, dtype=np.float64),
            range_m=np.asarray(fap.range_m, dtype=np.float64),
            snr_db=np.asarray(fap.snr_db, dtype=np.float64),
            sigma_m=np.asarray(fap.sigma_m, dtype=np.float64),
            detected=np.asarray(fap.detected, dtype=bool),
            mpc_class=np.asarray(fap.mpc_class, dtype=np.int8),
            aoa_deg=np.asarray(fap.aoa_deg, dtype=np.float64),
        )

    def subset(self, index: ArrayLike) -> FirstArrivalData:
        """The receivers ``index`` (integer or boolean index over N)."""
        i = np.asarray(index)
        return FirstArrivalData(
            anchors_m=self.anchors_m, nodes_m=self.nodes_m[i], range_m=self.range_m[i],
            snr_db=self.snr_db[i], sigma_m=self.sigma_m[i], detected=self.detected[i],
            mpc_class=self.mpc_class[i], aoa_deg=self.aoa_deg[i],
        )

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays (e.g. for ``numpy.savez``); :meth:`from_arrays` reads them back."""
        return {k: np.asarray(getattr(self, k)) for k in _FIELDS}

    @classmethod
    def from_arrays(
        cls, arrays: Mapping[str, ArrayLike], *, bandwidth_hz: float | None = None,
        range_error_floor_m: float = 0.0,
    ) -> FirstArrivalData:
        """From a mapping with the attribute names as keys (e.g. a loaded ``.npz``).

        ``anchors_m, nodes_m, range_m, snr_db, detected`` are required. ``sigma_m`` may be
        omitted if ``bandwidth_hz`` is given (then it is ``sqrt(CRLB^2 + floor^2)``, the ranging
        CRLB at ``snr_db`` and ``range_error_floor_m``, as :func:`diffpos.channel.emulator.first_arrival`);
        ``mpc_class`` defaults to 0 (unknown) and ``aoa_deg`` to NaN.
        """
        missing = [k for k in ("anchors_m", "nodes_m", "range_m", "snr_db", "detected")
                   if k not in arrays]
        if missing:
            raise ValueError(f"first-arrival data lacks {missing} (fields: {list(_FIELDS)})")
        rng = np.asarray(arrays["range_m"], dtype=np.float64)
        det = np.asarray(arrays["detected"], dtype=bool)
        snr = np.asarray(arrays["snr_db"], dtype=np.float64)
        if "sigma_m" in arrays:
            sigma = np.asarray(arrays["sigma_m"], dtype=np.float64)
        elif bandwidth_hz is not None:
            crlb = ranging_crlb_m(db_to_linear(snr), bandwidth_hz)
            sigma = np.where(det, np.hypot(crlb, range_error_floor_m), np.inf)
        else:
            raise ValueError("first-arrival data lacks sigma_m: give it or bandwidth_hz")
        return cls(
            anchors_m=np.asarray(arrays["anchors_m"], dtype=np.float64),
            nodes_m=np.asarray(arrays["nodes_m"], dtype=np.float64),
            range_m=rng,
            snr_db=snr,
            sigma_m=sigma,
            detected=det,
            mpc_class=np.asarray(arrays.get("mpc_class", np.zeros(rng.shape)), dtype=np.int8),
            aoa_deg=np.asarray(arrays.get("aoa_deg", np.full(rng.shape, np.nan)),
                               dtype=np.float64),
        )


_FIELDS = ("anchors_m", "nodes_m", "range_m", "snr_db", "sigma_m", "detected", "mpc_class",
           "aoa_deg")


@dataclass(frozen=True)
class PositioningStudy:
    """Results of :func:`positioning_study`.

    Attributes
    ----------
    positions_m : dict of str -> ndarray, shape (N, 3) [m]
        Estimates per method (NaN where the method gave none).
    error_3d_m, error_z_m : dict of str -> ndarray, shape (N,) [m]
        ``|estimate - truth|`` and ``|z_est - z|`` (``inf`` where no estimate).
    peb_m, z_bound_m : ndarray, shape (N,) [m]
        Diffraction-model PEB and z bound at the true positions (``inf`` if not identifiable).
    methods : tuple of str
    delta_case2_m : float [m]
    extra : dict
        ``status_ok_fraction``: per method, the share of fixes whose estimator status is OK
        (the others still count if they returned an estimate). With a building:
        ``floor_accuracy`` per method [-]. For methods with a covariance (``mnls``):
        ``covariance_m2`` per method, shape (N, 3, 3) [m^2].
    """

    positions_m: dict[str, FloatArray]
    error_3d_m: dict[str, FloatArray]
    error_z_m: dict[str, FloatArray]
    peb_m: FloatArray
    z_bound_m: FloatArray
    methods: tuple[str, ...]
    delta_case2_m: float
    extra: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """Percentiles (median, 80th, 95th) of the 3D and z errors per method and of the PEB.

        Returns
        -------
        dict
            ``{method: {"label", "3d": {...}, "z": {...}, "solved_fraction",
            "status_ok_fraction"}}`` plus
            ``"peb": {"label", "3d": {...}, "z": {...}}`` [m].
        """
        out: dict[str, Any] = {}
        for m in self.methods:
            e3, ez = self.error_3d_m[m], self.error_z_m[m]
            out[m] = {
                "label": method_label(m, self.delta_case2_m),
                "3d": percentile_summary(e3),
                "z": percentile_summary(ez),
                "solved_fraction": float(np.mean(np.isfinite(e3))) if e3.size else 0.0,
                "status_ok_fraction": self.extra.get("status_ok_fraction", {}).get(m),
                "floor_accuracy": self.extra.get("floor_accuracy", {}).get(m),
            }
            if m in self.extra.get("covariance_m2", {}):
                out[m]["ellipsoid95_coverage"] = self.ellipsoid_coverage(m)
        out["peb"] = {"label": "PEB", "3d": percentile_summary(self.peb_m),
                      "z": percentile_summary(self.z_bound_m)}
        return out


    def ellipsoid_coverage(self, method: str, probability: float = 0.95) -> float:
        """Share of the method's fixes whose reported ellipsoid holds the truth [-].

        The ellipsoid is ``d^T C^-1 d <= chi2_3(probability)`` with ``C`` the reported
        covariance and ``d`` the error; over the fixes with an estimate and a finite
        covariance (NaN if none or the method reports no covariance).
        """

        cov = self.extra.get("covariance_m2", {}).get(method)
        if cov is None:
            return float("nan")
        d = self.positions_m[method] - self.extra["truth_m"]
        ok = np.all(np.isfinite(d), axis=1) & np.all(np.isfinite(cov.reshape(len(d), -1)), axis=1)
        if not np.any(ok):
            return float("nan")
        with np.errstate(invalid="ignore"):
            m2 = np.einsum("ni,ni->n", d[ok], np.linalg.solve(cov[ok], d[ok][..., None])[..., 0])
        return float(np.mean(m2 <= chi2_3_quantile(probability)))


def method_label(method: str, delta_case2_m: float = 1.5) -> str:
    """Legend label of a method key."""
    if method == "dnls_case2":
        return f"D-NLS (Case-2, Δ={delta_case2_m:g} m)"
    return METHOD_LABELS.get(method, method)


def percentile_summary(values: ArrayLike) -> dict[str, float]:
    """Median, 80th and 95th percentiles and the mean of finite values [same unit].

    The ``p``-th percentile is the smallest value ``x`` with ``CDF(x) >= p`` (numpy's
    ``inverted_cdf``), the value read off the empirical CDF plots. Non-finite values (failed
    fixes) count as ``+inf`` errors; the mean is over finite values only. Empty input gives
    NaN.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size == 0:
        return {k: float("nan") for k, _ in PERCENTILES} | {"mean": float("nan"), "n": 0}
    v = np.where(np.isfinite(v), v, np.inf)
    s = np.sort(v)
    out = {}
    for k, p in PERCENTILES:
        # the smallest value with CDF >= p (no interpolation: an inf never mixes in)
        out[k] = float(np.percentile(s, p, method="inverted_cdf"))
    fin = s[np.isfinite(s)]
    out["mean"] = float(fin.mean()) if fin.size else float("nan")
    out["n"] = int(v.size)
    return out


def empirical_cdf(values: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Empirical CDF: sorted finite values and ``F = rank / n_total`` (failures never reach 1).

    Returns
    -------
    x : ndarray, shape (K,) [unit of values]
    f : ndarray, shape (K,) [-]
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    n = v.size
    x = np.sort(v[np.isfinite(v)])
    return x, np.arange(1, x.size + 1) / max(n, 1)


def _chunks(n: int, size: int) -> list[slice]:
    size = max(int(size), 1)
    return [slice(i, min(i + size, n)) for i in range(0, n, size)]


def floor_starts_m(building: Any) -> FloatArray:
    """Nominal node height of every floor of ``building`` [m]: the floor hypotheses.

    ``first_floor_z_m + k floor_height_m + sill_height_m + w/2`` for ``k = 0..n_floors-1``
    (Assumption 1: the node at the window's mid-height).
    """
    k = np.arange(building.n_floors)
    return np.asarray(building.floor_z_m(k) + building.nominal_node_height_m, dtype=np.float64)


def _check_methods(methods: Sequence[str], building: Any) -> None:
    """Every method is known (:data:`~diffpos.study_methods.METHOD_LABELS` but ``"peb"``) and ``mnls`` has its building."""
    unknown = [m for m in methods if m not in METHOD_LABELS or m == "peb"]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; choose from "
                         f"{[k for k in METHOD_LABELS if k != 'peb']}")
    if "mnls" in methods and building is None:
        raise ValueError("method 'mnls' needs the building (positioning_study(building=...))")


def positioning_study(
    data: FirstArrivalData,
    *,
    window_height_m: float,
    edge_x_m: tuple[float, float] | None = None,
    delta_case2_m: float = 1.5,
    methods: Sequence[str] = DEFAULT_METHODS,
    z_starts_m: ArrayLike | None = None,
    start_y_m: float | None = None,
    chunk_size: int = 2048,
    progress: Callable[[str, int, int], None] | None = None,
    building: Any = None,
    radio: Any = None,
    mnls_max_order: int = 2,
    mnls_snr_rule: SnrRule = DEFAULT_SNR_RULE,
) -> PositioningStudy:
    """Position every receiver with each method and compute the bounds.

    Parameters
    ----------
    data : FirstArrivalData
    window_height_m : float [m]
        Window height ``w`` of the path model.
    edge_x_m : (float, float), optional [m]
        Extent of the window edges along x (the building width), known a priori (Cor. 3).
    delta_case2_m : float [m]
        Model offset of D-NLS Case-2 (paper: 1.5 m).
    z_starts_m : array_like, shape (S,), optional [m]
        Floor hypotheses for the multi-start of D-NLS and IPPA, e.g. the node heights of the
        building's floors (the authors' ``ippa_floor.m`` starts once per floor). Default: the
        estimators' generic grid (every 3 m from 0 to 30 m).
    start_y_m : float, optional [m]
        Depth of the IPPA starts (e.g. the middle of the building). IPPA with all-NLoS balls
        barely moves in x-y when all anchors are on one side, so its x-y error is mostly the
        distance from this start. Default: the estimator's default (3 m).
    methods : sequence of str
        Keys of :data:`~diffpos.study_methods.METHOD_LABELS` (except ``"peb"``, always computed).
    chunk_size : int
        Receivers per estimator call; ``progress`` is called after each chunk.
    progress : callable(method, done, total), optional
    building : diffpos.scenario.Building, optional
        Required by ``mnls``; enables the per-method floor accuracy.
    radio : diffpos.scenario.Radio, optional
        Link budget for ``mnls``'s SNR test and its error floor / bandwidth.
    mnls_max_order : int
        ``mnls``'s mechanism families (:func:`diffpos.paths.mechanisms.mechanism_set`; 2: the
        18 mechanisms of the emulator).
    mnls_snr_rule : diffpos.estimators.mnls.rules.SnrRule
        ``mnls``'s use of the detector's rule (default: the predicted threshold, hard rule).

    Returns
    -------
    PositioningStudy
    """
    _check_methods(methods, building)
    anchors = np.asarray(data.anchors_m, dtype=np.float64)
    truth = np.asarray(data.nodes_m, dtype=np.float64)
    n = truth.shape[0]
    mask = np.asarray(data.detected, dtype=bool)
    ranges = np.where(mask, data.range_m, 0.0)
    # IPPA is told which ranges are LoS (first arrival = direct path, MPC-1), as the paper
    # grants it perfect LoS/NLoS identification; unknown classes (0) count as NLoS
    nlos = np.asarray(data.mpc_class) != 1
    dnls_delta = {"dnls_case1": 0.0, "dnls_case2": delta_case2_m, "dnls_lower": window_height_m}

    ippa_start: dict[str, Any] = {"z_starts_m": z_starts_m}
    if start_y_m is not None:
        ippa_start["y_start_m"] = start_y_m

    def solve(method: str, sl: slice):
        b = sl.stop - sl.start
        a = np.broadcast_to(anchors, (b, *anchors.shape))
        if method == "lls":
            return lls(a, ranges[sl], None, mask=mask[sl])
        if method == "ippa":
            return ippa(a, ranges[sl], None, mask=mask[sl], nlos=nlos[sl], **ippa_start)
        if method == "mnls":
            rkw = {} if radio is None else {"bandwidth_hz": radio.bandwidth_hz,
                                            "error_floor_m": radio.range_error_floor_m}
            return mnls(a, ranges[sl], np.where(mask[sl], data.sigma_m[sl], 1.0),
                        mask=mask[sl], building=building, snr_db=data.snr_db[sl], radio=radio,
                        max_order=mnls_max_order, snr_rule=mnls_snr_rule, **rkw)
        return dnls(a, ranges[sl], None, mask=mask[sl], window_height_m=window_height_m,
                    delta_m=dnls_delta[method], edge_x_m=edge_x_m, gating=None,
                    z_starts_m=z_starts_m)

    positions: dict[str, FloatArray] = {}
    e3: dict[str, FloatArray] = {}
    ez: dict[str, FloatArray] = {}
    ok_frac: dict[str, float] = {}
    covs: dict[str, FloatArray] = {}
    for m in methods:
        est = np.full((n, 3), np.nan)
        cov = np.full((n, 3, 3), np.nan)
        n_ok = 0
        for sl in _chunks(n, chunk_size):
            res = solve(m, sl)
            # like the paper, every estimate counts, whatever its status (ill-conditioned or
            # not converged within the iteration limit); only missing estimates are failures
            est[sl] = res.position_m
            cov[sl] = res.covariance_m2
            n_ok += int(np.sum(res.ok))
            if progress is not None:
                progress(m, sl.stop, n)
        positions[m] = est
        if m == "mnls":
            covs[m] = cov
        ok_frac[m] = n_ok / n if n else 0.0
        err = np.linalg.norm(est - truth, axis=1)
        e3[m] = np.where(np.isfinite(err), err, np.inf)
        dz = np.abs(est[:, 2] - truth[:, 2])
        ez[m] = np.where(np.isfinite(dz), dz, np.inf)

    sig = np.where(mask & np.isfinite(data.sigma_m), data.sigma_m, np.inf)
    bnd = position_error_bound(anchors, truth, sig, window_height_m, 0.0, edge_x_m=edge_x_m)
    if progress is not None:
        progress("peb", n, n)
    return PositioningStudy(
        positions_m=positions, error_3d_m=e3, error_z_m=ez, peb_m=bnd.peb_m,
        z_bound_m=bnd.z_bound_m, methods=tuple(methods), delta_case2_m=float(delta_case2_m),
        extra={"status_ok_fraction": ok_frac, "covariance_m2": covs, "truth_m": truth,
               "floor_accuracy": ({} if building is None else
                                  {m: floor_accuracy(positions[m], truth, building)
                                   for m in methods})},
    )


def floor_accuracy(estimates_m: ArrayLike, truth_m: ArrayLike, building: Any) -> float:
    """Share of ALL receivers whose estimate is on the receiver's floor (no estimate: miss)."""
    est = np.asarray(estimates_m, dtype=np.float64)
    tru = np.asarray(truth_m, dtype=np.float64)
    if tru.shape[0] == 0:
        return float("nan")
    ok = np.isfinite(est[:, 2])
    k_est = building.floor_index(np.where(ok, est[:, 2], -1e9))
    return float(np.mean(ok & (k_est == building.floor_index(tru[:, 2]))))


def first_arrival_statistics(
    data: FirstArrivalData,
    *,
    aoa_tolerance_deg: float = 6.0,
    snr_floor_db: float = 5.0,
) -> dict[str, Any]:
    """Distribution of the first-arriving path's AoA and SNR (the paper's box plots).

    Parameters
    ----------
    data : FirstArrivalData
    aoa_tolerance_deg : float [deg]
        Reports the share of first arrivals with ``|AoA - 90| <= aoa_tolerance_deg`` (the
        paper: "always within six degrees of 90").
    snr_floor_db : float [dB]
        Reports the share with ``SNR > snr_floor_db`` (the paper: "typically > 5 dB").

    Returns
    -------
    dict
        ``aoa_deg`` and ``snr_db`` box statistics (whiskers at the 5th/95th percentiles,
        quartiles, median), the two shares [%], ``P_fap`` per MPC group [%] and the detected
        share [%].
    """
    det = np.asarray(data.detected, dtype=bool)
    aoa = np.asarray(data.aoa_deg)[det]
    snr = np.asarray(data.snr_db)[det]

    def box(v: FloatArray) -> dict[str, float]:
        v = v[np.isfinite(v)]
        if v.size == 0:
            return {}
        q = np.percentile(v, [5, 25, 50, 75, 95])
        return {"p5": float(q[0]), "q1": float(q[1]), "median": float(q[2]), "q3": float(q[3]),
                "p95": float(q[4]), "min": float(v.min()), "max": float(v.max())}

    pairs = det.size
    cls = np.asarray(data.mpc_class)
    aoa_fin = aoa[np.isfinite(aoa)]
    return {
        "pairs": int(pairs),
        "detected_pct": 100.0 * float(det.mean()) if pairs else float("nan"),
        "aoa_deg": box(aoa),
        "snr_db": box(snr),
        "aoa_within_tolerance_pct": (100.0 * float(np.mean(np.abs(aoa_fin - 90.0)
                                                           <= aoa_tolerance_deg))
                                     if aoa_fin.size else float("nan")),
        "aoa_tolerance_deg": aoa_tolerance_deg,
        "snr_above_floor_pct": 100.0 * float(np.mean(snr > snr_floor_db)) if snr.size else
        float("nan"),
        "snr_floor_db": snr_floor_db,
        "P_fap_pct": {f"MPC-{g}": 100.0 * float(np.sum(cls == g)) / max(pairs, 1)
                      for g in (1, 2, 3, 4)},
    }


# --------------------------------------------------------------------------------------------
# reproduction: the study end to end on a scenario (``diffpos reproduce``)
# --------------------------------------------------------------------------------------------

#: The paper's Table "MPC through the windows" [%].
PAPER_TABLE: dict[str, dict[str, float]] = {
    "MPC-1": {"P_e": 3.47, "P_fap": 3.47},
    "MPC-2": {"P_e": 9.03, "P_fap": 1.60},
    "MPC-3": {"P_e": 91.52, "P_fap": 84.79},
    "MPC-4": {"P_e": 100.0, "P_fap": 10.12},
}


@dataclass(frozen=True)
class ReproduceConfig:
    """What to run.

    Attributes
    ----------
    seed : int
        Seed of the range noise and the ``quick`` subsample.
    quick : bool
        Keep a random subsample of ``quick_nodes`` receivers.
    quick_nodes : int
    methods : tuple of str
        Estimators (keys of :data:`~diffpos.study_methods.METHOD_LABELS` but ``"peb"``; default
        :data:`~diffpos.study_methods.REPRODUCE_METHODS`).
    delta_m : float [m]
        D-NLS Case-2 model offset.
    mnls_max_order : int
        M-NLS's mechanism families (2: the emulator's 18 mechanisms; 3, 4: higher-order
        reflections between the slabs, ground bounce before the edge).
    mnls_measured_threshold, mnls_first_arrival_prior, mnls_keep_hard_rule : bool, float, bool
    mnls_dielectric_edges : float
    mnls_floor_box : bool
    mnls_shadow_starts : float [m]
    mnls_path_region : bool
        M-NLS's :class:`~diffpos.estimators.mnls.rules.SnrRule` (default: all off).
    """

    seed: int = 0
    quick: bool = False
    quick_nodes: int = DEFAULT_QUICK_NODES
    methods: tuple[str, ...] = REPRODUCE_METHODS
    delta_m: float = 1.5
    mnls_max_order: int = 2
    mnls_measured_threshold: bool = False
    mnls_first_arrival_prior: float = 0.0
    mnls_keep_hard_rule: bool = False
    mnls_dielectric_edges: float = 0.0
    mnls_floor_box: bool = False
    mnls_shadow_starts: float = 0.0
    mnls_path_region: bool = False


class Progress(Protocol):
    """Progress sink: one task per stage (``key``), ``done`` of ``total``."""

    def add(self, key: str, label: str, total: int) -> None: ...

    def update(self, key: str, done: int) -> None: ...


class _NoProgress:
    def add(self, key: str, label: str, total: int) -> None:
        pass

    def update(self, key: str, done: int) -> None:
        pass


@dataclass(frozen=True)
class Arrivals:
    """First arrivals of a channel source; ``channel``/``table`` where the source has them."""

    data: FirstArrivalData
    channel: Channel | None = None
    table: dict[str, dict[str, float]] | None = None
    fap_by_mechanism: dict[str, float] | None = None


@dataclass(frozen=True)
class Reproduction:
    """Everything the writers need."""

    kind: str
    path: Any
    channel: Channel | None
    table: dict[str, dict[str, float]] | None
    data: FirstArrivalData
    study: PositioningStudy
    timing: dict[str, float] = field(default_factory=dict)
    fap_stats: dict[str, Any] = field(default_factory=dict)
    fap_by_mechanism: dict[str, float] | None = None


class _StageClock:
    """Forwards the study's progress and times every stage (methods run one after another).

    A stage's time runs from the previous stage's last update (or the clock's creation) to
    its own last update: the time of that method over all receivers, by wall clock and by
    process CPU time (the figure to compare when other processes share the cores).
    """

    def __init__(self, prog: Progress) -> None:
        self.prog = prog
        self.t_prev = (time.perf_counter(), time.process_time())
        self.last: dict[str, tuple[float, float]] = {}
        self.start: dict[str, tuple[float, float]] = {}

    def update(self, key: str, done: int, total: int) -> None:
        now = (time.perf_counter(), time.process_time())
        if key not in self.start:
            self.start[key] = max(self.last.values(), default=self.t_prev)
        self.last[key] = now
        self.prog.update(key, done)

    def durations(self, clock: int = 0) -> dict[str, float]:
        """Time per stage [s]: wall clock (``clock=0``) or process CPU time (``clock=1``)."""
        return {k: self.last[k][clock] - self.start[k][clock] for k in self.last}


def study_rngs(seed: int) -> tuple[np.random.Generator, np.random.Generator]:
    """The subsample and the range-noise generators of a run (two streams of ``seed``)."""
    ss = np.random.SeedSequence(seed)
    sub_rng, noise_rng = (np.random.default_rng(s) for s in ss.spawn(2))
    return sub_rng, noise_rng


def emulator_arrivals(scenario: Scenario, cfg: ReproduceConfig, sub_rng: np.random.Generator,
                      noise_rng: np.random.Generator) -> Arrivals:
    """The O2I emulator's channels and first arrivals on the scenario's receivers."""
    nodes = scenario.node_positions_m()
    if cfg.quick and cfg.quick_nodes < len(nodes):
        keep = np.sort(sub_rng.choice(len(nodes), cfg.quick_nodes, replace=False))
        nodes = nodes[keep]
    anchors = scenario.anchor_positions_m()
    channel = emulate_channel(anchors, nodes, building=scenario.building, radio=scenario.radio)
    fa = first_arrival(channel, radio=scenario.radio, rng=noise_rng)
    table = mpc_statistics(channel, fa)
    pairs = max(fa.slot.size, 1)
    by_mech = {lab: 100.0 * float(np.sum(fa.slot == k)) / pairs
               for k, lab in enumerate(channel.mechanism)}
    return Arrivals(data=FirstArrivalData.from_channel(fa, anchors, nodes), channel=channel,
                    table=table, fap_by_mechanism={k: v for k, v in by_mech.items() if v > 0})


def reproduce(
    scenario: Scenario,
    cfg: ReproduceConfig,
    *,
    kind: str = "emulator",
    path: Any = None,
    load: Callable[[np.random.Generator], Arrivals] | None = None,
    progress: Progress | None = None,
) -> Reproduction:
    """Run the whole study.

    ``load(noise_rng)`` gives the first arrivals of a source other than the emulator
    (``kind`` and ``path`` name it in the summary); they are subsampled like the emulator's
    receivers when ``cfg.quick``.
    """
    prog = progress or _NoProgress()
    sub_rng, noise_rng = study_rngs(cfg.seed)
    timing: dict[str, float] = {}
    t_all = t0 = time.perf_counter()
    if load is None:
        prog.add("channel", "channels + first arrival", 1)
        arr = emulator_arrivals(scenario, cfg, sub_rng, noise_rng)
        prog.update("channel", 1)
    else:
        arr = load(noise_rng)
    data = arr.data
    if load is not None and cfg.quick and cfg.quick_nodes < data.n_nodes:
        keep = np.sort(sub_rng.choice(data.n_nodes, cfg.quick_nodes, replace=False))
        data = data.subset(keep)
    timing["channel_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    for m in cfg.methods:
        prog.add(m, method_label(m, cfg.delta_m), data.n_nodes)
    prog.add("peb", "PEB / z bound", data.n_nodes)
    clock = _StageClock(prog)
    study = positioning_study(
        data, window_height_m=scenario.building.window_height_m,
        edge_x_m=scenario.building.edge_x_m, delta_case2_m=cfg.delta_m,
        methods=tuple(cfg.methods), progress=clock.update,
        z_starts_m=floor_starts_m(scenario.building),
        start_y_m=0.5 * scenario.building.depth_m,
        building=scenario.building, radio=scenario.radio, mnls_max_order=cfg.mnls_max_order,
        mnls_snr_rule=SnrRule(cfg.mnls_measured_threshold, cfg.mnls_first_arrival_prior,
                              cfg.mnls_keep_hard_rule, cfg.mnls_dielectric_edges,
                              cfg.mnls_floor_box, cfg.mnls_shadow_starts,
                              cfg.mnls_path_region),
    )
    timing["positioning_s"] = time.perf_counter() - t0
    timing["method_s"] = clock.durations()
    timing["method_cpu_s"] = clock.durations(1)
    timing["total_s"] = time.perf_counter() - t_all
    return Reproduction(kind=kind, path=path, channel=arr.channel, table=arr.table, data=data,
                        study=study, timing=timing, fap_stats=first_arrival_statistics(data),
                        fap_by_mechanism=arr.fap_by_mechanism if load is None else None)


def build_summary(cfg: ReproduceConfig, scenario: Scenario, res: Reproduction) -> dict[str, Any]:
    """The run's summary (what summary.json holds before JSON cleaning)."""
    data = res.data
    return {
        "scenario": scenario.name,
        "channel_source": res.kind + ("" if res.path is None else f":{res.path}"),
        "seed": cfg.seed,
        "quick": bool(cfg.quick),
        "n_receivers": data.n_nodes,
        "n_anchors": int(np.shape(data.anchors_m)[0]),
        "anchors_m": np.asarray(data.anchors_m).tolist(),
        "delta_case2_m": cfg.delta_m,
        "mnls_max_order": cfg.mnls_max_order,
        "mnls_measured_threshold": cfg.mnls_measured_threshold,
        "mnls_first_arrival_prior": cfg.mnls_first_arrival_prior,
        "mnls_keep_hard_rule": cfg.mnls_keep_hard_rule,
        "mnls_dielectric_edges": cfg.mnls_dielectric_edges,
        "mnls_floor_box": cfg.mnls_floor_box,
        "mnls_shadow_starts": cfg.mnls_shadow_starts,
        "mnls_path_region": cfg.mnls_path_region,
        "window_height_m": scenario.building.window_height_m,
        "mpc_table_pct": res.table,
        "first_arrival_mechanism_pct": res.fap_by_mechanism,
        "paper_mpc_table_pct": PAPER_TABLE,
        "first_arrival": res.fap_stats,
        "positioning_m": res.study.summary(),
        "timing_s": res.timing,
    }
