"""Outlier gating for D-NLS: physical pre-gate and RAIM-style fault detection and exclusion.

Three checks run after every fit, for all fixes of a batch at once:

1. **Physical gate ("pre-gate").** A diffraction path over an edge is a broken line from the
   anchor to the node, so it can never be shorter than the straight line between them:
   ``p_j(x) >= |a_j - x|``; and since the edge lies in the wall ``y = 0`` it can never be
   shorter than the anchor's distance to the wall, ``|y_a,j|``. Tolerance:
   ``k sigma_j + margin`` (``k = GatingConfig.pregate_sigmas``).

   * *Before the fit*, a range shorter than ``|y_a,j|`` is excluded (needs no position).
   * *After a fit that the chi-square test accepts or cannot test*, the worst range with
     ``r_j < |a_j - x_hat| - tol`` (in units of sigma) is excluded, the fix refitted, and the
     exclusion kept only if the range is also impossible at the new solution. It is not
     applied to fits that fail the test: there, a positive fault on another anchor pulls the
     solution so that honest ranges look "too short" (measured: with 4 anchors and a 1 m
     positive fault, a post-fit gate on failing fits excluded an honest anchor in 1 of 3
     trials), so those fixes go to the RAIM exclusion or are reported ``GATING_FAILED``.

2. **Chi-square residual test (RAIM fault detection).** With ``|S|`` used anchors and Gaussian
   noise, the sum of squared normalised residuals at the least-squares solution,
   ``T = sum_{j in S} (r_j / sigma_j)^2``, is (to first order) chi-square with ``|S| - 3``
   degrees of freedom. The test fails when ``T`` exceeds the ``1 - P_fa`` quantile.
   **Exclusion:** if it fails and at least ``min_anchors_after_exclusion`` anchors would
   remain, every candidate subset ``S \\ {j}`` is solved again from all starts of the first
   fit plus the current solution (``multistart_exclusion``; all candidates x starts of all
   failing fixes in one batch) and the anchor whose exclusion gives the smallest test
   statistic is removed (D-NLS bounds this search: candidates solved just far enough to
   rank them, the all-starts recheck only near consistency, hopeless candidates given up
   early, its ``exclusion_*`` options; on the 30 s ``large`` replay the used anchors of 20
   of 15,267 fixes differ from the exhaustive search's, with the same accuracy:
   docs/dnls_cost.md). Warm-starting the candidates at the current solution alone is not
   enough: a fault of metres pulls the all-anchor fit into a wrong local minimum (often
   another floor), the subset without the faulty anchor stays in it and still fails, and a
   second round removes an honest anchor (measured with 8 anchors, 3,000 fixes: honest
   anchors excluded in 32 % of fixes warm-started, 0.07 % multi-start at +10 m; 11 % and
   0.1 % at +2 m; ``docs/spoofing.md``). Screening as in the first fit, but the all-starts
   recheck is per fix: its candidates are re-solved from every start without screening only
   if none of them passes the test (the candidates that keep the faulty anchor all fail).
   With one given start (``dnls(x0_m=...)``) the candidates start from it and the current
   solution. Test and exclusion repeat at most ``max_exclusions`` times.

Fixes with ``|S| <= 3`` (no redundancy) or without ``sigmas_m`` cannot be tested and are
reported as ``OK_UNVERIFIED``. With ``|S| = 4`` a fault can be detected but not identified
(every 3-anchor subset fits exactly), so with the default ``min_anchors_after_exclusion = 4``
exclusion needs ``|S| >= 5``; otherwise a failed test gives ``GATING_FAILED``.

3. **Plausible height (``z_range_m``).** A fix that passes the test (status ``OK``) but lies
   outside the plausible node heights (default: below ground) is reported ``GATING_FAILED``
   (applied in :func:`~diffpos.estimators.dnls.solver`; :meth:`FixResult.message` explains it).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from diffpos.estimators.lm import LMResult, PathModel, cost_of, levenberg_marquardt
from diffpos.estimators.result import ExclusionReason
from diffpos.geometry import los_path

__all__ = ["GatingConfig", "chi2_threshold", "wall_pregate"]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class GatingConfig:
    """Settings of the D-NLS outlier gating (fault detection and exclusion).

    Attributes
    ----------
    false_alarm_probability : float [-]
        ``P_fa`` of the chi-square residual test (per test).
    max_exclusions : int
        Most anchors one fix may lose to the RAIM exclusion and the pre-gate together.
    min_anchors_after_exclusion : int
        RAIM exclusion is attempted only if at least this many anchors remain afterwards
        (4 keeps the remaining fix testable; 3 allows an unverifiable fix).
    pregate : bool
        Apply the physical "shorter than the straight line" pre-gate.
    pregate_sigmas : float [-]
        ``k``: a range is impossible if shorter than the LoS distance by more than
        ``k sigma_j + pregate_margin_m``.
    pregate_margin_m : float [m]
        Extra absolute tolerance of the pre-gate (e.g. for anchor position errors). Without
        ``sigmas_m`` the pre-gate runs only if this margin is > 0 (it is the whole tolerance).
    refit_max_iter : int
        Iteration limit of the warm-started refits (pre-gate confirmation, and the exclusion
        candidates when ``multistart_exclusion`` is False).
    multistart_exclusion : bool
        Solve every exclusion candidate ``S \\ {j}`` of a *failing* fix from all starts of
        the first fit (height grid + LLS, with the same screening; or the given ``x0_m``)
        plus the current solution, instead of only warm-starting at the current solution. A fault of metres pulls the
        all-anchor fit into a wrong local minimum; warm-started candidates stay in it and a
        second round then excludes an honest anchor (``docs/spoofing.md``). Costs up to
        ``M`` multi-start solves per failing fix; fixes that pass the test cost nothing more.
    z_range_m : (float, float) or None [m]
        Plausible node heights ``(z_min, z_max)``; default ``(0, inf)``: above ground. A fix
        that passes the residual test but lies outside is reported ``GATING_FAILED`` (its
        message says why) instead of ``OK``: with all anchors flying low, a weakened geometry
        has an approximate mirror solution below ground that passes the test. Fixes with
        another status (``OK_UNVERIFIED`` included) keep it. ``None`` disables the check.
    """

    false_alarm_probability: float = 1e-3
    max_exclusions: int = 2
    min_anchors_after_exclusion: int = 4
    pregate: bool = True
    pregate_sigmas: float = 4.0
    pregate_margin_m: float = 0.0
    refit_max_iter: int = 30
    multistart_exclusion: bool = True
    z_range_m: tuple[float, float] | None = (0.0, float("inf"))

    def __post_init__(self) -> None:
        if self.z_range_m is not None:
            try:
                lo, hi = (float(v) for v in self.z_range_m)
            except (TypeError, ValueError):
                raise ValueError(
                    "GatingConfig.z_range_m must be None or two numbers (z_min, z_max) [m], "
                    f"got {self.z_range_m!r}"
                ) from None
            if np.isnan(lo) or np.isnan(hi) or not lo < hi:
                raise ValueError(
                    f"GatingConfig.z_range_m must satisfy z_min < z_max, got {self.z_range_m!r}"
                )
            object.__setattr__(self, "z_range_m", (lo, hi))
        if not 0.0 < self.false_alarm_probability < 1.0:
            raise ValueError("GatingConfig.false_alarm_probability must be in (0, 1)")
        if self.max_exclusions < 0:
            raise ValueError("GatingConfig.max_exclusions must be >= 0")
        if self.min_anchors_after_exclusion < 3:
            raise ValueError("GatingConfig.min_anchors_after_exclusion must be >= 3")
        if self.pregate_sigmas < 0 or self.pregate_margin_m < 0:
            raise ValueError("GatingConfig.pregate_sigmas and pregate_margin_m must be >= 0")


#: ``scipy.special.chdtri(dof, p)`` (the chi-square inverse survival function) for dof 1 to
#: 64 of the false-alarm probabilities the estimators use (the gating default, D-NLS' recheck,
#: no gating), as scipy 1.17.1 computes them (shortest round-trip reprs: the same floats; a test
#: holds them equal to scipy's): a fusion never imports scipy.special for its tests
#: (~0.2 s of a process' start); other dof or probabilities ask scipy (imported then).
_CHI2_ISF_TABLE: dict[float, tuple[float, ...]] = {
    0.001: (
        10.827566170662733, 13.815510557964274, 16.26623619623813, 18.466826952903173,
        20.515005652432876, 22.457744484825323, 24.321886347856854, 26.124481558376143,
        27.877164871256575, 29.58829844507442, 31.26413362023999, 32.90949040736021,
        34.52817897487089, 36.12327368039814, 37.69729821835383, 39.25235479076848,
        40.79021670690253, 42.31239633167997, 43.82019596451753, 45.31474661812587,
        46.7970380415613, 48.26794229083519, 49.72823246643151, 51.17859777737739,
        52.61965577617283, 54.051962388576655, 55.47602020574521, 56.892285393353625,
        58.30117348979492, 59.703064304429944, 61.09830608105814, 62.487219057088495,
        63.87009852234495, 65.24721746094242, 66.61882884370104, 67.98516762602424,
        69.3464524962412, 70.70288741150503, 72.0546629519878, 73.40195751899103,
        74.74493839842374, 76.08376270770003, 77.41857824131394, 78.74952422804303,
        80.07673201081901, 81.40032565871002, 82.72042251912403, 84.0371337172235,
        85.350564608593, 86.66081519040317, 87.96798047562868, 89.27215083430448,
        90.57341230529862, 91.8718468816601, 93.16753277222854, 94.46054464187806,
        95.75095383248951, 97.03882856650873, 98.32423413474163, 99.60723306984946,
        100.88788530685825, 102.1662483318488, 103.44237731987324, 104.71632526304059,
    ),
    0.1: (
        2.70554345409542, 4.605170185988092, 6.2513886311703235, 7.779440339734858,
        9.236356899781116, 10.64464067566842, 12.01703662378053, 13.361566136511728,
        14.683656573259837, 15.987179172105261, 17.275008517500076, 18.54934778670325,
        19.811929307127564, 21.064144212997064, 22.307129581578696, 23.541828923096105,
        24.76903534390145, 25.98942308263721, 27.20357102935684, 28.411980584305635,
        29.615089436182735, 30.813282343953027, 32.006899681704304, 33.19624428862818,
        34.38158701755295, 35.56317127192346, 36.741216747797644, 37.915922544697075,
        39.08746977069395, 40.2560237387118, 41.42173582978521, 42.584745082980845,
        43.74517955943419, 44.90315751851994, 46.058788436836686, 47.212173894937365,
        48.36340835219432, 49.51257982657556, 50.65977049321373, 51.805057213317525,
        52.94851200308202, 54.090202450712404, 55.23019208840891, 56.36854072511875,
        57.50530474499599, 58.640537375791716, 59.77428893079596, 60.906607027448366,
        62.03753678530966, 63.167121005726315, 64.29540033521585, 65.42241341433977,
        66.54819701360925, 67.6727861577775, 68.79621423970933, 69.91851312487637,
        71.03971324740432, 72.15984369849215, 73.27893230793083, 74.3970057193686,
        75.51408945989918, 76.63020800448774, 77.74538483569489, 78.8596424991116,
    ),
    0.5: (
        0.4549364231195724, 1.386294361119891, 2.3659738843753377, 3.3566939800333224,
        4.351460191095526, 5.348120627447118, 6.345811195521515, 7.344121497701794,
        8.342832692252955, 9.34181776559197, 10.340998074391823, 11.340322377424142,
        12.339755882563905, 13.33927414909954, 14.338859510956647, 15.338498885001608,
        16.338182377392467, 17.33790236874074, 18.337652896756474, 19.337429229428256,
        20.337227563547934, 21.337044807672633, 22.336878423184253, 23.336726306089535,
        24.336586697884297, 25.336458117477264, 26.336339308591434, 27.3362291986898,
        28.33612686658445, 29.336031516661585, 30.33594245819813, 31.3358590886345,
        32.33578087994843, 33.33570736747922, 34.33563814070362, 35.335572835576905,
        36.33551112813836, 37.33545272914338, 38.33539737953598, 39.33534484661134,
        40.33529492074913, 41.335247412621, 42.33520215079366, 43.33515897966389,
        44.33511775767294, 45.33507835575727, 46.335040655999876, 47.33500455045263,
        48.33496994010476, 49.33493673397683, 50.334904848322715, 51.33487420592483,
        52.33484473547027, 53.33481637099703, 54.33478905140144, 55.334762719999034,
        56.33473732413218, 57.334712814818765, 58.33468914643707, 59.33466627644246,
        60.33464416511231, 61.334622775315836, 62.33460207230615, 63.334582023531965,
    ),
}


@functools.lru_cache(maxsize=1024)
def _chi2_isf(dof: int, false_alarm_probability: float) -> float:
    """``chdtri(dof, false_alarm_probability)``: :data:`_CHI2_ISF_TABLE`'s value, else
    scipy's."""
    known = _CHI2_ISF_TABLE.get(false_alarm_probability)
    if known is not None and 1 <= dof <= len(known):
        return known[dof - 1]
    from scipy.special import chdtri  # only here: a module-level import costs every process

    return float(chdtri(dof, false_alarm_probability))


