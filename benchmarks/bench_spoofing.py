"""Spoofed or faulty anchors: does D-NLS gating (RAIM FDE) catch them, how fast, at what cost?

One anchor misbehaves: it adds a constant or growing bias to its ranges, or it reports a wrong
own position (an offset or a slow drift). Every epoch (10 Hz for 30 s by default) every node
of a scenario is positioned with :func:`diffpos.estimators.dnls.solver` and its RAIM-style gating
(chi-square residual test at ``P_fa``, leave-one-out exclusion, physical pre-gate), all fixes
of all epochs in one batch. Pure core only (no zenoh): the nodes, anchors and trajectories of
``scenarios/large.toml`` (8 UAVs, 50 responders) and, to show the limits, the paper's 4 static
anchors (``scenarios/paper.toml``) with the same responders, and 3 of them.

Ranges come from one of two sources:

``matched``
    The estimator's own model (upper-edge diffraction path, ``window_edge_path``, Case-1)
    plus Gaussian noise at the ranging CRLB of that path's SNR (the emulator's upper-edge
    diffraction component, SNR clipped below at the detection floor). This isolates the
    gating: the chi-square statistic is (to first order) exactly chi-square.
``emulator``
    The first arrivals of the O2I channel emulator (``emulate_channel`` + ``first_arrival``):
    ceiling reflections, lower-edge diffraction, ... so the path model is wrong by ~0.7 m RMS
    while the CRLB claims millimetres. The solver is given
    ``sigma = sqrt(sigma_CRLB^2 + sigma_model^2)``; ``sigma_model`` is swept.

The faulty anchor is rotated over the nodes (node ``i`` sees anchor ``i mod M`` misbehave), so
the rates average over every anchor's geometry. The fault starts at ``t = 0``; ramps and
drifts start from zero. The same noise draw is used for every fault of one data set (common
random numbers), so rows differ only by the fault.

Metrics per case (over all fixes of all nodes and epochs):

- **alarm**: the fix is flagged (an anchor excluded, or status ``GATING_FAILED``);
- **excl. faulty**: the faulty anchor is excluded (detection *and* identification);
- **wrong excl.**: an honest anchor is excluded (with all anchors honest: false exclusions);
- **Pd model**: the first-order prediction of the alarm rate (matched data only): the
  non-central chi-square tail ``P(chi2'(dof, lambda) > threshold)`` with
  ``lambda = w^T (I - P) w``, ``w`` the fault's range error in sigma units at the true
  position and ``P`` the hat matrix of the weighted Jacobian (redundancy numbers);
- **fix error** (3D, median and 95th percentile) of D-NLS without gating and with gating,
  and the 95th percentile over fixes the gating reports ``OK`` (the ones a user trusts);
- **OK & err > 3 m**: fixes the gating reports ``OK`` although they are off by more than a
  floor height (missed detections that matter: the integrity risk);
- **time to exclusion** for ramps and drifts: per node, the first fix that excludes the faulty
  anchor, and the first excluding fix from which it stays excluded in >= 90 % of the next 10
  fixes (1 s); median over nodes (``-`` if fewer than half the nodes get there); **t model
  90%** is the first time the first-order alarm probability reaches 90 %.

Run:  /work/venv/bin/python benchmarks/bench_spoofing.py [--quick] [--seed N] [--epochs E]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.stats import binomtest, ncx2

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.channel.linkbudget import db_to_linear, ranging_crlb_m
from diffpos.estimators.dnls.solver import dnls
from diffpos.estimators.gating import GatingConfig, chi2_threshold
from diffpos.estimators.result import ExclusionReason, FixResult, FixStatus
from diffpos.geometry import window_edge_path
from diffpos.paths.mechanisms import MECHANISMS
from diffpos.scenario import Scenario

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

UPPER_SLOT = MECHANISMS.index("Tx-D(upper)-Rx")
#: Window of the sustained time-to-exclusion: 10 fixes (1 s at 10 Hz).
SUSTAIN_FIXES = 10
SUSTAIN_SHARE = 0.9
#: Alert limit of the "misleading" metric: an OK fix off by more than a floor height [m].
ALERT_LIMIT_M = 3.0

__all__ = [
    "CaseResult",
    "EpochData",
    "Fault",
    "apply_fault",
    "evaluate",
    "noncentrality",
    "predicted_detection",
    "reference_fde",
    "run_case",
    "simulate_epochs",
    "with_anchors",
]


# --------------------------------------------------------------------------------------------
# faults
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Fault:
    """One anchor's misbehaviour.

    Attributes
    ----------
    kind : {"honest", "bias", "bias_sigma", "ramp", "offset", "drift"}
        ``bias``: constant range bias ``size`` [m]; ``bias_sigma``: constant bias of ``size``
        times the link's sigma [-]; ``ramp``: range bias growing at ``size`` [m/s] from 0 at
        ``t = 0``; ``offset``: the anchor reports its position shifted by ``size`` [m] along
        ``direction``; ``drift``: the reported position drifts at ``size`` [m/s] along
        ``direction``.
    size : float [m, -, or m/s]
    direction : (float, float, float)
        Unit vector of ``offset`` / ``drift`` (building frame).
    """

    kind: str = "honest"
    size: float = 0.0
    direction: tuple[float, float, float] = (1.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        kinds = ("honest", "bias", "bias_sigma", "ramp", "offset", "drift")
        if self.kind not in kinds:
            raise ValueError(f"Fault.kind must be one of {kinds}, got {self.kind!r}")
        d = np.asarray(self.direction, dtype=np.float64)
        if d.shape != (3,) or not np.isclose(np.linalg.norm(d), 1.0):
            raise ValueError(f"Fault.direction must be a unit 3-vector, got {self.direction}")

    @property
    def label(self) -> str:
        axis = {(1.0, 0.0, 0.0): "x", (0.0, 1.0, 0.0): "y", (0.0, 0.0, 1.0): "z"}.get(
            tuple(float(v) for v in self.direction), str(self.direction))
        return {
            "honest": "honest",
            "bias": f"bias {self.size:+g} m",
            "bias_sigma": f"bias {self.size:g} sigma",
            "ramp": f"ramp {self.size:g} m/s",
            "offset": f"position {self.size:g} m in {axis}",
            "drift": f"position drift {self.size:g} m/s in {axis}",
        }[self.kind]

    @property
    def grows(self) -> bool:
        """True for faults that start at zero and grow (time to exclusion is meaningful)."""
        return self.kind in ("ramp", "drift")

    def range_bias_m(self, t_s: FloatArray, sigma_m: FloatArray) -> FloatArray:
        """Added range error, shape of ``sigma_m`` ``(E, N)`` [m]; ``t_s`` is ``(E,)`` [s]."""
        t = np.asarray(t_s, dtype=np.float64)[:, None]
        if self.kind == "bias":
            return np.full(sigma_m.shape, self.size)
        if self.kind == "bias_sigma":
            return self.size * sigma_m
        if self.kind == "ramp":
            return np.broadcast_to(self.size * t, sigma_m.shape).copy()
        return np.zeros(sigma_m.shape)

    def position_error_m(self, t_s: FloatArray) -> FloatArray:
        """Error of the reported anchor position, shape ``(E, 3)`` [m]."""
        t = np.asarray(t_s, dtype=np.float64)[:, None]
        d = np.asarray(self.direction, dtype=np.float64)[None, :]
        if self.kind == "offset":
            return np.broadcast_to(self.size * d, (t.shape[0], 3)).copy()
        if self.kind == "drift":
            return self.size * t * d
        return np.zeros((t.shape[0], 3))


# --------------------------------------------------------------------------------------------
# simulated measurements
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EpochData:
    """Honest measurements of N nodes from M anchors over E epochs.

    Attributes
    ----------
    t_s : ndarray, shape (E,) [s]
    anchors_m : ndarray, shape (E, M, 3) [m]
        True anchor positions.
    nodes_m : ndarray, shape (E, N, 3) [m]
        True node positions.
    clean_m : ndarray, shape (E, N, M) [m]
        Noise-free length of the measured path (model path or emulator first arrival).
    ranges_m : ndarray, shape (E, N, M) [m]
        Measured ranges (``clean_m`` + noise at the CRLB); 0 where ``mask`` is False.
    sigmas_m : ndarray, shape (E, N, M) [m]
        Sigmas given to the solver (CRLB, combined with ``sigma_model_m`` for the emulator).
    mask : ndarray of bool, shape (E, N, M)
        Link measured (first arrival detected).
    faulty : ndarray of int, shape (N,)
        Index of the misbehaving anchor for each node (``i mod M``).
    source : str
        ``"matched"`` or ``"emulator"``.
    window_height_m, delta_m : float [m]
        Path model of the solver (Case-1: ``delta_m = 0``).
    edge_x_m : (float, float) [m]
    sigma_model_m : float [m]
    """

    t_s: FloatArray
    anchors_m: FloatArray
    nodes_m: FloatArray
    clean_m: FloatArray
    ranges_m: FloatArray
    sigmas_m: FloatArray
    mask: BoolArray
    faulty: NDArray[np.int_]
    source: str
    window_height_m: float
    delta_m: float
    edge_x_m: tuple[float, float]
    sigma_model_m: float = 0.0

    @property
    def shape(self) -> tuple[int, int, int]:
        return self.ranges_m.shape  # type: ignore[return-value]

    def with_sigma_model(self, sigma_model_m: float) -> EpochData:
        """Same measurements, solver sigmas recomputed with another model-error floor [m]."""
        crlb = np.sqrt(np.maximum(self.sigmas_m**2 - self.sigma_model_m**2, 0.0))
        sig = np.sqrt(crlb**2 + sigma_model_m**2)
        return dataclasses.replace(self, sigmas_m=np.where(self.mask, sig, 1.0),
                                   sigma_model_m=float(sigma_model_m))


def with_anchors(scenario: Scenario, anchors_from: Scenario, count: int | None = None) -> Scenario:
    """``scenario`` (its building, radio and nodes) with the first ``count`` anchors of another."""
    anchors = anchors_from.anchors if count is None else anchors_from.anchors[:count]
    return dataclasses.replace(scenario, anchors=tuple(anchors))


def simulate_epochs(
    scenario: Scenario,
    *,
    epochs: int,
    rate_hz: float = 10.0,
    source: str = "matched",
    sigma_model_m: float = 0.0,
    rng: np.random.Generator,
    node_count: int | None = None,
) -> EpochData:
    """Honest ranges of every node from every anchor at ``epochs`` epochs.

    Parameters
    ----------
    scenario : Scenario
        Building, radio, anchors and (explicit) nodes with their trajectories.
    epochs : int
        Number of epochs, at ``t = k / rate_hz``.
    rate_hz : float [Hz]
    source : {"matched", "emulator"}
        See the module docstring.
    sigma_model_m : float [m]
        Model-error floor added in quadrature to the CRLB for the solver's sigmas.
    rng : numpy.random.Generator
        Noise source.
    node_count : int, optional
        Use only the first ``node_count`` nodes.

    Returns
    -------
    EpochData
    """
    if source not in ("matched", "emulator"):
        raise ValueError(f"source must be 'matched' or 'emulator', got {source!r}")
    if epochs < 1 or not rate_hz > 0:
        raise ValueError("epochs must be >= 1 and rate_hz > 0")
    if not scenario.nodes:
        raise ValueError("scenario has no explicit nodes (a node grid has no trajectories)")
    nodes_spec = scenario.nodes if node_count is None else scenario.nodes[:node_count]
    t = np.arange(epochs) / float(rate_hz)
    anchors = np.stack([a.trajectory.position_m(t) for a in scenario.anchors], axis=1)
    nodes = np.stack([n.trajectory.position_m(t) for n in nodes_spec], axis=1)
    b, radio = scenario.building, scenario.radio
    e, n, m = epochs, nodes.shape[1], anchors.shape[1]
    clean = np.empty((e, n, m))
    crlb = np.empty((e, n, m))
    mask = np.ones((e, n, m), dtype=bool)
    for k in range(e):  # the emulator takes one anchor set at a time (about 50 ms per epoch)
        ch = emulate_channel(anchors[k], nodes[k], building=b, radio=radio)
        if source == "matched":
            clean[k] = window_edge_path(anchors[k][None], nodes[k][:, None],
                                        window_height_m=b.window_height_m,
                                        edge_x_m=b.edge_x_m).length_m
            snr = np.maximum(ch.snr_db[..., UPPER_SLOT], radio.detection_snr_db)
            crlb[k] = ranging_crlb_m(db_to_linear(snr), radio.bandwidth_hz)
        else:
            fa = first_arrival(ch, radio=radio, rng=None)
            mask[k] = fa.detected
            clean[k] = np.where(fa.detected, fa.true_path_m, 0.0)
            crlb[k] = np.where(fa.detected, fa.sigma_m, 1.0)
    noise = rng.standard_normal((e, n, m))
    ranges = np.where(mask, clean + crlb * noise, 0.0)
    sig = np.sqrt(crlb**2 + sigma_model_m**2) if source == "emulator" else crlb
    return EpochData(
        t_s=t, anchors_m=anchors, nodes_m=nodes, clean_m=clean, ranges_m=ranges,
        sigmas_m=np.where(mask, sig, 1.0), mask=mask, faulty=np.arange(n) % m, source=source,
        window_height_m=float(b.window_height_m), delta_m=0.0, edge_x_m=b.edge_x_m,
        sigma_model_m=float(sigma_model_m) if source == "emulator" else 0.0,
    )


def apply_fault(data: EpochData, fault: Fault) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The solver's inputs under ``fault``.

    Returns
    -------
    anchors_m : ndarray, shape (E, N, M, 3) [m]
        Reported anchor positions (the faulty one shifted for offset / drift).
    ranges_m : ndarray, shape (E, N, M) [m]
        Measured ranges (the faulty one biased; clipped at 0).
    clean_m : ndarray, shape (E, N, M) [m]
        Noise-free ranges under the fault (for the first-order prediction).
    """
    n = data.shape[1]
    cols = np.arange(n)
    j = data.faulty
    anchors = np.repeat(data.anchors_m[:, None], n, axis=1)
    ranges = data.ranges_m.copy()
    clean = data.clean_m.copy()
    bias = fault.range_bias_m(data.t_s, data.sigmas_m[:, cols, j])
    bias = np.where(data.mask[:, cols, j], bias, 0.0)
    ranges[:, cols, j] = np.maximum(ranges[:, cols, j] + bias, 0.0)
    clean[:, cols, j] += bias
    anchors[:, cols, j, :] += fault.position_error_m(data.t_s)[:, None, :]
    return anchors, ranges, clean


