"""Per-responder tracker: an IMM over floors x vertical modes, one iterated EKF per hypothesis.

Functional core (pure numpy, vectorised over nodes, deterministic; no randomness at all):
:func:`init_state` -> (:func:`predict`) -> :func:`update` -> ``(TrackerState, TrackOutput)``.

Design
------
* **State per node and hypothesis h = (floor f, vertical mode)** (``F = building.n_floors``,
  ``H = 2F``, ``h = mode * F + f``, mode 0 level, 1 vertical): position and velocity
  ``[x, y, z, vx, vy, vz]``, a Gaussian (mean, covariance) and the hypothesis'
  log-probability. Every hypothesis keeps its own filter, so a floor the data has not yet
  decided stays alive (a particle filter over the same ranges locked whole tracks onto a wrong
  floor).
* **Vertical modes (stairs):** in the *level* mode the device is at the building's nominal
  height above its floor (``height_sigma_m``, a pseudo-measurement of every epoch: with 4
  anchors the ranges alone observe the height weakly); in the *vertical* mode (stairs,
  crouching) it is anywhere between floor and ceiling (uniform) and its height follows the
  ranges. Before, one filter per floor chose between the two at the prior of every epoch
  (max-mixture): while a responder walked down the stairs the prior stayed within 0.8 m of
  the nominal height, so the level term (0.3 m, every epoch) held the track level; 1-1.5 m
  off in height the floor's mechanisms no longer fitted and a mirror floor won (the two
  stairs walkers of the default scenario: 44 % and 91 % right floor). Now each mode has its
  own track and the data decides between them by their accumulated evidence. Mode
  transitions (Markov, per floor): vertical -> level at ``r_out = v_stairs / H`` (a flight
  spans one floor height), level -> vertical at ``r_in = r_out w / (1 - w)`` so that the
  long-run fraction of time on stairs is ``w = stairs_weight``. Entering the vertical mode
  moves probability but never the level track's state (the vertical track accumulates the
  evidence of a climb; restarted from the level track every epoch it never could); entering
  the level mode (the end of a flight) takes the vertical track's state with zero vertical
  speed (+- ``v_level_sigma_m_s``). The stairs' location is not assumed anywhere.
* **Motion:** nearly-constant velocity (white acceleration), per axis
  ``Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]]``. Horizontal ``q_h = 1.5 m^2/s^3``: a walker changes
  its velocity by about its walking speed (1.2 m/s: start, stop, a 90 degree turn) within ~1 s,
  ``q_h ~ (1.2 m/s)^2 / 1 s``. Vertical ``q_v = 0.36 m^2/s^3``: on stairs the vertical speed
  (0.3-0.6 m/s, 17 cm risers at ~2 steps/s, fast ascent) is reached within ~1 s.
* **Floor transitions (IMM mixing), only where physically possible:** a walker moving
  vertically at the stair speed ``v_stairs = 0.6 m/s`` crosses one floor height ``H`` in
  ``H / v_stairs`` seconds, so the probability of moving to an adjacent floor within ``dt`` is
  ``dt v_stairs / H`` (0.02 for 10 Hz, 3 m floors) times ``exp(-d^2 / 2 P_zz)``, ``d`` the
  height gap from the hypothesis to that floor's band beyond the reach ``dt v_stairs`` (a
  level walker 1.5 m below the next band never moves; one at the top of the stairs does);
  a hypothesis keeps its mode when it changes floor. Any floor keeps ``jump_rate_hz * dt`` of probability (recovery from a wrong lock) but a jump
  never moves a state: every floor hypothesis keeps its own track until the data decides
  (measured: with the old selection a leading wrong floor overwrote the true floor's state
  with its mirror image, and the true floor never recovered). Mixed into floor ``g`` a state
  from floor ``f`` keeps x, y and the velocity, its height is moved into floor g's band and
  its height variance inflated (``z_mix_sigma_m``).
* **SNR** (``snr_db`` with the scenario's ``radio``): every mechanism's predicted SNR
  (the emulator's amplitude model, :func:`diffpos.channel.pair_snr_db`, as M-NLS) against the
  measured one, Gaussian with a factor 2 in field (6 dB), plus the detector's rule (a first
  arrival is not far below the strongest path's threshold); a slot with no power at the
  hypothesis is no candidate, except within ``exist_margin_m`` of its existence boundary.
  Part of the mechanism choice and of the floor evidence: with 4 anchors the ranges alone
  leave another floor's mirror solution as good as the true one; with the SNR the floor is
  right for 85-100 % of node-epochs (bench_tracking.py).
  Near an existence boundary the prediction is smoothed over the entry point's
  uncertainty: a slot that exists within ``exist_margin_m`` but has no power at the point is
  scored at the nearest height (+- ``exist_margin_m``) where it does, and the detector's
  threshold comes only from paths that surely exist. Measured on the recorded inputs of the
  lockstep default run (a top-floor walker at the nominal height sits a few cm below the
  band edge of the ceiling-floor double bounce): each epoch whose prior was a few cm too high
  cost the true floor 1.4-4 nats and the track locked onto the mirror floor below; floor
  81.5 -> 86.3 % (default), 85.1 -> 96.7 % (tall-floors variant), see the lead's report.
* **Measurement model:** the first-arrival path model :func:`diffpos.paths.first_arrival_paths`
  for the hypothesis' floor. Per link the mechanism is a latent choice (max-mixture): the
  existing mechanism with the largest marginal likelihood of the range given the predicted
  state (innovation variance ``J P J^T + R``, mechanism prior ``1 / n_existing``: a
  hypothesis where few mechanisms exist is not rewarded for flexibility), or an outlier.
  Robust likelihood: Gaussian core with ``R = sigma_m^2 + sigma_model^2`` (``sigma_model``:
  anchor navigation error, 2-3 cm GNSS) and a one-sided outlier component, uniform over
  ``[|a - p|, |a - p| + outlier_span_m]``: a range is never shorter than the straight line
  (the hinge ``rho < |a - p|`` stays a Gaussian penalty on the straight line), but may be
  longer than any modelled mechanism (an unmodelled later arrival).
* **Update:** iterated Gauss-Newton (IEKF, information form) per node and floor with the
  mechanisms fixed after the selection at the prior; the floor's log-probability is updated
  with the Laplace marginal likelihood (prior term, residuals, log-determinants, mechanism
  and outlier weights).
* **Published estimate:** the most probable floor (marginal over modes); the probability-
  weighted mean of its two modes; its covariance is the mode-mixture covariance of that floor
  plus the spread of every hypothesis' mean about the point (the mean-square error of the
  reported point under the mixture, so model/floor/mode uncertainty is in it); per-floor
  probabilities; per anchor the mechanism slot (-1: outlier/missing) and the residual of the
  most probable hypothesis.
* **Lifecycle:** nodes start UNINITIALISED; with >= ``min_ranges_init`` ranges a snapshot
  initialisation (grid over every floor's (x, y) at the nominal height with the path model,
  then the IEKF from the best cells with a broad prior) gives every floor a state and a
  probability (both modes start from it, with the mode prior ``stairs_weight``) (INITIALISING until ``confirm_epochs`` consistent updates, then TRACKING);
  without usable ranges the filter only predicts (COASTING, the covariance grows); after
  ``lost_after_s`` without ranges it is LOST (no position published). Divergence: an
  exponentially averaged normalised innovation (NIS per used range) above ``nis_limit`` or a
  majority of outlier links for ``diverge_epochs`` epochs re-initialises the node.
* **Dormant hypotheses** (``dormant``; the cost: every hypothesis' update is the paths of every
  mechanism, the predicted SNR, the selection and the IEKF). Once the data has decided
  against a hypothesis its measurement update is skipped: it stays alive by the prediction
  and the IMM's mixing (its state is predicted, its probability mixed as every other's),
  and its evidence is stood in for by its log-likelihood ratio to the node's best at its last
  real update. The threshold (:func:`_dormant_log_p`): the floor jump gives every floor at
  least ``jump_rate_hz dt / (F - 1)`` of predicted probability each epoch (2.5e-5 at 10 Hz,
  5 floors), so a hypothesis the data does not decide against never falls below it; dormant
  is ``dormant_margin_nats`` (3 nats, 20:1) below it in posterior (1.2e-6 there), a share
  of any floor marginal or of the published covariance that changes nothing. A dormant
  hypothesis gets a real update again (1) every ``dormant_refresh_s`` (1 s; hypothesis ``h``
  at phase ``h / H`` of the period, so a node's refreshes spread over it; measurement time
  since the node's initialisation, so a replay refreshes at the same epochs and a constant
  shift of the input times changes nothing), (2) when the mixing brings it more than the
  threshold from the other hypotheses through a physical transition (a walker on the stairs
  reaching the next floor's band; the jump's mass does not count), (3) in the same epoch
  when the node's best hypothesis fits badly (epoch NIS above ``nis_limit``, most ranges
  outliers), (4) while the node is not TRACKING (or its most probable floor is below
  ``dormant_floor_p``, off by default). Floors thus stay alive until the data decides (a wrong-floor lock can
  still be left, ``jump_rate_hz``). Every rule is a function of the node's own inputs, so the
  outputs stay deterministic and independent of the batching. Measured (28 lockstep runs of
  20 s: default and other-building, seeds 0-13, benchmarks/bench_tracking.py's emulation):
  floor 91.5 % with dormant hypotheses against 91.3 % without (per run -5.4..+6.7 points:
  a wrong-floor lock is left earlier or later; default -0.7 +- 0.6, other-building +1.0 +-
  1.0 points on average), mean 3D p90 2.0 vs 2.8 m, 95 % coverage 83.4 vs 83.8 %; about 3.7
  of the 10 hypotheses of a 5-floor building are updated per node-epoch (2 awake, the rest
  the refreshes). Cheaper refresh rules lost floor accuracy (the same 28 runs: 89.6-90.5 %,
  mostly on other-building): refreshing every 2 s; the vertical modes every 2 s (a floor's
  vertical mode is woken through the mode switch once its level mode recovers); keeping a
  refreshed hypothesis dormant when it is 15 nats below the threshold; both of the last two.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .tracking_model import Links, clamp_to_floor, measurement_update, snapshot, snapshot_init

__all__ = [
    "TrackOutput",
    "TrackStatus",
    "TrackerConfig",
    "TrackerState",
    "floor_probabilities",
    "hypothesis_floor",
    "hypothesis_vertical",
    "init_state",
    "predict",
    "process_noise",
    "update",
]

FloatArray = NDArray[np.float64]


class TrackStatus(enum.IntEnum):
    """Status of one node's track (stored as int8 in :attr:`TrackerState.status`)."""

    UNINITIALISED = 0
    """No snapshot yet (too few ranges so far): no position."""
    INITIALISING = 1
    """Initialised from a snapshot, not yet confirmed by ``confirm_epochs`` updates."""
    TRACKING = 2
    COASTING = 3
    """No usable ranges this epoch: predicted only, the covariance grows."""
    LOST = 4
    """No usable ranges for ``lost_after_s``: no position published until re-initialised."""