def chi2_threshold(dof: NDArray[np.int_], false_alarm_probability: float) -> FloatArray:
    """Chi-square test threshold per fix; NaN where ``dof < 1`` (no test possible)."""
    dof = np.asarray(dof)
    if dof.size == 0:
        return np.full(dof.shape, np.nan)
    hi = int(dof.max())
    table = np.full(max(hi, 0) + 1, np.nan)
    for d in range(1, hi + 1):  # dof <= number of anchors: a short loop over a cached table
        table[d] = _chi2_isf(d, float(false_alarm_probability))
    return table[np.maximum(dof, 0)]


def _pregate_tol_m(
    config: GatingConfig, sigmas_m: FloatArray, sigmas_given: bool
) -> FloatArray | float | None:
    """Pre-gate tolerance ``k sigma_j + margin`` [m]; ``None`` when the pre-gate is off (disabled,
    or neither sigmas nor a margin to judge "shorter than LoS" by)."""
    if not config.pregate or not (sigmas_given or config.pregate_margin_m > 0):
        return None
    return config.pregate_sigmas * (sigmas_m if sigmas_given else 0.0) + config.pregate_margin_m


def wall_pregate(
    anchors_m: FloatArray,
    ranges_m: FloatArray,
    sigmas_m: FloatArray,
    used: BoolArray,
    config: GatingConfig,
    *,
    sigmas_given: bool,
) -> BoolArray:
    """Ranges shorter than the anchor's distance to the wall ``y = 0`` (minus tolerance).

    Returns
    -------
    ndarray of bool, shape (B, M)
        True for used measurements that no node inside the building can explain.
    """
    tol = _pregate_tol_m(config, sigmas_m, sigmas_given)
    if tol is None:
        return np.zeros(ranges_m.shape, dtype=bool)
    return used & (ranges_m < np.abs(anchors_m[..., 1]) - tol)


