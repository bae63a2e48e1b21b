"""Fusion service: time-aligns anchor ranges, solves batched D-NLS with gating, publishes fixes.

Two layers:

- :class:`FusionCore` is the whole logic without any network: feed it raw ``(key, payload)``
  samples and liveliness events, call :meth:`FusionCore.step` and get
  :class:`~diffpos_services.wire.messages.PositionEstimate` messages back. The unit tests drive it
  in memory.
- :func:`run_fusion` wires it to Zenoh: callbacks only enqueue raw bytes; the main thread
  drains the queue, decodes, solves and publishes (no work on Zenoh's threads).

What the fusion assumes about time is documented in :mod:`diffpos.alignment`.

Bad input (docs/bad_input.md): every sample is checked before it is used (size, key, allow-
lists and id caps, JSON and schema, key/payload ids, plausible values, duplicate sequence
numbers, plausible time against the anchors' consensus). A rejected sample is counted in
``diagnostics.rejected[<reason>]`` and logged once per anchor and reason; ingestion never
raises on bad input, and a rejected sample changes nothing else.
"""

from __future__ import annotations

import collections
import logging
import math
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from diffpos.alignment import (
    EpochBook,
    PendingEpoch,
    RangeEntry,
    StateHistory,
    compensate_node_motion,
    effective_sigma_m,
)
from diffpos_services.bus.session import ZenohSettings, open_session
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.kit import log_event
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key

__all__ = ["FusionConfig", "FusionCore", "fusion_subscription", "run_fusion"]

_NEG = -(2**62)
_ACCOUNTED_BYTES = 2048  # samples above this size count against max_queued_bytes


def fusion_subscription(keys: Keys) -> str:
    """The one key expression the fusion subscribes to: ``diffpos/<site>/anchor/**``.

    One subscriber for states, ranges and range batches of every anchor, so each anchor's
    messages reach the fusion's queue in their publish order (with several subscribers an
    anchor's range could be queued before its state of the same instant, and the fusion then
    extrapolated the anchor from its previous state). It never matches ``truth/**`` (tested).
    Keys under ``anchor/`` that are not fusion inputs are counted as ``unexpected_key``.
    """
    return f"{keys.root}/anchor/**"


class _Anchor:
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


class _RejectLog:
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


class _Track:
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