@dataclass(frozen=True)
class TrackerConfig:
    """Tracker constants (module docstring gives the physical source of each).

    Attributes
    ----------
    q_h_m2_s3, q_v_m2_s3 : float [m^2/s^3]
        White-acceleration spectral densities, horizontal and vertical (both modes; measured:
        a stiffer level mode, 0.01 m^2/s^3, pinned early wrong-floor locks for longer).
    v_level_sigma_m_s : float [m/s]
        Vertical speed standard deviation given to a state entering the level mode (the end of
        a flight: the carry's bobbing, ~0.1 m/s).
    v_stairs_m_s : float [m/s]
        Vertical speed on stairs; sets the adjacent-floor transition probability.
    jump_rate_hz : float [1/s]
        Rate of a jump to any floor (re-acquisition after a wrong lock).
    z_mix_sigma_m : float [m]
        Height standard deviation added when a state is mixed into another floor.
    z_margin_m : float [m]
        A floor hypothesis' position is kept ``margin`` inside its floor's box (walls, floor,
        ceiling).
    box_sigma_m : float [m]
        Standard deviation of the box pseudo-measurement applied outside the box.
    exist_margin_m : float [m]
        A specular path whose entry point is within this distance of the window band's
        boundary may or may not exist (the entry point's uncertainty while tracking).
    height_sigma_m, stairs_weight : float [m], [-]
        Device height above the floor in the level mode: the building's nominal node height
        (hand/chest carry, +- ``height_sigma_m``), a pseudo-measurement of every epoch (the
        ranges alone observe the height weakly: with 4 anchors a track drifted 1.5 m in z along
        a family of mechanism combinations with small residuals); in the vertical mode
        anywhere between floor and ceiling. ``stairs_weight``: the long-run fraction of time in
        the vertical mode (sets the rate of entering it, see the module docstring; also the
        mode prior at initialisation).
    sigma_model_m : float [m]
        Model error added to every range sigma (anchor navigation error).
    outlier_weight : float [-]
        Prior probability that a range is none of the modelled mechanisms.
    outlier_span_m : float [m]
        Width of the one-sided outlier density.
    mixing : {"select", "imm"}
        How a floor's prior is formed from the previous floors: ``"select"`` continues every
        floor from its most probable predecessor (its own state unless a neighbour moving in
        is more probable than staying: a floor that the data has not yet decided keeps its own
        position instead of being dragged towards a different position on another floor);
        ``"imm"`` moment-matches all predecessors (the classic IMM interaction).
    gn_iterations : int
    select_passes : int
        Mechanism selections per update: the first at the prior mean, each further one at the
        previous pass' fit (then the IEKF restarts from the prior).
    init_grid_m : float [m]
        Grid step of the snapshot initialisation.
    init_starts : int
        Best grid cells per floor refined by the IEKF at initialisation.
    init_sigma_v_m_s : float [m/s]
        Initial velocity standard deviation (walking speed).
    min_ranges_init : int
    confirm_epochs : int
    lost_after_s : float [s]
    nis_limit : float [-]
        Limit of the averaged NIS per used range (divergence).
    nis_alpha : float [-]
        Weight of the newest epoch in the NIS average.
    diverge_epochs : int
    reseed_epochs : int
        Consecutive bad epochs after which a floor hypothesis is re-seeded from a snapshot of
        its floor (so every floor keeps the best explanation of the data on that floor).
    reseed_max : int
        At most this many floor hypotheses are re-seeded per call (bounded cost). Default 0
        (off): measured on the default and large scenarios it changed no floor decision
        (46.0 % / 88.5 % with and without) and a snapshot costs ~0.1-0.3 s per node-floor.
    dormant : bool
        Skip the measurement update of hypotheses the data has decided against (*dormant*,
        see "Dormant hypotheses" in the module docstring); False: every hypothesis of every
        node is updated every epoch.
    dormant_margin_nats : float [nats]
        A hypothesis becomes dormant when its posterior probability is below the mass the
        floor jump alone gives it every epoch (``jump_rate_hz dt / (F - 1)``) by this margin
        (3 nats: a 20:1 likelihood ratio against it in the epoch).
    dormant_refresh_s : float [s]
        A dormant hypothesis gets a real update at least this often (measurement time;
        hypothesis ``h`` on its own phase ``h / H`` of the period, so the refreshes of one
        node are spread over the period).
    dormant_epochs : int
        Consecutive real updates below the threshold before a hypothesis becomes dormant
        The real update that refreshes or wakes a dormant hypothesis does not count: its
        state is up to ``dormant_refresh_s`` stale, so its broad prior and unconverged fit
        cost it several nats in that epoch alone (measured: judged on that update, a
        wrong-floor lock of other-building never recovered; judged on it without the excess
        Occam factor, floor 89.2 % against 91.3 % for the full run over 28 runs), so it is
        awake for at least one more update.
    dormant_floor_p : float [-]
        A node whose most probable floor (predicted, marginal over the modes) is below this
        probability is not confident: every hypothesis of it is updated. Default 0 (off):
        measured with 0.99 (the fusion's ``CONFIDENT_FLOOR_PROBABILITY``), 28 runs of
        default and other-building: floor 91.4 % against 91.6 % without it and 91.3 % with
        no dormant hypotheses; but ranges only (the soak), most nodes are not that sure of
        their floor and the 200 x 16 tracker cost rose from ~0.27 to 0.36 ms per node-epoch.
    """

    q_h_m2_s3: float = 1.5
    q_v_m2_s3: float = 0.36
    v_level_sigma_m_s: float = 0.1
    v_stairs_m_s: float = 0.6
    jump_rate_hz: float = 1e-3
    z_mix_sigma_m: float = 0.5
    z_margin_m: float = 0.05
    box_sigma_m: float = 0.02
    exist_margin_m: float = 0.2
    height_sigma_m: float = 0.3
    stairs_weight: float = 0.1
    sigma_model_m: float = 0.03
    outlier_weight: float = 0.02
    outlier_span_m: float = 30.0
    mixing: str = "select"
    gn_iterations: int = 3
    select_passes: int = 2
    init_grid_m: float = 2.0
    init_starts: int = 3
    init_sigma_v_m_s: float = 1.0
    min_ranges_init: int = 3
    confirm_epochs: int = 5
    lost_after_s: float = 5.0
    nis_limit: float = 9.0
    nis_alpha: float = 0.2
    diverge_epochs: int = 10
    reseed_epochs: int = 3
    reseed_max: int = 0
    dormant: bool = True
    dormant_margin_nats: float = 3.0
    dormant_refresh_s: float = 1.0
    dormant_epochs: int = 1
    dormant_floor_p: float = 0.0


