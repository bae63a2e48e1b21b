"""The fusion's batched solve in named steps (used by :meth:`FusionCore._solve`).

gather arrays -> prepare the batch -> warm/cold/retry solve policy -> messages:

- :func:`gather`: the ready epochs as ``(B, M)`` arrays (ranges, sigmas, times, masks) and
  every anchor's self-reported position at each range's own time;
- :func:`prepare`: warm starts from the node tracks, motion compensation, effective sigmas;
- :func:`solve_batch`: the estimator of ``method``; for D-NLS the warm fixes, then the cold
  (multi-start) fixes of rows without a warm start or whose warm fix failed (at most once per
  ``cold_retry_period_s`` of measurement time per node);
- :func:`exclusion_groups`: why each anchor of each row was not used, grouped by pattern so a
  batch builds its anchor lists once per pattern (the messages themselves are built by the
  core, which owns the counters and tracks).

Every step is a function of its arguments (no clock, no network).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from diffpos.alignment import PendingEpoch, compensate_node_motion, effective_sigma_m, epoch_columns
from diffpos.estimators import ippa, lls
from diffpos.estimators.dnls import solver as dnls_solver  # attribute lookup: tests count calls
from diffpos.estimators.result import ExclusionReason, FixStatus
from diffpos.geometry import window_edge_path
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.wire import messages as M

__all__ = ["GOOD_STATUS", "Batch", "Prepared", "Results", "exclusion_groups", "gather",
           "prepare", "solve_batch"]

_NEG = -(2**62)
#: statuses of a usable fix (a position is published and the node's track updated)
GOOD_STATUS = (int(FixStatus.OK), int(FixStatus.OK_UNVERIFIED))
#: Fastest plausible node (a responder running) [m/s]. A track velocity above it comes from a
#: wrong fix (an unverified LLS/IPPA fix hundreds of metres off): it is neither extrapolated
#: nor used for motion compensation, which would shift the ranges by (J . v) dt, e.g.
#: 4.4 km/s x 25 ms = 110 m, turning 24 m ranges negative (issue 15, item 14).
MAX_TRACK_SPEED_M_S = 15.0
_MAX_SPEED2 = MAX_TRACK_SPEED_M_S**2
# fixed exclusion reasons by code (see exclusion_groups); 3 = the estimator's reason
_FIXED = {1: "NOT_DETECTED", 2: "NO_ANCHOR_STATE", 4: "NOT_USED", 5: "ANCHOR_LOST",
          6: "NOT_REPORTED"}
_REASON_NAMES = {int(r): r.name for r in ExclusionReason}
_GATE_CODES = (int(ExclusionReason.RAIM), int(ExclusionReason.PREGATE_SHORTER_THAN_LOS))


@dataclass
class Batch:
    """``B`` epochs x ``M`` anchors (columns ``names``), as gathered from the epochs."""

    names: list[str]
    t: np.ndarray  # (B, M) int64 [ns] measurement time of each range
    rng: np.ndarray  # (B, M) [m], NaN where not detected
    sig: np.ndarray  # (B, M) [m]
    reported: np.ndarray  # (B, M) bool: the anchor reported for this epoch
    detected: np.ndarray  # (B, M) bool: ... with a range
    pub_wall: np.ndarray  # (B, M) int64 [ns] publish wall time
    apos: np.ndarray  # (B, M, 3) [m] anchor position at the range's time
    asig: np.ndarray  # (B, M, 3) [m] its sigma
    have_state: np.ndarray  # (B, M) bool: an anchor state was available
    use: np.ndarray  # (B, M) bool: detected and with a state
    t_ref: np.ndarray  # (B,) int64 [ns] mean time of the used ranges
    dt_s: np.ndarray  # (B, M) [s] range time - t_ref
    snr: np.ndarray  # (B, M) [dB] SNR of each detected range, NaN where none
    #: (B, M) bool: the anchor reported no path and has a state (its position in ``apos``);
    #: None unless gathered with ``silent`` (TrackerConfig.silent_anchor_nats)
    silent: np.ndarray | None = None


@dataclass
class Prepared:
    """Solver inputs of a :class:`Batch`."""

    x0: np.ndarray  # (B, 3) warm start, NaN rows: cold
    safe_apos: np.ndarray  # (B, M, 3) anchor positions, 0 where unused
    rng_in: np.ndarray  # (B, M) motion-compensated ranges, 0 where unused
    sig_eff: np.ndarray  # (B, M) effective sigmas, 1 where unused
    warm: np.ndarray  # (B,) bool


class Results:
    """The fixes of a batch as columns (filled by :meth:`put`); the verdict texts are built
    only when read (:attr:`msg`, at publish time), from the columns of every stored fix."""

    def __init__(self, b: int, m: int) -> None:
        self.pos = np.full((b, 3), np.nan)
        self.cov = np.full((b, 3, 3), np.nan)
        self.peb = np.full(b, np.nan)
        self.zb = np.full(b, np.nan)
        self.status = np.full(b, int(FixStatus.TOO_FEW_ANCHORS))
        self.resid = np.full((b, m), np.nan)
        self.used = np.zeros((b, m), bool)
        self.reason = np.zeros((b, m), int)
        self._parts: list[tuple[np.ndarray, Any]] = []
        self._msg: list[str] | None = None

    def put(self, rows: np.ndarray, fix: Any) -> None:
        """Store the :class:`~diffpos.estimators.FixResult` ``fix`` of ``rows`` (a later fix
        of the same rows replaces an earlier one, also in :attr:`msg`)."""
        self.pos[rows], self.cov[rows] = fix.position_m, fix.covariance_m2
        self.peb[rows], self.zb[rows] = fix.peb_m, fix.z_bound_m
        self.status[rows], self.resid[rows] = fix.status, fix.residuals_m
        self.used[rows], self.reason[rows] = fix.used, fix.exclusion_reason
        self._parts.append((np.asarray(rows), fix))
        self._msg = None

    @property
    def msg(self) -> list[str]:
        """Each row's verdict text ("" where no fix was stored), built on first read."""
        if self._msg is None:
            msg = [""] * self.pos.shape[0]
            for rows, fix in self._parts:  # in put order: later fixes overwrite
                for r, text in zip(rows.tolist(), fix.messages(), strict=True):
                    msg[r] = text
            self._msg = msg
        return self._msg


