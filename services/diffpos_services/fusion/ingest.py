"""What the fusion keeps per anchor, and the checks of incoming values (docs/bad_input.md).

- :class:`AnchorStream`: one anchor's state history, liveliness, counters, recent sequence
  numbers and clock bookkeeping;
- :class:`RejectLog`: each rejection reason logged once per source (counts in diagnostics);
- :class:`Track`: a node's last good fixes (warm start, velocity);
- :func:`bad_value`, :func:`bad_state`, :func:`bad_batch`: ``(reason, detail)`` of an
  implausible range, anchor state or range batch, or ``None``; :func:`batch_all_good`: the
  vectorised check that a whole range batch is plausible (its columns as kept, or ``None``);
- :func:`count_releases`: why each released epoch was released (diagnostics).
"""

from __future__ import annotations

import collections
import logging
import math

import numpy as np

from diffpos.alignment import EpochBook, PendingEpoch, epoch_reports
from diffpos.anchor_history import StateHistory
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.logs import log_event
from diffpos_services.wire import messages as M

__all__ = ["AnchorStream", "RejectLog", "Track", "bad_batch", "bad_state", "bad_value",
           "batch_all_good", "count_releases"]


class AnchorStream:
    """What the fusion knows of one anchor: its state history, liveliness, counters and the
    stream bookkeeping of the bad-input checks (sequence numbers, clock reference)."""

    __slots__ = ("alive", "history", "id", "last_rx_wall_ns", "last_t_ns", "lost_wall_ns",
                 "ranges", "resync", "seqs", "states", "token")

    def __init__(self, anchor_id: str, max_extrapolation_ns: int, history_ns: int) -> None:
        self.id = anchor_id
        # states kept for history_ns (a backlog of unsolved epochs still finds its states)
        self.history = StateHistory(4096, max_extrapolation_ns=max_extrapolation_ns,
                                    max_age_ns=history_ns)
        self.alive = True
        self.token = False
        self.lost_wall_ns: int | None = None
        self.states = 0
        self.ranges = 0
        self.last_t_ns: int | None = None  # newest accepted measurement time [ns]
        self.last_rx_wall_ns = 0  # ingestion wall time of the last accepted message [ns]
        # recent sequence numbers per key kind ("state", "ranges", "range/<node>")
        self.seqs: dict[str, collections.deque[int]] = {}
        # (count, last t_ns) of consecutive time rejections (clock jump detection)
        self.resync: tuple[int, int] = (0, 0)

    def reset_stream(self) -> None:
        """Forget sequence numbers and the clock reference (the anchor restarted)."""
        self.seqs.clear()
        self.last_t_ns = None
        self.resync = (0, 0)


class RejectLog:
    """Log each rejection reason once per source (an anchor, or the bus for bad keys).

    ``seen[(key, reason)]`` counts every rejection per key (bounded number of keys); only
    the first rejection of each ``(source, reason)`` is logged, so a flood of bad messages
    gives a handful of log lines (their counts are in the diagnostics).
    """

    def __init__(self, logger: logging.Logger, *, max_keys: int = 10_000,
                 max_logged: int = 1_000) -> None:
        self.logger = logger
        self.max_keys = max_keys
        self.max_logged = max_logged
        self.seen: dict[tuple[str, str], int] = {}
        self.logged: set[tuple[str, str]] = set()
        self.suppressed = False

    def __call__(self, key: str, reason: str, detail: str = "", *, source: str = "bus",
                 level: int = logging.WARNING) -> None:
        k = (key, reason)
        n = self.seen.get(k)
        if n is not None:
            self.seen[k] = n + 1
        elif len(self.seen) < self.max_keys:
            self.seen[k] = 1
        s = (source, reason)
        if s in self.logged:
            return
        if len(self.logged) >= self.max_logged:
            if not self.suppressed:
                self.suppressed = True
                log_event(self.logger, logging.WARNING, "too many distinct rejection sources: "
                          "further ones are only counted in the diagnostics",
                          limit=self.max_logged)
            return
        self.logged.add(s)
        log_event(self.logger, level, f"rejected {reason} from {source} (logged once; "
                  "counted in diagnostics.rejected)", key=key[:200], reason=reason,
                  source=source, detail=detail[:300])


