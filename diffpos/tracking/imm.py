"""Motion model and IMM interaction of the tracker (:mod:`diffpos.tracking.tracker`).

Transition probabilities between the hypotheses (floor x vertical mode), the mixing of the
hypotheses' Gaussians into each other's priors and their NCV prediction; all vectorised over
nodes, deterministic.

* **Mode transitions** (Markov, per floor; the vertical modes are described in
  :mod:`diffpos.tracking.tracker`): vertical -> level at ``r_out = v_stairs / H`` (a flight
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
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.tracking.state import (
    FloatArray,
    TrackerConfig,
    TrackerState,
    hypothesis_floor,
    hypothesis_vertical,
)

__all__ = ["process_noise"]


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
    adj, other, same_mode, to_floor, same_floor, start = _layout(nf)[:6]
    fl, vert = hypothesis_floor(nf), hypothesis_vertical(nf)
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
    cross_f, cross_j = _to_floors(move, jump, fl, to_floor, same_mode)
    own = same_floor * np.where(same_mode > 0, 1.0 - p_switch[..., None], p_switch[..., None])
    own = own * stay[..., None]
    # entering the vertical mode moves probability but not the level track's state: the
    # vertical hypothesis keeps its own track (free height), which is what accumulates the
    # evidence of a climb (restarted from the level track every epoch it could not: measured
    # on other-building, a descending walker's level track stayed pinned at the nominal height
    # and the track was lost to a mirror floor)
    return own + cross_f + cross_j, own * (1.0 - start) + cross_f, cross_j


class _Layout(NamedTuple):
    """The hypotheses' fixed transition layout of a floor count (float 0/1 unless said)."""

    adj: FloatArray  #: (H, F) hypothesis h's floor next to floor g
    other: FloatArray  #: (H, F) another floor
    same_mode: FloatArray  #: (H, H)
    to_floor: FloatArray  #: (F, H) floor g -> hypothesis h
    same_floor: FloatArray  #: (H, H)
    start: FloatArray  #: (H, H) level -> vertical of any floor
    start_b: NDArray[np.bool_]  #: (H, H) ``start`` as bool: level f -> vertical g
    stop: NDArray[np.bool_]  #: (H, H) vertical f -> level g


@functools.lru_cache(maxsize=64)
def _layout(n_floors: int) -> _Layout:
    """The :class:`_Layout` of ``n_floors`` floors (read-only, built once, not on every
    tracker call)."""
    fl, vert = hypothesis_floor(n_floors), hypothesis_vertical(n_floors)
    g = np.arange(n_floors)
    start_b = ~vert[:, None] & vert[None, :]
    out = _Layout((np.abs(fl[:, None] - g[None, :]) == 1).astype(np.float64),
                  (fl[:, None] != g[None, :]).astype(np.float64),
                  (vert[:, None] == vert[None, :]).astype(np.float64),
                  (fl[None, :] == g[:, None]).astype(np.float64),
                  (fl[:, None] == fl[None, :]).astype(np.float64),
                  start_b.astype(np.float64), start_b, vert[:, None] & ~vert[None, :])
    for a in out:
        a.flags.writeable = False
    return out