# ------------------------------------------------------------------------------- gather
def gather(epochs: list[PendingEpoch], ids: list[str], anchors: dict[str, Any],
           silent: bool = False) -> Batch:
    """The epochs' ranges as ``(B, M)`` arrays over the anchor columns ``ids``, from the epoch
    book's columns (:func:`~diffpos.alignment.epoch_columns`: no Python object per range);
    anchor positions from each anchor's state history (``anchors[id].history``) at the range
    times; the reference times. ``silent``: also the positions of the anchors that reported
    no path (``Batch.silent``; the tracker's ``silent_anchor_nats``)."""
    c = epoch_columns(epochs, ids)
    col = {a: j for j, a in enumerate(ids)}
    apos, asig, have_state = _anchor_positions(col, anchors, c.t,
                                               c.reported if silent else c.detected)
    use = c.detected & have_state
    t_ref, dt_s = _reference_times(c.t, c.reported, use)
    return Batch(list(col), c.t, c.range_m, c.sigma_m, c.reported, c.detected, c.t_pub_wall,
                 apos, asig, have_state & c.detected, use, t_ref, dt_s,
                 np.where(np.isfinite(c.snr_db), c.snr_db, np.nan),
                 (c.reported & ~c.detected & have_state) if silent else None)


def _anchor_positions(col: dict[str, int], anchors: dict[str, Any], t: np.ndarray,
                      detected: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Anchor positions, their sigmas and availability at each detected range's own time."""
    b, m = t.shape
    apos = np.full((b, m, 3), np.nan)
    asig = np.zeros((b, m, 3))
    have_state = np.zeros((b, m), bool)
    for a, j in col.items():
        rows = np.flatnonzero(detected[:, j])
        if rows.size == 0 or a not in anchors:
            continue
        p, s, ok = anchors[a].history.at(t[rows, j])
        apos[rows, j], asig[rows, j], have_state[rows, j] = p, s, ok
    return apos, asig, have_state


def _reference_times(t: np.ndarray, reported: np.ndarray,
                     use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each row's mean time of the used ranges [ns] and each range's offset from it [s]."""
    n_use = use.sum(axis=1)
    # relative to a per-row base (int64 sums of absolute ns times would overflow beyond 4
    # anchors)
    base = np.max(np.where(reported, t, _NEG), axis=1)
    rel = np.where(use, t - base[:, None], 0).astype(np.float64)
    t_ref = base + np.round(rel.sum(axis=1) / np.maximum(n_use, 1)).astype(np.int64)
    dt_s = np.where(use, (t - t_ref[:, None]) * 1e-9, 0.0)
    return t_ref, dt_s


# ------------------------------------------------------------------------------ prepare
def _start_points(epochs: list[PendingEpoch], tracks: Any, t_ref: np.ndarray,
                  cfg: FusionConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Warm start (NaN: cold) and velocity of each row from its node's track.

    The rows with a start are collected as Python lists (the tracks' positions and
    velocities are lists of floats, the times Python ints) and written into the arrays at
    once: the same values as per-row numpy item assignment, without its fixed cost per row."""
    b = len(epochs)
    x0 = np.full((b, 3), np.nan)
    vel = np.zeros((b, 3))
    has_vel = np.zeros(b, bool)
    if not tracks:
        return x0, vel, has_vel
    rows: list[int] = []
    starts: list[list[float]] = []
    moving: list[int] = []
    velocities: list[list[float]] = []
    max_age = cfg.warm_start_max_age_s * 1e9
    period_ns = round(cfg.cold_retry_period_s * 1e9)
    for i, (pe, t) in enumerate(zip(epochs, t_ref.tolist(), strict=True)):
        tr = tracks.get(pe.node_id)
        if tr is None:
            continue
        if tr.t_ns is not None and abs(t - tr.t_ns) <= max_age:
            v, p = tr.vel, tr.pos
            if v is not None and v[0] * v[0] + v[1] * v[1] + v[2] * v[2] <= _MAX_SPEED2:
                dt = (t - tr.t_ns) * 1e-9
                moving.append(i)
                velocities.append(v)
                p = [p[0] + v[0] * dt, p[1] + v[1] * dt, p[2] + v[2] * dt]
            rows.append(i)
            starts.append(p)
        elif tr.try_pos is not None and tr.cold_ns is not None and 0 <= t - tr.cold_ns < period_ns:
            # no good fix lately, but a cold solve within the retry period: start from its
            # result instead of paying for another multi-start every epoch
            rows.append(i)
            starts.append(tr.try_pos)
    if rows:
        x0[rows] = starts
    if moving:
        vel[moving] = velocities
        has_vel[moving] = True
    return x0, vel, has_vel


def prepare(batch: Batch, epochs: list[PendingEpoch], tracks: Any,
            cfg: FusionConfig) -> Prepared:
    """Warm starts, motion-compensated ranges and effective sigmas of ``batch``."""
    use = batch.use
    x0, vel, has_vel = _start_points(epochs, tracks, batch.t_ref, cfg)
    comp = has_vel & cfg.motion_compensation
    safe_apos = np.where(use[..., None], batch.apos, 0.0)
    rng = batch.rng
    if np.any(comp):
        jac = window_edge_path(
            safe_apos,
            np.where(comp[:, None], x0, 0.0)[:, None, :],
            window_height_m=cfg.window_height_m,
            delta_m=cfg.delta_m,
            edge_x_m=cfg.edge_x_m,
        ).jacobian
        rng = np.where(
            comp[:, None] & use, compensate_node_motion(rng, jac, vel[:, None, :], batch.dt_s),
            rng
        )
    speed_sigma = np.where(comp, cfg.velocity_sigma_m_s, cfg.node_speed_sigma_m_s)
    los = (
        np.where(np.isfinite(x0[:, None, :]), x0[:, None, :], np.array([0.0, 5.0, 6.0]))
        - safe_apos
    )
    sig_eff = effective_sigma_m(batch.sig, batch.asig, los, batch.dt_s, speed_sigma[:, None])
    sig_eff = np.where(use, sig_eff, 1.0)
    rng_in = np.where(use, rng, 0.0)
    return Prepared(x0, safe_apos, rng_in, sig_eff, np.isfinite(x0).all(axis=1))


# -------------------------------------------------------------------------------- solve
def solve_batch(batch: Batch, prep: Prepared, epochs: list[PendingEpoch], tracks: Any,
                cfg: FusionConfig, gating: Any) -> Results:
    """The fixes of every row: ``lls``/``ippa`` in one call; D-NLS warm, then cold.

    Updates the tracks' cold-solve bookkeeping (``cold_ns``, ``try_pos``).
    """
    b = len(epochs)
    res = Results(b, len(batch.names))
    use = batch.use
    if cfg.method != "dnls":
        solver = lls.lls if cfg.method == "lls" else ippa.ippa
        res.put(np.arange(b), solver(prep.safe_apos, prep.rng_in, prep.sig_eff, mask=use))
        return res
    common: dict[str, Any] = dict(
        window_height_m=cfg.window_height_m,
        delta_m=cfg.delta_m,
        edge_x_m=cfg.edge_x_m,
        gating=gating,
        exclusion_starts=cfg.dnls_exclusion_starts,
    )
    if cfg.dnls_exclusion_search == "exhaustive":  # as before 2026-12-06 (old recordings)
        common.update(exclusion_ftol=None, exclusion_recheck_ratio=None, exclusion_bound=None)
    warm = prep.warm
    rows_w = np.flatnonzero(warm)
    if rows_w.size:
        fix = dnls_solver.dnls(prep.safe_apos[rows_w], prep.rng_in[rows_w], prep.sig_eff[rows_w],
                       mask=use[rows_w], x0_m=prep.x0[rows_w], **common)
        res.put(rows_w, fix)
    retry = _cold_retries(warm, res.status, epochs, tracks, batch.t_ref, cfg)
    rows_c = np.flatnonzero(~warm | retry)
    if rows_c.size:
        fix = dnls_solver.dnls(prep.safe_apos[rows_c], prep.rng_in[rows_c], prep.sig_eff[rows_c],
                       mask=use[rows_c], **common)
        res.put(rows_c, fix)
        for i in rows_c:
            tr = tracks[epochs[i].node_id]
            tr.cold_ns = int(batch.t_ref[i])
            tr.try_pos = res.pos[i].tolist() if np.all(np.isfinite(res.pos[i])) else None
    return res


def _cold_retries(warm: np.ndarray, status: np.ndarray, epochs: list[PendingEpoch],
                  tracks: Any, t_ref: np.ndarray, cfg: FusionConfig) -> np.ndarray:
    """Rows whose warm fix failed and whose node is due a cold (multi-start) retry.

    A warm fix that failed is re-solved from all starts (re-acquisition after a wrong basin),
    but at most once per cold_retry_period_s of measurement time per node: on realistic
    channels a third of the fixes fail every epoch for reasons a cold start does not change,
    and the multi-start re-solve costs ~10x a warm fix. Measurement time (not the wall clock)
    keeps replays deterministic.
    """
    period_ns = round(cfg.cold_retry_period_s * 1e9)
    retry = np.zeros(len(epochs), bool)
    for i in np.flatnonzero(warm & ~np.isin(status, GOOD_STATUS)):
        tr = tracks[epochs[i].node_id]
        if tr.cold_ns is None or t_ref[i] - tr.cold_ns >= period_ns:
            retry[i] = True
            tr.cold_ns = int(t_ref[i])
    return retry


# ----------------------------------------------------------------------------- messages
def gated_count(batch: Batch, res: Results) -> int:
    """Ranges excluded by the gating (RAIM or the LoS pre-gate)."""
    gated = (batch.reported & batch.detected & batch.have_state & ~res.used
             & ((res.reason == _GATE_CODES[0]) | (res.reason == _GATE_CODES[1])))
    return int(gated.sum())


def _row_bytes(a: np.ndarray) -> list[bytes]:
    """Each row of the 2-D array ``a`` as bytes (equal rows, equal bytes)."""
    if a.shape[1] == 0:
        return [b""] * a.shape[0]
    a = np.ascontiguousarray(a)
    return a.view(np.dtype((np.void, a.dtype.itemsize * a.shape[1]))).ravel().tolist()


def exclusion_groups(batch: Batch, res: Results, lost: set[str]
                     ) -> tuple[list[int], list[tuple[list[int], list[str], list[M.Exclusion], bool]]]:
    """Each row's group of identical (used anchors, exclusion reasons), and per group
    ``(used column indices, used anchor ids, exclusions, every anchor used)``.

    Rows with the same used set and exclusion reasons share their anchor lists (most rows of
    an epoch batch use every anchor): built once per pattern, not per fix.
    """
    names = batch.names
    m = len(names)
    reported, detected, have_state = batch.reported, batch.detected, batch.have_state
    res_used, res_reason = res.used, res.reason
    lost_col = np.array([a in lost for a in names], bool)
    # reason codes: 0 used/absent-not-live, 1 NOT_DETECTED, 2 NO_ANCHOR_STATE, 3 gating
    # reason (from res_reason), 4 NOT_USED, 5 ANCHOR_LOST, 6 NOT_REPORTED
    code = np.zeros(reported.shape, np.int8)
    code[~reported & ~lost_col[None, :]] = 6
    code[~reported & lost_col[None, :]] = 5
    code[reported & ~res_used] = 4
    code[reported & detected & have_state & ~res_used & (res_reason != 0)] = 3
    code[reported & detected & ~have_state] = 2
    code[reported & ~detected] = 1
    why = np.where(code == 3, 16 + res_reason, code) * ~res_used
    pattern = np.concatenate([res_used.astype(np.int64), why], axis=1)
    # group ids in order of first appearance, each group's first row its representative
    # (each row's bytes as a dict key: no sort)
    seen: dict[bytes, int] = {}
    first: list[int] = []
    group_l = []
    for i, r in enumerate(_row_bytes(pattern)):
        g = seen.get(r)
        if g is None:
            g = seen[r] = len(first)
            first.append(i)
        group_l.append(g)
    reps = np.array(first, np.intp)
    shared = []
    for row in pattern[reps].tolist():
        used_idx = [j for j in range(m) if row[j]]
        excluded = [
            M.Exclusion(names[j], _REASON_NAMES[c - 16] if c >= 16 else _FIXED[c])
            for j, c in enumerate(row[m:]) if c
        ]
        shared.append((used_idx, [names[j] for j in used_idx], excluded, len(used_idx) == m))
    return group_l, shared
