"""The fusion's logic without any network: :class:`FusionCore`.

Feed it raw ``(key, payload)`` samples and liveliness events, call :meth:`FusionCore.step`
and get estimates back: :class:`~diffpos_services.wire.messages.PositionEstimateV2` for the
method ``mnls`` (with the per-responder tracker of :mod:`diffpos_services.fusion.tracked`
when ``tracking``), :class:`~diffpos_services.wire.messages.PositionEstimate` (v1, as before)
for ``dnls``/``lls``/``ippa``. The unit tests drive it in memory, ``diffpos replay`` re-runs it
offline, and :func:`diffpos_services.fusion.service.run_fusion` wires it to Zenoh.

What the fusion assumes about time is documented in :mod:`diffpos.alignment`.

Bad input (docs/bad_input.md): every sample is checked before it is used (size, key, allow-
lists and id caps, JSON and schema, key/payload ids, plausible values, duplicate sequence
numbers, plausible time against the anchors' consensus). A rejected sample is counted in
``diagnostics.rejected[<reason>]`` and logged once per anchor and reason; ingestion never
raises on bad input, and a rejected sample changes nothing else.

The core never reads the machine's clock: every wall time is an argument.
"""

from __future__ import annotations

import collections
import logging
import math
from collections.abc import Sequence
from typing import Any

import msgspec
import numpy as np

from diffpos.alignment import EpochBook, PendingEpoch, RangeEntry, reported_anchors
from diffpos.estimators.gating import GatingConfig
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.decisions import DecisionLog
from diffpos_services.fusion.estimates import ColumnBatch, Estimates
from diffpos_services.fusion.estimates_v1 import v1_estimates
from diffpos_services.fusion.ingest import (
    AnchorStream,
    RejectLog,
    Track,
    bad_batch,
    bad_state,
    bad_value,
    batch_all_good,
    count_releases,
)
from diffpos_services.fusion.overload import BEHIND_KEEP_EPOCHS, OverloadPolicy
from diffpos_services.fusion.step import (
    gated_count,
    gather,
    prepare,
    solve_batch,
)
from diffpos_services.logs import log_event
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, ParsedKey, parse_key

__all__ = ["BEHIND_KEEP_EPOCHS", "FusionConfig", "FusionCore"]

#: why an epoch was released (FusionDiagnostics.releases)
RELEASE_REASONS = ("complete", "passed", "watermark", "wall_fallback", "flush")

# The mnls + tracking modules (fusion/tracked.py, estimates_v2.py, warm.py and through them
# M-NLS's and the tracker's compiled kernels) are imported where mnls uses them, not at the
# top: a D-NLS/LLS/IPPA fusion (and its replay) loads none of them.


def _track_bank(building: Any, config: FusionConfig) -> Any:
    """The tracker bank of an mnls + tracking core (:class:`~diffpos_services.fusion.tracked.TrackBank`)."""
    from diffpos_services.fusion.tracked import TrackBank

    return TrackBank(building, config.tracker_config())


def _heavy_budget(n_epochs: int, lagging: bool) -> int | None:
    """:func:`~diffpos_services.fusion.tracked.heavy_budget` (mnls + tracking only)."""
    from diffpos_services.fusion.tracked import heavy_budget

    return heavy_budget(n_epochs, lagging)


