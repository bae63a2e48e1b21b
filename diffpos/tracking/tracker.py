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
  own track and the data decides between them by their accumulated evidence (the mode
  transitions: :mod:`diffpos.tracking.imm`).
* **Motion and IMM mixing** (:mod:`diffpos.tracking.imm`): nearly-constant velocity (white
  acceleration) per hypothesis; floor transitions only where physically possible (a walker
  reaches the next floor's band at the stair speed), mode switches at the stairs' rates, and a
  small jump to any floor (recovery from a wrong lock) that moves probability but never a
  state: every hypothesis keeps its own track until the data decides.
* **SNR** (``snr_db`` with the scenario's ``radio``): every mechanism's predicted SNR
  (the emulator's amplitude model, :func:`diffpos.channel.emulator.pair_snr_db`, as M-NLS) against the
  measured one, Gaussian with a factor 2 in field (6 dB), plus the detector's rule (a first
  arrival is not far below the strongest path's threshold); a slot with no power at the
  hypothesis is no candidate, except within the hypothesis' existence margin of its
  existence boundary (:func:`diffpos.tracking.model.existence_margin`: at least
  ``exist_margin_m``, wider with the hypothesis' own height uncertainty).
  Part of the mechanism choice and of the floor evidence: with 4 anchors the ranges alone
  leave another floor's mirror solution as good as the true one; with the SNR the floor is
  right for 85-100 % of node-epochs (bench_tracking.py).
  Near an existence boundary the prediction is smoothed over the entry point's
  uncertainty: a slot that exists within the existence margin but has no power at the point
  is scored at the nearest height (+- the margin) where it does, and the detector's
  threshold comes only from paths that surely exist. Measured on the recorded inputs of the
  lockstep default run (a top-floor walker at the nominal height sits a few cm below the
  band edge of the ceiling-floor double bounce): each epoch whose prior was a few cm too high
  cost the true floor 1.4-4 nats and the track locked onto the mirror floor below; floor
  81.5 -> 86.3 % (default), 85.1 -> 96.7 % (tall-floors variant), see the lead's report.
* **Measurement model:** the first-arrival path model :func:`diffpos.paths.model.first_arrival_paths`
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
  probabilities (tempered for the correlation of the evidence from epoch to epoch:
  :func:`diffpos.tracking.state.published_floor_probabilities`; the choice of the floor and
  the covariance use the untempered ones); per anchor the mechanism slot (-1:
  outlier/missing) and the residual of the most probable hypothesis.
* **Lifecycle:** nodes start UNINITIALISED; with >= ``min_ranges_init`` ranges a snapshot
  initialisation (grid over every floor's (x, y) at the nominal height with the path model,
  then the IEKF from the best cells with a broad prior) gives every floor a state and a
  probability (both modes start from it, with the mode prior ``stairs_weight``) (INITIALISING until ``confirm_epochs`` consistent updates, then TRACKING);
  without usable ranges the filter only predicts (COASTING, the covariance grows); after
  ``lost_after_s`` without ranges it is LOST (no position published). Divergence: an
  exponentially averaged normalised innovation (NIS per used range) above ``nis_limit`` or a
  majority of outlier links for ``diverge_epochs`` epochs re-initialises the node.
* **Dormant hypotheses** (``TrackerConfig.dormant``; section "Dormant hypotheses" below): once
  the data has decided against a hypothesis its measurement update is skipped (it is
  predicted and mixed as every other, its evidence stood in for by its last likelihood
  ratio to the node's best) until a refresh (every ``dormant_refresh_s``), the mixing, a
  poor fit of the node's best hypothesis or a node that is not TRACKING wakes it. Measured
  (28 lockstep runs of 20 s, default and other-building): floor 91.5 % with dormant
  hypotheses against 91.3 % without, about 3.7 of a 5-floor building's 10 hypotheses updated
  per node-epoch (the rules and the measurements: below).

Modules: :mod:`diffpos.tracking.state` (config, state, output types, hypothesis layout),
:mod:`diffpos.tracking.imm` (motion, transitions, mixing, prediction of the Gaussians),
:mod:`diffpos.tracking.links` (one epoch's links, the paths of every mechanism),
:mod:`diffpos.tracking.initialisation` (the snapshot initialisation's grid search),
:mod:`diffpos.tracking.model` (measurement model: SNR term, mechanism selection, IEKF,
snapshot initialisation); this module: the epoch (prediction, the measurement update with
dormant hypotheses, lifecycle, published estimate) and :func:`warm_tracking`.

Dormant hypotheses
------------------
Which hypotheses of a node get a real measurement update (:func:`_track_update`), the
stand-in evidence of the others (:func:`_posterior`), the dormant threshold and the refresh
schedule; the update itself is :func:`diffpos.tracking.model.measurement_update`.

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

import time
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.paths.mechanisms import DEFAULT_ORDER
from diffpos.tracking.evidence import (
    LINK_FIELDS,
    LINK_SLOTS,
    _gather,
    count_unexplained,
    fewer_outliers,
    learn,
    learned_weights,
    match_links,
    model_doubt,
    node_weights,
    posterior_weights,
    reset_links,
    unexplained_log_odds,
)
from diffpos.tracking.evidence_nb import warm_evidence
from diffpos.tracking.families import family_log_weight
from diffpos.tracking.iekf_nb import warm_iekf
from diffpos.tracking.imm import _mix, _propagate
from diffpos.tracking.initialisation import local_starts
from diffpos.tracking.initialisation_nb import warm_grid
from diffpos.tracking.links import Links, all_paths, candidates
from diffpos.tracking.model import (
    SNR_SIGMA_DB,
    SNR_SPAN_DB,
    Selection,
    SnrCache,
    existence_margin,
    family_refit,
    link_weights,
    measurement_update,
    snapshot,
    snapshot_init,
    snr_reuse_on,
)
from diffpos.tracking.model_nb import warm_model
from diffpos.tracking.silent import silent_update
from diffpos.tracking.snr_nb import warm_snr_cache
from diffpos.tracking.snr_term_nb import warm_snr_term
from diffpos.tracking.state import (
    SNR_CACHE_LINKS,
    SNR_CACHE_SLOTS,
    FloatArray,
    TrackerConfig,
    TrackerState,
    TrackOutput,
    TrackStatus,
    clamp_to_floor,
    credible_floor_weights,
    few_ranges,
    floor_contested,
    floor_probabilities,
    floor_reweighted,
    has_position,
    height_band_bound,
    hypothesis_floor,
    hypothesis_vertical,
    mixture_mse_cov,
    n_floors_of,
    published_floor_probabilities,
)
from diffpos.tracking.update_nb import warm_update

__all__ = ["init_state", "predict", "update", "warm_tracking"]


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
        refresh_origin_ns=np.full(n_nodes, t_ns, np.int64),
        snr_node=np.full((n_nodes, h, 3), np.nan),
        snr_anchor=np.full((n_nodes, h, SNR_CACHE_LINKS, 3), np.nan, np.float32),
        snr_pred=np.full((n_nodes, h, SNR_CACHE_LINKS, len(SNR_CACHE_SLOTS)), np.nan,
                         np.float32),
        link_anchor=np.full((n_nodes, LINK_SLOTS, 3), np.nan),
        link_seen_ns=np.full((n_nodes, LINK_SLOTS), t_ns, np.int64),
        unexplained=np.zeros(n_nodes), redundant=np.zeros(n_nodes),
        lead_floor=np.full(n_nodes, -1, int), lead_ns=np.full(n_nodes, t_ns, np.int64),
        deficit_count=np.zeros((n_nodes, h), int), **_empty_links(n_nodes, h, t_ns),
        link_slot=np.full((n_nodes, h, LINK_SLOTS), np.nan),
        chal_mean=np.zeros((n_nodes, h // 2, 6)),
        chal_cov=np.broadcast_to(np.eye(6), (n_nodes, h // 2, 6, 6)).copy(),
        chal_llr=np.zeros((n_nodes, h // 2)), chal_age=np.zeros((n_nodes, h // 2), int))


def _empty_links(n: int, h: int, t_ns: int = 0) -> dict:
    """The learned per-link arrays of ``n`` nodes with nothing learned."""
    shape = (n, h, LINK_SLOTS)
    return {"link_out": np.zeros(shape), "link_all": np.zeros(shape), "link_ev": np.zeros(shape),
            "link_bias": np.full(shape, np.nan), "link_bias_var": np.full(shape, np.nan),
            "link_snr": np.full(shape, np.nan), "link_t_ns": np.full(shape, t_ns, np.int64),
            "link_fit": np.full(shape, np.nan)}


def predict(state: TrackerState, t_ns: ArrayLike, building, config: TrackerConfig
            ) -> TrackerState:
    """IMM mixing and NCV prediction of every initialised node to ``t_ns`` (scalar or (N,)).

    A node whose state is already at or after ``t_ns`` is left unchanged.
    """
    return _predict(state, t_ns, building, config)[0]


def _predict(state: TrackerState, t_ns: ArrayLike, building, config: TrackerConfig,
             n_meas: NDArray | None = None) -> tuple[TrackerState, FloatArray]:
    """:func:`predict`, and the probability every hypothesis received from the others
    through physical transitions (:func:`_mix`; 0 for the nodes not predicted), (N, H).
    ``n_meas`` (N,): the ranges of the epoch predicted to (:func:`_mix`)."""
    t = np.broadcast_to(np.asarray(t_ns, dtype=np.int64), state.t_ns.shape)
    live = (state.status != TrackStatus.UNINITIALISED) & (t > state.t_ns)
    if not np.any(live):
        return (replace(state, t_ns=np.where(state.status == 0, t, state.t_ns)),
                np.zeros(state.log_prob.shape))
    dt = np.where(live, (t - state.t_ns) * 1e-9, 0.0)
    x0, p0, lp, inflow = _mix(state, dt, building, config, n_meas)
    xn, pn = _propagate(x0, p0, dt, config)
    t_new = np.where(live | (state.status == 0), t, state.t_ns)
    if live.all():  # (the new arrays are _mix's and _propagate's own)
        return replace(state, mean=xn, cov=pn, log_prob=lp, t_ns=t_new), inflow
    lv = live[:, None]
    return replace(
        state, mean=np.where(lv[..., None], xn, state.mean),
        cov=np.where(lv[..., None, None], pn, state.cov),
        log_prob=np.where(lv, lp, state.log_prob), t_ns=t_new), np.where(lv, inflow, 0.0)


# --------------------------------------------------------------------------------------------
# update and published estimate
# --------------------------------------------------------------------------------------------


def _publish(state: TrackerState, mech: NDArray, resid: FloatArray,
             config: TrackerConfig | None = None, n_meas: NDArray | None = None,
             contested: NDArray | None = None, doubt: tuple | None = None,
             cov_kept_only: bool = False) -> TrackOutput:
    """The published estimate of every node. ``cov_kept_only``: the covariance only of the
    rows :func:`_published_floor_cov` keeps as they are (a position but a non-finite floor
    probability; every other row is NaN or replaced there): the same published values, bit
    for bit (every row of :func:`~diffpos.tracking.state.mixture_mse_cov` is computed on its
    own); :func:`update` with ``cov_published_floors`` on and ``floor_band_bound`` off (which
    reads the covariance first). ``doubt``: the model doubt in a 1-tuple (its value None: off;
    :func:`_node_doubt`), computed here when not given."""
    config = TrackerConfig() if config is None else config
    if doubt is None:  # (the model doubt, or None: off; :func:`_node_doubt`)
        doubt = (_node_doubt(state, config, n_meas),)
    n, h = state.log_prob.shape
    nf = h // 2
    rows = np.arange(n)
    prob_h = np.exp(state.log_prob)  # (N, H)
    prob = floor_probabilities(state.log_prob, prob_h)
    best = np.argmax(prob, axis=1)
    # the most probable floor's estimate: the mixture of its two modes (moment-matched)
    pair = np.stack([best, best + nf], axis=1)  # (N, 2)
    w = prob_h[rows[:, None], pair]
    w = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    pos = np.einsum("nm,nmi->ni", w, state.mean[rows[:, None], pair, :3])
    # the best floor's modes' covariance plus the spread of every hypothesis' mean about the
    # published point (floor and mode uncertainty): the mean-square error of the point under
    # the mixture; a posteriori variance factor: the averaged NIS per used range above 1 says
    # the ranges scatter more than their sigmas (model mismatch), so it widens the covariance
    has = has_position(state.status)
    position = np.where(has[:, None], pos, np.nan)
    floor_p = published_floor_probabilities(
        state.log_prob, config, prob_h, link_ev=state.link_ev, link_all=state.link_all,
        doubt=doubt[0], contested=contested)
    need = has
    if cov_kept_only:  # the rows _published_floor_cov replaces are not computed here
        need = has & ~(np.isfinite(position).all(axis=1) & np.isfinite(floor_p).all(axis=1))
    cov = np.full((n, 3, 3), np.nan)
    if need.all():
        cov = mixture_mse_cov(state.mean, state.cov, prob_h, pos, best, prob[rows, best],
                              np.clip(state.nis, 1.0, 100.0))
    elif need.any():
        cov[need] = mixture_mse_cov(state.mean[need], state.cov[need], prob_h[need], pos[need],
                                    best[need], prob[rows, best][need],
                                    np.clip(state.nis[need], 1.0, 100.0))
    return TrackOutput(
        position_m=position, covariance_m2=np.where(has[:, None, None], cov, np.nan),
        floor_index=np.where(has, best, -1), floor_probabilities=floor_p,
        status=state.status.copy(), mechanism=np.where(has[:, None], mech, -1),
        residual_m=np.where(has[:, None], resid, np.nan), nis=state.nis.copy())


def _node_doubt(state: TrackerState, config: TrackerConfig, n_meas: NDArray | None
                ) -> FloatArray | None:
    """The published floor probabilities' model doubt (``floor_model_doubt``;
    :func:`model_doubt`), None where off."""
    if not (config.floor_model_doubt and config.link_learn):
        return None
    return model_doubt(state.log_prob, state.link_out, state.link_all, config, n_meas)


def _few_anchors(out: TrackOutput, n_meas: NDArray, config: TrackerConfig) -> TrackOutput:
    """Publication of the nodes updated with fewer than ``min_anchors_tracking`` ranges:
    COASTING instead of TRACKING, the most probable floor's probability capped at
    ``few_anchors_floor_p_max`` (mixed towards uniform; the order of the floors kept)."""
    few = (n_meas > 0) & (n_meas < config.min_anchors_tracking)
    if not np.any(few):
        return out
    status = np.where(few & (out.status == TrackStatus.TRACKING),
                      np.int8(TrackStatus.COASTING), out.status).astype(np.int8)
    p = out.floor_probabilities
    nf = p.shape[1]
    top = p.max(axis=1, keepdims=True)
    cap = max(float(config.few_anchors_floor_p_max), 1.0 / nf)
    w = np.where(few[:, None] & (top > cap), (top - cap) / np.maximum(top - 1.0 / nf, 1e-12),
                 0.0)
    return replace(out, status=status, floor_probabilities=(1 - w) * p + w / nf)


def _band_bound(out: TrackOutput, building) -> TrackOutput:
    """The published floor's probability capped at its height band's mass under the published
    height and its variance (``TrackerConfig.floor_band_bound``; :func:`height_band_bound`)."""
    return replace(out, floor_probabilities=height_band_bound(
        out.floor_probabilities, out.floor_index, out.position_m[:, 2],
        out.covariance_m2[:, 2, 2], building.first_floor_z_m, building.floor_height_m))


def _published_floor_cov(state: TrackerState, out: TrackOutput, which: str,
                         q_floor: FloatArray | None = None) -> TrackOutput:
    """The published covariance with the floors' hypotheses weighted by the published floor
    probabilities (``which`` = ``TrackerConfig.cov_published_floors``: "all" every floor,
    "credible" those of the 95 % credible set: :func:`credible_floor_weights`;
    :func:`floor_reweighted`, :func:`mixture_mse_cov`); rows without a position keep NaN.
    ``q_floor`` (N, F): those weights instead of the published probabilities
    (:func:`_few_floor_weights`; None: the published)."""
    if which not in ("all", "credible"):
        raise ValueError(f"cov_published_floors must be 'off', 'all' or 'credible'; got {which!r}")
    has = np.isfinite(out.position_m).all(axis=1) & np.isfinite(out.floor_probabilities).all(
        axis=1)
    if not np.any(has):
        return out
    q = (out.floor_probabilities if q_floor is None else q_floor)[has]
    q = q / np.maximum(q.sum(axis=1, keepdims=True), 1e-300)
    best = out.floor_index[has]
    prob_h = np.exp(state.log_prob[has])
    if which == "credible":
        q = credible_floor_weights(q, floor_probabilities(None, prob_h))
    cov = out.covariance_m2.copy()
    cov[has] = mixture_mse_cov(
        state.mean[has], state.cov[has], floor_reweighted(prob_h, q),
        out.position_m[has], best, q[np.arange(best.size), best],
        np.clip(state.nis[has], 1.0, 100.0))
    return replace(out, covariance_m2=cov)


def _reseed_ranges(config: TrackerConfig) -> int:
    """The ranges a node needs this epoch for a re-seed of its hypotheses (``min_ranges_init``,
    ``reseed_min_links``); the evidence-deficit test tests only such nodes."""
    return max(config.min_ranges_init, config.reseed_min_links)


def _reseed(mean, cov, floor_bad, links: Links, eligible, building, config: TrackerConfig,
            at_phase: NDArray[np.bool_] | None = None):
    """Re-seed every node's worst hypotheses (at most ``reseed_max`` per node and epoch, the
    most bad epochs first, ties by hypothesis) from snapshots of their floors; ``at_phase``
    (N, H): only those at a boundary of their re-seed period (:func:`_reseed_phase`; None:
    any). Per node, so a node's result does not depend on the other rows of the call (the
    fusion's batches, workers and shards give the same estimates)."""
    cand = (floor_bad >= config.reseed_epochs) & eligible[:, None]
    if at_phase is not None:
        cand &= at_phase
    if config.reseed_max <= 0 or not np.any(cand):  # (none: no empty snapshot)
        return
    order = np.argsort(-np.where(cand, floor_bad, -1), axis=1,
                       kind="stable")[:, :config.reseed_max]
    nodes, j = np.nonzero(np.take_along_axis(cand, order, axis=1))
    hyps = order[nodes, j]
    floors = hyps % (floor_bad.shape[1] // 2)
    sub = links.take(nodes)
    x, p, _, _, _ = snapshot(sub, floors[:, None], building, config,
                             config.reseed_starts or None)  # 0: init_starts
    mean[nodes, hyps], cov[nodes, hyps] = x[:, 0], p[:, 0]
    floor_bad[nodes, hyps] = 0


def _reseed_phase(prev_ns: NDArray[np.int64], t_ns: NDArray[np.int64],
                  origin_ns: NDArray[np.int64], n_hyp: int,
                  config: TrackerConfig) -> NDArray[np.bool_] | None:
    """The hypotheses (N, H) whose re-seed period boundary (``reseed_period_s``, the
    phases of :func:`_refresh_due`) falls in ``(prev_ns, t_ns]`` (each node's previous and
    this epoch's time); None where the setting is off (0: any epoch)."""
    if config.reseed_period_s <= 0 or config.reseed_max <= 0:
        return None
    period = max(round(config.reseed_period_s * 1e9), 1)
    phase = (np.arange(n_hyp, dtype=np.int64) * period) // n_hyp
    return (_period_index(t_ns[:, None], origin_ns, phase, period)
            > _period_index(prev_ns[:, None], origin_ns, phase, period))


def _init_hypotheses(x, p, lp_floor, config: TrackerConfig):
    """Both modes of every floor from a snapshot (N, F, ...): the same Gaussian, the mode
    prior ``stairs_weight`` (the vertical one with the stairs' vertical speed spread)."""
    xv, pv = x.copy(), p.copy()
    pv[..., 5, 5] += (config.v_stairs_m_s / 2) ** 2
    w = config.stairs_weight
    lp = np.concatenate([lp_floor + np.log1p(-w), lp_floor + np.log(w)], axis=1)
    return np.concatenate([x, xv], axis=1), np.concatenate([p, pv], axis=1), lp


def _with_rows(a: NDArray, idx: NDArray, v: NDArray) -> NDArray:
    """A new array: ``a`` with the rows ``idx`` (sorted, distinct) replaced by ``v`` (a new
    array itself); ``v`` when ``idx`` is every row (the SNR cache, ~7 KB per node: no copy
    of what is replaced anyway)."""
    if idx.size == a.shape[0]:
        return v
    out = a.copy()
    out[idx] = v
    return out


#: The state's arrays a measurement update replaces row by row (:func:`_merged`).
_UPDATED = ("mean", "cov", "log_prob", "nis", "dormant_llr", "updated_ns", "below_epochs")
#: The learned link arrays (:mod:`diffpos.tracking.evidence`) among them.
_LINK_STATE = (*LINK_FIELDS, "link_anchor", "link_seen_ns", "unexplained", "redundant",
               "link_slot")


def _merged(st: TrackerState, idx: NDArray, new: dict) -> dict:
    """New arrays of the fields :data:`_UPDATED` and :data:`_LINK_STATE` of ``st``: each a
    copy with the rows ``idx`` (sorted, distinct) replaced by ``new[field]`` where ``new`` has
    the field. When ``idx`` is every row, ``new[field]`` itself where it is what the copy
    would be (same shape and dtype, C-contiguous, writeable, not another field's array):
    the same values and layout without copying what is replaced anyway (most tracker calls
    update every node they get)."""
    out: dict = {}
    taken: set[int] = set()
    for k in (*_UPDATED, *_LINK_STATE):
        a, v = getattr(st, k), new.get(k)
        if (v is not None and idx.size == a.shape[0] and v.shape == a.shape
                and v.dtype == a.dtype and v.flags.c_contiguous and v.flags.writeable
                and id(v) not in taken):
            out[k] = v
            taken.add(id(v))
            continue
        out[k] = a.copy()
        if v is not None:
            out[k][idx] = v
    return out


def _reinitialise(jdx: NDArray, links: Links, t: NDArray, building, config: TrackerConfig,
                  lk: dict, a: dict) -> None:
    """Start the nodes ``jdx`` again from their snapshot (every floor's hypotheses), in place:
    ``a`` holds :func:`update`'s working arrays by short name, ``lk`` the learned link state
    (forgotten for those nodes). The snapshot's grid step is ``start_grid_m`` where set (the
    re-seeds' stays ``init_grid_m``)."""
    first = replace(config, init_grid_m=config.start_grid_m) if config.start_grid_m > 0 else config
    x, p, lpi, sel, res = snapshot_init(links.take(jdx), building, first)
    a["mean"][jdx], a["cov"][jdx], a["lp"][jdx] = _init_hypotheses(x, p, lpi, config)
    best = np.argmax(lpi, axis=1)
    r = np.arange(jdx.size)
    a["mech"][jdx], a["resid"][jdx] = sel.slot[r, best], res[r, best]
    a["status"][jdx] = TrackStatus.INITIALISING
    a["nis"][jdx], a["good"][jdx], a["bad"][jdx], a["last"][jdx] = 1.0, 0, 0, t[jdx]
    a["floor_bad"][jdx], a["llr"][jdx], a["upd"][jdx], a["below"][jdx] = (
        0, np.nan, t[jdx, None], 0)
    a["deficit"][jdx] = 0
    a["origin"][jdx] = t[jdx]
    reset_links({k: lk[k] for k in LINK_FIELDS}, jdx)
    lk["unexplained"][jdx], lk["redundant"][jdx] = 0.0, 0.0
    lk["link_slot"][jdx] = np.nan


def _count_updated(idx, bad_epoch, t, status, good, bad, last) -> None:
    """The updated nodes ``idx``: their runs of bad / good epochs (``bad_epoch`` per row),
    their last fix time and a coasting node tracking again, in place."""
    bad[idx] = np.where(bad_epoch, bad[idx] + 1, 0)
    good[idx] = np.where(bad_epoch, 0, good[idx] + 1)
    last[idx] = t[idx]
    status[idx] = np.where(status[idx] == TrackStatus.COASTING, TrackStatus.TRACKING,
                           status[idx])


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
    n_meas = links.mask[:, 0].sum(axis=1)
    st, inflow = _predict(state, t, building, config, n_meas)
    dt_s = (t - state.t_ns) * 1e-9
    status, good, bad = st.status.copy(), st.good.copy(), st.bad.copy()
    floor_bad = st.floor_bad.copy()
    deficit, origin = st.deficit_count.copy(), st.refresh_origin_ns.copy()
    snr_cache = (st.snr_node, st.snr_anchor, st.snr_pred)  # new arrays where updated
    last = st.last_fix_ns.copy()
    mech, resid = np.full((n, m), -1), np.full((n, m), np.nan)
    if config.lost_on_gap:  # stale after a stall: re-initialised below, not updated
        status[has_position(status) & (n_meas > 0) & ((t - last) * 1e-9 > config.lost_after_s)] = (
            TrackStatus.LOST)
    live = ((status == TrackStatus.INITIALISING) | (status == TrackStatus.TRACKING)
            | (status == TrackStatus.COASTING))  # np.isin's values (np.isin: 1.5 % of a 1-node call)
    idx = np.flatnonzero(live & (n_meas > 0))
    new: dict = {}
    if idx.size:
        due = _deficit_schedule(state.t_ns[idx], t[idx], st.refresh_origin_ns[idx],
                                n_floors_of(st), config)
        new, ran, bad_epoch, bad_f, mech[idx], resid[idx], burst = _track_update(
            st, links, idx, t, inflow, dt_s, building, config, due)
        if "snr_node" in new:  # the SNR cache carried along (diffpos.tracking.model.snr_reuse_on)
            snr_cache = tuple(_with_rows(a, idx, new[key]) for a, key in
                              zip(snr_cache, ("snr_node", "snr_anchor", "snr_pred"),
                                  strict=True))
    merged = _merged(st, idx, new)
    mean, cov, lp, nis, llr, upd, below = (merged[k] for k in _UPDATED)
    lp = _more_floor_evidence(lp, st.log_prob, (mean, cov), (anchors_m, mask, snr_db), n_meas,
                              live, building, radio, config)
    lk = {k: merged[k] for k in _LINK_STATE}
    if idx.size:
        _mark_reseeds(floor_bad, deficit, idx, (ran, bad_f, burst),
                      None if due is None else new["deficit_count"], config)
        _count_updated(idx, bad_epoch, t, status, good, bad, last)
    _reseed(mean, cov, floor_bad, links, live & (n_meas >= _reseed_ranges(config)), building,
            config, _reseed_phase(state.t_ns, t, origin, floor_bad.shape[1], config))
    chal = tuple(a.copy() for a in (st.chal_mean, st.chal_cov, st.chal_llr, st.chal_age))  # owned
    if config.challenger_m > 0:  # a second level mode per floor (_challengers)
        chal = _challengers(st, state.t_ns, links, idx, dt_s, (mean, cov, lp, floor_bad),
                            building, config)
    coast = live & (n_meas == 0)
    status[coast] = TrackStatus.COASTING
    status[coast & ((t - last) * 1e-9 > config.lost_after_s)] = TrackStatus.LOST
    need = ((status == TrackStatus.UNINITIALISED) | (status == TrackStatus.LOST)
            | (bad >= config.diverge_epochs)) & (n_meas >= config.min_ranges_init)
    jdx = np.flatnonzero(need)
    if jdx.size:
        _reinitialise(jdx, links, t, building, config, lk, dict(
            mean=mean, cov=cov, lp=lp, mech=mech, resid=resid, status=status, nis=nis,
            good=good, bad=bad, last=last, floor_bad=floor_bad, llr=llr, upd=upd, below=below,
            deficit=deficit, origin=origin))
        if config.challenger_m > 0:  # a restarted node's challengers are gone
            chal[3][jdx] = 0
    status[(status == TrackStatus.INITIALISING) & (good >= config.confirm_epochs)] = (
        TrackStatus.TRACKING)
    if snr_cache[0] is st.snr_node:  # not updated: the new state owns its arrays
        snr_cache = tuple(a.copy() for a in snr_cache)
    contested, lead = floor_contested(lp, st.lead_floor, n_meas,
                                      vertical=config.floor_contest_vertical)
    lead_ns = np.where(contested, t, st.lead_ns)
    new = TrackerState(mean=mean, cov=cov, log_prob=lp, status=status.astype(np.int8),
                       t_ns=st.t_ns.copy(), last_fix_ns=last, nis=nis, good=good, bad=bad,
                       floor_bad=floor_bad, dormant_llr=llr, updated_ns=upd,
                       below_epochs=below, refresh_origin_ns=origin, snr_node=snr_cache[0],
                       snr_anchor=snr_cache[1], snr_pred=snr_cache[2], **lk,
                       lead_floor=lead, lead_ns=lead_ns, deficit_count=deficit,
                       chal_mean=chal[0], chal_cov=chal[1], chal_llr=chal[2], chal_age=chal[3])
    recent = (t - lead_ns) * 1e-9 < config.floor_contest_s
    return new, _output(new, (mech, resid), config, n_meas, (recent, st.lead_floor),
                        building)


def _output(state: TrackerState, fit: tuple, config: TrackerConfig, n_meas: NDArray,
            contest: tuple, building) -> TrackOutput:
    """The publication of the updated ``state`` (``fit``: the epoch's mechanisms and
    residuals; ``contest``: the nodes contested within ``floor_contest_s`` and the previous
    update's lead floors): :func:`_publish`, the few-anchors cap, the band bound and the
    covariance with the floors' spread (``cov_published_floors``, ``cov_few_floors``); the
    covariance :func:`_published_floor_cov` replaces is not computed before
    (``cov_kept_only``) unless :func:`_band_bound` reads it first."""
    again = config.cov_published_floors != "off"
    recent, doubt = contest[0], (_node_doubt(state, config, n_meas),)
    out = _few_anchors(_publish(state, *fit, config, n_meas, recent, doubt,
                                cov_kept_only=again and not config.floor_band_bound),
                       n_meas, config)
    out = _band_bound(out, building) if config.floor_band_bound else out
    if not again:
        return out
    q = (None if config.cov_few_floors == "off"
         else _few_floor_weights(state, out, config, n_meas, (*contest, doubt[0]), building))
    return _published_floor_cov(state, out, config.cov_published_floors, q)


def _few_floor_weights(state: TrackerState, out: TrackOutput, config: TrackerConfig,
                       n_meas: NDArray, contest: tuple, building) -> FloatArray:
    """The floor weights (N, F) of the published covariance's spread under
    ``TrackerConfig.cov_few_floors``: the published floor probabilities, but at the nodes
    whose floor the families' SNR tested (``min_anchors_tracking`` <= ranges <=
    ``family_few_links``) and the floors did not contest (:func:`floor_contested` as if the
    node had four ranges) those published with the evidence temper instead of the contest's
    ("temper"; model doubt and band bound as published) and without the model doubt too
    ("model"). ``contest``: the nodes contested within ``floor_contest_s``, the previous
    update's lead floors and the published model doubt (None: off)."""
    if config.cov_few_floors not in ("temper", "model"):
        raise ValueError(f"cov_few_floors must be 'off', 'temper' or 'model'; "
                         f"got {config.cov_few_floors!r}")
    recent, lead_prev, doubt = contest
    n_meas = np.asarray(n_meas)
    prob_h = np.exp(state.log_prob)
    by_floor, _ = floor_contested(state.log_prob, lead_prev, np.full(n_meas.shape, 4),
                                  prob_h, vertical=config.floor_contest_vertical)
    few = ((n_meas >= max(config.min_anchors_tracking, 1))
           & (n_meas <= config.family_few_links) & ~by_floor)
    if not np.any(few):
        return out.floor_probabilities
    q = published_floor_probabilities(
        state.log_prob, config, prob_h, link_ev=state.link_ev, link_all=state.link_all,
        doubt=doubt if config.cov_few_floors == "temper" else None,
        contested=np.asarray(recent, bool) & ~few)
    if config.floor_band_bound:
        q = height_band_bound(q, out.floor_index, out.position_m[:, 2],
                              out.covariance_m2[:, 2, 2], building.first_floor_z_m,
                              building.floor_height_m)
    return np.where(few[:, None], q, out.floor_probabilities)


def _more_floor_evidence(lp: FloatArray, lp_pred: FloatArray, moments: tuple, inputs: tuple,
                         n_meas: NDArray, live: NDArray[np.bool_], building, radio,
                         config: TrackerConfig) -> FloatArray:
    """The hypotheses' log-probabilities ``lp`` (N, H) after the epoch's update, with the two
    settings off by default: ``floor_hold_max_links`` (the ``live`` nodes with 1 to that many
    ranges ``n_meas`` keep their predicted log-probabilities ``lp_pred``: too few ranges to
    place the node, so the floors' evidence is the amplitude model's alone, which drifts on a
    channel we did not write) and then the silent anchors' negative information
    (:func:`diffpos.tracking.silent.silent_update`; ``inputs`` = the epoch's anchors, mask
    and SNRs) at the hypotheses' means (``moments`` = means (N, H, 6), covariances (N, H, 6,
    6)). ``lp`` itself when both are off."""
    k = config.floor_hold_max_links
    if k > 0:
        hold = live & few_ranges(n_meas, k, 1)
        if hold.any():
            lp = np.where(hold[:, None], lp_pred, lp)
    return silent_update(lp, moments[0], *inputs, n_meas, live, building, radio, config,
                         SNR_SIGMA_DB, moments[1])


# --------------------------------------------------------------------------------------------
# the measurement update of an epoch, with dormant hypotheses
# --------------------------------------------------------------------------------------------


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
    return (_period_index(t_ns[:, None], origin_ns, phase, period)
            > _period_index(updated_ns, origin_ns, phase, period))


def _period_index(t_ns: NDArray[np.int64], origin_ns: NDArray[np.int64],
                  phase: NDArray[np.int64], period: int) -> NDArray[np.int64]:
    """Which period ``k`` of ``period`` ns each time is in, the periods starting at ``origin +
    k T - phase`` (``t_ns`` (n, 1) or (n, K), ``origin_ns`` (n,), ``phase`` (K,)): measurement
    time relative to the node's origin, so a replay has the same boundaries as the live run
    (:func:`_refresh_due`, :func:`_deficit_due`)."""
    return (t_ns - origin_ns[:, None] + phase) // period


def _update_pairs(mean, cov, links: Links, rr, cc, n_floors: int, building,
                  config: TrackerConfig, snr_cache: tuple | None = None,
                  link_w: FloatArray | None = None, fam_gate: NDArray | None = None,
                  prev: FloatArray | None = None):
    """Measurement update of the hypotheses ``(rr[i], cc[i])`` (node row, hypothesis) of
    ``mean`` (n, H, 6), ``cov``, ``links`` (n nodes): each pair as a node with one
    hypothesis; per pair x, P, log-evidence, slot, NIS, residual and log-weight of every link.
    ``snr_cache``: the nodes' ``(snr_node, snr_anchor, snr_pred)`` arrays (n, H, ...)
    (:class:`~diffpos.tracking.state.TrackerState`), the pairs' rows read and updated in
    place (:class:`diffpos.tracking.model.SnrCache`). ``link_w``: the nodes' learned link
    weights (n, H, M, 2) (:func:`diffpos.tracking.evidence.learned_weights`), or None.
    ``fam_gate`` (n, H, M): the links whose out-of-model component includes the extra
    families (``config.max_order``, :mod:`diffpos.tracking.families`; None: every link).
    ``prev`` (n, H, M): the hypotheses' previous mechanisms (``mechanism_switch_p``), or None."""
    sc = None
    if snr_cache is not None:
        sc = SnrCache(*(a[rr, cc][:, None] for a in snr_cache))
    out = _update_at(mean[rr, cc], cov[rr, cc], links, rr, cc, n_floors, building, config, sc,
                     link_w, fam_gate, None if prev is None else prev[rr, cc][:, None])
    if sc is not None:
        for a, v in zip(snr_cache, (sc.node, sc.anchor, sc.pred), strict=True):
            a[rr, cc] = v[:, 0]
    return out


def _update_at(x_prior, p_prior, links: Links, rr, cc, n_floors: int, building,
               config: TrackerConfig, sc: SnrCache | None = None,
               link_w: FloatArray | None = None, fam_gate: NDArray | None = None,
               prev: FloatArray | None = None):
    """:func:`_update_pairs` from the priors ``x_prior`` (P, 6), ``p_prior`` (P, 6, 6) of the
    pairs ``(rr[i], cc[i])`` (``sc``: their SNR cache, (P, 1, ...), updated in place)."""
    fl = hypothesis_floor(n_floors)[cc][:, None]
    level = ~hypothesis_vertical(n_floors)[cc][:, None]
    x0, p0 = x_prior[:, None], p_prior[:, None]
    sub = links.take(rr)
    w = None if link_w is None else link_w[rr, cc][:, None]
    fam = pos = None
    if config.max_order > DEFAULT_ORDER:  # the extra families (diffpos.tracking.families)
        if w is None:
            w = link_weights(sub, config, sub.snr is not None, rr.size, 1)
        pos = clamp_to_floor(x0[:, 0, :3], fl[:, 0], building, config.z_margin_m)
        gate = (np.ones((rr.size, links.rho.shape[-1]), bool) if fam_gate is None
                else fam_gate[rr, cc])
        dw = family_log_weight(pos, p0[:, 0, :3, :3], links, rr, fl[:, 0], gate, building,
                               config, np.log(-np.expm1(w[:, 0, :, 0])),
                               snr_sigma_db=SNR_SIGMA_DB, snr_span_db=SNR_SPAN_DB,
                               fit=config.family_fit_links > 0)
        if config.family_fit_links > 0:
            dw, fam = dw
        w[:, 0, :, 1] += dw
    x, p, ev, sel, res = measurement_update(x0, p0, sub, fl, building, config,
                                            level=level, snr_cache=sc, link_w=w,
                                            prev_slot=prev)
    if fam is not None:
        x, p, ev, res = _family_refit(x, p, ev, res, x0, p0, sub, fl, level, sel, pos, fam,
                                      building, config)
    out = [x[:, 0], p[:, 0], ev[:, 0], sel.slot[:, 0], sel.nis[:, 0], res[:, 0],
           sel.log_weight[:, 0]]
    if config.edge_retry_margin_m > 0.0:
        _edge_retry(out, x0, p0, sub, fl, level, w, building, config, rr)
    return tuple(out)


def _family_refit(x, p, ev, res, x0, p0, sub: Links, fl, level, sel, pos, fam: tuple,
                  building, config: TrackerConfig) -> tuple:
    """``TrackerConfig.family_fit_links``: the pairs (P, 1) of nodes with at most that many
    ranges (and at least ``min_anchors_tracking``) whose update (``x``, ``p``, ``ev``,
    ``res``; its selection ``sel``) left a present link out of the fit (``slot`` -1) that
    an extra family explains (``fam``: :func:`~diffpos.tracking.families.family_log_weight`'s
    ``best`` at the clamped prior ``pos`` (P, 3), the families' part of the out-of-model
    component the larger) are fitted again with that link's range as the family's path
    (:func:`~diffpos.tracking.model.family_refit`); the others as they are. Returns the four
    arrays (copies where rows changed)."""
    length, jac, spread = fam
    m = sub.mask[:, 0]
    few = few_ranges(m.sum(axis=-1), config.family_fit_links, config.min_anchors_tracking)
    use = m & (sel.slot[:, 0] < 0) & np.isfinite(length) & few[:, None]
    rows = np.flatnonzero(use.any(axis=-1))
    if rows.size == 0:
        return x, p, ev, res
    sel_r = Selection(*(a[rows] for a in (sel.slot, sel.log_weight, sel.nis, sel.extra_var)))
    sub_r = sub.take(rows)
    xr, pr, er, rr_ = family_refit(x0[rows], p0[rows], sub_r, fl[rows], sel_r,
                                   np.where(use[rows], length[rows], np.nan), jac[rows],
                                   sub_r.var[:, 0] + spread[rows], pos[rows], building,
                                   config, level[rows])
    x, p, ev, res = x.copy(), p.copy(), ev.copy(), res.copy()
    x[rows], p[rows], ev[rows], res[rows] = xr, pr, er, rr_
    return x, p, ev, res


def _edge_retry(out: list, x0, p0, sub: Links, fl, level, w, building,
                config: TrackerConfig, rr: NDArray | None = None) -> None:
    """``TrackerConfig.edge_retry_margin_m``: the level-mode pairs of ``out``
    (``_update_at``'s lists, replaced in place) in good standing (at least four ranges, every
    present link's learned outlier probability ``1 - exp(w[..., 0])`` below
    ``edge_retry_eps``; the prior's where ``w`` is None) that called a present link an outlier
    are updated again with their existence margins at least ``edge_retry_margin_m`` (the SNR
    predicted afresh, the cache untouched); that update replaces the first (with
    ``edge_retry_prior`` only where :func:`_refits_at_prior` holds). The vertical
    mode's margin already follows its own height uncertainty (``existence_margin``). Per
    pair: rows stay independent. With ``edge_retry_node`` every level pair of a node (``rr``
    (P,): the pairs' nodes) that has a retried pair is updated again and replaced: the
    node's floors compared under one existence model."""
    m = sub.mask[:, 0]
    good = _good_standing(m, None if w is None else w[:, 0, :, 0], 4, config)
    rows = np.flatnonzero(good & level[:, 0] & np.any(m & (out[3] < 0), axis=-1))
    if rows.size == 0:
        return
    if config.edge_retry_node and rr is not None:
        rows = np.flatnonzero(np.isin(rr, rr[rows]) & level[:, 0])
    x, p, ev, sel, res = measurement_update(
        x0[rows], p0[rows], sub.take(rows), fl[rows], building, config, level=level[rows],
        snr_cache=None, link_w=None if w is None else w[rows],
        min_margin=config.edge_retry_margin_m)
    k = np.arange(rows.size)
    if config.edge_retry_prior:
        k = np.flatnonzero(_refits_at_prior(x0[rows], p0[rows], sub.take(rows), fl[rows],
                                            out[3][rows], sel.slot[:, 0], building, config))
        rows = rows[k]
    for j, v in enumerate((x, p, ev, sel.slot, sel.nis, res, sel.log_weight)):
        out[j] = out[j].copy()
        out[j][rows] = v[k, 0]


def _good_standing(mask: NDArray, log_inlier_w: FloatArray | None, min_ranges: int,
                   config: TrackerConfig) -> NDArray[np.bool_]:
    """Tracks in good standing (the edge retry's and the burst re-seed's test): at least
    ``min_ranges`` present links (``mask`` (..., M), broadcast against the weights) and every
    present link's learned outlier probability ``1 - exp(log_inlier_w)`` (..., M) below
    ``edge_retry_eps`` (None: the prior ``outlier_weight``): it has been fitting every
    link."""
    eps = (np.full(mask.shape, config.outlier_weight) if log_inlier_w is None
           else -np.expm1(log_inlier_w))
    return (np.all(~mask | (eps < config.edge_retry_eps), axis=-1)
            & (mask.sum(axis=-1) >= min_ranges))


def _refits_at_prior(x0, p0, sub: Links, fl, slot0, slot1, building,
                     config: TrackerConfig) -> NDArray[np.bool_]:
    """``TrackerConfig.edge_retry_prior``: the retried pairs (P) whose every re-fitted link
    (present, an outlier in the first update ``slot0`` (P, M), a mechanism in the retry's
    ``slot1``) is fitted with a mechanism that is a candidate (:func:`candidates`) at the
    pair's prior ``x0`` (P, 1, 6) clamped into its floor's box, with the ordinary existence
    margin of its covariance ``p0`` (:func:`existence_margin`): the first update's own
    first-pass test."""
    refit = sub.mask[:, 0] & (slot0 < 0) & (slot1 >= 0)
    xc = clamp_to_floor(x0[..., :3], fl, building, config.z_margin_m)
    cand = candidates(all_paths(xc, sub, fl, building, existence_margin(p0, config)))[:, 0]
    ok = np.take_along_axis(cand, np.maximum(slot1, 0)[..., None], axis=-1)[..., 0]
    return np.all(~refit | ok, axis=-1)


def _mode_pairs(mean, cov, links: Links, rr, cc, out: tuple, eps: FloatArray, n_floors: int,
                building, config: TrackerConfig, link_w: FloatArray | None = None,
                fam_gate: NDArray | None = None, allow: NDArray | None = None,
                counted: NDArray | None = None) -> tuple:
    """Other modes of the updated pairs ``(rr, cc)`` (``out``: their :func:`_update_pairs`
    outputs from the priors ``mean``, ``cov`` (n, H, ...)) that call at least
    ``mode_search_outliers`` of their ranges outliers, have ``min_ranges_init`` ranges and
    are ``allow``-ed; ``counted`` (n, H, M): the links whose outlier counts towards
    ``mode_search_outliers`` (:func:`_new_misfit`; None: every link) (the caller: ``allow``
    the pairs of TRACKING nodes; while a node is INITIALISING
    its priors are the snapshot's broad ones, and a search there is a second snapshot that
    lets every floor find its best fit of the four ranges again: measured on Sionna's live
    paper 72.8 % right floor with it, 81.5 % without, 88.2 % with no search).

    The IEKF from the prior mean finds the posterior's nearest mode only; a first arrival
    that switched to a path existing a few decimetres away (or a prior that sits in the wrong
    mode) leaves it calling links outliers while a mode that explains them lies within reach.
    The candidates: the same measurement update (:func:`_update_at`) from the best cell of a
    local grid (:func:`local_starts`) with a broad prior ``N(s, C)`` centred at the cell
    (``C = P + J``, ``J``: ``mode_jump_sigma_m`` squared on each position axis), whose
    Laplace posterior is carried in closed form to another prior (:func:`_reprior`):
    (1) the pair's own prior ``N(x, P)`` (another mode of the same posterior: max-mixture
    with the pair's own fit), (2) the jump component ``N(x, P + J)`` with the weight ``e``
    (``eps`` (P,), ``mode_jump_rate_hz``; 0: none). The pair's evidence becomes
    ``log((1 - e) max(Z_0, Z_own) + e Z_jump)`` and its state the largest term's posterior.
    The prior's spread makes a far or loose fit pay its Occam factor: a fit of three ranges
    that fits anything far from the prediction does not win."""
    x, p, ev, slot, nis, res, lw = out
    present = links.mask[rr, 0]
    n_out = np.sum(present & (slot < 0) & (True if counted is None else counted[rr, cc]),
                   axis=-1)
    k = np.flatnonzero((n_out >= config.mode_search_outliers) & np.isfinite(ev)
                       & (np.sum(present, axis=-1)
                          >= max(config.min_ranges_init, config.mode_search_min_links))
                       & (True if allow is None else allow))
    if k.size == 0:
        return out
    r, c = rr[k], cc[k]
    x0, p0 = mean[r, c], cov[r, c]
    cj = p0.copy()
    i3 = np.arange(3)
    cj[:, i3, i3] += config.mode_jump_sigma_m ** 2
    starts, cost = local_starts(links.take(r), hypothesis_floor(n_floors)[c], x0[:, :3],
                                cj[:, :2, :2], building, config)  # (k, S, 3)
    better = np.isfinite(cost)
    keep = np.flatnonzero(better.any(axis=1))
    if keep.size == 0:
        return out
    k, r, c, x0, cj, starts, better = (a_[keep] for a_ in (k, r, c, x0, cj, starts, better))
    ns = starts.shape[1]
    xs = np.repeat(x0, ns, axis=0)
    xs[:, :3] = starts.reshape(-1, 3)
    cs = np.repeat(cj, ns, axis=0)
    x1, p1, e1, s1, n1, r1, w1 = _update_at(xs, cs, links, np.repeat(r, ns),
                                            np.repeat(c, ns), n_floors, building, config,
                                            None, link_w, fam_gate)
    p0 = p0[keep]
    x0r, p0r = np.repeat(x0, ns, axis=0), np.repeat(p0, ns, axis=0)
    terms = [np.log1p(-eps[k]) + ev[k]]
    cand = []
    with np.errstate(divide="ignore"):  # no jump (eps 0): its term -inf
        log_eps = np.log(eps[k])
    for prior_cov, w in ((p0r, np.log1p(-eps[k])), (cs, log_eps)):
        e_c, m_c, p_c = _reprior(x1, p1, e1, xs, cs, x0r, prior_cov)
        e_c = np.where(np.isfinite(e_c) & better.reshape(-1), e_c, -np.inf).reshape(k.size, ns)
        b = np.argmax(e_c, axis=1)
        j = np.arange(k.size) * ns + b
        terms.append(w + e_c[np.arange(k.size), b])
        cand.append((j, m_c, p_c))
    t = np.stack(terms)  # (3, k): own fit, another mode, the jump
    win = np.argmax(t, axis=0)
    ev, x, p, slot, nis, res, lw = (a_.copy() for a_ in (ev, x, p, slot, nis, res, lw))
    ev[k] = np.logaddexp(np.maximum(t[0], t[1]), t[2])  # max-mixture over the modes
    for w_, (j, m_c, p_c) in zip((1, 2), cand, strict=True):
        kw, jw = k[win == w_], j[win == w_]
        xm = m_c[jw]
        xm[:, :3] = clamp_to_floor(xm[:, :3], hypothesis_floor(n_floors)[cc[kw]], building,
                                   config.z_margin_m)
        x[kw], p[kw], slot[kw], nis[kw], res[kw], lw[kw] = xm, p_c[jw], s1[jw], n1[jw], \
            r1[jw], w1[jw]
    return x, p, ev, slot, nis, res, lw


def _new_misfit(lk: dict | None, col: NDArray[np.int_], config: TrackerConfig
                ) -> NDArray[np.bool_] | None:
    """The links (n, H, M) whose outlier this update counts towards ``mode_search_outliers``
    (``config.mode_search_new_misfit``): those the hypothesis fitted in its recent real
    updates, its forgotten outlier rate ``link_out / link_all`` before this update (the
    learned arrays ``lk``, every column's link ``col``) below ``mode_search_new_misfit``,
    with at least one real update of the link learned. A first-arrival switch (the link's
    arrival just left the hypothesis' model) counts; a link out of its model all along (a
    persistent out-of-model arrival, or a wrong floor that never explained it) does not.
    None (every link counts): the setting off (0) or nothing learned (``link_learn`` off)."""
    if config.mode_search_new_misfit <= 0.0 or lk is None:
        return None
    n_all = _gather(lk["link_all"], col)
    with np.errstate(invalid="ignore", divide="ignore"):
        rate = _gather(lk["link_out"], col) / n_all
    return (n_all > 0.0) & (rate < config.mode_search_new_misfit)


def _most_probable(lp: FloatArray, rr: NDArray, cc: NDArray, k: int) -> NDArray[np.bool_]:
    """The pairs ``(rr, cc)`` among the ``k`` most probable hypotheses of their node by the
    predicted log-probabilities ``lp`` (n, H) (ties: the lower index); ``k`` <= 0: all."""
    if k <= 0:
        return np.ones(rr.size, dtype=bool)
    rank = np.argsort(np.argsort(-lp, axis=1, kind="stable"), axis=1, kind="stable")
    return rank[rr, cc] < k


def _reprior(x1: FloatArray, p1: FloatArray, ev1: FloatArray, xs: FloatArray, cs: FloatArray,
             x0: FloatArray, p0: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """A Laplace fit under the prior ``N(xs, cs)`` (posterior ``N(x1, p1)``, log-evidence
    ``ev1``; (P, 6), (P, 6, 6), (P,)) carried to the prior ``N(x0, p0)``: the likelihood is
    ``Z1 N(x; x1, p1) / N(x; xs, cs)``, so with ``A = p1^-1 + p0^-1 - cs^-1`` and ``b =
    p0^-1 (x0 - x1) - cs^-1 (xs - x1)`` the new log-evidence is ``ev1 - (u0' p0^-1 u0 -
    us' cs^-1 us) / 2 + b' A^-1 b / 2 - (log|p1| + log|p0| - log|cs| + log|A|) / 2``
    (``u0 = x0 - x1``, ``us = xs - x1``), the posterior ``N(x1 + A^-1 b, A^-1)``. Exact for
    a linear-Gaussian likelihood; ``A`` is positive definite (``p1^-1 >= cs^-1``)."""
    i1, i0, ic = np.linalg.inv(p1), np.linalg.inv(p0), np.linalg.inv(cs)
    a = i1 + i0 - ic
    a = 0.5 * (a + np.swapaxes(a, -1, -2))
    u0, us = x0 - x1, xs - x1
    b = np.einsum("pij,pj->pi", i0, u0) - np.einsum("pij,pj->pi", ic, us)
    cov = np.linalg.inv(a)
    cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
    shift = np.einsum("pij,pj->pi", cov, b)
    logdet = (np.linalg.slogdet(p1)[1] + np.linalg.slogdet(p0)[1] - np.linalg.slogdet(cs)[1]
              + np.linalg.slogdet(a)[1])
    quad = (np.einsum("pi,pij,pj->p", u0, i0, u0) - np.einsum("pi,pij,pj->p", us, ic, us)
            - np.einsum("pi,pi->p", b, shift))
    return ev1 - 0.5 * quad - 0.5 * logdet, x1 + shift, cov


def _normalise(lp: FloatArray) -> FloatArray:
    lp = np.maximum(lp - lp.max(axis=1, keepdims=True), -700.0)
    return lp - np.log(np.exp(lp).sum(axis=1, keepdims=True))


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
    total = np.sum(np.where(np.isnan(nis_links), 0.0, nis_links), axis=-1)  # np.nansum's sum
    return np.where(n_in > 0, total / np.maximum(n_in, 1), np.inf), n_in


def _link_misfit(nis_h: FloatArray, res: FloatArray, var: FloatArray,
                 config: TrackerConfig) -> FloatArray:
    """Every link's misfit (n, H, M) kept as ``link_fit`` for the family gate: its selection
    NIS at the prior covariance (``config.family_fit="prior"``) or its fitted residual over
    the range noise, ``res^2 / var`` at the updated state (``"residual"``); NaN where the
    link was an outlier or absent. ``var`` (n, M): the links' range variances."""
    if config.family_fit == "prior":
        return nis_h
    if config.family_fit != "residual":
        raise ValueError(f"family_fit must be 'prior' or 'residual'; got {config.family_fit!r}")
    with np.errstate(invalid="ignore"):
        return np.where(np.isfinite(nis_h), res * res / var[:, None, :], np.nan)


def _mark_reseeds(floor_bad: NDArray, deficit: NDArray, idx: NDArray, flags,
                  deficit_count: NDArray | None, config: TrackerConfig) -> None:
    """Count, in place, the floors of the nodes ``idx`` that fitted badly this epoch
    (``floor_bad``; ``flags`` = (ran, bad_f, burst) of :func:`_track_update`) and mark for a
    re-seed in this epoch the believed floor's burst of outliers (``reseed_outliers``) and the
    floors whose evidence deficit reached ``deficit_tests`` tests (``deficit_count``, None:
    the setting off; the count restarts)."""
    ran, bad_f, burst = flags
    floor_bad[idx] = np.where(ran, np.where(bad_f, floor_bad[idx] + 1, 0), floor_bad[idx])
    if burst is not None:  # reseed_outliers: re-seeded below, in this epoch
        floor_bad[idx] = np.where(burst, np.maximum(floor_bad[idx], config.reseed_epochs),
                                  floor_bad[idx])
    if deficit_count is not None:  # an evidence deficit in deficit_tests tests
        hit = deficit_count >= max(config.deficit_tests, 1)
        floor_bad[idx] = np.where(hit, np.maximum(floor_bad[idx], config.reseed_epochs),
                                  floor_bad[idx])
        deficit[idx] = np.where(hit, 0, deficit_count)


def _track_update(state: TrackerState, links: Links, idx: NDArray, t_ns: NDArray,
                  inflow: FloatArray, dt_s: FloatArray, building, config: TrackerConfig,
                  deficit_due: NDArray[np.bool_] | None = None):
    """Measurement update of the nodes ``idx`` (their rows of the predicted ``state``, ``t_ns``,
    ``inflow`` (:func:`diffpos.tracking.imm._mix`), ``dt_s``): the hypotheses that are awake,
    due for a refresh, woken by the mixing, or of a node that is not TRACKING; then, for a
    node whose best hypothesis fits badly this epoch (NIS above ``nis_limit``, most ranges
    outliers), its dormant ones too. Returns the nodes' new arrays (a dict of state fields), the updated
    hypotheses (n, H), every hypothesis' bad flag, and the best's mechanism/residual.
    ``deficit_due`` (n, F): the floors of the nodes due for an evidence-deficit test
    (:func:`_deficit_counts`; None: the setting off, no ``deficit_count`` in the dict)."""
    nf = n_floors_of(state)
    h = 2 * nf
    sub = links.take(idx)
    n, m = idx.size, sub.rho.shape[-1]
    m0, c0, lp0, llr0 = state.mean[idx], state.cov[idx], state.log_prob[idx], \
        state.dormant_llr[idx]
    x, p = m0.copy(), c0.copy()
    snr_cache = ((state.snr_node[idx], state.snr_anchor[idx], state.snr_pred[idx])  # copies
                 if snr_reuse_on(config) else None)
    ev, slot = np.full((n, h), np.nan), np.full((n, h, m), -1)
    nis_h, res = np.full((n, h, m), np.nan), np.full((n, h, m), np.nan)
    lw = np.zeros((n, h, m))
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
    lk = col = link_w = fam_gate = fresh = None
    if config.link_learn:  # the learned unmodelled-path component (diffpos.tracking.evidence)
        lk, col, tab, seen, link_w, fam_gate, fresh = _link_inputs(state, idx, sub, t_ns, m0,
                                                                   c0, n_meas, config)
    counted = _new_misfit(lk, col, config) if config.mode_search_outliers > 0 else None
    prev = _prev_slots(state, idx, col, fresh, config)
    todo = run
    while True:
        rr, cc = np.nonzero(todo)
        if rr.size:
            out = _update_pairs(m0, c0, sub, rr, cc, nf, building, config, snr_cache, link_w,
                                fam_gate, prev)
            if config.mode_search_outliers > 0:  # other modes (and the jump component)
                out = _mode_pairs(m0, c0, sub, rr, cc, out, np.minimum(
                    config.mode_jump_rate_hz * np.maximum(dt_s[idx][rr], 0.0), 0.5), nf,
                    building, config, link_w, fam_gate,
                    (state.status[idx][rr] == TrackStatus.TRACKING)
                    & _most_probable(lp0, rr, cc, config.mode_search_max), counted)
            (x[rr, cc], p[rr, cc], ev[rr, cc], slot[rr, cc], nis_h[rr, cc],
             res[rr, cc], lw[rr, cc]) = out
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
    new_deficit = (None if deficit_due is None else _deficit_tested(
        state, idx, sub, deficit_due, n_meas, (m0, c0, run, x, ev, slot, res), building, config,
        link_w, fam_gate))
    bad_epoch, bad_f, burst = _bad_flags(state, idx, sub, (nis, n_in, n_meas, nis_h),
                                         (slot, link_w, run, lp, col, fresh), config)
    # consecutive real updates below the threshold; the update of a dormant hypothesis
    # (refresh or wake-up) re-converges its stale state and does not count
    below = np.where(run, np.where(np.isfinite(llr0), 0,
                                   np.where(lp < log_thr, state.below_epochs[idx] + 1, 0)),
                     state.below_epochs[idx])
    asleep = below >= max(config.dormant_epochs, 1)
    new = {"mean": x, "cov": p, "log_prob": lp, "nis": nis, "below_epochs": below,
           "dormant_llr": np.where(asleep, np.where(run, llr, llr0), np.nan),
           "updated_ns": np.where(run, t_ns[idx, None], state.updated_ns[idx])}
    if new_deficit is not None:
        new["deficit_count"] = new_deficit
    if snr_cache is not None:  # the SNR cache's rows (reuse off: the state's stay as they are)
        new.update(zip(("snr_node", "snr_anchor", "snr_pred"), snr_cache, strict=True))
    if lk is not None:
        new.update(_learned(state, idx, sub, t_ns, n_meas, config, (lk, col, tab, seen),
                            (run, x, p, slot, lw, nis_h, res)))
    if prev is not None or (config.reseed_outliers > 0 and col is not None):
        new["link_slot"] = _kept_slots(state.link_slot[idx], fresh, col, run, slot,
                                       sub.mask[:, 0])
    return new, run, bad_epoch, bad_f, slot[r, best], res[r, best], burst


# --------------------------------------------------------------------------------------------
# a second level mode per floor (TrackerConfig.challenger_m)
# --------------------------------------------------------------------------------------------


def _challengers(st: TrackerState, prev_ns: NDArray[np.int64], links: Links, idx: NDArray,
                 dt_s: FloatArray, track: tuple, building, config: TrackerConfig) -> tuple:
    """``TrackerConfig.challenger_m``: the challengers of the floors' level tracks after this
    epoch's update, new arrays ``(chal_mean, chal_cov, chal_llr, chal_age)``. ``st``: the
    predicted state (the level tracks' priors), ``prev_ns`` the nodes' previous times, ``idx``
    the nodes updated this epoch, ``track`` = (mean, cov, log_prob, floor_bad) after the
    update (mean, cov and floor_bad changed in place where a challenger wins). Per node: no
    row reads another's."""
    mean, cov, lp, floor_bad = track
    cm, cp, cl, ca = (st.chal_mean.copy(), st.chal_cov.copy(), st.chal_llr.copy(),
                      st.chal_age.copy())
    ok = np.zeros(ca.shape[0], bool)
    ok[idx] = True
    ok &= ((st.status == TrackStatus.TRACKING)
           & (links.mask[:, 0].sum(axis=1) >= max(_reseed_ranges(config), 4)))
    ca[~ok] = 0
    rows, fl = np.nonzero(ca > 0)
    if rows.size:
        _challenge(st, links, rows, fl, dt_s, (cm, cp, cl, ca), (mean, cov, floor_bad),
                   building, config)
    due = _deficit_due(prev_ns, st.t_ns, st.refresh_origin_ns, ca.shape[1],
                       config.challenger_period_s) > 0
    if config.challenger_floors > 0:  # the most probable floors after the leading one
        fp = floor_probabilities(lp)
        rank = np.argsort(np.argsort(-fp, axis=1, kind="stable"), axis=1, kind="stable")
        due &= (rank >= 1) & (rank <= config.challenger_floors)
    if config.challenger_min_p > 0:  # floors the data keeps alive (not mixed in from others)
        due &= floor_probabilities(lp) >= config.challenger_min_p
    rows, fl = np.nonzero(due & ok[:, None] & (ca == 0))
    if rows.size:
        _challenger_start(st, links, rows, fl, mean, (cm, cp, cl, ca), building, config)
    return cm, cp, cl, ca


def _challenge(st: TrackerState, links: Links, rows: NDArray, fl: NDArray, dt_s: FloatArray,
               chal: tuple, track: tuple, building, config: TrackerConfig) -> None:
    """One epoch of the active challengers ``(rows, fl)`` (node, floor), in place: each is
    predicted and updated in the level mode (:func:`_update_at`, the prior link weights, no
    mechanism history) and the floor's more probable mode (predicted; a node on the stairs:
    its vertical one) is updated again from its prior (``st.mean``) with the same inputs
    (with ``challenger_beat_lead`` the better of it and the node's most probable
    hypothesis). After ``challenger_grace`` updates the evidence difference is accumulated;
    above ``challenger_nats`` after at least ``challenger_min_epochs`` scored updates the
    challenger's state replaces both modes of the floor (``track`` = (mean, cov, floor_bad),
    in place: the level mode's prior is mixed from the vertical one when that is the more
    probable, so replacing the level mode alone is undone in the next epoch; what the
    hypotheses learned of their links is kept: forgetting it lost Sionna paper 1-2 points
    offline); below ``-challenger_nats``, after ``challenger_epochs`` scored updates or
    within ``challenger_m / 2`` of either mode it is dropped."""
    cm, cp, cl, ca = chal
    mean, cov, floor_bad = track
    nf = ca.shape[1]
    xc, pc = _propagate(cm[rows, fl][:, None], cp[rows, fl][:, None], dt_s[rows], config)
    x1, p1, e1 = _update_at(xc[:, 0], pc[:, 0], links, rows, fl, nf, building, config)[:3]
    h0 = np.where(st.log_prob[rows, fl + nf] > st.log_prob[rows, fl], fl + nf, fl)
    if config.challenger_beat_lead:  # also the node's most probable hypothesis
        h0 = np.stack([h0, np.argmax(st.log_prob[rows], axis=1)], axis=1).ravel()
    r0 = np.repeat(rows, h0.size // rows.size)
    e0 = _update_at(st.mean[r0, h0], st.cov[r0, h0], links, r0, h0, nf, building,
                    config)[2].reshape(rows.size, -1)
    e0 = np.where(np.isfinite(e0), e0, -np.inf).max(axis=1)
    age = ca[rows, fl] + 1
    with np.errstate(invalid="ignore"):
        gap = np.where(np.isfinite(e1) & np.isfinite(e0), e1 - e0,
                       np.where(np.isfinite(e1), 0.0, -np.inf))
    llr = cl[rows, fl] + np.where(age > config.challenger_grace, gap, 0.0)
    cm[rows, fl], cp[rows, fl], cl[rows, fl], ca[rows, fl] = x1, p1, llr, age
    win = (llr > config.challenger_nats) & (age >= config.challenger_grace
                                            + config.challenger_min_epochs)
    near = _track_distance(mean, rows, fl, x1) < 0.5 * config.challenger_m
    lose = ((llr < -config.challenger_nats) | near
            | (age > config.challenger_grace + config.challenger_epochs))
    w = np.flatnonzero(win)
    r, f = np.concatenate([rows[w], rows[w]]), np.concatenate([fl[w], fl[w] + nf])
    pv = p1[w].copy()
    pv[:, 5, 5] += (config.v_stairs_m_s / 2) ** 2  # the vertical mode: _init_hypotheses' spread
    mean[r, f], cov[r, f] = np.concatenate([x1[w], x1[w]]), np.concatenate([p1[w], pv])
    floor_bad[r, f] = 0
    ca[rows[win | lose], fl[win | lose]] = 0


def _track_distance(mean: FloatArray, rows: NDArray, fl: NDArray, x: FloatArray) -> FloatArray:
    """Horizontal distance (P,) of the positions ``x`` (P, >= 2) from the nearer of the two
    modes (level, vertical) of the floors ``(rows, fl)`` in ``mean`` (n, 2F, 6)."""
    nf = mean.shape[1] // 2
    return np.minimum(np.hypot(*(x[:, :2] - mean[rows, fl, :2]).T),
                      np.hypot(*(x[:, :2] - mean[rows, fl + nf, :2]).T))


def _challenger_start(st: TrackerState, links: Links, rows: NDArray, fl: NDArray,
                      mean: FloatArray, chal: tuple, building, config: TrackerConfig) -> None:
    """Start challengers (in place, ``chal`` = the four arrays) for the floors ``(rows, fl)``:
    the candidates (:func:`_challenger_candidates`) farther than ``challenger_m``
    (horizontally) from both of the floor's modes (``mean``, after this epoch's update) are
    each updated (:func:`_update_at`, every range) from the level track's prior moved there;
    the best evidence per floor starts its challenger (its update this epoch counted)."""
    cm, cp, cl, ca = chal
    nf = ca.shape[1]
    pair, xs = _challenger_candidates(links, rows, fl, building, config)
    far = _track_distance(mean, rows[pair], fl[pair], xs) > config.challenger_m
    pair, xs = pair[far], xs[far]
    if pair.size == 0:
        return
    r, f = rows[pair], fl[pair]
    x0 = st.mean[r, f].copy()
    x0[:, :3] = xs[:, :3]
    x1, p1, e1 = _update_at(x0, st.cov[r, f], links, r, f, nf, building, config)[:3]
    e1 = np.where(np.isfinite(e1), e1, -1e300)
    for k in np.argsort(e1, kind="stable"):  # the best candidate of a floor written last
        cm[r[k], f[k]], cp[r[k], f[k]] = x1[k], p1[k]
    cl[r, f], ca[r, f] = 0.0, 1


def _challenger_candidates(links: Links, rows: NDArray, fl: NDArray, building,
                           config: TrackerConfig) -> tuple[NDArray, FloatArray]:
    """Candidate positions of the floors ``(rows, fl)`` (P pairs): each floor's snapshot
    (:func:`diffpos.tracking.model.snapshot`, the grid's best cell) and, for nodes with 4 to
    ``challenger_loo_max_links`` ranges, its snapshot once per present range left out.
    Returns the pair of every candidate (K,) and its state (K, 6)."""
    sub = links.take(rows)
    xs = snapshot(sub, fl[:, None], building, config, 1)[0][:, 0]
    present = sub.mask[:, 0]
    n_m = present.sum(axis=1)
    loo_ok = (n_m >= 4) & (n_m <= config.challenger_loo_max_links)
    pr, jj = np.nonzero(present & loo_ok[:, None])
    if pr.size == 0:
        return np.arange(rows.size), xs
    loo = sub.take(pr)
    mask = loo.mask.copy()
    mask[np.arange(pr.size), 0, jj] = False
    loo = Links(loo.rho, loo.var, mask, loo.anchors, loo.snr, loo.radio)
    xl = snapshot(loo, fl[pr][:, None], building, config, 1)[0][:, 0]
    return np.concatenate([np.arange(rows.size), pr]), np.concatenate([xs, xl])


def _bad_flags(state: TrackerState, idx: NDArray, sub: Links, fit, picked,
               config: TrackerConfig):
    """The epoch's bad flags of the nodes ``idx`` after their update: the node's (its smoothed
    NIS ``nis`` above ``nis_limit`` or most of its ``n_meas`` ranges outliers), each floor's
    (its hypotheses' NIS ``nis_h``, the same rule) and the believed floor's burst of outliers
    (:func:`_outlier_burst`; None: ``reseed_outliers`` off). ``fit`` = (nis, n_in, n_meas,
    nis_h); ``picked`` = (slot, link_w, run, lp, col, fresh) of :func:`_track_update`."""
    nis, n_in, n_meas, nis_h = fit
    slot, link_w, run, lp, col, fresh = picked
    bad_epoch = (nis > config.nis_limit) | (2 * n_in < n_meas)
    nis_f, n_in_f = _epoch_nis(nis_h)
    bad_f = (2 * n_in_f < n_meas[:, None]) | (nis_f > config.nis_limit)
    burst = (_outlier_burst(slot, sub.mask[:, 0], link_w, run & _believed_floor(lp), config,
                            _seen_before(state, idx, col, fresh))
             if config.reseed_outliers > 0 else None)
    return bad_epoch, bad_f, burst


def _believed_floor(lp: FloatArray) -> NDArray[np.bool_]:
    """The hypotheses (n, H) (both modes) of each node's believed floor under ``lp`` (n, H):
    the floor more probable than every other together (probability above 1/2); none where
    no floor is."""
    fp = floor_probabilities(lp)
    lead = np.argmax(fp, axis=1)
    lead = np.where(fp[np.arange(fp.shape[0]), lead] > 0.5, lead, -1)
    return np.tile(np.arange(fp.shape[1]), 2)[None, :] == lead[:, None]


def _seen_before(state: TrackerState, idx: NDArray, col: NDArray | None,
                 fresh: NDArray | None) -> NDArray[np.bool_] | None:
    """(n, H, M): whether each hypothesis of the nodes ``idx`` has updated with each column's
    learned link (``col``) before (``TrackerState.link_slot`` holds its mechanism or -1 for an
    outlier; a link a new anchor took (``fresh``): not); None without the learned links."""
    if col is None:
        return None
    return np.isfinite(_gather(np.where(fresh[:, None, :], np.nan, state.link_slot[idx]), col))


def _outlier_burst(slot: NDArray, mask: NDArray, link_w: FloatArray | None, run: NDArray,
                   config: TrackerConfig, seen: NDArray | None = None) -> NDArray[np.bool_]:
    """``TrackerConfig.reseed_outliers``: of the hypotheses ``run`` (n, H) (updated this
    epoch, of the floor the node believes after this epoch's evidence), those in good
    standing before this epoch (at least ``reseed_min_links`` and four ranges, every present
    link's learned outlier probability
    ``1 - exp(link_w[..., 0])`` below ``edge_retry_eps``; the prior's where ``link_w`` is
    None) that call at least ``reseed_outliers`` present links (``mask`` (n, M)) outliers in
    this epoch's update (``slot`` (n, H, M) -1) among the links they have updated with
    before (``seen`` (n, H, M); None: any link): a link new to the track is no sign that
    the track went wrong. A hypothesis that calls MOST of its present links outliers is left
    to the ordinary count (``reseed_epochs`` bad epochs): then every floor fits badly (the
    data jumped), and re-seeding the believed floor alone first lets the others' stale
    tracks lead (a 16 m jump: the true floor's track back after 10 epochs instead of 3)."""
    m = mask[:, None, :]
    good = _good_standing(m, None if link_w is None else link_w[..., 0],
                          max(config.reseed_min_links, 4), config)
    n_meas = mask.sum(axis=-1)
    out = m & (slot < 0)
    good = good & (2 * np.sum(out, axis=-1) <= n_meas[:, None])  # most: the ordinary rule's
    lost = out if seen is None else out & seen
    return run & good & (np.sum(lost, axis=-1) >= config.reseed_outliers)


def _learned(state: TrackerState, idx: NDArray, sub: Links, t_ns: NDArray, n_meas: NDArray,
             config: TrackerConfig, inputs: tuple, fit: tuple) -> dict:
    """The learned link state of the nodes ``idx`` after their measurement update
    (:func:`_track_update`): ``inputs`` = :func:`_link_inputs`' (state, column, anchor table,
    seen), ``fit`` = the update's (run, mean, cov, slot, mixture log-weight, NIS, residual)
    per hypothesis and link."""
    lk, col, tab, seen = inputs
    run, x, p, slot, lw, nis_h, res = fit
    # every link's share of the hypothesis' evidence: its mixture log-weight (mechanism
    # prior, SNR, or the outlier's density) and its range term at the fit
    ev_link = np.where(sub.mask[:, 0][:, None, :], lw - 0.5 * np.nan_to_num(nis_h), 0.0)
    fits = None  # the hypotheses whose state fits most ranges (link_learn_minority)
    if config.link_learn_minority:
        n_out = np.sum(sub.mask[:, 0][:, None, :] & (slot < 0), axis=-1)
        fits = 2 * n_out < n_meas[:, None]
    new = dict(learn(lk, col, run, x, p, slot, sub, t_ns[idx], config, ev_link,
                     _link_misfit(nis_h, res, sub.var[:, 0], config), fits),
               link_anchor=tab, link_seen_ns=seen)
    if _counts_unexplained(config):  # (off: nothing reads them, nothing counted)
        new["unexplained"], new["redundant"] = count_unexplained(
            state.unexplained[idx], state.redundant[idx], new["link_fit"], col,
            sub.mask[:, 0], n_meas, config)
    return new


#: Unless ``TrackerConfig.deficit_exact``: a floor whose probability is below this value and
#: whose modes have no evidence deficit counted is tested every ``deficit_quiet_every``
#: ``deficit_period_s``
#: (on the emulator's ``large30`` 80 % of the due floors were below it, with 97 % of the
#: deficits found; docs/tracking_evidence.md "Session 25: a cheaper deficit test").
DEFICIT_QUIET_P = 1e-3


def _deficit_tested(state: TrackerState, idx: NDArray, sub: Links, due: NDArray,
                    n_meas: NDArray, update: tuple, building, config: TrackerConfig, link_w,
                    fam_gate) -> NDArray:
    """The evidence-deficit counts (n, H) of the nodes ``idx`` after this epoch's tests
    (:func:`_deficit_counts`) of their floors ``due`` (n, F) that are TRACKING with enough
    ranges for a re-seed; ``update`` = (prior mean, prior cov, updated, and the posterior
    mean, evidence, slots, residuals) of :func:`_track_update`; ``due`` (:func:`_deficit_due`:
    2 at a quiet floor's boundary). Unless ``deficit_exact``, a floor below
    :data:`DEFICIT_QUIET_P` whose modes have no deficit counted is tested every
    ``deficit_quiet_every`` periods only."""
    if not config.deficit_exact:
        quiet = ((floor_probabilities(state.log_prob[idx]) < DEFICIT_QUIET_P)
                 & ~(state.deficit_count[idx].reshape(idx.size, 2, -1) > 0).any(axis=1))
        due = np.where(quiet, due == 2, due > 0)
    due = ((due > 0) & (state.status[idx] == TrackStatus.TRACKING)[:, None]
           & (n_meas >= _reseed_ranges(config))[:, None])
    return _deficit_counts(update, sub, due, state.deficit_count[idx], n_floors_of(state),
                           building, config, link_w, fam_gate)


def _deficit_schedule(prev_ns: NDArray[np.int64], t_ns: NDArray[np.int64],
                      origin_ns: NDArray[np.int64], n_floors: int, config: TrackerConfig
                      ) -> NDArray[np.int8] | None:
    """:func:`_deficit_due` with the settings of ``config`` (0: not due; 1: due; 2: due, a
    quiet floor's too), None where the deficit test is off (``deficit_nats`` 0)."""
    if config.deficit_nats <= 0:
        return None
    return _deficit_due(prev_ns, t_ns, origin_ns, n_floors, config.deficit_period_s,
                        not config.deficit_exact, config.deficit_quiet_every)


def _deficit_due(prev_ns: NDArray[np.int64], t_ns: NDArray[np.int64],
                 origin_ns: NDArray[np.int64], n_floors: int, period_s: float,
                 level_phase: bool = False, every: int = 2) -> NDArray[np.int8]:
    """The floors (n, F) due for an evidence-deficit test this epoch
    (``TrackerConfig.deficit_period_s``): floor ``f``'s boundaries at ``origin + k T - f T /
    F`` (measurement time relative to the node's ``origin_ns``, as :func:`_refresh_due`)
    passed between the node's previous time ``prev_ns`` and ``t_ns`` (n,). ``level_phase``:
    at ``- f T / (2 F)``, the phase of the floor's level hypothesis in :func:`_refresh_due`
    (with ``dormant_refresh_s`` = ``deficit_period_s`` a dormant level hypothesis is
    refreshed, so updated, in the epoch its floor is due). Returns 0 (not due), 1 (due) or
    2 (due, and a boundary ``k`` with ``k % every == 0`` among those passed: the quiet floors'
    test, :data:`DEFICIT_QUIET_P`)."""
    period = max(round(period_s * 1e9), 1)
    phase = (np.arange(n_floors, dtype=np.int64) * period) // (
        2 * n_floors if level_phase else n_floors)
    k_t = _period_index(t_ns[:, None], origin_ns, phase, period)
    k_p = _period_index(prev_ns[:, None], origin_ns, phase, period)
    due = k_t > k_p
    every = max(int(every), 1)
    return due.astype(np.int8) + (due & ((k_t % every == 0) | (k_t - k_p >= every)))


def _deficit_counts(update: tuple, sub: Links, due: NDArray[np.bool_],
                    count: NDArray[np.int_], n_floors: int, building, config: TrackerConfig,
                    link_w: FloatArray | None, fam_gate: NDArray | None) -> NDArray[np.int_]:
    """The new evidence-deficit counts (n, H) (``TrackerConfig.deficit_nats``) of nodes with
    this epoch's update ``update`` = (predicted priors ``m0``, ``c0`` (n, H, ...), the updated
    hypotheses ``run``, their posterior means, log-evidences, slots and residuals) and their
    links ``sub``: for every floor ``due`` (n, F) a snapshot of the floor
    (:func:`diffpos.tracking.model.snapshot`) at ``s``, and for both its modes
    (``deficit_level_only``: the level one) ``D = log Z(s, P) - log Z(x, P)``, the same
    measurement update (:func:`_update_at`, the learned link weights ``link_w``, family gate
    ``fam_gate``) from the prior ``N(x, P)`` with its position moved to ``s`` against from
    ``N(x, P)`` (a hypothesis not updated this epoch is updated for the test, its state
    unchanged). Unless ``deficit_exact``: only the modes updated this epoch are tested (the
    others keep their counts), and a floor is snapshot (from the grid's best cell only)
    only where a tested mode's :func:`_deficit_bound` exceeds ``deficit_nats``; the other
    tested modes' ``D`` counts as below it. The count of a tested hypothesis is one more where
    ``D > deficit_nats``, else 0; the others keep theirs. Per node: no row reads another's."""
    m0, c0, run, x, ev, slot, res = update
    rows, fl = np.nonzero(due)
    out = count.copy()
    if rows.size == 0:
        return out
    modes = 1 if config.deficit_level_only else 2  # the level mode only, or both
    rr = np.repeat(rows, modes)
    cc = np.stack([fl, fl + n_floors][:modes], axis=1).ravel()
    x1, e_own, s1, r1 = x[rr, cc], np.where(run[rr, cc], ev[rr, cc], np.nan), slot[rr, cc], \
        res[rr, cc]
    k = np.flatnonzero(~run[rr, cc] & config.deficit_exact)
    if k.size:
        x1[k], _, e_own[k], s1[k], _, r1[k], _ = _update_at(
            m0[rr[k], cc[k]], c0[rr[k], cc[k]], sub, rr[k], cc[k], n_floors, building, config,
            None, link_w, fam_gate)
    starts = None
    if not config.deficit_exact:  # the updated modes whose deficit may exceed the level
        low = _deficit_bound(m0[rr, cc], c0[rr, cc], x1, s1, r1, sub, rr,
                             config) <= config.deficit_nats
        out[rr[low & run[rr, cc]], cc[low & run[rr, cc]]] = 0
        keep = ~low & run[rr, cc]  # (a mode not updated this epoch: not tested, count kept)
        big = keep.reshape(-1, modes).any(axis=1)  # the floors snapshot
        rows, fl, rr, cc, e_own = rows[big], fl[big], rr[keep], cc[keep], e_own[keep]
        starts = 1
        if rows.size == 0:
            return out
    xs, _, _, _, _ = snapshot(sub.take(rows), fl[:, None], building, config, starts)
    xs = xs[np.searchsorted(np.flatnonzero(big), np.flatnonzero(keep) // modes)] if (
        not config.deficit_exact) else np.repeat(xs, modes, axis=0)
    xm = m0[rr, cc].copy()
    xm[:, :3] = xs[:, 0, :3]
    e_snap = _update_at(xm, c0[rr, cc], sub, rr, cc, n_floors, building, config, None, link_w,
                        fam_gate)[2]
    with np.errstate(invalid="ignore"):
        gap = e_snap - e_own
    out[rr, cc] = np.where(gap > config.deficit_nats, count[rr, cc] + 1, 0)
    return out


def _deficit_bound(x0: FloatArray, p0: FloatArray, x1: FloatArray, slot: NDArray,
                   res: FloatArray, sub: Links, rr: NDArray, config: TrackerConfig
                   ) -> FloatArray:
    """The deficit test's pre-check (P,) from a hypothesis' own update this epoch (prior
    ``N(x0, p0)``, posterior mean ``x1``, slots ``slot`` and residuals ``res`` (P, M) of the
    links ``sub`` of rows ``rr``): ``(q + c) / 2 + n_out w``, ``q`` the posterior's prior
    term ``(x1 - x0)' p0^-1 (x1 - x0)``, ``c`` the fitted links' chi-square ``res^2 / var``
    at the range variance (the mechanisms' extra variance left out: larger), ``n_out`` the
    links it calls outliers and ``w = log(outlier_span_m / outlier_weight)`` an outlier's
    cost. With the same mechanisms the evidence of a prior ``N(c, P)`` is a Gaussian in the
    centre ``c`` peaking at the ranges' own fit, and ``2 log Z(x, P)`` falls short of that
    peak by ``q + c`` minus the fit's residual chi-square: ``(q + c) / 2`` bounds ``D`` for
    any centre (linearised, same mechanisms); a mode that fits an outlier link gains at most
    about its cost ``w``. Not a bound where the snapshot's mechanisms carry a larger prior
    weight than the track's (measured: 12 of 217 tests with ``D`` > 9.2 on the main command
    seed 7 were under it, docs/tracking_evidence.md "Session 25: a cheaper deficit test")."""
    d = x1 - x0
    q = np.einsum("pi,pi->p", d, np.linalg.solve(p0, d[..., None])[..., 0])
    present = sub.mask[rr, 0]
    fitted = present & (slot >= 0)
    with np.errstate(invalid="ignore"):
        c = np.sum(np.where(fitted, res * res / sub.var[rr, 0], 0.0), axis=1)
    w = np.log(config.outlier_span_m / config.outlier_weight)
    return 0.5 * (q + c) + w * np.sum(present & (slot < 0), axis=1)


def _link_inputs(state: TrackerState, idx: NDArray, sub: Links, t_ns: NDArray,
                 m0: FloatArray, c0: FloatArray, n_meas: NDArray[np.int_],
                 config: TrackerConfig) -> tuple:
    """The learned link inputs of the nodes ``idx`` (``sub``: their links; ``m0``, ``c0``:
    their hypotheses' priors): their learned arrays (copies, the links a new anchor took
    forgotten), every column's link, the new link table and times
    (:func:`~diffpos.tracking.evidence.match_links`), the link weights
    (:func:`~diffpos.tracking.evidence.learned_weights`; with ``link_learn_unexplained`` the
    prior's for the nodes whose track has not learned an out-of-model channel) and the
    family gate (:func:`_family_gate`; None: ``max_order`` 2)."""
    col, tab, seen, fresh = match_links(state.link_anchor[idx], state.link_seen_ns[idx],
                                        sub.anchors[:, 0], sub.mask[:, 0], t_ns[idx],
                                        config.link_match_m)
    lk = {k: getattr(state, k)[idx] for k in LINK_FIELDS}  # copies
    reset_links(lk, np.arange(idx.size), fresh)
    learned = None
    if _counts_unexplained(config):  # the track's channel has out-of-model arrivals
        need = None if config.link_learn_unexplained else (  # else only the gate reads it:
            (n_meas >= config.family_learned_links) & (n_meas < config.family_min_links))
        learned = _learned_families(state.unexplained[idx], state.redundant[idx], n_meas,
                                    config, need)
    link_w = learned_weights(lk, col, m0, c0, sub, t_ns[idx], config, SNR_SIGMA_DB,
                             SNR_SPAN_DB, ~learned if config.link_learn_unexplained else None)
    if config.link_eps_node:  # the node's outlier weight of every link (node_weights)
        link_w = node_weights(link_w, ~np.isfinite(state.dormant_llr[idx])
                              if config.link_eps_node_awake else None)
    if config.link_eps_posterior > 0:  # the node's model-averaged outlier weight
        link_w = posterior_weights(link_w, state.log_prob[idx],
                                   _borrowers(state, idx, link_w, sub, t_ns, n_meas, config))
    fam_gate = None
    if config.max_order > DEFAULT_ORDER:  # the families of the links the 18 did not explain
        settled = None  # family_worst_outliers_settled: not contested within floor_contest_s
        if config.family_worst_outliers and config.family_worst_outliers_settled:
            settled = (t_ns[idx] - state.lead_ns[idx]) * 1e-9 >= config.floor_contest_s
        fam_gate = _family_gate(lk, col, n_meas, config, sub.mask[:, 0],
                                learned if config.family_learned_links > 0 else None, settled)
    return lk, col, tab, seen, link_w, fam_gate, fresh


def _borrowers(state: TrackerState, idx: NDArray, link_w: FloatArray, sub: Links,
               t_ns: NDArray, n_meas: NDArray[np.int_], config: TrackerConfig) -> NDArray:
    """Who borrows the node's model-averaged outlier weight (``link_eps_posterior``): the
    nodes ``idx`` (n,) with enough ranges ``n_meas``; with ``link_eps_lend_below_p`` only those
    whose published floor was below that probability (:func:`_prior_published_top`); with ``link_eps_lend_contest_s`` only
    those whose floor was contested (``TrackerState.lead_ns``) within that many seconds; with
    ``link_eps_lend_fewer`` only their hypotheses (n, H) that have learned fewer present links
    as outliers than the node's most probable one
    (:func:`~diffpos.tracking.evidence.fewer_outliers`)."""
    use = n_meas >= config.link_eps_posterior
    if config.link_eps_lend_below_p > 0:
        use = use & (_prior_published_top(state, idx, t_ns, n_meas, config)
                     < config.link_eps_lend_below_p)
    if config.link_eps_lend_contest_s > 0:
        use = use & ((t_ns[idx] - state.lead_ns[idx]) * 1e-9 <= config.link_eps_lend_contest_s)
    if not config.link_eps_lend_fewer:
        return use
    return use[:, None] & fewer_outliers(link_w, state.log_prob[idx], sub.mask[:, 0])


def _prior_published_top(state: TrackerState, idx: NDArray, t_ns: NDArray,
                         n_meas: NDArray[np.int_], config: TrackerConfig) -> FloatArray:
    """The most probable floor's published probability (n,) of the nodes ``idx`` from their
    state before this epoch (:func:`published_floor_probabilities` with the one-link-out
    robustness, the contest's tempering at this epoch's time ``t_ns`` and the model doubt at
    this epoch's range count ``n_meas``; ``TrackerConfig.link_eps_lend_below_p``)."""
    lp = state.log_prob[idx]
    prob = np.exp(lp)
    doubt = (model_doubt(lp, state.link_out[idx], state.link_all[idx], config, n_meas, prob)
             if config.floor_model_doubt and config.link_learn else None)
    contested = (t_ns[idx] - state.lead_ns[idx]) * 1e-9 < config.floor_contest_s
    return np.max(published_floor_probabilities(
        lp, config, prob, link_ev=state.link_ev[idx], link_all=state.link_all[idx], doubt=doubt,
        contested=contested), axis=1)


def _prev_slots(state: TrackerState, idx: NDArray, col: NDArray | None, fresh: NDArray | None,
                config: TrackerConfig) -> FloatArray | None:
    """The previous mechanism (n, H, M) every hypothesis of the nodes ``idx`` chose for every
    column's learned link (``col``; a link a new anchor took (``fresh``): none), NaN: none;
    None unless ``TrackerConfig.mechanism_switch_p`` (with ``mechanism_prior_min_links``)
    and the learned links are on."""
    if (config.mechanism_switch_p <= 0.0 or config.mechanism_prior_min_links <= 0
            or col is None):
        return None
    return _gather(np.where(fresh[:, None, :], np.nan, state.link_slot[idx]), col)


def _kept_slots(link_slot: FloatArray, fresh: NDArray, col: NDArray, run: NDArray,
                slot: NDArray, mask: NDArray) -> FloatArray:
    """``link_slot`` (n, H, L) (a copy) with the links a new anchor took forgotten and every
    present link of the updated hypotheses ``run`` (n, H) set to its chosen ``slot`` (n, H, M;
    -1: outlier)."""
    out = np.where(fresh[:, None, :], np.nan, link_slot)
    for m in range(col.shape[1]):  # columns hold distinct links
        ok = mask[:, m] & (col[:, m] >= 0)
        rows, hyps = np.nonzero(run & ok[:, None])
        out[rows, hyps, col[rows, m]] = slot[rows, hyps, m]
    return out


def _counts_unexplained(config: TrackerConfig) -> bool:
    """Whether the tracker counts its nodes' unexplained epochs (someone reads them:
    ``family_learned_links``, ``link_learn_unexplained``)."""
    return config.family_learned_links > 0 or config.link_learn_unexplained


def _learned_families(unexplained: FloatArray, redundant: FloatArray,
                      n_meas: NDArray[np.int_], config: TrackerConfig,
                      need: NDArray[np.bool_] | None = None) -> NDArray[np.bool_]:
    """The nodes (n,) whose track has learned that its channel has first arrivals out of the
    path model (``config.family_learned_links``): its counts of unexplained epochs favour an
    unknown rate over the model's own (:func:`diffpos.tracking.evidence.unexplained_log_odds`
    > 0). ``need`` (n,): only these nodes are evaluated, the others False (the family gate
    reads it only for nodes with ``family_learned_links`` to ``family_min_links`` - 1
    ranges); None: every node."""
    out = np.zeros(n_meas.shape, dtype=bool)
    rows = np.arange(n_meas.size) if need is None else np.flatnonzero(need)
    if rows.size:
        out[rows] = unexplained_log_odds(unexplained[rows], redundant[rows],
                                         np.maximum(n_meas[rows], 4), config) > 0.0
    return out


def _family_gate(lk: dict, col: NDArray[np.int_], n_meas: NDArray[np.int_],
                 config: TrackerConfig, present: NDArray[np.bool_] | None = None,
                 learned: NDArray[np.bool_] | None = None,
                 settled: NDArray[np.bool_] | None = None) -> NDArray[np.bool_]:
    """The links (n, H, M) whose out-of-model component includes the extra families
    (``config.family_gate``, ``family_history``, ``family_min_links``;
    :mod:`diffpos.tracking.families`) from the nodes' learned arrays ``lk`` before this
    update, their links ``col`` (:func:`~diffpos.tracking.evidence.match_links`) and numbers
    of ranges ``n_meas`` (n,); ``learned`` (n,): the nodes that get the families from
    ``family_learned_links`` ranges (:func:`_learned_families`; None: none); ``settled`` (n,):
    the nodes whose worst link may be an outlier (``family_worst_outliers_settled``; None:
    every node, as ``family_worst_outliers`` says)."""
    if config.family_gate == "outlier":
        gate = _gather(lk["link_out"], col) > 0.5
    else:
        gate = ~(_gather(lk["link_fit"], col) <= config.nis_limit)
    fitted = np.ones(gate.shape, bool)
    if config.family_history > 0:  # a misfit after this many real updates with the link
        f = config.link_forget
        need = config.family_history if f >= 1.0 else (1.0 - f ** config.family_history) / (1.0 - f)
        fitted = _gather(lk["link_all"], col) >= need * (1.0 - 1e-9)
        gate &= fitted
    worst = (_worst_link(lk, col, n_meas, gate, fitted, present, config, settled)
             if config.family_worst_min_links > 0 else None)
    scarce = (few_ranges(n_meas, config.family_few_links, config.min_anchors_tracking)
              if config.family_few_links > 0 else None)  # few ranges: SNR-scored families
    if config.family_min_links > 0:
        enough = n_meas >= config.family_min_links
        if learned is not None:  # fewer ranges where the track learned the channel has them
            enough |= learned & (n_meas >= config.family_learned_links)
        if scarce is not None:  # few ranges: scored with their SNR (family_log_weight)
            enough |= scarce
        gate &= enough[:, None, None]
        fitted &= enough[:, None, None]
    offered = fitted if config.family_select else gate  # every fitted link, or the misfits
    rich = None
    if config.family_select_min_links > 0:  # many ranges: every fitted link, no minority rule
        rich = (n_meas >= config.family_select_min_links)[:, None, None]
        offered = np.where(rich, fitted, offered)
    if scarce is not None:  # few ranges: every fitted link too (SNR-scored there)
        rich = scarce[:, None, None] if rich is None else rich | scarce[:, None, None]
        offered = np.where(scarce[:, None, None], fitted, offered)
    if config.family_minority:  # most ranges misfit: the state is wrong, not the links
        mis = gate if present is None else gate & present[:, None, :]
        few = (2 * np.sum(mis, axis=-1) < n_meas[:, None])[..., None]
        offered = offered & (few if rich is None else few | rich)
    return offered if worst is None else offered | worst


def _worst_link(lk: dict, col: NDArray[np.int_], n_meas: NDArray[np.int_],
                gate: NDArray[np.bool_], fitted: NDArray[np.bool_],
                present: NDArray[np.bool_] | None, config: TrackerConfig,
                settled: NDArray[np.bool_] | None = None) -> NDArray[np.bool_]:
    """``TrackerConfig.family_worst_min_links``: the links (n, H, M) offered the extra
    families at the nodes with at least that many ranges but fewer than ``family_min_links``
    (``n_meas`` (n,)): per hypothesis its ONE worst-fitted present link among those the 18
    mechanisms fitted, the largest finite ``link_fit`` of its last real update (a link it
    called an outlier, inf, or never fitted, NaN, does not count: an outlier's families are
    the misfit gate's), where that is at least ``family_worst_nis`` and the link has a fit
    history (``fitted``, :func:`_family_gate`'s); with ``family_minority`` none where the
    hypothesis misfits half of the ranges or more (``gate``: the misfits with a fit history,
    before the ``family_min_links`` rule). With ``family_worst_outliers`` a link the last real
    update called an outlier (``link_fit`` inf) is the worst of all (ahead of every finite
    NIS), at the nodes ``settled`` (n,) only where given."""
    fit = _gather(lk["link_fit"], col)
    if config.family_worst_outliers:  # an outlier link is the worst of all (NIS inf)
        take = fit == np.inf
        if settled is not None:
            take &= settled[:, None, None]
        fit = np.where(take, np.finfo(np.float64).max, fit)
    fit = np.where(np.isfinite(fit), fit, -np.inf)
    if present is not None:
        fit = np.where(present[:, None, :], fit, -np.inf)
    w = np.argmax(fit, axis=-1)[..., None]
    one = np.zeros(fit.shape, bool)
    np.put_along_axis(one, w, np.take_along_axis(fit, w, axis=-1) >= config.family_worst_nis,
                      axis=-1)
    four = (n_meas >= config.family_worst_min_links) & (n_meas < config.family_min_links)
    out = one & fitted & four[:, None, None]
    if config.family_minority:
        mis = gate if present is None else gate & present[:, None, :]
        out &= (2 * np.sum(mis, axis=-1) < n_meas[:, None])[..., None]
    return out


def warm_tracking() -> float:
    """Compile the tracker's kernels (or load them from numba's on-disk cache) on tiny inputs:
    ~4-6 s the first time on a machine, then ~0.2-0.3 s (the callers in
    :mod:`diffpos.tracking.model` pass C-contiguous writable arrays, so one signature per
    kernel). Returns the seconds it took. (The fusion's warm-up runs a throw-away tracker
    update, which does the same.)"""
    t0 = time.perf_counter()
    planes = (3.0, 3.0, 0.9, 1.5, -20.0, 20.0, 22.0)
    anc = np.array([[[0.0, -15.0, 1.0]]])
    warm_model(planes, anc)
    warm_grid(planes, anc)
    warm_iekf(planes, anc)
    warm_snr_cache()
    warm_snr_term()
    warm_update()
    warm_evidence()
    return time.perf_counter() - t0