@dataclass(frozen=True)
class TrackerState:
    """Filter bank of every node (arrays over N nodes and H = 2F hypotheses: hypothesis
    ``h = mode * F + floor``, mode 0 level, 1 vertical; :func:`hypothesis_floor`,
    :func:`hypothesis_vertical`).

    Attributes
    ----------
    mean : ndarray, shape (N, H, 6) [m, m/s]
    cov : ndarray, shape (N, H, 6, 6)
    log_prob : ndarray, shape (N, H)
        Normalised joint log-probability of every (floor, mode) hypothesis.
    status : ndarray of int8, shape (N,)
        :class:`TrackStatus`.
    t_ns : ndarray of int64, shape (N,) [ns]
        Time the state refers to.
    last_fix_ns : ndarray of int64, shape (N,) [ns]
        Last epoch with usable ranges.
    nis : ndarray, shape (N,)
        Averaged NIS per used range.
    good, bad : ndarray of int, shape (N,)
        Consecutive consistent / inconsistent epochs.
    floor_bad : ndarray of int, shape (N, H)
        Consecutive epochs in which a hypothesis explained fewer than half of the ranges
        or had an NIS above ``nis_limit`` (at ``reseed_epochs`` it is re-seeded from a
        snapshot of that floor).
    dormant_llr : ndarray, shape (N, H)
        NaN for a hypothesis that is updated every epoch; for a *dormant* one its log
        likelihood ratio to the node's best hypothesis at its last real update (<= 0), which
        stands in for its evidence until the next real update.
    updated_ns : ndarray of int64, shape (N, H) [ns]
        Time of each hypothesis' last real measurement update (the refresh schedule of the
        dormant ones).
    below_epochs : ndarray of int, shape (N, H)
        Consecutive real updates with the hypothesis below the dormant threshold (dormant
        from ``dormant_epochs`` on).
    refresh_origin_ns : ndarray of int64, shape (N,) [ns]
        Origin of the node's refresh schedule (its snapshot initialisation): the schedule
        depends on time differences only, so shifting every input time by a constant
        changes no output.
    """

    mean: FloatArray
    cov: FloatArray
    log_prob: FloatArray
    status: NDArray[np.int8]
    t_ns: NDArray[np.int64]
    last_fix_ns: NDArray[np.int64]
    nis: FloatArray
    good: NDArray[np.int_]
    bad: NDArray[np.int_]
    floor_bad: NDArray[np.int_]
    dormant_llr: FloatArray
    updated_ns: NDArray[np.int64]
    below_epochs: NDArray[np.int_]
    refresh_origin_ns: NDArray[np.int64]