def _to_floors(move: FloatArray, jump: FloatArray, fl, to_floor: FloatArray,
               same_mode: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``einsum("nhf,fk->nhk", a, to_floor) * same_mode`` of ``move`` and ``jump`` (N, H, F):
    ``to_floor`` has one 1 per column (floor ``fl[k]``), so each sum is one product ``a * 1``
    plus exact zeros: ``a[..., fl]``, the same values bit for bit (finite ``a``; a non-finite
    one would spread over every column through ``inf * 0``: the einsum then)."""
    if np.isfinite(move).all() and np.isfinite(jump).all():
        return move[..., fl] * same_mode, jump[..., fl] * same_mode
    return (np.einsum("nhf,fk->nhk", move, to_floor) * same_mode,
            np.einsum("nhf,fk->nhk", jump, to_floor) * same_mode)


def _floor_band(building, n_floors: int, config: TrackerConfig) -> tuple[FloatArray, FloatArray]:
    zf = building.floor_z_m(np.arange(n_floors))
    return zf + config.z_margin_m, zf + building.floor_height_m - config.z_margin_m


def _mix(state: TrackerState, dt_s: FloatArray, building, config: TrackerConfig,
         n_meas: NDArray[np.int_] | None = None
         ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """IMM interaction: mixed means/covariances and predicted log-probabilities (N, H), and
    the predicted probability each hypothesis receives from the *other* hypotheses through
    physical transitions (adjacent-floor moves, mode switches; not the floor jump), (N, H):
    what wakes a dormant hypothesis. ``n_meas`` (N,): the ranges of the epoch predicted to
    (``stairs_follow_min_links``; None: a prediction without ranges)."""
    h = state.log_prob.shape[1]
    nf = h // 2
    fl = hypothesis_floor(nf)
    pi, pi_move, pi_jump = _transitions(state.mean, state.cov, dt_s, building, config)
    lw = state.log_prob
    mx = lw.max(axis=1, keepdims=True)
    w = np.exp(lw - mx)  # (N, H)
    joint = w[:, :, None] * pi  # (N, H, H)
    c = joint.sum(axis=1)  # (N, H)
    lo, hi = _floor_band(building, nf, config)
    lay = _layout(nf)
    start, stop = lay.start_b, lay.stop  # (H, H): level f -> vertical g, vertical f -> level g
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
        if config.stairs_follow > 0:
            _follow_leader(x0, p0, np.argmax(lw, axis=1), nf, config.stairs_follow,
                           _follow_nodes(state, config, n_meas), config.stairs_follow_m)
    log_pred = np.log(np.maximum(c, 1e-300)) + mx
    log_pred = log_pred - _logsumexp(log_pred)[:, None]
    inflow = np.einsum("nf,nfg->ng", w, (pi - pi_jump) * (1.0 - np.eye(h)))
    return x0, p0, log_pred, inflow / c.sum(axis=1, keepdims=True)


#: the horizontal components of a hypothesis' state (x, y, vx, vy) and the vertical (z, vz)
_HORIZ = np.array([0, 1, 3, 4])
_VERT = np.array([2, 5])


def _follower_mask(lead: NDArray[np.int_], n_floors: int, scope: int) -> NDArray[np.bool_]:
    """``TrackerConfig.stairs_follow``: the hypotheses (N, H) that take the horizontal state
    of their node's leading hypothesis ``lead`` (N,): the other mode of the leader's floor
    (``scope`` bit 1) and the vertical modes of the floors next to it (bit 2)."""
    fl, vert = hypothesis_floor(n_floors), hypothesis_vertical(n_floors)
    lf = fl[lead][:, None]
    out = np.zeros((lead.size, 2 * n_floors), bool)
    if scope & 1:
        out |= (fl[None, :] == lf) & (np.arange(2 * n_floors)[None, :] != lead[:, None])
    if scope & 2:
        out |= vert[None, :] & (np.abs(fl[None, :] - lf) == 1)
    return out


def _follow_nodes(state: TrackerState, config: TrackerConfig,
                  n_meas: NDArray[np.int_] | None) -> NDArray[np.bool_] | None:
    """The nodes (N,) whose hypotheses may follow their leader (None: every node):
    ``stairs_follow_settled_s``, those whose most probable floor was last contested
    (``TrackerState.lead_ns``) at least that long before their last update;
    ``stairs_follow_min_links``, those with at least that many ranges ``n_meas`` in the epoch
    predicted to (none without ``n_meas``); ``stairs_follow_after_s``, those initialised
    (``TrackerState.refresh_origin_ns``) at least that long before their last update."""
    out = None
    if config.stairs_follow_settled_s > 0:
        out = (state.t_ns - state.lead_ns) * 1e-9 >= config.stairs_follow_settled_s
    if config.stairs_follow_after_s > 0:
        old = (state.t_ns - state.refresh_origin_ns) * 1e-9 >= config.stairs_follow_after_s
        out = old if out is None else out & old
    if config.stairs_follow_min_links > 0:
        enough = (np.zeros(state.t_ns.shape, bool) if n_meas is None
                  else np.asarray(n_meas) >= config.stairs_follow_min_links)
        out = enough if out is None else out & enough
    return out


def _follow_leader(x0: FloatArray, p0: FloatArray, lead: NDArray[np.int_], n_floors: int,
                   scope: int, nodes: NDArray[np.bool_] | None = None,
                   far_m: float = 0.0) -> None:
    """Give the hypotheses of :func:`_follower_mask` (in place, the select-mixed priors ``x0``
    (N, H, 6), ``p0`` (N, H, 6, 6)) the horizontal state of their node's leading hypothesis
    ``lead`` (only the ``nodes`` (N,) when given, only followers whose horizontal mean is
    more than ``far_m`` from the leader's): x, y, vx, vy and their covariance block;
    each keeps its own height and vertical speed (its own z block) and none of its
    horizontal-vertical correlation (zero cross terms: a block-diagonal covariance of two
    valid blocks stays positive definite).

    Why: the walker's horizontal position does not depend on its vertical mode, nor on the
    floor it is about to reach on the stairs. A mode that keeps its own horizontal track
    while the data follow the leader drifts metres off (measured on Sionna's paper
    building: the climbing walker's vertical mode 3-7 m off while its level mode was at
    0.1 m), so when the walker starts up the stairs no hypothesis is there to take the
    climb. The leader's floor and the other floors' level modes keep their own tracks (a
    leader on a mirror floor must not drag the true floor's level track with it)."""
    follow = _follower_mask(lead, n_floors, scope)
    if nodes is not None:  # only these nodes (stairs_follow_settled_s)
        follow &= nodes[:, None]
    rr, hh = np.nonzero(follow)
    src = lead[rr]
    if far_m > 0:  # only the followers that drifted away (stairs_follow_m)
        far = np.hypot(*(x0[rr, hh, :2] - x0[rr, src, :2]).T) > far_m
        rr, hh, src = rr[far], hh[far], src[far]
    if rr.size == 0:
        return
    x0[rr[:, None], hh[:, None], _HORIZ[None, :]] = x0[rr[:, None], src[:, None], _HORIZ[None, :]]
    ph = p0[rr, src][:, _HORIZ[:, None], _HORIZ[None, :]]
    pv = p0[rr, hh][:, _VERT[:, None], _VERT[None, :]]
    pn = np.zeros((rr.size, 6, 6))
    pn[:, _HORIZ[:, None], _HORIZ[None, :]] = ph
    pn[:, _VERT[:, None], _VERT[None, :]] = pv
    p0[rr, hh] = pn


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