def noncentrality(data: EpochData, fault: Fault) -> tuple[FloatArray, FloatArray]:
    """First-order effect of ``fault`` on the chi-square statistic, per fix.

    The normalised fault vector ``w_j = (r_clean_j - p_j(a_reported, x_true)) / sigma_j`` enters
    the least-squares residual through ``I - P`` (``P`` the hat matrix of the weighted Jacobian
    at the true position), so the test statistic is non-central chi-square with
    ``dof = |S| - 3`` and non-centrality ``lambda = w^T (I - P) w``.

    Returns
    -------
    lam : ndarray, shape (E, N) [-]
        Non-centrality ``lambda``.
    fault_sigma : ndarray, shape (E, N) [-]
        ``|w_j|`` of the faulty anchor (fault size in sigma units).
    """
    n = data.shape[1]
    anchors, _, clean = apply_fault(data, fault)
    path = window_edge_path(anchors, data.nodes_m[:, :, None, :],
                            window_height_m=data.window_height_m, delta_m=data.delta_m,
                            edge_x_m=data.edge_x_m)
    wt = data.mask / data.sigmas_m
    w = (clean - path.length_m) * wt
    a = path.jacobian * wt[..., None]  # (E, N, M, 3)
    ata = np.einsum("...mi,...mj->...ij", a, a)
    proj = a @ np.linalg.solve(ata, np.swapaxes(a, -1, -2))  # (E, N, M, M)
    lam = np.einsum("...m,...m->...", w, w) - np.einsum("...m,...mk,...k->...", w, proj, w)
    cols = np.arange(n)
    return np.maximum(lam, 0.0), np.abs(w[:, cols, data.faulty])