@dataclass(frozen=True)
class TrackOutput:
    """Published estimate of every node.

    Attributes
    ----------
    position_m : ndarray, shape (N, 3) [m]
        NaN where no position is published (UNINITIALISED, LOST).
    covariance_m2 : ndarray, shape (N, 3, 3) [m^2]
    floor_index : ndarray of int, shape (N,)
        Most probable floor (-1 without a position).
    floor_probabilities : ndarray, shape (N, F)
    status : ndarray of int8, shape (N,)
    mechanism : ndarray of int, shape (N, M)
        Slot of :data:`diffpos.paths.MECHANISMS` used per anchor on the chosen floor (-1:
        missing or treated as an outlier).
    residual_m : ndarray, shape (N, M) [m]
        Range minus the chosen mechanism's length at the estimate (NaN where -1).
    nis : ndarray, shape (N,)
        Averaged normalised innovation per used range.
    """

    position_m: FloatArray
    covariance_m2: FloatArray
    floor_index: NDArray[np.int_]
    floor_probabilities: FloatArray
    status: NDArray[np.int8]
    mechanism: NDArray[np.int_]
    residual_m: FloatArray
    nis: FloatArray


# --------------------------------------------------------------------------------------------
# motion model and IMM mixing
# --------------------------------------------------------------------------------------------


def process_noise(dt_s: ArrayLike, config: TrackerConfig) -> FloatArray:
    """White-acceleration process noise ``Q(dt)``, shape ``(..., 6, 6)`` (state x,y,z,vx,vy,vz)."""
    dt = np.asarray(dt_s, dtype=np.float64)[..., None]
    q = np.array([config.q_h_m2_s3, config.q_h_m2_s3, config.q_v_m2_s3])
    out = np.zeros((*dt.shape[:-1], 6, 6))
    i = np.arange(3)
    out[..., i, i] = q * dt**3 / 3.0
    out[..., i, i + 3] = q * dt**2 / 2.0
    out[..., i + 3, i] = q * dt**2 / 2.0
    out[..., i + 3, i + 3] = q * dt
    return out


def n_floors_of(state: TrackerState) -> int:
    """Number of floors of a state (its hypotheses are floors x 2 vertical modes)."""
    return state.log_prob.shape[1] // 2


def hypothesis_floor(n_floors: int) -> NDArray[np.int_]:
    """Floor of every hypothesis ``h = mode * F + floor``, shape (2F,)."""
    return np.tile(np.arange(n_floors), 2)


def hypothesis_vertical(n_floors: int) -> NDArray[np.bool_]:
    """Vertical mode (stairs) of every hypothesis, shape (2F,) (the first F are level)."""
    return np.repeat([False, True], n_floors)


def _mode_rates(building, config: TrackerConfig) -> tuple[float, float]:
    """Rates [1/s] of entering and leaving the vertical mode.

    Leaving: a flight of stairs spans one floor height at ``v_stairs``, so the walker is on it
    for ``H / v_stairs`` s. Entering: chosen so that the long-run fraction of time in the
    vertical mode is ``stairs_weight``: ``r_in = r_out * w / (1 - w)``.
    """
    r_out = config.v_stairs_m_s / building.floor_height_m
    w = config.stairs_weight
    return r_out * w / (1.0 - w), r_out


def _transition_matrix(mean: FloatArray, cov: FloatArray, dt_s: FloatArray, building,
                       config: TrackerConfig) -> tuple[FloatArray, FloatArray]:
    """``(pi, pi_move)`` of :func:`_transitions`."""
    pi, pi_move, _ = _transitions(mean, cov, dt_s, building, config)
    return pi, pi_move