class Track:
    """Last good fixes of a node (warm start and velocity for motion compensation).

    Positions and velocities are lists of 3 floats (per-fix updates in plain Python cost a
    fraction of the same arithmetic on 3-element numpy arrays; the values are identical).
    """

    __slots__ = ("cold_ns", "pos", "t_ns", "try_pos", "vel")

    def __init__(self) -> None:
        self.t_ns: int | None = None
        self.pos: list[float] | None = None
        self.vel: list[float] | None = None
        self.cold_ns: int | None = None  # measurement time of the last cold (multi-start) solve
        self.try_pos: list[float] | None = None  # its position, whatever its status

    def update(self, t_ns: int, pos: list[float]) -> None:
        p0 = self.pos
        if self.t_ns is not None and p0 is not None and t_ns > self.t_ns:
            dt = (t_ns - self.t_ns) * 1e-9
            if dt < 1.0:
                v = [(pos[0] - p0[0]) / dt, (pos[1] - p0[1]) / dt, (pos[2] - p0[2]) / dt]
                w = self.vel
                self.vel = v if w is None else [0.5 * w[0] + 0.5 * v[0], 0.5 * w[1] + 0.5 * v[1],
                                                0.5 * w[2] + 0.5 * v[2]]
            else:
                self.vel = None
        self.t_ns, self.pos = t_ns, list(pos)



# ------------------------------------------------------------------------ value checks
def bad_value(cfg: FusionConfig, range_m, sigma_m, snr_db) -> tuple[str, str] | None:
    """``(reason, detail)`` if a range, its sigma or SNR is implausible, else None."""
    if range_m is not None:
        if not math.isfinite(range_m):
            return "nonfinite", "range_m"
        if range_m > cfg.max_range_m:
            return "absurd_value", (f"range_m={range_m:g} outside [0, max_range_m="
                                    f"{cfg.max_range_m:g}] m")
    if sigma_m is not None and not (cfg.min_sigma_m <= sigma_m <= cfg.max_sigma_m):
        if not math.isfinite(sigma_m):
            return "nonfinite", "sigma_m"
        return "absurd_value", (f"sigma_m={sigma_m:g} outside [{cfg.min_sigma_m:g}, "
                                f"{cfg.max_sigma_m:g}] m")
    if snr_db is not None and not -300.0 <= snr_db <= 300.0:
        if not math.isfinite(snr_db):
            return "nonfinite", "snr_db"
        return "absurd_value", f"snr_db={snr_db:g} outside [-300, 300] dB"
    return None


def bad_state(cfg: FusionConfig, msg: M.AnchorState) -> tuple[str, str] | None:
    """``(reason, detail)`` if an anchor state is implausible, else None."""
    vals = (*msg.position_m, *msg.velocity_m_s, *msg.position_sigma_m,
            msg.velocity_sigma_m_s, msg.range_rate_hz)
    if not all(math.isfinite(v) for v in vals):
        return "nonfinite", "position_m, velocity_m_s or a sigma is not finite"
    if max(abs(v) for v in msg.position_m) > cfg.max_coordinate_m:
        return "absurd_value", (f"position_m={list(msg.position_m)} beyond "
                                f"max_coordinate_m={cfg.max_coordinate_m:g} m")
    if math.hypot(*msg.velocity_m_s) > cfg.max_speed_m_s:
        return "absurd_value", (f"velocity_m_s={list(msg.velocity_m_s)} faster than "
                                f"max_speed_m_s={cfg.max_speed_m_s:g} m/s")
    if max(msg.position_sigma_m) > cfg.max_sigma_m or msg.velocity_sigma_m_s > cfg.max_sigma_m:
        return "absurd_value", f"a sigma exceeds max_sigma_m={cfg.max_sigma_m:g}"
    return None