def predicted_detection(
    data: EpochData,
    fault: Fault,
    *,
    false_alarm_probability: float,
) -> tuple[FloatArray, FloatArray]:
    """First-order probability that the chi-square test raises an alarm, per fix.

    ``P(chi2'(dof, lambda) > chi2.isf(P_fa, dof))`` with ``lambda`` from
    :func:`noncentrality`; equals ``P_fa`` for honest anchors.

    Returns
    -------
    pd : ndarray, shape (E, N) [-]
        Alarm probability (``nan`` where ``dof < 1``).
    fault_sigma : ndarray, shape (E, N) [-]
        Fault size of the faulty anchor in sigma units.
    """
    lam, fault_sigma = noncentrality(data, fault)
    dof = data.mask.sum(axis=-1) - 3
    thr = chi2_threshold(dof.ravel(), false_alarm_probability).reshape(dof.shape)
    with np.errstate(invalid="ignore"):
        pd = np.where(dof >= 1, ncx2.sf(thr, np.maximum(dof, 1), lam), np.nan)
    return pd, fault_sigma


# --------------------------------------------------------------------------------------------
# one case
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CaseResult:
    """Per-fix outcomes of one (data, fault, gating) case; rates and errors as properties.

    Attributes
    ----------
    fault : Fault
    gating : GatingConfig or None
    t_s : ndarray, shape (E,) [s]
    faulty_excluded, wrong_excluded, alarm, ok : ndarray of bool, shape (E, N)
    error_m : ndarray, shape (E, N) [m]
        3D error of the gated fix (``inf`` where no position).
    error_ungated_m : ndarray, shape (E, N) [m] or None
    status : ndarray of int, shape (E, N)
    pd_model : ndarray, shape (E, N) or None
        First-order alarm probability (matched data).
    fault_sigma : ndarray, shape (E, N) or None
        Fault size in sigma units.
    seconds : float [s]
        Wall-clock time of the gated solve.
    """

    fault: Fault
    gating: GatingConfig | None
    t_s: FloatArray
    faulty_excluded: BoolArray
    wrong_excluded: BoolArray
    alarm: BoolArray
    ok: BoolArray
    error_m: FloatArray
    error_ungated_m: FloatArray | None
    status: NDArray[np.int_]
    pd_model: FloatArray | None = None
    fault_sigma: FloatArray | None = None
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def n_fixes(self) -> int:
        return int(self.alarm.size)

    def rate(self, name: str) -> float:
        return float(np.mean(getattr(self, name)))

    def time_to_exclusion_s(self) -> tuple[float, float, int]:
        """Median over nodes of (first exclusion, sustained exclusion) [s], and how many nodes
        never reach the sustained criterion (>= 90 % of the next 10 fixes)."""
        return time_to_exclusion(self.t_s, self.faulty_excluded)

    def misleading_rate(self, limit_m: float = ALERT_LIMIT_M) -> float:
        """Share of fixes reported ``OK`` (trusted) whose 3D error exceeds ``limit_m``."""
        return float(np.mean(self.ok & (self.error_m > limit_m)))

    def predicted_time_s(self) -> float:
        """Median over nodes of the first time the predicted alarm probability is >= 0.9 [s]."""
        if self.pd_model is None:
            return float("nan")
        hit = np.nan_to_num(self.pd_model) >= SUSTAIN_SHARE
        return _median_first(self.t_s, hit)