#: ``(problem_idx (K,), used (K, M), warm_x_m (K, 3)) -> (x_m, iterations, converged)``
CandidateSolver = Callable[
    [NDArray[np.int_], BoolArray, FloatArray],
    tuple[FloatArray, NDArray[np.int_], BoolArray],
]


@dataclass(frozen=True)
class _Fit:
    x_m: FloatArray
    iterations: NDArray[np.int_]
    converged: BoolArray


@dataclass
class GateState:
    """Mutable per-fix state the gating loop updates (internal)."""

    x_m: FloatArray  # (B, 3)
    cost: FloatArray  # (B,)
    iterations: NDArray[np.int_]  # (B,)
    converged: BoolArray  # (B,)
    used: BoolArray  # (B, M)
    reason: NDArray[np.int_]  # (B, M)
    gating_failed: BoolArray  # (B,)
    tested: BoolArray  # (B,) a chi-square test was performed on the final set


def run_gating(
    state: GateState,
    anchors_m: FloatArray,
    ranges_m: FloatArray,
    sigmas_m: FloatArray,
    model: PathModel,
    config: GatingConfig,
    *,
    active: BoolArray,
    sigmas_given: bool,
    loss: str,
    loss_scale: float,
    solve_candidates: CandidateSolver | None = None,
) -> None:
    """Pre-gate and RAIM FDE on the fixes where ``active`` is True; updates ``state``.

    ``solve_candidates(problem_idx, used, warm_x)`` solves exclusion candidates (problem
    ``problem_idx[i]`` restricted to the anchors ``used[i]``) from all starts of the first fit
    plus the warm start ``warm_x[i]`` and returns ``(x_m, iterations, converged)``; ``None``
    (or ``config.multistart_exclusion = False``) refits them warm-started only.

    Each round (:func:`_gating_round`) checks the pending fixes (:func:`_check_fixes`), excludes
    at most one anchor per fix (:func:`_raim_exclude`, :func:`_confirm_pregate`) and retires
    the fixes that pass; fixes still pending after ``max_exclusions`` rounds are decided by
    their final test (:func:`_final_test`).
    """
    gate = _Gate(
        anchors_m=anchors_m,
        ranges_m=ranges_m,
        sigmas_m=sigmas_m,
        model=model,
        config=config,
        sigmas_given=sigmas_given,
        loss=loss,
        loss_scale=loss_scale,
        solve_candidates=solve_candidates,
    )
    pending = active.copy()
    n_excl = np.zeros(ranges_m.shape[0], dtype=np.int_)
    for _round in range(config.max_exclusions + 1):
        idx = np.flatnonzero(pending)
        if idx.size == 0:
            break
        _gating_round(gate, state, idx, pending, n_excl)
    # fixes still pending hit the exclusion limit: their final test decides
    idx = np.flatnonzero(pending)
    if idx.size:
        _final_test(gate, state, idx)