class FusionCore:
    """Network-free fusion logic.

    Parameters
    ----------
    config : FusionConfig
    logger : logging.Logger, optional
    """

    def __init__(self, config: FusionConfig, *, logger: logging.Logger | None = None) -> None:
        from diffpos.estimators import GatingConfig

        self.config = config
        self.keys = Keys(config.site)
        self.align = config.alignment()
        self.book = EpochBook(self.align)
        self.anchors: dict[str, _Anchor] = {}
        self.tracks: dict[str, _Track] = collections.defaultdict(_Track)
        self.log = logger or logging.getLogger("diffpos.fusion")
        self.log_once = _RejectLog(self.log)
        self._allowed_anchors = None if config.anchors is None else frozenset(config.anchors)
        self._allowed_nodes = None if config.nodes is None else frozenset(config.nodes)
        self._nodes: set[str] = set()
        self._max_future_ns = round(config.max_future_s * 1e9)
        self._max_past_ns = round(config.max_past_s * 1e9)
        self._tref: int | None = None
        self._tref_dirty = True
        self._tref_wall_ns = 0
        self.gating = (
            GatingConfig(false_alarm_probability=config.false_alarm_probability)
            if config.gating
            else None
        )
        self.received: collections.Counter[str] = collections.Counter()
        self.rejected: collections.Counter[str] = collections.Counter()
        self.by_status: collections.Counter[str] = collections.Counter()
        self.gated = 0
        self.solved = 0
        self.published = 0
        self.seq = 0
        self.latencies_ns: collections.deque[int] = collections.deque(maxlen=4096)
        self._dec_state = M.decoder(M.AnchorState)
        self._dec_range = M.decoder(M.RangeMeasurement)
        self._dec_batch = M.decoder(M.RangeBatch)
        self.changed = False  # liveliness changed since the last diagnostics
        self._ready: collections.deque[PendingEpoch] = collections.deque()

    # ------------------------------------------------------------------ ingestion
    def _reject(self, key: str, reason: str, detail: str = "", *, source: str = "bus",
                count: int = 1) -> None:
        if count:
            self.rejected[reason] += count
        self.log_once(key, reason, detail, source=source)

    def _anchor(self, anchor_id: str) -> _Anchor:
        a = self.anchors.get(anchor_id)
        if a is None:
            a = self.anchors[anchor_id] = _Anchor(anchor_id, self.align.max_state_extrapolation_ns,
                                                  round(self.config.state_history_s * 1e9))
            log_event(self.log, logging.INFO, "anchor seen", anchor=anchor_id)
        return a

    def _anchor_refused(self, anchor_id: str) -> str | None:
        """Reason why data of this anchor is not accepted at all (or None)."""
        if self._allowed_anchors is not None and anchor_id not in self._allowed_anchors:
            return "unknown_anchor"
        if anchor_id not in self.anchors and len(self.anchors) >= self.config.max_anchors:
            return "too_many_anchors"
        return None

    def _node_refused(self, node_id: str) -> str | None:
        if self._allowed_nodes is not None and node_id not in self._allowed_nodes:
            return "unknown_node"
        if node_id not in self._nodes:
            if len(self._nodes) >= self.config.max_nodes:
                return "too_many_nodes"
            self._nodes.add(node_id)
        return None

    def _time_reference(self, now_wall_ns: int) -> int | None:
        """Consensus measurement time: the lower median of the newest accepted times of the
        anchors that delivered within the last 2 s (wall), if at least 3 did; else None."""
        if self._tref_dirty or now_wall_ns - self._tref_wall_ns > 100_000_000:
            fresh = sorted(
                a.last_t_ns for a in self.anchors.values()
                if a.alive and a.last_t_ns is not None
                and now_wall_ns - a.last_rx_wall_ns <= 2_000_000_000
            )
            self._tref = fresh[(len(fresh) - 1) // 2] if len(fresh) >= 3 else None
            self._tref_dirty = False
            self._tref_wall_ns = now_wall_ns
        return self._tref

    def _check_time(self, anchor: _Anchor | None, t_ns: int, now_wall_ns: int) -> str | None:
        """``time_future``/``time_past`` if ``t_ns`` is implausible, else None.

        Against the consensus of >= 3 fresh anchors (future: ``max_future_s``, past:
        ``max_past_s``); without a consensus, against the anchor's own newest time (a jump
        beyond ``max_past_s`` either way). ``time_resync_after`` consecutive rejections that
        progress consistently mean the anchor's clock really jumped (a new run, a clock
        fix): the anchor is re-synchronised and the message accepted.
        """
        ref = self._time_reference(now_wall_ns)
        if ref is not None:
            lo, hi = ref - self._max_past_ns, ref + self._max_future_ns
        elif anchor is not None and anchor.last_t_ns is not None:
            lo, hi = anchor.last_t_ns - self._max_past_ns, anchor.last_t_ns + self._max_past_ns
        else:
            return None
        if lo <= t_ns <= hi:
            if anchor is not None:
                if anchor.resync[0]:
                    anchor.resync = (0, 0)
                if ref is not None and anchor.last_t_ns is not None and anchor.last_t_ns > hi:
                    # the anchor's own newest time is implausible (e.g. its first message
                    # was far in the future): follow the consensus again
                    anchor.last_t_ns = t_ns
                    self.book.set_anchor_time(anchor.id, t_ns)
                    self._tref_dirty = True
            return None
        reason = "time_future" if t_ns > hi else "time_past"
        if anchor is not None:
            n, t_prev = anchor.resync
            consistent = n == 0 or 0 <= t_ns - t_prev <= self._max_future_ns
            n = n + 1 if consistent else 1
            if n >= self.config.time_resync_after:
                anchor.reset_stream()
                self._tref_dirty = True
                log_event(self.log, logging.WARNING, "anchor clock jumped: re-synchronised",
                          anchor=anchor.id, t_ns=t_ns, reference_ns=ref)
                return None
            anchor.resync = (n, t_ns)
        return reason

    def _check_seq(self, anchor: _Anchor | None, stream: str, seq: int) -> bool:
        """True if ``seq`` was already accepted on this stream (one of its last 16)."""
        if anchor is None:
            return False
        recent = anchor.seqs.get(stream)
        return recent is not None and seq in recent

    @staticmethod
    def _note_seq(anchor: _Anchor, stream: str, seq: int) -> None:
        recent = anchor.seqs.get(stream)
        if recent is None:
            recent = anchor.seqs[stream] = collections.deque(maxlen=16)
        recent.append(seq)

    def on_oversized(self, key: str, size: int) -> None:
        """Count a sample dropped for its size before it was even copied (see run_fusion)."""
        pk = parse_key(key)
        self.received[pk.kind if pk is not None else "other"] += 1
        src = f"anchor {pk.anchor_id}" if pk is not None and pk.anchor_id else "bus"
        self._reject(key, "oversized", f"{size} bytes > max_message_bytes="
                     f"{self.config.max_message_bytes}", source=src)

    def on_sample(self, key: str, payload: bytes, rx_wall_ns: int) -> None:
        """Ingest one data sample.

        Never raises on bad input: a rejected message is counted in
        ``diagnostics().rejected[reason]`` and logged once per anchor and reason (the reasons
        are listed in docs/bad_input.md). A message is accepted or rejected as a whole, except
        the entries of a RangeBatch, which are checked one by one.
        """
        pk = parse_key(key)
        if pk is None or pk.site != self.config.site or pk.kind not in (
            "anchor_state", "range", "range_batch"
        ):
            self.received["other"] += 1
            self._reject(key, "unexpected_key")
            return
        self.received[pk.kind] += 1
        aid = pk.anchor_id
        src = f"anchor {aid}"
        cfg = self.config
        if len(payload) > cfg.max_message_bytes:
            self._reject(key, "oversized", f"{len(payload)} bytes > max_message_bytes="
                         f"{cfg.max_message_bytes}", source=src)
            return
        why = self._anchor_refused(aid)
        if why is None and pk.kind == "range" and self._allowed_nodes is not None \
                and pk.node_id not in self._allowed_nodes:
            why = "unknown_node"
        if why is not None:
            self._reject(key, why, f"anchor {aid!r}, node {pk.node_id!r}", source=src)
            return
        try:
            if pk.kind == "range":
                msg = self._dec_range(payload)
            elif pk.kind == "range_batch":
                msg = self._dec_batch(payload)
            else:
                msg = self._dec_state(payload)
        except M.DecodeError as exc:
            self._reject(key, exc.reason, exc.detail, source=src)
            return
        if msg.anchor_id != aid or (pk.kind == "range" and msg.node_id != pk.node_id):
            self._reject(key, "key_mismatch", "ids in the payload differ from the key",
                         source=src)
            return
        anchor = self.anchors.get(aid)
        stream = "state" if pk.kind == "anchor_state" else (
            "ranges" if pk.kind == "range_batch" else pk.node_id)
        if pk.kind == "anchor_state":
            bad = self._bad_state(msg)
        elif pk.kind == "range":
            bad = self._bad_range(msg.range_m, msg.sigma_m, msg.snr_db)
            if bad is None:
                why = self._node_refused(msg.node_id)
                if why is not None:
                    self._reject(key, why, f"node {msg.node_id!r}", source=src)
                    return
        else:
            bad = self._bad_batch(msg)
        if bad is not None:
            self._reject(key, bad[0], bad[1], source=src)
            return
        if self._check_seq(anchor, stream, msg.seq):
            self._reject(key, "duplicate_seq", f"seq {msg.seq} already received on this key",
                         source=src)
            return
        why = self._check_time(anchor, msg.t_ns, rx_wall_ns)
        if why is not None:
            ref = self._tref
            self._reject(key, why, f"t_ns={msg.t_ns} vs reference "
                         f"{ref if ref is not None else anchor.last_t_ns} (allowed "
                         f"-{cfg.max_past_s} s / +{cfg.max_future_s} s)", source=src)
            return
        # accepted: from here on the message is used
        anchor = self._anchor(aid) if anchor is None else anchor
        self._note_seq(anchor, stream, msg.seq)
        anchor.last_rx_wall_ns = rx_wall_ns
        if anchor.last_t_ns is None or msg.t_ns > anchor.last_t_ns:
            anchor.last_t_ns = msg.t_ns
            self._tref_dirty = True
        # (a lost anchor comes back only with its liveliness token: in-flight data from a
        # killed process must not revive it)
        if pk.kind == "anchor_state":
            anchor.history.add(msg.t_ns, msg.position_m, msg.velocity_m_s,
                               msg.position_sigma_m, msg.velocity_sigma_m_s)
            anchor.states += 1
            self.book.note_anchor_time(anchor.id, msg.t_ns)
        elif pk.kind == "range":
            self._add_range(anchor, msg.node_id, msg.t_ns, msg.range_m, msg.sigma_m,
                            msg.snr_db, msg.t_pub_wall_ns, rx_wall_ns)
        else:
            self._add_batch(key, src, anchor, msg, rx_wall_ns)

    def _bad_value(self, range_m, sigma_m, snr_db) -> tuple[str, str] | None:
        cfg = self.config
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

    def _bad_range(self, range_m, sigma_m, snr_db) -> tuple[str, str] | None:
        return self._bad_value(range_m, sigma_m, snr_db)

    def _bad_state(self, msg: M.AnchorState) -> tuple[str, str] | None:
        cfg = self.config
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

    def _bad_batch(self, msg: M.RangeBatch) -> tuple[str, str] | None:
        n = len(msg.node_ids)
        if not (len(msg.range_m) == len(msg.sigma_m) == len(msg.snr_db) == n):
            return "schema", "range_batch lists differ in length"
        if n > self.config.max_nodes:
            return "oversized", f"{n} nodes > max_nodes={self.config.max_nodes}"
        if len(set(msg.node_ids)) != n:
            return "schema", "range_batch node_ids has duplicates"
        return None

    def _batch_all_good(self, msg: M.RangeBatch) -> bool:
        """True if every entry of ``msg`` passes the per-entry checks of :meth:`_add_batch`
        (no null, finite values within the configured limits, only known allowed nodes),
        checked with a few vectorised operations instead of per entry."""
        ids, r, sg, snr = msg.node_ids, msg.range_m, msg.sigma_m, msg.snr_db
        if not ids or None in r or None in sg or None in snr:
            return False
        if not self._nodes.issuperset(ids) or (
            self._allowed_nodes is not None and not self._allowed_nodes.issuperset(ids)
        ):
            return False
        cfg = self.config
        ra = np.array(r, dtype=np.float64)
        sa = np.array(sg, dtype=np.float64)
        na = np.array(snr, dtype=np.float64)
        # NaN compares False: a non-finite value fails these and takes the checked path
        return bool(
            (ra.max() <= cfg.max_range_m) & (ra.min() >= 0.0)
            & (sa.min() >= cfg.min_sigma_m) & (sa.max() <= cfg.max_sigma_m)
            & (na.min() >= -300.0) & (na.max() <= 300.0)
        )

    def _add_batch(self, key: str, src: str, anchor: _Anchor, msg: M.RangeBatch,
                   rx_wall_ns: int) -> None:
        self.received["range"] += len(msg.node_ids)
        t, pw = msg.t_ns, msg.t_pub_wall_ns
        rows = zip(msg.node_ids, msg.range_m, msg.sigma_m, msg.snr_db, strict=True)
        if self._batch_all_good(msg):
            # the usual batch: every entry valid and every node known, so the per-entry checks
            # would accept them all and no value is None (what _entry then does, inlined)
            min_snr = self.config.min_snr_db
            entries = [(nid, RangeEntry(t, r if min_snr is None or snr >= min_snr else None,
                                        sg, snr, pw, rx_wall_ns)) for nid, r, sg, snr in rows]
        else:
            entries = []
            for nid, r, sg, snr in rows:
                bad = self._bad_value(r, sg, snr)
                if bad is None:
                    why = self._node_refused(nid)
                    if why is not None:
                        bad = (why, f"node {nid!r}")
                if bad is not None:
                    self._reject(key, bad[0], bad[1], source=src)
                    continue
                entries.append((nid, self._entry(t, r, sg, snr, pw, rx_wall_ns)))
        anchor.ranges += len(entries)
        late = self.book.add_many(anchor.id, t, entries)
        if late:
            self.rejected["late"] += late

    def _entry(self, t_ns: int, r: float | None, sigma_m: float | None, snr_db: float | None,
               pub_wall: int, rx_wall: int) -> RangeEntry:
        """What the fusion keeps of one accepted range: ``range_m`` None when no path was
        detected or its SNR is below ``min_snr_db``."""
        min_snr = self.config.min_snr_db
        if r is None or sigma_m is None or (min_snr is not None
                                            and (snr_db is None or snr_db < min_snr)):
            r = None
        return RangeEntry(t_ns, r, sigma_m or 1.0, snr_db if snr_db is not None else -math.inf,
                          pub_wall, rx_wall)

    def _add_range(self, anchor, node_id, t_ns, r, sigma_m, snr_db, pub_wall, rx_wall) -> None:
        anchor.ranges += 1
        entry = self._entry(t_ns, r, sigma_m, snr_db, pub_wall, rx_wall)
        if not self.book.add(anchor.id, node_id, entry):
            self.rejected["late"] += 1

    def on_liveliness(self, anchor_id: str, alive: bool, wall_ns: int) -> None:
        """Liveliness token of an anchor appeared (``alive``) or vanished.

        Tokens of anchors outside the allow-list (or beyond ``max_anchors``) are ignored, so
        an unknown anchor can never make the fusion wait for it. A token that reappears
        after the anchor was lost starts a new stream (sequence numbers and clock reference
        are forgotten: the anchor restarted).
        """
        why = self._anchor_refused(anchor_id)
        if why is not None:
            self._reject(f"alive/anchor/{anchor_id}", why, "liveliness token ignored",
                         source=f"anchor {anchor_id}", count=0)
            return
        a = self._anchor(anchor_id)
        a.token = alive
        if alive:
            if not a.alive:
                log_event(self.log, logging.INFO, "anchor back", anchor=anchor_id)
                a.reset_stream()
            a.alive, a.lost_wall_ns = True, None
        else:
            a.alive, a.lost_wall_ns = False, wall_ns
            self.book.forget_anchor(anchor_id)
            log_event(self.log, logging.WARNING, "anchor lost", anchor=anchor_id)
        self._tref_dirty = True
        self.changed = True

    def warm_up(self) -> None:
        """Run one tiny D-NLS problem so imports and first-call costs are paid before the
        service declares itself ready (the first real epoch is then not late)."""
        from diffpos.estimators import dnls
        from diffpos.geometry import window_edge_path

        anchors = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0],
                            [15.0, -20.0, 1.0]])
        node = np.array([1.0, 5.0, self.config.first_floor_z_m + 1.5])
        r = window_edge_path(anchors, node, window_height_m=self.config.window_height_m).length_m
        dnls(anchors[None], r[None], np.full((1, 4), 0.1),
             window_height_m=self.config.window_height_m, gating=self.gating)

    @property
    def live_anchors(self) -> frozenset[str]:
        return frozenset(a.id for a in self.anchors.values() if a.alive)

    # ------------------------------------------------------------------ solving
    def step(self, now_wall_ns: int, *, limit: int | None = None) -> list[M.PositionEstimate]:
        """Solve the ready epochs (batched D-NLS calls of at most ``max_fixes_per_step``
        epochs each, bounded working memory) and return the estimates, oldest first.

        With ``limit``, solve at most that many and keep the rest for the next call (the live
        service ingests in between after a stall, see :attr:`backlog`); without, all.
        """
        self._ready.extend(self.book.ready(self.live_anchors, now_wall_ns))
        out: list[M.PositionEstimate] = []
        todo = len(self._ready) if limit is None else min(int(limit), len(self._ready))
        while todo > 0:
            n = min(todo, self.config.max_fixes_per_step)
            out += self._solve([self._ready.popleft() for _ in range(n)], now_wall_ns)
            todo -= n
        return out

    @property
    def backlog(self) -> int:
        """Ready epochs not solved yet (call :meth:`step` again without waiting)."""
        return len(self._ready)

    def flush(self, now_wall_ns: int) -> list[M.PositionEstimate]:
        """Solve everything ready or pending (at shutdown: nothing received is lost).

        Parameters
        ----------
        now_wall_ns : int [ns]
            Wall clock of the call (the estimates' ``t_pub_wall_ns``).
        """
        self._ready.extend(sorted(self.book.pending.values(), key=lambda p: p.epoch))
        self.book.pending.clear()
        out: list[M.PositionEstimate] = []
        while self._ready:
            n = min(len(self._ready), self.config.max_fixes_per_step)
            out += self._solve([self._ready.popleft() for _ in range(n)], now_wall_ns)
        return out

    def _solve(self, epochs: list[PendingEpoch], now_wall_ns: int) -> list[M.PositionEstimate]:
        """Solve ``epochs`` in one batch; ``now_wall_ns`` [ns] is the caller's wall clock
        (``t_pub_wall_ns`` and latency of the estimates): the result depends only on the
        core's state and the arguments, never on the machine's clock."""
        from diffpos.estimators import ExclusionReason, FixStatus, dnls, ippa, lls
        from diffpos.geometry import window_edge_path

        cfg = self.config
        ids = sorted(
            {a for pe in epochs for a in pe.ranges}
            | set(self.live_anchors)
            | {a.id for a in self.anchors.values() if a.lost_wall_ns is not None}
        )
        col = {a: j for j, a in enumerate(ids)}
        b, m = len(epochs), len(ids)
        t = np.zeros((b, m), np.int64)
        rng = np.full((b, m), np.nan)
        sig = np.ones((b, m))
        reported = np.zeros((b, m), bool)
        detected = np.zeros((b, m), bool)
        pub_wall = np.zeros((b, m), np.int64)
        # gather every (epoch, anchor) entry in flat lists, then scatter with fancy indexing
        ri: list[int] = []
        rj: list[int] = []
        ents: list[RangeEntry] = []
        for i, pe in enumerate(epochs):
            k = len(pe.ranges)
            ri += [i] * k
            rj += [col[a] for a in pe.ranges]
            ents += pe.ranges.values()
        if ents:
            e_t, e_r, e_s, _, e_pub, _ = zip(*ents, strict=True)
            ri_a, rj_a = np.array(ri), np.array(rj)
            reported[ri_a, rj_a] = True
            t[ri_a, rj_a] = e_t
            pub_wall[ri_a, rj_a] = e_pub
            det = np.array([r is not None for r in e_r])
            di, dj = ri_a[det], rj_a[det]
            detected[di, dj] = True
            rng[di, dj] = [r for r in e_r if r is not None]
            sig[di, dj] = np.array(e_s, dtype=np.float64)[det]
        # anchor positions at each range's own time
        apos = np.full((b, m, 3), np.nan)
        asig = np.zeros((b, m, 3))
        have_state = np.zeros((b, m), bool)
        for a, j in col.items():
            rows = np.flatnonzero(detected[:, j])
            if rows.size == 0 or a not in self.anchors:
                continue
            p, s, ok = self.anchors[a].history.at(t[rows, j])
            apos[rows, j], asig[rows, j], have_state[rows, j] = p, s, ok
        use = detected & have_state
        n_use = use.sum(axis=1)
        # mean time of the used ranges, relative to a per-row base (int64 sums of absolute
        # ns times would overflow beyond 4 anchors)
        base = np.max(np.where(reported, t, _NEG), axis=1)
        rel = np.where(use, t - base[:, None], 0).astype(np.float64)
        t_ref = base + np.round(rel.sum(axis=1) / np.maximum(n_use, 1)).astype(np.int64)
        dt_s = np.where(use, (t - t_ref[:, None]) * 1e-9, 0.0)
        # warm start / motion compensation from the node's track
        x0 = np.full((b, 3), np.nan)
        vel = np.zeros((b, 3))
        has_vel = np.zeros(b, bool)
        max_age = cfg.warm_start_max_age_s * 1e9
        period_ns = round(cfg.cold_retry_period_s * 1e9)
        for i, pe in enumerate(epochs):
            tr = self.tracks.get(pe.node_id)
            if tr is not None and tr.t_ns is not None and abs(t_ref[i] - tr.t_ns) <= max_age:
                dt = (t_ref[i] - tr.t_ns) * 1e-9
                if tr.vel is not None:
                    v = tr.vel
                    vel[i], has_vel[i] = v, True
                    x0[i] = [p + u * dt for p, u in zip(tr.pos, v, strict=True)]
                else:
                    x0[i] = tr.pos
            elif (tr is not None and tr.try_pos is not None and tr.cold_ns is not None
                  and 0 <= t_ref[i] - tr.cold_ns < period_ns):
                # no good fix lately, but a cold solve within the retry period: start from its
                # result instead of paying for another multi-start every epoch
                x0[i] = tr.try_pos
        comp = has_vel & cfg.motion_compensation
        safe_apos = np.where(use[..., None], apos, 0.0)
        if np.any(comp):
            jac = window_edge_path(
                safe_apos,
                np.where(comp[:, None], x0, 0.0)[:, None, :],
                window_height_m=cfg.window_height_m,
                delta_m=cfg.delta_m,
                edge_x_m=cfg.edge_x_m,
            ).jacobian
            rng = np.where(
                comp[:, None] & use, compensate_node_motion(rng, jac, vel[:, None, :], dt_s), rng
            )
        speed_sigma = np.where(comp, cfg.velocity_sigma_m_s, cfg.node_speed_sigma_m_s)
        los = (
            np.where(np.isfinite(x0[:, None, :]), x0[:, None, :], np.array([0.0, 5.0, 6.0]))
            - safe_apos
        )
        sig_eff = effective_sigma_m(sig, asig, los, dt_s, speed_sigma[:, None])
        sig_eff = np.where(use, sig_eff, 1.0)
        rng_in = np.where(use, rng, 0.0)
        common: dict[str, Any] = dict(
            window_height_m=cfg.window_height_m,
            delta_m=cfg.delta_m,
            edge_x_m=cfg.edge_x_m,
            gating=self.gating,
        )
        warm = np.isfinite(x0).all(axis=1)
        res_pos = np.full((b, 3), np.nan)
        res_cov = np.full((b, 3, 3), np.nan)
        res_peb = np.full(b, np.nan)
        res_zb = np.full(b, np.nan)
        res_status = np.full(b, int(FixStatus.TOO_FEW_ANCHORS))
        res_resid = np.full((b, m), np.nan)
        res_used = np.zeros((b, m), bool)
        res_reason = np.zeros((b, m), int)
        res_msg: list[str] = [""] * b

        def put(rows: np.ndarray, fix: Any) -> None:
            res_pos[rows], res_cov[rows] = fix.position_m, fix.covariance_m2
            res_peb[rows], res_zb[rows] = fix.peb_m, fix.z_bound_m
            res_status[rows], res_resid[rows] = fix.status, fix.residuals_m
            res_used[rows], res_reason[rows] = fix.used, fix.exclusion_reason
            for r, text in zip(rows.tolist(), fix.messages(), strict=True):
                res_msg[r] = text

        good = (int(FixStatus.OK), int(FixStatus.OK_UNVERIFIED))
        if cfg.method != "dnls":
            solver = lls if cfg.method == "lls" else ippa
            put(np.arange(b), solver(safe_apos, rng_in, sig_eff, mask=use))
        else:
            rows_w = np.flatnonzero(warm)
            if rows_w.size:
                fix = dnls(safe_apos[rows_w], rng_in[rows_w], sig_eff[rows_w],
                           mask=use[rows_w], x0_m=x0[rows_w], **common)
                put(rows_w, fix)
            # A warm fix that failed is re-solved from all starts (re-acquisition after a wrong
            # basin), but at most once per cold_retry_period_s of measurement time per node:
            # on realistic channels a third of the fixes fail every epoch for reasons a cold
            # start does not change, and the multi-start re-solve costs ~10x a warm fix.
            # Measurement time (not the wall clock) keeps replays deterministic.
            retry = np.zeros(b, bool)
            for i in np.flatnonzero(warm & ~np.isin(res_status, good)):
                tr = self.tracks[epochs[i].node_id]
                if tr.cold_ns is None or t_ref[i] - tr.cold_ns >= period_ns:
                    retry[i] = True
                    tr.cold_ns = int(t_ref[i])
            rows_c = np.flatnonzero(~warm | retry)
            if rows_c.size:
                fix = dnls(safe_apos[rows_c], rng_in[rows_c], sig_eff[rows_c],
                           mask=use[rows_c], **common)
                put(rows_c, fix)
                for i in rows_c:
                    tr = self.tracks[epochs[i].node_id]
                    tr.cold_ns = int(t_ref[i])
                    tr.try_pos = res_pos[i].tolist() if np.all(np.isfinite(res_pos[i])) else None
        self.solved += b

        # ---- messages (vectorised reasons; numpy -> Python lists once, not per element)
        now = int(now_wall_ns)
        out = []
        names = list(col)
        lost_col = np.array([a in {x.id for x in self.anchors.values() if not x.alive}
                             for a in names], bool)
        gate_codes = (int(ExclusionReason.RAIM), int(ExclusionReason.PREGATE_SHORTER_THAN_LOS))
        gated_mask = reported & detected & have_state & ~res_used & np.isin(res_reason, gate_codes)
        self.gated += int(gated_mask.sum())
        # reason codes: 0 used/absent-not-live, 1 NOT_DETECTED, 2 NO_ANCHOR_STATE, 3 gating
        # reason (from res_reason), 4 NOT_USED, 5 ANCHOR_LOST, 6 NOT_REPORTED
        code = np.zeros((b, m), np.int8)
        code[~reported & ~lost_col[None, :]] = 6
        code[~reported & lost_col[None, :]] = 5
        code[reported & ~res_used] = 4
        code[reported & detected & have_state & ~res_used & (res_reason != 0)] = 3
        code[reported & detected & ~have_state] = 2
        code[reported & ~detected] = 1
        fixed = {1: "NOT_DETECTED", 2: "NO_ANCHOR_STATE", 4: "NOT_USED", 5: "ANCHOR_LOST",
                 6: "NOT_REPORTED"}
        reason_names = {int(r): r.name for r in ExclusionReason}
        status_names = {int(st): st.name for st in FixStatus}
        floors = np.clip(np.floor((res_pos[:, 2] - cfg.first_floor_z_m) / cfg.floor_height_m),
                         -1, cfg.n_floors)
        status_l = res_status.tolist()
        finite_pos = np.all(np.isfinite(res_pos), axis=1).tolist()
        finite_cov = np.all(np.isfinite(res_cov), axis=(1, 2)).tolist()
        pos_l, cov_l = res_pos.tolist(), res_cov.tolist()
        peb_l, zb_l, floor_l = res_peb.tolist(), res_zb.tolist(), floors.tolist()
        resid_l = np.where(np.isfinite(res_resid), res_resid, 0.0).tolist()
        t_ref_l = t_ref.tolist()
        in_wall_l = np.where(reported, pub_wall, 0).max(axis=1).tolist()
        # rows with the same used set and exclusion reasons share their anchor lists (most
        # rows of an epoch batch use every anchor): built once per pattern, not per fix
        why = np.where(code == 3, 16 + res_reason, code) * ~res_used
        pattern = np.concatenate([res_used.astype(np.int64), why], axis=1)
        first: dict[bytes, int] = {}  # pattern -> group id
        reps: list[int] = []  # group id -> its first row
        group_l: list[int] = []
        for i, row in enumerate(pattern):
            g = first.setdefault(row.tobytes(), len(first))
            if g == len(reps):
                reps.append(i)
            group_l.append(g)
        shared = []
        for row in pattern[reps].tolist():
            used_idx = [j for j in range(m) if row[j]]
            excluded = [
                M.Exclusion(names[j], reason_names[c - 16] if c >= 16 else fixed[c])
                for j, c in enumerate(row[m:]) if c
            ]
            shared.append((used_idx, [names[j] for j in used_idx], excluded, len(used_idx) == m))
        self.by_status.update(status_names[st] for st in status_l)
        tracks = self.tracks
        for i, (pe, gi) in enumerate(zip(epochs, group_l, strict=True)):
            st = status_l[i]
            used_idx, used_ids, excluded, all_used = shared[gi]
            resid = resid_l[i] if all_used else [resid_l[i][j] for j in used_idx]
            ok = st in good
            if ok and finite_pos[i]:
                pos = tuple(pos_l[i])
                tracks[pe.node_id].update(t_ref_l[i], pos_l[i])
                cov_t = tuple(map(tuple, cov_l[i])) if finite_cov[i] else None
                fl = int(floor_l[i])
            else:
                pos, cov_t, fl = None, None, None
            in_wall = in_wall_l[i]
            self.seq += 1
            est = M.PositionEstimate(
                node_id=pe.node_id,
                t_ns=t_ref_l[i],
                epoch=pe.epoch,
                seq=self.seq,
                status=status_names[st],
                position_m=pos,
                covariance_m2=cov_t,  # type: ignore[arg-type]
                peb_m=M.finite_or_none(peb_l[i]) if ok else None,
                z_bound_m=M.finite_or_none(zb_l[i]) if ok else None,
                floor_index=fl,
                used_anchors=list(used_ids),
                residuals_m=resid,
                excluded=list(excluded),
                message=res_msg[i],
                t_input_wall_ns=max(in_wall, 0),
                t_pub_wall_ns=now,
            )
            if in_wall > 0:
                self.latencies_ns.append(now - in_wall)
            out.append(est)
        return out

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self, now_wall_ns: int) -> M.FusionDiagnostics:
        lat = np.asarray(self.latencies_ns, dtype=np.float64) * 1e-6
        stats = M.LatencyStats(
            count=int(lat.size),
            p50_ms=float(np.percentile(lat, 50)) if lat.size else None,
            p99_ms=float(np.percentile(lat, 99)) if lat.size else None,
            max_ms=float(lat.max()) if lat.size else None,
        )
        wm = [a.last_t_ns for a in self.anchors.values() if a.last_t_ns is not None]
        self.changed = False
        return M.FusionDiagnostics(
            t_wall_ns=now_wall_ns,
            watermark_ns=max(wm) if wm else None,
            received=dict(self.received),
            rejected=dict(self.rejected),
            gated=self.gated,
            solved=self.solved,
            published=self.published,
            fixes_by_status=dict(self.by_status),
            late_ranges=self.book.late,
            pending_epochs=len(self.book.pending) + len(self._ready),
            live_anchors=sorted(self.live_anchors),
            anchors=[
                M.AnchorHealth(a.id, a.alive, a.states, a.ranges, a.last_t_ns, a.lost_wall_ns)
                for a in sorted(self.anchors.values(), key=lambda x: x.id)
            ],
            latency=stats,
        )