def _transitions(mean: FloatArray, cov: FloatArray, dt_s: FloatArray, building,
                 config: TrackerConfig) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Transition probabilities between the hypotheses (floor x vertical mode) over ``dt_s``
    (shape (N,)): ``(pi, pi_move)``, both (N, H, H), rows = from, columns = to.

    Floors: a walker leaves floor ``f`` for an adjacent floor ``g`` only where it can get
    there, i.e. at most ``dt v_stairs`` vertical travel from hypothesis f's height to g's band
    (stairs or any vertical move): with the height gap ``d`` beyond that reach,
    ``dt v_stairs / H * exp(-d^2 / (2 P_zz))`` (a level walker 1.5 m below the next floor's
    band never moves; one at the top of the stairs does); it keeps its mode. ``pi`` adds the
    jump to any floor (``jump_rate_hz``: a floor the data has not decided is never given up, so
    a wrong lock can be left), which moves probability but never a state (it is not in
    ``pi_move``). Modes (same floor): level -> vertical at ``r_in dt``, vertical -> level at
    ``r_out dt`` (:func:`_mode_rates`). The third array is the jump's part of ``pi``.
    """
    h = mean.shape[1]
    nf = h // 2
    fl, vert = hypothesis_floor(nf), hypothesis_vertical(nf)
    g = np.arange(nf)
    adj = (np.abs(fl[:, None] - g[None, :]) == 1).astype(np.float64)  # (H, F)
    other = (fl[:, None] != g[None, :]).astype(np.float64)
    dt = np.maximum(dt_s, 0.0)[:, None, None]
    lo, hi = _floor_band(building, nf, config)
    z = mean[:, :, None, 2]  # (N, H, 1)
    gap = np.maximum(np.maximum(lo[None, None, :] - z, z - hi[None, None, :]), 0.0)
    reach = gap - dt * config.v_stairs_m_s
    var_z = np.maximum(cov[:, :, None, 2, 2], 1e-6)
    near = np.exp(-0.5 * np.maximum(reach, 0.0) ** 2 / var_z)
    p_adj = np.minimum(dt * config.v_stairs_m_s / building.floor_height_m, 0.45)
    p_jump = np.minimum(dt * config.jump_rate_hz, 0.05) / max(nf - 1, 1)
    move = adj * p_adj * near  # (N, H, F): to floor g in the same mode
    jump = other * p_jump
    stay = 1.0 - (move + jump).sum(axis=-1)  # (N, H): stays on its floor
    r_in, r_out = _mode_rates(building, config)
    dt1 = dt[:, :, 0]
    p_switch = np.where(vert[None, :], np.minimum(r_out * dt1, 0.5),
                        np.minimum(r_in * dt1, 0.5))  # (N, H)
    same_mode = (vert[:, None] == vert[None, :]).astype(np.float64)  # (H, H)
    to_floor = (fl[None, :] == g[:, None]).astype(np.float64)  # (F, H): floor g -> hyp h
    cross_f = np.einsum("nhf,fk->nhk", move, to_floor) * same_mode
    cross_j = np.einsum("nhf,fk->nhk", jump, to_floor) * same_mode
    same_floor = (fl[:, None] == fl[None, :]).astype(np.float64)
    own = same_floor * np.where(same_mode > 0, 1.0 - p_switch[..., None], p_switch[..., None])
    own = own * stay[..., None]
    # entering the vertical mode moves probability but not the level track's state: the
    # vertical hypothesis keeps its own track (free height), which is what accumulates the
    # evidence of a climb (restarted from the level track every epoch it could not: measured
    # on other-building, a descending walker's level track stayed pinned at the nominal height
    # and the track was lost to a mirror floor)
    start = (~vert[:, None] & vert[None, :]).astype(np.float64)
    return own + cross_f + cross_j, own * (1.0 - start) + cross_f, cross_j


def _floor_band(building, n_floors: int, config: TrackerConfig) -> tuple[FloatArray, FloatArray]:
    zf = building.floor_z_m(np.arange(n_floors))
    return zf + config.z_margin_m, zf + building.floor_height_m - config.z_margin_m


def _mix(state: TrackerState, dt_s: FloatArray, building, config: TrackerConfig
         ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """IMM interaction: mixed means/covariances and predicted log-probabilities (N, H), and
    the predicted probability each hypothesis receives from the *other* hypotheses through
    physical transitions (adjacent-floor moves, mode switches; not the floor jump), (N, H):
    what wakes a dormant hypothesis."""
    h = state.log_prob.shape[1]
    nf = h // 2
    fl, vert = hypothesis_floor(nf), hypothesis_vertical(nf)
    pi, pi_move, pi_jump = _transitions(state.mean, state.cov, dt_s, building, config)
    lw = state.log_prob
    mx = lw.max(axis=1, keepdims=True)
    w = np.exp(lw - mx)  # (N, H)
    joint = w[:, :, None] * pi  # (N, H, H)
    c = joint.sum(axis=1)  # (N, H)
    lo, hi = _floor_band(building, nf, config)
    start = (~vert[:, None] & vert[None, :])  # (H, H): level f -> vertical g
    stop = (vert[:, None] & ~vert[None, :])
    if config.mixing == "imm":
        mu = joint / np.maximum(c[:, None, :], 1e-300)  # mu[f | g]
        # state of hypothesis f moved into hypothesis g: (N, H, H, 6)
        xs = np.broadcast_to(state.mean[:, :, None, :], (*joint.shape, 6)).copy()
        ps = np.broadcast_to(state.cov[:, :, None], (*joint.shape, 6, 6)).copy()
        _move_into(xs, ps, state.mean[:, :, None, 2], lo[fl][None, None, :],
                   hi[fl][None, None, :], start[None], stop[None], config)
        x0 = np.einsum("nfg,nfgi->ngi", mu, xs)
        d = xs - x0[:, None]
        p0 = np.einsum("nfg,nfgij->ngij", mu, ps + d[..., :, None] * d[..., None, :])
    else:  # "select": every hypothesis continues from its most probable predecessor
        src = np.argmax(w[:, :, None] * pi_move, axis=1)  # (N, H)
        rows = np.arange(joint.shape[0])[:, None]
        # only the chosen predecessor's state is moved (the same operations as on all
        # H x H pairs, so the same numbers)
        x0, p0 = state.mean[rows, src], state.cov[rows, src]
        cols = np.arange(h)[None, :]
        _move_into(x0, p0, x0[..., 2].copy(), lo[fl][None, :], hi[fl][None, :],
                   start[src, cols], stop[src, cols], config)
    log_pred = np.log(np.maximum(c, 1e-300)) + mx
    log_pred = log_pred - _logsumexp(log_pred)[:, None]
    inflow = np.einsum("nf,nfg->ng", w, (pi - pi_jump) * (1.0 - np.eye(h)))
    return x0, p0, log_pred, inflow / c.sum(axis=1, keepdims=True)


def _move_into(xs: FloatArray, ps: FloatArray, z_from: FloatArray, lo: FloatArray,
               hi: FloatArray, start, stop, config: TrackerConfig) -> None:
    """Move states (``xs`` (..., 6), ``ps`` (..., 6, 6), in place) from their hypothesis
    into another: the height into the target floor's band ``[lo, hi]`` (its variance
    inflated when moved), the vertical speed spread of a walker entering the vertical mode
    (``start``) or none beyond the carry's when entering the level mode (``stop``)."""
    xs[..., 2] = np.clip(xs[..., 2], lo, hi)
    moved = xs[..., 2] != z_from
    ps[..., 2, 2] += np.where(moved, config.z_mix_sigma_m**2, 0.0)
    ps[..., 5, 5] += np.where(moved, (config.v_stairs_m_s / 2) ** 2, 0.0)
    # entering the vertical mode: the walker may start up or down the stairs at v_stairs
    ps[..., 5, 5] += np.where(start, (config.v_stairs_m_s / 2) ** 2, 0.0)
    # entering the level mode: no vertical speed beyond the carry's (v_level_sigma)
    xs[..., 5] = np.where(stop, 0.0, xs[..., 5])
    ps[..., 5, :] = np.where(stop[..., None], 0.0, ps[..., 5, :])
    ps[..., :, 5] = np.where(stop[..., None], 0.0, ps[..., :, 5])
    ps[..., 5, 5] = np.where(stop, config.v_level_sigma_m_s**2, ps[..., 5, 5])


def _logsumexp(a: FloatArray) -> FloatArray:
    m = a.max(axis=-1)
    return m + np.log(np.exp(a - m[..., None]).sum(axis=-1))


def _propagate(x: FloatArray, p: FloatArray, dt_s: FloatArray, config: TrackerConfig
               ) -> tuple[FloatArray, FloatArray]:
    """NCV prediction of every hypothesis' Gaussian over ``dt_s`` (shape (N,))."""
    dt = dt_s[:, None]
    xn = x.copy()
    xn[..., :3] = x[..., :3] + dt[..., None] * x[..., 3:]
    phi = np.broadcast_to(np.eye(6), (dt_s.shape[0], 6, 6)).copy()
    i = np.arange(3)
    phi[:, i, i + 3] = dt_s[:, None]
    q = process_noise(dt_s, config)[:, None]
    pn = phi[:, None] @ p @ np.swapaxes(phi, -1, -2)[:, None] + q
    return xn, 0.5 * (pn + np.swapaxes(pn, -1, -2))


def init_state(n_nodes: int, building, *, t_ns: int = 0) -> TrackerState:
    """Empty tracker for ``n_nodes`` nodes (all UNINITIALISED) at time ``t_ns``."""
    h = 2 * int(building.n_floors)
    return TrackerState(
        mean=np.zeros((n_nodes, h, 6)), cov=np.broadcast_to(np.eye(6), (n_nodes, h, 6, 6)).copy(),
        log_prob=np.full((n_nodes, h), -np.log(h)),
        status=np.zeros(n_nodes, np.int8), t_ns=np.full(n_nodes, t_ns, np.int64),
        last_fix_ns=np.full(n_nodes, t_ns, np.int64), nis=np.ones(n_nodes),
        good=np.zeros(n_nodes, int), bad=np.zeros(n_nodes, int),
        floor_bad=np.zeros((n_nodes, h), int), dormant_llr=np.full((n_nodes, h), np.nan),
        updated_ns=np.full((n_nodes, h), t_ns, np.int64), below_epochs=np.zeros((n_nodes, h), int),
        refresh_origin_ns=np.full(n_nodes, t_ns, np.int64))