@dataclass(frozen=True)
class _Gate:
    """The problems and settings of one :func:`run_gating` call."""

    anchors_m: FloatArray
    ranges_m: FloatArray
    sigmas_m: FloatArray
    model: PathModel
    config: GatingConfig
    sigmas_given: bool
    loss: str
    loss_scale: float
    solve_candidates: CandidateSolver | None

    def refit(self, rows: NDArray[np.int_], used: BoolArray, x_start: FloatArray) -> LMResult:
        """Warm-started LM refit of problems ``rows`` on the anchors ``used``."""
        return levenberg_marquardt(
            self.anchors_m[rows],
            self.ranges_m[rows],
            used / self.sigmas_m[rows],
            x_start,
            self.model.take(rows),
            loss=self.loss,
            loss_scale=self.loss_scale,
            max_iter=self.config.refit_max_iter,
        )


@dataclass
class _Checks:
    """The checks of one round on the pending fixes ``idx`` (rows of ``idx``)."""

    x: FloatArray  # (K, 3) current solutions
    used: BoolArray  # (K, M) anchors used before this round
    fail: BoolArray  # (K,) the chi-square test failed
    raim: BoolArray  # (K,) RAIM exclusion to try
    pg_excl: BoolArray  # (K,) post-fit pre-gate exclusion to try
    pg_j: NDArray[np.int_]  # (K,) its anchor