def _median_first(t_s: FloatArray, hit: BoolArray) -> float:
    first = np.where(hit.any(axis=0), np.argmax(hit, axis=0), -1)
    if np.mean(first >= 0) < 0.5:
        return float("nan")
    vals = np.where(first >= 0, t_s[np.maximum(first, 0)], np.inf)
    return float(np.percentile(vals, 50, method="inverted_cdf"))


def time_to_exclusion(t_s: FloatArray, excluded: BoolArray) -> tuple[float, float, int]:
    """Time to exclusion per node from per-epoch exclusion flags ``(E, N)``.

    Returns
    -------
    first_s : float [s]
        Median over nodes of the time of the first exclusion (``nan`` if fewer than half of
        the nodes ever exclude).
    sustained_s : float [s]
        Median over nodes of the first time ``t_k`` at which the faulty anchor is excluded and
        stays excluded in at least 90 % of the fixes ``k .. k + 9`` (1 s at 10 Hz).
    never : int
        Nodes that never meet the sustained criterion.
    """
    e = excluded.shape[0]
    w = min(SUSTAIN_FIXES, e)
    c = np.concatenate([np.zeros((1, excluded.shape[1])), np.cumsum(excluded, axis=0)])
    win = (c[w:] - c[:-w]) / w  # (E - w + 1, N) share in the window starting at k
    sustained = (win >= SUSTAIN_SHARE) & excluded[: e - w + 1]
    never = int(np.sum(~sustained.any(axis=0)))
    return (_median_first(t_s, excluded), _median_first(t_s[: e - w + 1], sustained), never)


def _solve(data: EpochData, anchors: FloatArray, ranges: FloatArray,
           gating: GatingConfig | None) -> FixResult:
    e, n, m = data.shape
    return dnls(anchors.reshape(e * n, m, 3), ranges.reshape(e * n, m),
                data.sigmas_m.reshape(e * n, m), mask=data.mask.reshape(e * n, m),
                window_height_m=data.window_height_m, delta_m=data.delta_m,
                edge_x_m=data.edge_x_m, gating=gating)