def predict(state: TrackerState, t_ns: ArrayLike, building, config: TrackerConfig
            ) -> TrackerState:
    """IMM mixing and NCV prediction of every initialised node to ``t_ns`` (scalar or (N,)).

    A node whose state is already at or after ``t_ns`` is left unchanged.
    """
    return _predict(state, t_ns, building, config)[0]


def _predict(state: TrackerState, t_ns: ArrayLike, building, config: TrackerConfig
             ) -> tuple[TrackerState, FloatArray]:
    """:func:`predict`, and the probability every hypothesis received from the others
    through physical transitions (:func:`_mix`; 0 for the nodes not predicted), (N, H)."""
    t = np.broadcast_to(np.asarray(t_ns, dtype=np.int64), state.t_ns.shape)
    live = (state.status != TrackStatus.UNINITIALISED) & (t > state.t_ns)
    if not np.any(live):
        return (replace(state, t_ns=np.where(state.status == 0, t, state.t_ns)),
                np.zeros(state.log_prob.shape))
    dt = np.where(live, (t - state.t_ns) * 1e-9, 0.0)
    x0, p0, lp, inflow = _mix(state, dt, building, config)
    xn, pn = _propagate(x0, p0, dt, config)
    lv = live[:, None]
    return replace(
        state, mean=np.where(lv[..., None], xn, state.mean),
        cov=np.where(lv[..., None, None], pn, state.cov),
        log_prob=np.where(lv, lp, state.log_prob),
        t_ns=np.where(live | (state.status == 0), t, state.t_ns)), np.where(lv, inflow, 0.0)


# --------------------------------------------------------------------------------------------
# update and published estimate
# --------------------------------------------------------------------------------------------


def _normalise(lp: FloatArray) -> FloatArray:
    lp = np.maximum(lp - lp.max(axis=1, keepdims=True), -700.0)
    return lp - np.log(np.exp(lp).sum(axis=1, keepdims=True))


def floor_probabilities(log_prob: ArrayLike, prob: FloatArray | None = None) -> FloatArray:
    """Floor marginals (N, F) of the hypotheses' log-probabilities (N, H = 2F) (e.g.
    :attr:`TrackerState.log_prob`): the sum of every floor's two vertical modes
    (``prob``: ``exp(log_prob)`` if the caller has it)."""
    p = np.exp(np.asarray(log_prob, dtype=np.float64)) if prob is None else prob
    nf = p.shape[-1] // 2
    return p[..., :nf] + p[..., nf:]


def _publish(state: TrackerState, mech: NDArray, resid: FloatArray) -> TrackOutput:
    n, h = state.log_prob.shape
    nf = h // 2
    rows = np.arange(n)
    prob_h = np.exp(state.log_prob)  # (N, H)
    prob = floor_probabilities(state.log_prob, prob_h)
    best = np.argmax(prob, axis=1)
    # the most probable floor's estimate: the mixture of its two modes (moment-matched)
    pair = np.stack([best, best + nf], axis=1)  # (N, 2)
    w = np.take_along_axis(prob_h, pair, axis=1)
    w = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    xm = state.mean[rows[:, None], pair, :3]  # (N, 2, 3)
    pos = np.einsum("nm,nmi->ni", w, xm)
    pm = np.einsum("nm,nmij->nij", w, state.cov[rows[:, None], pair, :3, :3])
    # spread of every hypothesis' mean about the published point (floor and mode uncertainty):
    # the mean-square error of the point under the mixture
    d = state.mean[..., :3] - pos[:, None]
    # a posteriori variance factor: the averaged NIS per used range above 1 says the ranges
    # scatter more than their sigmas (model mismatch), so the covariance is widened by it
    vf = np.clip(state.nis, 1.0, 100.0)[:, None, None]
    dm = xm - pos[:, None]
    cov = (vf * pm + np.einsum("nh,nhi,nhj->nij", prob_h, d, d)
           + np.einsum("nm,nmi,nmj->nij", w * (1.0 - prob[rows, best])[:, None], dm, dm))
    has = (state.status != TrackStatus.UNINITIALISED) & (state.status != TrackStatus.LOST)
    return TrackOutput(
        position_m=np.where(has[:, None], pos, np.nan),
        covariance_m2=np.where(has[:, None, None], cov, np.nan),
        floor_index=np.where(has, best, -1), floor_probabilities=prob,
        status=state.status.copy(), mechanism=np.where(has[:, None], mech, -1),
        residual_m=np.where(has[:, None], resid, np.nan), nis=state.nis.copy())


def _dormant_log_p(dt_s: FloatArray, n_floors: int, config: TrackerConfig) -> FloatArray:
    """Log-probability (N,) below which a hypothesis is dormant: the floor jump's mass per
    epoch ``min(jump_rate_hz dt, 0.05) / (F - 1)`` (every floor's predicted probability is at
    least about that much, whatever the data said before) less ``dormant_margin_nats``. A
    hypothesis the data does not decide against (per-epoch likelihood ratio near 1) stays at
    or above the jump's mass, so it is never dormant; one below it by the margin lost the
    epoch by a likelihood ratio of at least ``exp(margin)`` (20:1). 10 Hz, 5 floors: jump
    mass 2.5e-5, threshold 1.2e-6; its share of any floor marginal or of the published
    covariance (``p d^2``) is then negligible. -inf (nothing dormant) when ``dormant`` is off
    or no time passed."""
    jump = np.minimum(np.maximum(dt_s, 0.0) * config.jump_rate_hz, 0.05) / max(n_floors - 1, 1)
    if not config.dormant:
        jump = np.zeros_like(jump)
    with np.errstate(divide="ignore"):
        return np.log(jump) - config.dormant_margin_nats


def _refresh_due(updated_ns: NDArray[np.int64], t_ns: NDArray[np.int64],
                 origin_ns: NDArray[np.int64], period_s: float) -> NDArray[np.bool_]:
    """Hypotheses (N, H) whose refresh period boundary passed since their last real update:
    hypothesis ``h``'s boundaries are at ``origin + k T - h T / H`` (measurement time
    relative to the node's ``origin_ns``, so a replay refreshes at the same epochs as the
    live run, and a constant shift of every time changes nothing)."""
    period = max(round(period_s * 1e9), 1)
    h = updated_ns.shape[1]
    phase = (np.arange(h, dtype=np.int64) * period) // h
    o = origin_ns[:, None]
    return (t_ns[:, None] - o + phase) // period > (updated_ns - o + phase) // period