def _gating_round(
    gate: _Gate,
    state: GateState,
    idx: NDArray[np.int_],
    pending: BoolArray,
    n_excl: NDArray[np.int_],
) -> None:
    """One test-and-exclude round on the pending fixes ``idx`` (updates all arguments)."""
    c = _check_fixes(gate, state, idx, n_excl)
    # fixes that pass (and have no pre-gate violation) are done
    done = ~c.pg_excl & ~c.raim
    state.gating_failed[idx[done]] = c.fail[done]
    pending[idx[done]] = False
    # apply pre-gate exclusions (refit below with the others)
    new_used = c.used.copy()
    rows = np.flatnonzero(c.pg_excl)
    new_used[rows, c.pg_j[rows]] = False
    state.reason[idx[rows], c.pg_j[rows]] = ExclusionReason.PREGATE_SHORTER_THAN_LOS
    rrows = np.flatnonzero(c.raim)
    if rrows.size:
        _raim_exclude(gate, state, idx, rrows, c, new_used)
    if rows.size:
        _confirm_pregate(gate, state, idx, rows, c, new_used, pending)
    changed = c.pg_excl | c.raim
    state.used[idx] = new_used
    n_excl[idx[changed]] += 1
    gi = idx[changed]
    if gi.size:
        pf, _ = gate.model.take(gi).evaluate(gate.anchors_m[gi], state.x_m[gi])
        state.cost[gi] = cost_of(
            gate.ranges_m[gi] - pf, state.used[gi] / gate.sigmas_m[gi], gate.loss, gate.loss_scale
        )