def _error(data: EpochData, fix: FixResult) -> FloatArray:
    e, n, _ = data.shape
    err = np.linalg.norm(fix.position_m.reshape(e, n, 3) - data.nodes_m, axis=-1)
    return np.where(np.isfinite(err), err, np.inf)


def run_case(
    data: EpochData,
    fault: Fault,
    gating: GatingConfig,
    *,
    ungated_error_m: FloatArray | None = None,
    ungated: bool = True,
    predict: bool | None = None,
) -> CaseResult:
    """Solve every fix of ``data`` under ``fault`` with ``gating`` and score it.

    Parameters
    ----------
    data : EpochData
    fault : Fault
    gating : GatingConfig
    ungated_error_m : ndarray, shape (E, N), optional [m]
        Reuse the error of a previous ungated solve of the same (data, fault).
    ungated : bool
        Also solve without gating (for the error comparison) if not given.
    predict : bool, optional
        Compute the first-order alarm probability (default: for matched data).

    Returns
    -------
    CaseResult
    """
    e, n, m = data.shape
    anchors, ranges, _ = apply_fault(data, fault)
    t0 = time.perf_counter()
    fix = _solve(data, anchors, ranges, gating)
    seconds = time.perf_counter() - t0
    if ungated_error_m is None and ungated:
        ungated_error_m = _error(data, _solve(data, anchors, ranges, None))
    excl = fix.excluded.reshape(e, n, m)
    cols = np.arange(n)
    faulty_col = np.zeros((n, m), dtype=bool)
    if fault.kind != "honest":
        faulty_col[cols, data.faulty] = True
    status = fix.status.reshape(e, n)
    faulty_excl = np.any(excl & faulty_col, axis=-1)
    wrong = np.any(excl & ~faulty_col, axis=-1)
    alarm = np.any(excl, axis=-1) | (status == FixStatus.GATING_FAILED)
    pd = sig = None
    if predict if predict is not None else data.source == "matched":
        pd, sig = predicted_detection(data, fault,
                                      false_alarm_probability=gating.false_alarm_probability)
    reasons = fix.exclusion_reason.reshape(e, n, m)
    extra = {"pregate_share": float(np.mean(np.any(
        reasons == ExclusionReason.PREGATE_SHORTER_THAN_LOS, axis=-1)))}
    return CaseResult(
        fault=fault, gating=gating, t_s=data.t_s, faulty_excluded=faulty_excl,
        wrong_excluded=wrong, alarm=alarm, ok=status == FixStatus.OK,
        error_m=_error(data, fix), error_ungated_m=ungated_error_m, status=status,
        pd_model=pd, fault_sigma=sig, seconds=seconds, extra=extra,
    )


def evaluate(
    data: EpochData,
    faults: Sequence[Fault],
    gating: GatingConfig,
    *,
    ungated: bool = True,
) -> list[CaseResult]:
    """:func:`run_case` for every fault (one gated and one ungated batch per fault)."""
    return [run_case(data, f, gating, ungated=ungated) for f in faults]


# --------------------------------------------------------------------------------------------
# tables
# --------------------------------------------------------------------------------------------


def _pct(x: float) -> str:
    if not np.isfinite(x):
        return "-"
    if x == 0:
        return "0"
    if x < 0.001:
        return f"{100 * x:.3f}"
    return f"{100 * x:.2f}" if x < 0.1 else f"{100 * x:.1f}"


def _m(x: float) -> str:
    if not np.isfinite(x):
        return "inf" if x == np.inf else "-"
    return f"{x:.3f}" if x < 1 else (f"{x:.2f}" if x < 10 else f"{x:.1f}")