def _update_pairs(mean, cov, links: Links, rr, cc, n_floors: int, building,
                  config: TrackerConfig):
    """Measurement update of the hypotheses ``(rr[i], cc[i])`` (node row, hypothesis) of
    ``mean`` (n, H, 6), ``cov``, ``links`` (n nodes): each pair as a node with one
    hypothesis; per pair x, P, log-evidence, slot, NIS and residual of every link."""
    fl = hypothesis_floor(n_floors)[cc][:, None]
    level = ~hypothesis_vertical(n_floors)[cc][:, None]
    x0, p0 = mean[rr, cc][:, None], cov[rr, cc][:, None]
    # the pairs whose prior is inside their floor's box and the others in separate calls:
    # measurement_update evaluates the paths at the prior once more for the whole batch
    # when any prior is outside (the same numbers either way)
    inside = np.all(clamp_to_floor(x0[:, 0, :3], fl[:, 0], building, config.z_margin_m)
                    == x0[:, 0, :3], axis=-1)
    groups = [g for g in (np.flatnonzero(inside), np.flatnonzero(~inside)) if g.size]
    out = [np.empty((rr.size, *shape), dtype) for shape, dtype in (
        ((6,), float), ((6, 6), float), ((), float), ((links.rho.shape[-1],), int),
        ((links.rho.shape[-1],), float), ((links.rho.shape[-1],), float))]
    for g in groups:
        x, p, ev, sel, res = measurement_update(x0[g], p0[g], links.take(rr[g]), fl[g], building,
                                                config, level=level[g])
        for o, v in zip(out, (x, p, ev, sel.slot, sel.nis, res), strict=True):
            o[g] = v[:, 0]
    return tuple(out)