def _check_fixes(
    gate: _Gate, state: GateState, idx: NDArray[np.int_], n_excl: NDArray[np.int_]
) -> _Checks:
    """Post-fit pre-gate (worst "shorter than LoS" range) and chi-square test at the current
    solutions; records which fixes were tested."""
    config = gate.config
    x = state.x_m[idx]
    used = state.used[idx]
    a = gate.anchors_m[idx]
    r = gate.ranges_m[idx]
    s = gate.sigmas_m[idx]
    sw = used / s
    p, _ = gate.model.take(idx).evaluate(a, x)
    res = r - p
    n_used = used.sum(axis=-1)
    can_exclude = n_excl[idx] < config.max_exclusions
    # 1. physical pre-gate
    pg_excl = np.zeros(idx.size, dtype=bool)
    pg_j = np.zeros(idx.size, dtype=np.int_)
    tol = _pregate_tol_m(config, s, gate.sigmas_given)
    if tol is not None:
        los, _ = los_path(a, x[:, None, :])
        short = np.where(used, (los - r) - tol, -np.inf)
        worst = (los - r) / (s if gate.sigmas_given else 1.0)
        worst = np.where(used & (short > 0), worst, -np.inf)
        pg_j = np.argmax(worst, axis=-1)
        pg_excl = np.isfinite(worst.max(axis=-1)) & (n_used - 1 >= 3) & can_exclude
    # 2. chi-square test
    dof = n_used - 3
    t_stat = np.einsum("nm,nm->n", res * sw, res * sw)
    thr = chi2_threshold(dof, config.false_alarm_probability)
    testable = (dof >= 1) & gate.sigmas_given
    fail = testable & (t_stat > thr)
    state.tested[idx] = testable
    raim = fail & (n_used - 1 >= config.min_anchors_after_exclusion) & can_exclude
    # the post-fit pre-gate acts only on fits the residual test accepts (or cannot test):
    # in a failing fit a positive fault elsewhere makes honest ranges look "too short"
    pg_excl &= ~fail
    return _Checks(x=x, used=used, fail=fail, raim=raim, pg_excl=pg_excl, pg_j=pg_j)


def _raim_exclude(
    gate: _Gate,
    state: GateState,
    idx: NDArray[np.int_],
    rrows: NDArray[np.int_],
    c: _Checks,
    new_used: BoolArray,
) -> None:
    """RAIM exclusion for rows ``rrows`` of ``idx``: refit every leave-one-out subset in one
    batch and exclude the anchor whose exclusion gives the smallest test statistic."""
    m = gate.ranges_m.shape[1]
    k = rrows.size
    cand_used = np.repeat(c.used[rrows][:, None, :], m, axis=1)  # (k, m, m)
    eye = np.eye(m, dtype=bool)
    valid_cand = c.used[rrows]  # candidate j must currently be used
    cand_used &= ~eye[None]
    cu = cand_used.reshape(k * m, m)
    rep_idx = np.repeat(idx[rrows], m)
    warm = np.repeat(c.x[rrows], m, axis=0)
    fit = _fit_candidates(gate, rep_idx, cu, warm, valid_cand.ravel())
    pc, _ = gate.model.take(rep_idx).evaluate(gate.anchors_m[rep_idx], fit.x_m)
    rc = (gate.ranges_m[rep_idx] - pc) * (cu / gate.sigmas_m[rep_idx])
    tc = np.einsum("nm,nm->n", rc, rc).reshape(k, m)
    tc = np.where(valid_cand, tc, np.inf)
    best = np.argmin(tc, axis=-1)
    sel = np.arange(k) * m + best
    gi = idx[rrows]
    state.x_m[gi] = fit.x_m[sel]
    state.iterations[gi] = fit.iterations[sel]
    state.converged[gi] = fit.converged[sel]
    new_used[rrows, best] = False
    state.reason[gi, best] = ExclusionReason.RAIM


