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
* **Dormant hypotheses** (:mod:`diffpos.tracking.dormant`, ``TrackerConfig.dormant``): once
  the data has decided against a hypothesis its measurement update is skipped (it is
  predicted and mixed as every other, its evidence stood in for by its last likelihood
  ratio to the node's best) until a refresh (every ``dormant_refresh_s``), the mixing, a
  poor fit of the node's best hypothesis or a node that is not TRACKING wakes it. Measured
  (28 lockstep runs of 20 s, default and other-building): floor 91.5 % with dormant
  hypotheses against 91.3 % without, about 3.7 of a 5-floor building's 10 hypotheses updated
  per node-epoch (the rules and the measurements: :mod:`diffpos.tracking.dormant`).

Modules: :mod:`diffpos.tracking.state` (config, state, output types, hypothesis layout),
:mod:`diffpos.tracking.imm` (motion, transitions, mixing, prediction of the Gaussians),
:mod:`diffpos.tracking.dormant` (the epoch's measurement update with dormant hypotheses),
:mod:`diffpos.tracking.model` (measurement model, snapshot initialisation); every public
name is importable from here.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

# the pieces in the role modules; the ``x as x`` names are re-exported for the tests and any
# caller that imported them from here before the split
from diffpos.tracking.dormant import _dormant_log_p as _dormant_log_p
from diffpos.tracking.dormant import _refresh_due as _refresh_due
from diffpos.tracking.dormant import _track_update
from diffpos.tracking.dormant import _update_pairs as _update_pairs
from diffpos.tracking.imm import _mix, _propagate, process_noise
from diffpos.tracking.imm import _transition_matrix as _transition_matrix
from diffpos.tracking.links import Links
from diffpos.tracking.model import snapshot, snapshot_init
from diffpos.tracking.state import (
    SNR_CACHE_LINKS,
    SNR_CACHE_SLOTS,
    FloatArray,
    TrackerConfig,
    TrackerState,
    TrackOutput,
    TrackStatus,
    floor_probabilities,
    hypothesis_floor,
    hypothesis_vertical,
    published_floor_probabilities,
)
from diffpos.tracking.state import n_floors_of as n_floors_of

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
    "published_floor_probabilities",
    "update",
]


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
                         np.float32))


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


def _publish(state: TrackerState, mech: NDArray, resid: FloatArray,
             config: TrackerConfig | None = None) -> TrackOutput:
    config = TrackerConfig() if config is None else config
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
        floor_index=np.where(has, best, -1),
        floor_probabilities=published_floor_probabilities(state.log_prob, config, prob_h),
        status=state.status.copy(), mechanism=np.where(has[:, None], mech, -1),
        residual_m=np.where(has[:, None], resid, np.nan), nis=state.nis.copy())


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


def _with_rows(a: NDArray, idx: NDArray, v: NDArray) -> NDArray:
    """A new array: ``a`` with the rows ``idx`` (sorted, distinct) replaced by ``v`` (a new
    array itself); ``v`` when ``idx`` is every row (the SNR cache, ~7 KB per node: no copy
    of what is replaced anyway)."""
    if idx.size == a.shape[0]:
        return v
    out = a.copy()
    out[idx] = v
    return out


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
    snr_cache = (st.snr_node, st.snr_anchor, st.snr_pred)  # new arrays where updated
    last = st.last_fix_ns.copy()
    mech, resid = np.full((n, m), -1), np.full((n, m), np.nan)
    n_meas = links.mask[:, 0].sum(axis=1)
    live = ((status == TrackStatus.INITIALISING) | (status == TrackStatus.TRACKING)
            | (status == TrackStatus.COASTING))  # np.isin's values (np.isin: 1.5 % of a 1-node call)
    idx = np.flatnonzero(live & (n_meas > 0))
    if idx.size:
        new, ran, bad_epoch, bad_f, mech[idx], resid[idx] = _track_update(
            st, links, idx, t, inflow, dt_s, building, config)
        if "snr_node" in new:  # the SNR cache carried along (tracking_snr.snr_reuse_on)
            snr_cache = tuple(_with_rows(a, idx, new[key]) for a, key in
                              zip(snr_cache, ("snr_node", "snr_anchor", "snr_pred"),
                                  strict=True))
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
    if snr_cache[0] is st.snr_node:  # not updated: the new state owns its arrays
        snr_cache = tuple(a.copy() for a in snr_cache)
    new = TrackerState(mean=mean, cov=cov, log_prob=lp, status=status.astype(np.int8),
                       t_ns=st.t_ns.copy(), last_fix_ns=last, nis=nis, good=good, bad=bad,
                       floor_bad=floor_bad, dormant_llr=llr, updated_ns=upd,
                       below_epochs=below, refresh_origin_ns=origin, snr_node=snr_cache[0],
                       snr_anchor=snr_cache[1], snr_pred=snr_cache[2])
    return new, _publish(new, mech, resid, config)