def bad_batch(cfg: FusionConfig, msg: M.RangeBatch) -> tuple[str, str] | None:
    """``(reason, detail)`` if a range batch is malformed as a whole, else None."""
    n = len(msg.node_ids)
    if not (len(msg.range_m) == len(msg.sigma_m) == len(msg.snr_db) == n):
        return "schema", "range_batch lists differ in length"
    if n > cfg.max_nodes:
        return "oversized", f"{n} nodes > max_nodes={cfg.max_nodes}"
    if len(set(msg.node_ids)) != n:
        return "schema", "range_batch node_ids has duplicates"
    return None


def batch_all_good(cfg: FusionConfig, msg: M.RangeBatch, nodes: set[str],
                   allowed_nodes: frozenset[str] | None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The columns ``(range_m, sigma_m, snr_db)`` of ``msg`` as float arrays, as the per-entry
    checks of :meth:`FusionCore._add_batch` would keep them, when every entry passes them:
    finite values within the configured limits, or no detection at all (range, sigma and SNR
    all null: kept as range NaN (``None`` in a :class:`~diffpos.alignment.RangeEntry`),
    sigma 1, SNR -inf, as :meth:`FusionCore._entry` does), only known (``nodes``) and allowed
    nodes; checked with a few vectorised operations instead of per entry. ``None``: some
    entry needs the per-entry checks."""
    ids, r, sg, snr = msg.node_ids, msg.range_m, msg.sigma_m, msg.snr_db
    if not ids or not nodes.issuperset(ids) or (
        allowed_nodes is not None and not allowed_nodes.issuperset(ids)
    ):
        return None
    missing = r.count(None)
    if missing and (sg.count(None) != missing or snr.count(None) != missing
                    or any(sg[i] is not None or snr[i] is not None
                           for i, v in enumerate(r) if v is None)):
        return None  # a partly null entry: checked per entry
    if not missing and (None in sg or None in snr):
        return None
    # (None -> NaN; the undetected entries are left out of the checks)
    if missing == len(r):
        return np.full(missing, np.nan), np.ones(missing), np.full(missing, -math.inf)
    cols = np.array((r, sg, snr), dtype=np.float64)  # (3, n)
    det = np.fromiter((v is not None for v in r), bool, len(r)) if missing else None
    checked = cols if det is None else cols[:, det]
    lo, hi = checked.min(axis=1).tolist(), checked.max(axis=1).tolist()
    # NaN compares False: a non-finite value fails these and takes the checked path
    if not (hi[0] <= cfg.max_range_m and lo[0] >= 0.0 and lo[1] >= cfg.min_sigma_m
            and hi[1] <= cfg.max_sigma_m and lo[2] >= -300.0 and hi[2] <= 300.0):
        return None
    ra, sa, na = cols
    if det is not None:  # the undetected entries as _entry keeps them
        sa[~det] = 1.0
        na[~det] = -math.inf
    return ra, sa, na


def count_releases(book: EpochBook, released: list[PendingEpoch], live: frozenset[str],
                   rel: collections.Counter) -> None:
    """Count in ``rel`` why each released epoch was released (``complete``: every live anchor
    reported; ``passed``: the missing ones' clocks passed its end; ``watermark``;
    ``wall_fallback``), from the epochs' columns."""
    if not released:
        return
    align = book.config
    ids = sorted(live)
    reported, count = epoch_reports(released, ids)
    complete = reported.all(axis=1)
    epoch = np.fromiter((pe.epoch for pe in released), np.int64, len(released))
    end = (epoch + 1) * align.epoch_period_ns + align.clock_tolerance_ns
    never = -(2**62)  # an anchor without a time has not passed any end
    latest = np.array([book.latest_t_ns.get(a, never) for a in ids], np.int64)
    passed = ~complete & (count >= align.min_reports) & (
        reported | (latest[None, :] >= end[:, None])).all(axis=1)
    watermark = ~complete & ~passed & (epoch <= book.closed_upto)
    n_complete, n_passed = int(complete.sum()), int(passed.sum())
    n_watermark = int(watermark.sum())
    for reason, n in (("complete", n_complete), ("passed", n_passed),
                      ("watermark", n_watermark),
                      ("wall_fallback", len(released) - n_complete - n_passed - n_watermark)):
        if n:
            rel[reason] += n