def _fit_candidates(
    gate: _Gate,
    rep_idx: NDArray[np.int_],
    cu: BoolArray,
    warm: FloatArray,
    live: BoolArray,
) -> _Fit | LMResult:
    """Solve the exclusion candidates: multi-start (only those that exist, ``live``: anchor j
    currently used) with ``solve_candidates``, else warm-started refits of all of them."""
    if gate.solve_candidates is not None and gate.config.multistart_exclusion:
        n = rep_idx.size
        fit_x = warm.copy()
        fit_it = np.zeros(n, dtype=np.int_)
        fit_cv = np.zeros(n, dtype=bool)
        li = np.flatnonzero(live)
        fx, fi, fc = gate.solve_candidates(rep_idx[li], cu[li], warm[li])
        fit_x[li], fit_it[li], fit_cv[li] = fx, fi, fc
        return _Fit(fit_x, fit_it, fit_cv)
    return gate.refit(rep_idx, cu, warm)


def _confirm_pregate(
    gate: _Gate,
    state: GateState,
    idx: NDArray[np.int_],
    rows: NDArray[np.int_],
    c: _Checks,
    new_used: BoolArray,
    pending: BoolArray,
) -> None:
    """Refit the pre-gated rows ``rows`` of ``idx`` from their current position, then
    confirm: the excluded range must also be impossible at the new solution, otherwise
    revert (a fit pulled by a positive fault elsewhere can make an honest range look too
    short) and retire the fix with its test result."""
    config = gate.config
    gi = idx[rows]
    fit = gate.refit(gi, new_used[rows], state.x_m[gi])
    jj = c.pg_j[rows]
    los_new, _ = los_path(gate.anchors_m[gi, jj], fit.x_m)
    tol_j = config.pregate_sigmas * (gate.sigmas_m[gi, jj] if gate.sigmas_given else 0.0)
    confirmed = gate.ranges_m[gi, jj] < los_new - tol_j - config.pregate_margin_m
    keep = rows[confirmed]
    gk = idx[keep]
    state.x_m[gk] = fit.x_m[confirmed]
    state.iterations[gk] = fit.iterations[confirmed]
    state.converged[gk] = fit.converged[confirmed]
    back = rows[~confirmed]
    new_used[back, c.pg_j[back]] = True
    state.reason[idx[back], c.pg_j[back]] = ExclusionReason.NONE
    c.pg_excl[back] = False
    state.gating_failed[idx[back]] = c.fail[back]
    pending[idx[back]] = False


def _final_test(gate: _Gate, state: GateState, idx: NDArray[np.int_]) -> None:
    """The chi-square test of fixes ``idx`` on their final anchor set (no more exclusions)."""
    x = state.x_m[idx]
    used = state.used[idx]
    p, _ = gate.model.take(idx).evaluate(gate.anchors_m[idx], x)
    res = (gate.ranges_m[idx] - p) * used / gate.sigmas_m[idx]
    dof = used.sum(axis=-1) - 3
    t_stat = np.einsum("nm,nm->n", res, res)
    thr = chi2_threshold(dof, gate.config.false_alarm_probability)
    testable = (dof >= 1) & gate.sigmas_given
    state.tested[idx] = testable
    state.gating_failed[idx] = testable & (t_stat > thr)