def _posterior(lp_pred: FloatArray, ev: FloatArray, run: NDArray[np.bool_],
               llr: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Posterior log-probabilities (n, H) from the predicted ones: the log-evidence of every
    updated hypothesis (``run``), a dormant one's stand-in ``ref + llr`` (``ref``: the best
    updated evidence of the node); and the log-ratio of every hypothesis to ``ref``."""
    evf = np.where(np.isfinite(ev), ev, -1e300)
    ref = np.max(np.where(run, evf, -np.inf), axis=1, keepdims=True)
    ref = np.where(np.isfinite(ref), ref, 0.0)
    ev_all = np.where(run, evf, ref + np.where(run, 0.0, llr))
    return _normalise(lp_pred + ev_all), ev_all - ref


def _epoch_nis(nis_links: FloatArray) -> tuple[FloatArray, NDArray[np.int_]]:
    """NIS per used range of one epoch and the number of used ranges, (...) from (..., M)."""
    n_in = np.sum(np.isfinite(nis_links), axis=-1)
    return np.where(n_in > 0, np.nansum(nis_links, axis=-1) / np.maximum(n_in, 1), np.inf), n_in


def _track_update(state: TrackerState, links: Links, idx: NDArray, t_ns: NDArray,
                  inflow: FloatArray, dt_s: FloatArray, building, config: TrackerConfig):
    """Measurement update of the nodes ``idx`` (their rows of the predicted ``state``, ``t_ns``,
    ``inflow`` (:func:`_mix`), ``dt_s``): the hypotheses that are awake, due for a refresh,
    woken by the mixing, or of a node that is not TRACKING; then, for a node whose best
    hypothesis fits badly this epoch (NIS above ``nis_limit``, most ranges outliers), its
    dormant ones too. Returns the nodes' new arrays (a dict of state fields), the updated
    hypotheses (n, H), every hypothesis' bad flag, and the best's mechanism/residual."""
    nf = n_floors_of(state)
    h = 2 * nf
    sub = links.take(idx)
    n, m = idx.size, sub.rho.shape[-1]
    m0, c0, lp0, llr0 = state.mean[idx], state.cov[idx], state.log_prob[idx], \
        state.dormant_llr[idx]
    x, p = m0.copy(), c0.copy()
    ev, slot = np.full((n, h), np.nan), np.full((n, h, m), -1)
    nis_h, res = np.full((n, h, m), np.nan), np.full((n, h, m), np.nan)
    log_thr = _dormant_log_p(dt_s[idx], nf, config)[:, None]
    doubt = ((state.status[idx] != TrackStatus.TRACKING)
             | (floor_probabilities(lp0).max(axis=1) < config.dormant_floor_p))
    run = ~np.isfinite(llr0) | doubt[:, None]
    if config.dormant:
        run |= _refresh_due(state.updated_ns[idx], t_ns[idx], state.refresh_origin_ns[idx],
                            config.dormant_refresh_s)
        run |= inflow[idx] > np.exp(log_thr)
    else:
        run[:] = True
    r = np.arange(n)
    n_meas = np.sum(sub.mask[:, 0], axis=1)
    todo = run
    while True:
        rr, cc = np.nonzero(todo)
        if rr.size:
            (x[rr, cc], p[rr, cc], ev[rr, cc], slot[rr, cc], nis_h[rr, cc],
             res[rr, cc]) = _update_pairs(m0, c0, sub, rr, cc, nf, building, config)
        run = run | todo
        lp, llr = _posterior(lp0, ev, run, llr0)
        best = np.argmax(lp, axis=1)
        nis_epoch, n_in = _epoch_nis(nis_h[r, best])
        # the best hypothesis fits this epoch badly (or is a dormant one): the data may have
        # changed, so the node's dormant hypotheses get a real update too
        poor = (nis_epoch > config.nis_limit) | (2 * n_in < n_meas) | ~run[r, best]
        todo = poor[:, None] & ~run
        if not np.any(todo):
            break
    nis = (1 - config.nis_alpha) * state.nis[idx] + config.nis_alpha * np.minimum(nis_epoch, 1e3)
    bad_epoch = (nis > config.nis_limit) | (2 * n_in < n_meas)
    nis_f, n_in_f = _epoch_nis(nis_h)
    bad_f = (2 * n_in_f < n_meas[:, None]) | (nis_f > config.nis_limit)
    # consecutive real updates below the threshold; the update of a dormant hypothesis
    # (refresh or wake-up) re-converges its stale state and does not count
    below = np.where(run, np.where(np.isfinite(llr0), 0,
                                   np.where(lp < log_thr, state.below_epochs[idx] + 1, 0)),
                     state.below_epochs[idx])
    asleep = below >= max(config.dormant_epochs, 1)
    new = {"mean": x, "cov": p, "log_prob": lp, "nis": nis, "below_epochs": below,
           "dormant_llr": np.where(asleep, np.where(run, llr, llr0), np.nan),
           "updated_ns": np.where(run, t_ns[idx, None], state.updated_ns[idx])}
    return new, run, bad_epoch, bad_f, slot[r, best], res[r, best]


def _reseed(mean, cov, floor_bad, links: Links, eligible, building, config: TrackerConfig):
    """Re-seed the worst hypotheses (at most ``reseed_max`` per epoch) from snapshots of their
    floors."""
    cand = (floor_bad >= config.reseed_epochs) & eligible[:, None]
    if config.reseed_max <= 0 or not np.any(cand):  # (off by default: no empty snapshot)
        return
    flat = np.flatnonzero(cand)
    order = np.argsort(-floor_bad.reshape(-1)[flat], kind="stable")[:config.reseed_max]
    nodes, hyps = np.unravel_index(flat[order], floor_bad.shape)
    floors = hyps % (floor_bad.shape[1] // 2)
    sub = links.take(nodes)
    x, p, _, _, _ = snapshot(sub, floors[:, None], building, config)
    mean[nodes, hyps], cov[nodes, hyps] = x[:, 0], p[:, 0]
    floor_bad[nodes, hyps] = 0


def _init_hypotheses(x, p, lp_floor, config: TrackerConfig):
    """Both modes of every floor from a snapshot (N, F, ...): the same Gaussian, the mode
    prior ``stairs_weight`` (the vertical one with the stairs' vertical speed spread)."""
    xv, pv = x.copy(), p.copy()
    pv[..., 5, 5] += (config.v_stairs_m_s / 2) ** 2
    w = config.stairs_weight
    lp = np.concatenate([lp_floor + np.log1p(-w), lp_floor + np.log(w)], axis=1)
    return np.concatenate([x, xv], axis=1), np.concatenate([p, pv], axis=1), lp


def update(state: TrackerState, anchors_m: ArrayLike, ranges_m: ArrayLike, sigmas_m: ArrayLike,
           mask: ArrayLike, t_ns: ArrayLike, building, config: TrackerConfig, *,
           snr_db: ArrayLike | None = None, radio=None) -> tuple[TrackerState, TrackOutput]:
    """Predict every node to ``t_ns`` and update it with one epoch of ranges.

    Parameters
    ----------
    state : TrackerState
    anchors_m : array_like, shape (N, M, 3) [m]
        Anchor positions of every node's ranges (padding rows are ignored via ``mask``).
    ranges_m, sigmas_m : array_like, shape (N, M) [m]
        Measured first-arrival ranges and their standard deviations.
    mask : array_like of bool, shape (N, M)
        Which ranges are present (non-finite values are dropped too).
    t_ns : int or array_like of int, shape (N,) [ns]
    building : diffpos.scenario.Building
    config : TrackerConfig
    snr_db : array_like, shape (N, M), optional [dB]
        Measured SNR of every range (NaN: unknown); used with ``radio``
        (:class:`diffpos.scenario.Radio`) to score each mechanism's predicted strength.

    Returns
    -------
    (TrackerState, TrackOutput)
    """
    links = Links.from_arrays(np.asarray(anchors_m, float), np.asarray(ranges_m, float),
                              np.asarray(sigmas_m, float), mask, config.sigma_model_m,
                              snr_db=snr_db, radio=radio)
    n, m = links.rho.shape[0], links.rho.shape[2]
    t = np.broadcast_to(np.asarray(t_ns, dtype=np.int64), (n,))
    st, inflow = _predict(state, t, building, config)
    dt_s = (t - state.t_ns) * 1e-9
    mean, cov, lp = st.mean.copy(), st.cov.copy(), st.log_prob.copy()
    status, nis, good, bad = st.status.copy(), st.nis.copy(), st.good.copy(), st.bad.copy()
    floor_bad = st.floor_bad.copy()
    llr, upd, below = st.dormant_llr.copy(), st.updated_ns.copy(), st.below_epochs.copy()
    origin = st.refresh_origin_ns.copy()
    last = st.last_fix_ns.copy()
    mech, resid = np.full((n, m), -1), np.full((n, m), np.nan)
    n_meas = links.mask[:, 0].sum(axis=1)
    live = np.isin(status, (TrackStatus.INITIALISING, TrackStatus.TRACKING, TrackStatus.COASTING))
    idx = np.flatnonzero(live & (n_meas > 0))
    if idx.size:
        new, ran, bad_epoch, bad_f, mech[idx], resid[idx] = _track_update(
            st, links, idx, t, inflow, dt_s, building, config)
        mean[idx], cov[idx], lp[idx], nis[idx] = new["mean"], new["cov"], new["log_prob"], \
            new["nis"]
        llr[idx], upd[idx], below[idx] = new["dormant_llr"], new["updated_ns"], \
            new["below_epochs"]
        floor_bad[idx] = np.where(ran, np.where(bad_f, floor_bad[idx] + 1, 0), floor_bad[idx])
        bad[idx] = np.where(bad_epoch, bad[idx] + 1, 0)
        good[idx] = np.where(bad_epoch, 0, good[idx] + 1)
        last[idx] = t[idx]
        status[idx] = np.where(status[idx] == TrackStatus.COASTING, TrackStatus.TRACKING,
                               status[idx])
    _reseed(mean, cov, floor_bad, links, live & (n_meas >= config.min_ranges_init), building,
            config)
    coast = live & (n_meas == 0)
    status[coast] = TrackStatus.COASTING
    status[coast & ((t - last) * 1e-9 > config.lost_after_s)] = TrackStatus.LOST
    need = ((status == TrackStatus.UNINITIALISED) | (status == TrackStatus.LOST)
            | (bad >= config.diverge_epochs)) & (n_meas >= config.min_ranges_init)
    jdx = np.flatnonzero(need)
    if jdx.size:
        sub = links.take(jdx)
        x, p, lpi, sel, res = snapshot_init(sub, building, config)
        mean[jdx], cov[jdx], lp[jdx] = _init_hypotheses(x, p, lpi, config)
        best = np.argmax(lpi, axis=1)
        r = np.arange(jdx.size)
        mech[jdx], resid[jdx] = sel.slot[r, best], res[r, best]
        status[jdx] = TrackStatus.INITIALISING
        nis[jdx], good[jdx], bad[jdx], last[jdx] = 1.0, 0, 0, t[jdx]
        floor_bad[jdx], llr[jdx], upd[jdx], below[jdx] = 0, np.nan, t[jdx, None], 0
        origin[jdx] = t[jdx]
    status[(status == TrackStatus.INITIALISING) & (good >= config.confirm_epochs)] = (
        TrackStatus.TRACKING)
    new = TrackerState(mean=mean, cov=cov, log_prob=lp, status=status.astype(np.int8),
                       t_ns=st.t_ns.copy(), last_fix_ns=last, nis=nis, good=good, bad=bad,
                       floor_bad=floor_bad, dormant_llr=llr, updated_ns=upd,
                       below_epochs=below, refresh_origin_ns=origin)
    return new, _publish(new, mech, resid)