# ---------------------------------------------------------------------- process wiring
def run_fusion(
    config: FusionConfig,
    zenoh_config: Any,
    stop: threading.Event,
    *,
    logger: logging.Logger | None = None,
    on_ready: Callable[[], None] | None = None,
) -> FusionCore:
    """Run the fusion on a Zenoh session until ``stop`` is set.

    Callbacks only put raw samples on a bounded queue (a full queue blocks Zenoh, which
    with congestion control BLOCK pushes back on the anchors instead of dropping); this
    thread decodes, aligns, solves and publishes.
    """
    import zenoh

    log = logger or logging.getLogger("diffpos.fusion")
    core = FusionCore(config, logger=log)
    keys = core.keys
    q: queue.Queue = queue.Queue(maxsize=config.queue_size)

    max_bytes = config.max_message_bytes
    # the queue is bounded in samples (small ones) and in bytes (large ones, e.g. range
    # batches): a full queue blocks Zenoh's thread, which paces BLOCK publishers
    max_queued = config.max_queued_bytes
    queued = [0]
    room = threading.Condition()

    def release(size: int) -> None:
        with room:
            queued[0] -= size
            room.notify_all()

    def on_data(sample: zenoh.Sample) -> None:
        size = len(sample.payload)
        if size > max_bytes:  # never copied nor queued: bounded memory whatever arrives
            q.put((2, str(sample.key_expr), size, time.time_ns()))
            return
        if size > _ACCOUNTED_BYTES:
            with room:
                while queued[0] > 0 and queued[0] + size > max_queued and not stop.is_set():
                    room.wait(0.1)
                queued[0] += size
        q.put((0, str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    def on_alive(sample: zenoh.Sample) -> None:
        q.put((1, str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT, time.time_ns()))

    period_ns = int(config.diagnostics_period_s * 1e9)
    core.warm_up()
    session = open_session(zenoh_config, stop, logger=log) if isinstance(
        zenoh_config, ZenohSettings) else zenoh.open(zenoh_config)
    if session is None:
        return core
    with session:
        est_pubs: dict[str, zenoh.Publisher] = {}
        diag_pub = session.declare_publisher(
            keys.fusion_diagnostics(),
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        # ONE subscriber: an anchor's states, ranges and batches keep their publish order
        subs = [session.declare_subscriber(fusion_subscription(keys), on_data)]
        live_sub = session.liveliness().declare_subscriber(
            keys.alive_anchors(), on_alive, history=True
        )
        token = session.liveliness().declare_token(keys.alive_fusion())
        log_event(
            log,
            logging.INFO,
            "fusion ready",
            site=config.site,
            subscriptions=[fusion_subscription(keys)],
        )
        if on_ready is not None:
            on_ready()
        next_diag = time.time_ns() + period_ns
        linger_s = config.linger_s
        try:
            while not stop.is_set():
                now = time.time_ns()
                dl = core.book.next_deadline_wall_ns()
                wake = min(next_diag, dl if dl is not None else next_diag)
                timeout = 0.0 if core.backlog else min(max((wake - now) * 1e-9, 0.0), 0.1)
                try:
                    item = q.get(timeout=timeout)
                except queue.Empty:
                    item = None
                # ingest what is queued (bounded, so solving and diagnostics keep going);
                # epoch deadlines count from each sample's own ingestion, so neither a backlog
                # nor a long drain releases epochs before their queued ranges were seen
                budget = 20_000
                while item is not None:
                    kind, key, val, rx = item
                    try:
                        if kind == 0:
                            if len(val) > _ACCOUNTED_BYTES:
                                release(len(val))
                            core.on_sample(key, val, time.time_ns())
                        elif kind == 2:
                            core.on_oversized(key, val)
                        else:
                            pk = parse_key(key)
                            if pk is not None and pk.anchor_id is not None:
                                core.on_liveliness(pk.anchor_id, bool(val), rx)
                    except Exception as exc:  # a bug, not bad input: count, log once, go on
                        core.rejected["internal_error"] += 1
                        if core.rejected["internal_error"] == 1:
                            log.exception("internal error while ingesting %s: %s", key, exc)
                    budget -= 1
                    try:
                        item = q.get_nowait() if budget > 0 else None
                    except queue.Empty:
                        # linger briefly: an anchor publishes its ranges to all nodes back to
                        # back, so waiting ~1 ms batches them into one solve
                        try:
                            item = q.get(timeout=linger_s) if budget > 0 else None
                        except queue.Empty:
                            item = None
                now = time.time_ns()
                for est in core.step(now, limit=config.max_fixes_per_step):
                    pub = est_pubs.get(est.node_id)
                    if pub is None:
                        pub = est_pubs[est.node_id] = session.declare_publisher(
                            keys.node_estimate(est.node_id),
                            encoding=zenoh.Encoding.APPLICATION_JSON,
                            congestion_control=zenoh.CongestionControl.BLOCK,
                        )
                    pub.put(M.encode(est))
                    core.published += 1
                if now >= next_diag or core.changed:
                    diag_pub.put(M.encode(core.diagnostics(now)))
                    next_diag = now + period_ns
        finally:
            # flush what is pending so nothing already received is lost
            for est in core.flush(time.time_ns()):
                session.put(
                    keys.node_estimate(est.node_id),
                    M.encode(est),
                    encoding=zenoh.Encoding.APPLICATION_JSON,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
                core.published += 1
            diag_pub.put(M.encode(core.diagnostics(time.time_ns())))
            token.undeclare()
            live_sub.undeclare()
            for s in subs:
                s.undeclare()
            log_event(
                log,
                logging.INFO,
                "fusion stopped",
                solved=core.solved,
                published=core.published,
                rejected=dict(core.rejected),
            )
    return core