def _s(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{x:.1f}"


def _q(v: FloatArray | None, p: float) -> float:
    if v is None:
        return float("nan")
    v = np.asarray(v).ravel()
    if v.size == 0:
        return float("nan")
    return float(np.percentile(v, p, method="inverted_cdf"))


def binomial_ci(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Clopper-Pearson interval of a rate ``k / n``."""
    ci = binomtest(int(k), int(n)).proportion_ci(confidence_level=confidence, method="exact")
    return float(ci.low), float(ci.high)


def table(rows: list[list[str]], header: list[str], *, left: int = 1) -> str:
    """Markdown table; the first ``left`` columns left-aligned, the others right-aligned."""
    out = ["| " + " | ".join(header) + " |",
           "| " + " | ".join("---" if i < left else "---:" for i in range(len(header))) + " |"]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def fault_table(results: list[CaseResult], *, with_model: bool = True) -> str:
    """Markdown table of fault cases (see the module docstring for the columns)."""
    header = ["fault", "fault med [sigma]", "alarm %"]
    if with_model:
        header.append("Pd model %")
    header += ["excl. faulty %", "wrong excl. %", "not OK %", "err no gating med/p95 [m]",
               "err gated med/p95 [m]", "OK fixes p95 [m]",
               f"OK & err > {ALERT_LIMIT_M:g} m %", "t first / 90% [s]"]
    if with_model:
        header.append("t model 90% [s]")
    rows = []
    for r in results:
        ok_err = r.error_m[r.ok]
        first, sust, _never = r.time_to_exclusion_s() if r.fault.grows else (np.nan,) * 3
        row = [r.fault.label, _m(_q(r.fault_sigma, 50)) if r.fault_sigma is not None else "-",
               _pct(r.rate("alarm"))]
        if with_model:
            row.append(_pct(float(np.nanmean(r.pd_model))) if r.pd_model is not None else "-")
        row += [
            _pct(r.rate("faulty_excluded")) if r.fault.kind != "honest" else "-",
            _pct(r.rate("wrong_excluded")),
            _pct(1.0 - float(np.mean(r.ok))),
            f"{_m(_q(r.error_ungated_m, 50))} / {_m(_q(r.error_ungated_m, 95))}",
            f"{_m(_q(r.error_m, 50))} / {_m(_q(r.error_m, 95))}",
            _m(_q(ok_err, 95)) if ok_err.size else "-",
            _pct(r.misleading_rate()),
            f"{_s(first)} / {_s(sust)}" if r.fault.grows else "",
        ]
        if with_model:
            row.append(_s(r.predicted_time_s()) if r.fault.grows else "")
        rows.append(row)
    return table(rows, header)


def honest_rows(label: str, results: list[CaseResult]) -> list[list[str]]:
    """Rows of the honest-anchor table: alarm rate and its 95 % CI against ``P_fa``."""
    rows = []
    for r in results:
        pfa = r.gating.false_alarm_probability if r.gating is not None else float("nan")
        ka = int(np.sum(r.alarm))
        lo, hi = binomial_ci(ka, r.n_fixes)
        inside = "yes" if lo <= pfa <= hi else "no"
        rows.append([label, f"{pfa:g}", str(r.n_fixes), _pct(ka / r.n_fixes),
                     f"[{_pct(lo)}, {_pct(hi)}]", inside, _pct(r.rate("wrong_excluded")),
                     _pct(1.0 - float(np.mean(r.ok))),
                     f"{_m(_q(r.error_m, 50))} / {_m(_q(r.error_m, 95))}"])
    return rows


HONEST_HEADER = ["data", "P_fa", "fixes", "alarm %", "alarm 95% CI %", "P_fa in CI",
                 "false excl. %", "not OK %", "err gated med/p95 [m]"]


def reference_fde(
    data: EpochData,
    fault: Fault,
    gating: GatingConfig,
    *,
    stride: int = 1,
) -> dict[str, float]:
    """Exhaustive single-exclusion FDE with a full multi-start fit of every subset (reference).

    Every fix is solved from all starts with all anchors; if its chi-square test fails, every
    leave-one-out subset is solved again from all starts (not warm-started at the faulty
    solution) and the subset with the smallest statistic is kept if at least
    ``gating.min_anchors_after_exclusion`` anchors remain. Costs ``M + 1`` full solves per
    failing fix, so only every ``stride``-th epoch is used.

    Returns
    -------
    dict
        ``fixes``, ``excl_faulty``, ``wrong_excl`` (rates) and ``err_p50_m``, ``err_p95_m``.
    """
    sub = _every(data, stride)
    e, n, m = sub.shape
    anchors, ranges, _ = apply_fault(sub, fault)
    a = anchors.reshape(e * n, m, 3)
    r = ranges.reshape(e * n, m)
    s = sub.sigmas_m.reshape(e * n, m)
    mask = sub.mask.reshape(e * n, m)
    kw = {"window_height_m": sub.window_height_m, "delta_m": sub.delta_m,
          "edge_x_m": sub.edge_x_m, "gating": None}
    full = dnls(a, r, s, mask=mask, **kw)
    pos = full.position_m.copy()
    thr = chi2_threshold(full.dof, gating.false_alarm_probability)
    fail = (full.dof >= 1) & (full.test_statistic > thr)
    fail &= mask.sum(axis=-1) - 1 >= gating.min_anchors_after_exclusion
    idx = np.flatnonzero(fail)
    excluded = np.full(e * n, -1)
    if idx.size:
        k = idx.size
        cand = np.repeat(mask[idx][:, None, :], m, axis=1) & ~np.eye(m, dtype=bool)[None]
        sol = dnls(np.repeat(a[idx], m, axis=0), np.repeat(r[idx], m, axis=0),
                   np.repeat(s[idx], m, axis=0), mask=cand.reshape(k * m, m), **kw)
        t = np.where(mask[idx], sol.test_statistic.reshape(k, m), np.inf)
        t = np.where(np.isfinite(t), t, np.inf)
        best = np.argmin(t, axis=-1)
        excluded[idx] = best
        pos[idx] = sol.position_m.reshape(k, m, 3)[np.arange(k), best]
    excl = np.zeros((e * n, m), dtype=bool)
    hit = np.flatnonzero(excluded >= 0)
    excl[hit, excluded[hit]] = True
    return _score(sub, fault, excl, pos)


def _every(data: EpochData, stride: int) -> EpochData:
    return dataclasses.replace(
        data, t_s=data.t_s[::stride], anchors_m=data.anchors_m[::stride],
        nodes_m=data.nodes_m[::stride], clean_m=data.clean_m[::stride],
        ranges_m=data.ranges_m[::stride], sigmas_m=data.sigmas_m[::stride],
        mask=data.mask[::stride])


def _score(sub: EpochData, fault: Fault, excl: BoolArray, pos: FloatArray) -> dict[str, float]:
    e, n, m = sub.shape
    faulty_col = np.zeros((e * n, m), dtype=bool)
    if fault.kind != "honest":
        faulty_col[np.arange(e * n), np.tile(sub.faulty, e)] = True
    err = np.linalg.norm(pos - sub.nodes_m.reshape(e * n, 3), axis=-1)
    err = np.where(np.isfinite(err), err, np.inf)
    return {
        "fixes": float(e * n),
        "excl_faulty": float(np.mean(np.any(excl & faulty_col, axis=-1))),
        "wrong_excl": float(np.mean(np.any(excl & ~faulty_col, axis=-1))),
        "err_p50_m": _q(err, 50),
        "err_p95_m": _q(err, 95),
    }


def reference_table(data: EpochData, faults: Sequence[Fault], gating: GatingConfig, *,
                    stride: int) -> str:
    """Gating with warm-started exclusion candidates (the earlier implementation), gating as
    implemented (multi-start candidates, ``GatingConfig.multistart_exclusion``), and
    :func:`reference_fde`."""
    rows = []
    sub = _every(data, stride)
    before = dataclasses.replace(gating, multistart_exclusion=False, z_range_m=None)
    for f in faults:
        res = {}
        for name, g_cfg in (("warm-started candidates (before)", before),
                            ("multi-start candidates (as implemented)", gating)):
            t0 = time.perf_counter()
            g = run_case(sub, f, g_cfg, ungated=False, predict=False)
            res[name] = {
                "fixes": float(g.n_fixes), "excl_faulty": g.rate("faulty_excluded"),
                "wrong_excl": g.rate("wrong_excluded"), "err_p50_m": _q(g.error_m, 50),
                "err_p95_m": _q(g.error_m, 95), "not_ok": 1.0 - float(np.mean(g.ok)),
                "misleading": g.misleading_rate(), "seconds": time.perf_counter() - t0}
        res["multi-start leave-one-out (reference)"] = reference_fde(sub, f, gating)
        for name, v in res.items():
            rows.append([f.label, name, str(int(v["fixes"])), _pct(v["excl_faulty"]),
                         _pct(v["wrong_excl"]),
                         f"{_m(v['err_p50_m'])} / {_m(v['err_p95_m'])}",
                         _pct(v.get("not_ok", np.nan)), _pct(v.get("misleading", np.nan)),
                         _s(v.get("seconds", np.nan))])
    return table(rows, ["fault", "exclusion", "fixes", "excl. faulty %", "wrong excl. %",
                        "err med/p95 [m]", "not OK %", f"OK & err > {ALERT_LIMIT_M:g} m %",
                        "solve [s]"], left=2)


# --------------------------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------------------------

#: Tables of the report, in order (``--sections``).
SECTIONS = ("honest", "matched8", "identification", "paper4", "three", "emulator")


def default_faults(quick: bool) -> dict[str, list[Fault]]:
    ax = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
    bias_m = (0.5, 1, 2, 5, 10, 20) if not quick else (0.5, 2, 10)
    sig_k = (3, 5, 10, 20) if not quick else (5, 20)
    const = [Fault("bias", float(b)) for b in bias_m] + [Fault("bias", -1.0), Fault("bias", -5.0)]
    const += [Fault("bias_sigma", float(k)) for k in sig_k]
    ramps = [Fault("ramp", r) for r in (0.1, 0.5, 2.0)]
    offs = [Fault("offset", float(s), ax[a]) for s in (1, 3, 10) for a in "xyz"]
    if quick:
        offs = [Fault("offset", float(s), ax[a]) for s in (1, 10) for a in "xz"]
    drift = [Fault("drift", 0.1, ax["x"]), Fault("drift", 0.1, ax["z"])]
    return {"const": const, "ramp": ramps + drift, "offset": offs}


def main(argv: Sequence[str] | None = None) -> int:
    from diffpos_services.scenario_io import load_scenario  # file I/O lives in services

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="fewer epochs (default 60), nodes and faults: about a minute")
    ap.add_argument("--seed", type=int, default=1, help="noise seed (default 1)")
    ap.add_argument("--epochs", type=int, default=None,
                    help="epochs at 10 Hz (default 300 = 30 s; 60 with --quick)")
    ap.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS),
                    help="tables to print (default all): " + ", ".join(SECTIONS))
    args = ap.parse_args(argv)
    sections = set(args.sections)
    if args.epochs is not None and args.epochs < SUSTAIN_FIXES:
        ap.error(f"--epochs must be >= {SUSTAIN_FIXES}")
    epochs = args.epochs or (60 if args.quick else 300)
    nodes = 25 if args.quick else None
    t_start = time.perf_counter()
    large = load_scenario("large")
    paper = load_scenario("paper")
    sc4 = with_anchors(large, paper)
    sc3 = with_anchors(large, paper, 3)
    faults = default_faults(args.quick)
    all_faults = faults["const"] + faults["ramp"] + faults["offset"]
    g3 = GatingConfig(false_alarm_probability=1e-3)
    print(f"# Spoofed / faulty anchors vs D-NLS gating ({epochs} epochs at 10 Hz, seed "
          f"{args.seed}{', quick' if args.quick else ''})\n")

    rng = np.random.default_rng(args.seed)
    m8 = simulate_epochs(large, epochs=epochs, source="matched", rng=rng, node_count=nodes)
    if sections - {"matched8", "identification"}:  # same draws as a full run
        m4 = simulate_epochs(sc4, epochs=epochs, source="matched", rng=rng, node_count=nodes)
        m3 = simulate_epochs(sc3, epochs=epochs, source="matched", rng=rng, node_count=nodes)
        em8 = simulate_epochs(large, epochs=epochs, source="emulator", rng=rng,
                              node_count=nodes)
        em4 = simulate_epochs(sc4, epochs=epochs, source="emulator", rng=rng,
                              node_count=nodes)
    sig_med = float(np.median(m8.sigmas_m))
    print(f"matched model, 8 anchors: ranging sigma median {sig_med * 100:.1f} cm "
          f"(5-95 %: {np.percentile(m8.sigmas_m, 5) * 100:.1f}-"
          f"{np.percentile(m8.sigmas_m, 95) * 100:.1f} cm); "
          f"{m8.shape[1]} nodes x {m8.shape[0]} epochs = {m8.shape[0] * m8.shape[1]} fixes per "
          "case\n")

    pfas = (1e-2, 1e-3, 1e-4)
    honest = Fault()

    def flush() -> None:
        print(flush=True, end="")

    # 1. honest anchors: false alarms / exclusions vs P_fa
    if "honest" in sections:
        rows: list[list[str]] = []
        for label, data in (("matched, 8 anchors", m8), ("matched, 4 anchors (paper)", m4)):
            res = [run_case(data, honest, GatingConfig(false_alarm_probability=p), ungated=False)
                   for p in pfas]
            rows += honest_rows(label, res)
        for s_mod in (0.0, 0.3, 0.5, 0.7, 1.0):
            d = em8.with_sigma_model(s_mod)
            res = [run_case(d, honest, GatingConfig(false_alarm_probability=p), ungated=False)
                   for p in pfas]
            rows += honest_rows(f"emulator, 8 anchors, sigma_model {s_mod:g} m", res)
        print("## Honest anchors: false alarms and exclusions vs the configured P_fa\n")
        print(table(rows, HONEST_HEADER) + "\n")
        flush()

    # 2. matched, 8 anchors: every fault
    if "matched8" in sections:
        print("## Matched model, 8 anchors (large.toml), P_fa = 1e-3\n")
        print(fault_table(evaluate(m8, [honest, *all_faults], g3)) + "\n")
        flush()
    if "identification" in sections:
        stride = 3 if args.quick else 5
        print(f"## Identification: warm-started vs multi-start exclusion candidates vs exhaustive "
              f"multi-start leave-one-out (reference), matched, 8 anchors, every {stride}th "
              "epoch\n")
        ref_faults = [Fault("bias", 2.0), Fault("bias", 10.0), Fault("bias", -1.0),
                      Fault("bias", -5.0), Fault("offset", 10.0), Fault("offset", 3.0, (0.0, 0.0, 1.0)),
                      Fault("ramp", 2.0)]
        print(reference_table(m8, ref_faults, g3, stride=stride) + "\n")
        flush()

    # 3. the paper's 4 anchors: detection without identification; 3 anchors: nothing
    if "paper4" in sections:
        print("## Matched model, the paper's 4 anchors: detection only "
              "(min_anchors_after_exclusion = 4, the default)\n")
        f4 = [honest, *faults["const"], *faults["ramp"][:3], *faults["offset"][-3:]]
        print(fault_table(evaluate(m4, f4, g3)) + "\n")
        flush()
        print("## Matched model, 4 anchors with min_anchors_after_exclusion = 3 "
              "(exclusion forced with 1 dof)\n")
        sel4 = [f for f in f4 if f.kind in ("honest", "bias", "offset")]
        print(fault_table(evaluate(m4, sel4, GatingConfig(min_anchors_after_exclusion=3)))
              + "\n")
        flush()
    if "three" in sections:
        print("## Matched model, 3 anchors (paper's uav1-uav3): no redundancy\n")
        rows3 = []
        for r in evaluate(m3, [honest, Fault("bias", 2.0), Fault("bias", 10.0)], g3):
            st = r.status
            rows3.append([r.fault.label, _pct(float(np.mean(st == FixStatus.OK_UNVERIFIED))),
                          _pct(float(np.mean(st == FixStatus.OK))),
                          _pct(1.0 - float(np.mean(st == FixStatus.OK_UNVERIFIED))),
                          f"{_m(_q(r.error_m, 50))} / {_m(_q(r.error_m, 95))}",
                          _pct(float(np.mean((st == FixStatus.OK_UNVERIFIED)
                                             & (r.error_m > ALERT_LIMIT_M))))])
        print(table(rows3, ["fault", "OK_UNVERIFIED %", "OK %", "other status %",
                            "err med/p95 [m]",
                            f"unverified & err > {ALERT_LIMIT_M:g} m %"]) + "\n")
        flush()

    # 4. emulator first arrivals (model mismatch)
    if "emulator" in sections:
        sel_em = [honest, Fault("bias", 1.0), Fault("bias", 2.0), Fault("bias", 5.0),
                  Fault("bias", 20.0), Fault("ramp", 0.5), Fault("offset", 10.0),
                  Fault("offset", 10.0, (0.0, 0.0, 1.0))]
        for s_mod in (0.5, 1.0):
            print(f"## Emulator first arrivals, 8 anchors, sigma_model = {s_mod:g} m, "
                  "P_fa = 1e-3\n")
            d = em8.with_sigma_model(s_mod)
            print(fault_table(evaluate(d, sel_em, g3), with_model=False) + "\n")
            flush()
        print("## Emulator first arrivals, paper's 4 anchors, sigma_model = 1 m, P_fa = 1e-3\n")
        print(fault_table(evaluate(em4.with_sigma_model(1.0), sel_em[:5], g3), with_model=False)
              + "\n")
    print(f"total {time.perf_counter() - t_start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