class FusionCore:
    """Network-free fusion logic.

    Parameters
    ----------
    config : FusionConfig
    logger : logging.Logger, optional
    record_decisions : bool
        Keep the decision record (:mod:`diffpos_services.fusion.decisions`), handed out with
        every :meth:`diagnostics` (the live fusion; replay turns it off).
    """

    def __init__(self, config: FusionConfig, *, logger: logging.Logger | None = None,
                 record_decisions: bool = True) -> None:
        self.config = config
        self.keys = Keys(config.site)
        self.align = config.alignment()
        self.book = EpochBook(self.align)
        self.anchors: dict[str, AnchorStream] = {}
        self.tracks: dict[str, Track] = collections.defaultdict(Track)
        self.log = logger or logging.getLogger("diffpos.fusion")
        self.log_once = RejectLog(self.log)
        self._allowed_anchors = None if config.anchors is None else frozenset(config.anchors)
        self._allowed_nodes = None if config.nodes is None else frozenset(config.nodes)
        self._nodes: set[str] = set()
        # with shards: responder id -> owned by this shard (config.owns, memoised)
        self._owned: dict[str, bool] | None = {} if config.shards > 1 else None
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
        self.releases: collections.Counter[str] = collections.Counter()
        self.decisions = DecisionLog(200_000) if record_decisions else None
        self._dec_state = M.decoder(M.AnchorState)
        self._dec_range = M.decoder(M.RangeMeasurement)
        self._dec_batch = M.decoder(M.RangeBatch)
        self.changed = False  # liveliness changed since the last diagnostics
        self._ready: collections.deque[PendingEpoch] = collections.deque()
        self.overload = OverloadPolicy(config)  # what a live step that is behind drops
        # mnls: the building of the path model; with tracking, every node's tracker state
        self.building = config.building_model() if config.method == "mnls" else None
        # (building, radio, M-NLS's SnrRule fields: diffpos.estimators.mnls.rules, imported
        # only where mnls runs, M-NLS's mechanism order)
        self.model = (self.building, config.radio_model(),
                      (config.mnls_measured_threshold, config.mnls_first_arrival_prior,
                       config.mnls_keep_hard_rule, config.mnls_dielectric_edges,
                       config.mnls_floor_box),
                      config.mnls_max_order)
        self.bank = (_track_bank(self.building, config)
                     if self.building is not None and config.tracking else None)
        self.method_name = config.method + ("+tracking" if self.bank is not None else "")
        self.overload.status_of = None if self.bank is None else self.bank.status_of

    # ------------------------------------------------------------------ ingestion
    def _reject(self, key: str, reason: str, detail: str = "", *, source: str = "bus",
                count: int = 1) -> None:
        if count:
            self.rejected[reason] += count
        self.log_once(key, reason, detail, source=source)

    def _anchor(self, anchor_id: str) -> AnchorStream:
        a = self.anchors.get(anchor_id)
        if a is None:
            a = self.anchors[anchor_id] = AnchorStream(anchor_id, self.align.max_state_extrapolation_ns,
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

    def _owns(self, node_id: str) -> bool:
        """True if this fusion's shard owns ``node_id`` (always without shards)."""
        owned = self._owned
        if owned is None:
            return True
        mine = owned.get(node_id)
        if mine is None:
            if len(owned) >= self.config.max_nodes:
                owned.clear()  # (bounded: ids never seen again are forgotten)
            mine = owned[node_id] = self.config.owns(node_id)
        return mine

    def _other_shard(self, anchor_id: str, t_ns: int, rx_wall_ns: int, n: int) -> None:
        """``n`` ranges of ``anchor_id`` at ``t_ns`` for responders of other shards: counted
        (``received["other_shard"]``) and not kept, but the epoch book learns the anchor's
        time and the newest receive time exactly as one fusion of every responder does, so
        each shard releases its responders' epochs when that fusion would."""
        self.received["other_shard"] += n
        book = self.book
        prev = book.latest_t_ns.get(anchor_id)
        if prev is None or t_ns > prev:
            book.note_anchor_time(anchor_id, t_ns)
        if book.last_rx_wall_ns is None or rx_wall_ns > book.last_rx_wall_ns:
            book.last_rx_wall_ns = int(rx_wall_ns)

    def _node_refused(self, node_id: str) -> str | None:
        if self._allowed_nodes is not None and node_id not in self._allowed_nodes:
            return "unknown_node"
        if node_id not in self._nodes:
            if len(self._nodes) >= self.config.max_nodes:
                return "too_many_nodes"
            self._nodes.add(node_id)
        return None

    def _time_reference(self, now_wall_ns: int) -> int | None:
        """Consensus measurement time: the second newest of the newest accepted times of the
        anchors that delivered within the last 2 s (wall), if at least 3 did; else None."""
        if self._tref_dirty or now_wall_ns - self._tref_wall_ns > 100_000_000:
            fresh = sorted(
                a.last_t_ns for a in self.anchors.values()
                if a.alive and a.last_t_ns is not None
                and now_wall_ns - a.last_rx_wall_ns <= 2_000_000_000
            )
            self._tref = fresh[-2] if len(fresh) >= 3 else None
            self._tref_dirty = False
            self._tref_wall_ns = now_wall_ns
        return self._tref

    def _check_time(self, anchor: AnchorStream | None, t_ns: int, now_wall_ns: int) -> str | None:
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

    def _check_seq(self, anchor: AnchorStream | None, stream: str, seq: int) -> bool:
        """True if ``seq`` was already accepted on this stream (one of its last 16)."""
        if anchor is None:
            return False
        recent = anchor.seqs.get(stream)
        return recent is not None and seq in recent

    @staticmethod
    def _note_seq(anchor: AnchorStream, stream: str, seq: int) -> None:
        recent = anchor.seqs.get(stream)
        if recent is None:
            recent = anchor.seqs[stream] = collections.deque(maxlen=16)
        recent.append(seq)

    def on_oversized(self, key: str, size: int) -> None:
        """Count a sample dropped for its size before it was even copied (see run_fusion)."""
        if self.decisions is not None:
            self.decisions.oversized(key, size)
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
        if self.decisions is not None:
            self.decisions.sample(key, payload, rx_wall_ns)
        pk = self._admit_key(key, len(payload))
        if pk is None:
            return
        src = f"anchor {pk.anchor_id}"
        msg = self._decode(key, pk, payload, src)
        if msg is None:
            return
        stream = "state" if pk.kind == "anchor_state" else (
            "ranges" if pk.kind == "range_batch" else pk.node_id)
        if self._plausible(key, pk, msg, stream, src, rx_wall_ns):
            self._accept(key, pk, msg, stream, src, rx_wall_ns)

    def _admit_key(self, key: str, size: int) -> ParsedKey | None:
        """The parsed key of a sample worth decoding (our site, an input kind, not oversized,
        an accepted anchor and node); None after counting and logging the rejection."""
        pk = parse_key(key)
        if pk is None or pk.site != self.config.site or pk.kind not in (
            "anchor_state", "range", "range_batch"
        ):
            self.received["other"] += 1
            self._reject(key, "unexpected_key")
            return None
        self.received[pk.kind] += 1
        aid = pk.anchor_id
        src = f"anchor {aid}"
        cfg = self.config
        if size > cfg.max_message_bytes:
            self._reject(key, "oversized", f"{size} bytes > max_message_bytes="
                         f"{cfg.max_message_bytes}", source=src)
            return None
        why = self._anchor_refused(aid)
        if why is None and pk.kind == "range" and self._allowed_nodes is not None \
                and pk.node_id not in self._allowed_nodes:
            why = "unknown_node"
        if why is not None:
            self._reject(key, why, f"anchor {aid!r}, node {pk.node_id!r}", source=src)
            return None
        return pk

    def _decode(self, key: str, pk: ParsedKey, payload: bytes, src: str) -> Any:
        """The decoded message, if valid and its ids match the key's; else None (rejected)."""
        try:
            if pk.kind == "range":
                msg = self._dec_range(payload)
            elif pk.kind == "range_batch":
                msg = self._dec_batch(payload)
            else:
                msg = self._dec_state(payload)
        except M.DecodeError as exc:
            self._reject(key, exc.reason, exc.detail, source=src)
            return None
        if msg.anchor_id != pk.anchor_id or (pk.kind == "range" and msg.node_id != pk.node_id):
            self._reject(key, "key_mismatch", "ids in the payload differ from the key",
                         source=src)
            return None
        return msg

    def _plausible(self, key: str, pk: ParsedKey, msg: Any, stream: str, src: str,
                   rx_wall_ns: int) -> bool:
        """Values, node, sequence number and time of a decoded message; False if rejected."""
        cfg = self.config
        anchor = self.anchors.get(pk.anchor_id)
        if pk.kind == "anchor_state":
            bad = bad_state(cfg, msg)
        elif pk.kind == "range":
            bad = bad_value(cfg, msg.range_m, msg.sigma_m, msg.snr_db)
            if bad is None and self._owns(msg.node_id):
                why = self._node_refused(msg.node_id)
                if why is not None:
                    self._reject(key, why, f"node {msg.node_id!r}", source=src)
                    return False
        else:
            bad = bad_batch(cfg, msg)
        if bad is not None:
            self._reject(key, bad[0], bad[1], source=src)
            return False
        if self._check_seq(anchor, stream, msg.seq):
            self._reject(key, "duplicate_seq", f"seq {msg.seq} already received on this key",
                         source=src)
            return False
        why = self._check_time(anchor, msg.t_ns, rx_wall_ns)
        if why is not None:
            ref = self._tref
            self._reject(key, why, f"t_ns={msg.t_ns} vs reference "
                         f"{ref if ref is not None else anchor.last_t_ns} (allowed "
                         f"-{cfg.max_past_s} s / +{cfg.max_future_s} s)", source=src)
            return False
        return True

    def _accept(self, key: str, pk: ParsedKey, msg: Any, stream: str, src: str,
                rx_wall_ns: int) -> None:
        """Use an accepted message: anchor bookkeeping, then its state or ranges."""
        anchor = self.anchors.get(pk.anchor_id)
        anchor = self._anchor(pk.anchor_id) if anchor is None else anchor
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
        elif pk.kind == "range" and not self._owns(msg.node_id):
            self._other_shard(anchor.id, msg.t_ns, rx_wall_ns, 1)
        elif pk.kind == "range":
            self._add_range(anchor, msg.node_id, msg.t_ns, msg.range_m, msg.sigma_m,
                            msg.snr_db, msg.t_pub_wall_ns, rx_wall_ns)
        else:
            self._add_batch(key, src, anchor, msg, rx_wall_ns)

    def _add_batch(self, key: str, src: str, anchor: AnchorStream, msg: M.RangeBatch,
                   rx_wall_ns: int) -> None:
        self.received["range"] += len(msg.node_ids)
        t, pw = msg.t_ns, msg.t_pub_wall_ns
        if self._owned is not None:
            msg = self._shard_batch(anchor.id, msg, rx_wall_ns)
        cols = batch_all_good(self.config, msg, self._nodes, self._allowed_nodes)
        if cols is not None:
            # the usual batch: every entry valid (or not detected at all) and every node
            # known, so the per-entry checks would accept them all (what _entry then does,
            # by columns, into the epoch book's columns: no object per range)
            r_col, sg_col, snr_col = cols
            min_snr = self.config.min_snr_db
            if min_snr is not None and snr_col.min() < min_snr:
                r_col = np.where(snr_col >= min_snr, r_col, np.nan)
            anchor.ranges += len(r_col)
            late = self.book.add_columns(anchor.id, t, msg.node_ids, r_col, sg_col, snr_col,
                                         t, pw, rx_wall_ns)
        else:
            entries = []
            for nid, r, sg, snr in zip(msg.node_ids, msg.range_m, msg.sigma_m, msg.snr_db,
                                       strict=True):
                bad = bad_value(self.config, r, sg, snr)
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

    def _shard_batch(self, anchor_id: str, msg: M.RangeBatch, rx_wall_ns: int) -> M.RangeBatch:
        """``msg`` with only this shard's responders (the others: :meth:`_other_shard`)."""
        mine = [i for i, nid in enumerate(msg.node_ids) if self._owns(nid)]
        n_other = len(msg.node_ids) - len(mine)
        if not n_other:
            return msg
        self._other_shard(anchor_id, msg.t_ns, rx_wall_ns, n_other)
        pick = lambda col: [col[i] for i in mine]  # noqa: E731
        return msgspec.structs.replace(msg, node_ids=pick(msg.node_ids), range_m=pick(msg.range_m),
                                       sigma_m=pick(msg.sigma_m), snr_db=pick(msg.snr_db))

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
        if self.decisions is not None:
            self.decisions.liveliness(anchor_id, alive, wall_ns)
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
        """Pay imports and first-call costs before the service declares itself ready (the
        first real epoch is then not late): :func:`~diffpos_services.fusion.warm.warm_up`."""
        from diffpos_services.fusion.warm import warm_up

        warm_up(self)

    @property
    def node_ids(self) -> set[str]:
        """The nodes whose ranges were accepted so far (do not modify)."""
        return self._nodes

    @property
    def live_anchors(self) -> frozenset[str]:
        return frozenset(a.id for a in self.anchors.values() if a.alive)

    # ------------------------------------------------------------------ solving
    def step(self, now_wall_ns: int, *, limit: int | None = None,
             emit: Any = None) -> Estimates:
        """Solve the ready epochs (batches of at most ``max_fixes_per_step`` epochs, bounded
        working memory) and return the estimates in queue order but for a batch's rows that
        wait for a snapshot fix (last: :func:`~diffpos_services.fusion.tracked.in_publish_order`);
        with ``emit``, a previous batch's and those ready before a batch's initialisations or
        fixes go to ``emit(estimates)`` (published before that work) and are not returned.

        With ``limit``, solve at most that many and keep the rest for the next call (the live
        service ingests in between after a stall, see :attr:`backlog`), and do at most
        :func:`~diffpos_services.fusion.tracked.heavy_budget` (of the epochs solved) track
        initialisations and snapshot fixes per batch (mnls + tracking: the rest follow in
        later steps), after the batch's other epochs (``TrackBank.hold_inits``). Without
        ``limit``, all.

        With ``max_backlog_s`` set (the live fusion), a step with more ready epochs than its
        ``limit``, once they span more than ``supersede_after_s``, first keeps only each
        node's :data:`BEHIND_KEEP_EPOCHS` newest ready epochs, nodes least recently served
        first (``superseded``), and then drops what is more than ``max_backlog_s`` behind the
        newest (``overloaded``; :class:`~diffpos_services.fusion.overload.OverloadPolicy`).
        The queue is oldest first unless the policy reordered it. A fusion that keeps up
        (never more ready than the limit) is not affected.
        """
        live = self.live_anchors
        released = self.book.ready(live, now_wall_ns)
        if self.decisions is not None and (released or self._ready):
            self.decisions.step(now_wall_ns, limit, len(released) + len(self._ready))
        if released:
            count_releases(self.book, released, live, self.releases)
        self._ready.extend(released)
        self._ready = self.overload.apply(self._ready, limit, self.rejected)
        out = Estimates()
        todo = len(self._ready) if limit is None else min(int(limit), len(self._ready))
        behind = todo < len(self._ready)  # no snapshot fix of a placed node (solve_mnls)
        lagging = limit is not None and self.overload.lagging(self._ready, todo)  # admit_lag_s
        while todo > 0:
            n = min(todo, self.config.max_fixes_per_step)
            now, held = [self._ready.popleft() for _ in range(n)], []
            if limit is not None:
                self.overload.taken(now)
            if limit is not None and self.bank is not None:
                now, held = self.bank.hold_inits(now, _heavy_budget(n, lagging), lagging)
            if out and emit is not None:  # (a previous batch of this step)
                emit(out)
                out = Estimates()
            heavy = (None if limit is None or self.building is None  # (mnls only)
                     else 0 if held else _heavy_budget(n, lagging))
            out += self._solve(now, now_wall_ns, heavy, emit, behind)
            if held:  # the initialisations after the other estimates are out
                if emit is not None:
                    emit(out)
                    out = Estimates()
                out += self._solve(held, now_wall_ns, len(held), emit)
            todo -= n
        return out

    @property
    def backlog(self) -> int:
        """Ready epochs not solved yet (call :meth:`step` again without waiting)."""
        return len(self._ready)

    def flush(self, now_wall_ns: int) -> Estimates:
        """Solve everything ready or pending (at shutdown: nothing received is lost);
        ``now_wall_ns`` [ns]: wall clock of the call (the estimates' ``t_pub_wall_ns``)."""
        if self.decisions is not None:
            self.decisions.flush(now_wall_ns)
        self.releases["flush"] += len(self.book.pending)
        self._ready.extend(self.book.take_all())
        out = Estimates()
        while self._ready:
            n = min(len(self._ready), self.config.max_fixes_per_step)
            out += self._solve([self._ready.popleft() for _ in range(n)], now_wall_ns)
        return out

    def _solve(self, epochs: list[PendingEpoch], now_wall_ns: int, heavy: int | None = None,
               emit: Any = None, behind: bool = False) -> Sequence[M.PositionEstimate]:
        """Solve ``epochs`` in one batch; ``now_wall_ns`` [ns] is the caller's wall clock
        (``t_pub_wall_ns`` and latency of the estimates), ``heavy`` the work budget of mnls +
        tracking: the result depends only on the core's state and the arguments, never on
        the machine's clock. With tracking, the rows without a snapshot fix first (to ``emit``
        if given), see :func:`~diffpos_services.fusion.tracked.in_publish_order`; ``behind``:
        see ``solve_mnls``. The steps are in :mod:`diffpos_services.fusion.step`: gather arrays -> prepare the
        batch -> warm/cold/retry solve -> messages (built here: counters and tracks)."""
        ids = sorted(reported_anchors(epochs) | set(self.live_anchors)
                     | {a.id for a in self.anchors.values() if a.lost_wall_ns is not None})
        batch = gather(epochs, ids, self.anchors, silent=self.bank is not None
                       and self.bank.config.silent_anchor_nats > 0)
        prep = prepare(batch, epochs, self.tracks, self.config)
        self.solved += len(epochs)
        if self.building is not None:
            from diffpos_services.fusion.estimates_v2 import v2_builder
            from diffpos_services.fusion.tracked import in_publish_order, solve_mnls

            s = solve_mnls(batch, prep, epochs, self.config, self.model, self.bank, heavy,
                           defer=True, behind=behind)
            self.gated += gated_count(batch, s.res)
            lost = {x.id for x in self.anchors.values() if not x.alive}
            build = v2_builder(epochs, batch, s, lost)  # the batch's columns once
            now = int(now_wall_ns)
            return in_publish_order(s, epochs, emit, lambda rows: self._count(build(
                rows, seq0=self.seq, now=now, method=self.method_name), now))
        res = solve_batch(batch, prep, epochs, self.tracks, self.config, self.gating)
        return v1_estimates(self, epochs, batch, res, int(now_wall_ns))

    def _count(self, out: ColumnBatch, now: int) -> ColumnBatch:
        """Counters and latencies of the v2 estimates ``out`` published at ``now`` (v1:
        ``v1_estimates``), from their columns."""
        self.seq += len(out)
        self.by_status.update(out.rows.status)
        self.latencies_ns.extend(out.rows.latencies(now))
        return out

    # ------------------------------------------------------------------ diagnostics
    def diagnostics(self, now_wall_ns: int) -> M.FusionDiagnostics:
        """Counters, why fixes were lost (late ranges per anchor, the release rule in force,
        release reasons) and the decision record since the previous call (``decisions``:
        handed out once, so call this only to publish it)."""
        lat = np.asarray(self.latencies_ns, dtype=np.float64) * 1e-6
        stats = M.LatencyStats(
            count=int(lat.size),
            p50_ms=float(np.percentile(lat, 50)) if lat.size else None,
            p99_ms=float(np.percentile(lat, 99)) if lat.size else None,
            max_ms=float(lat.max()) if lat.size else None,
        )
        wm = [a.last_t_ns for a in self.anchors.values() if a.last_t_ns is not None]
        self.changed = False
        book = self.book
        lags = {a: q for a in sorted(self.anchors) if (q := book.lag_ns(a)) is not None}
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
            late_by_anchor=dict(sorted(book.late_by_anchor.items())),
            deadline_ns=int(book.allowance_ns),
            max_lag_ns=int(book.max_lag_ns),
            lag_by_anchor=lags,
            releases={r: self.releases[r] for r in RELEASE_REASONS},
            decisions=None if self.decisions is None else self.decisions.take(),
        )
