"""The fusion process: :class:`~diffpos_services.fusion.core.FusionCore` on a Zenoh session.

Zenoh's callbacks only put raw samples on a bounded queue (:class:`_Inbox`; a full queue
blocks Zenoh, which with congestion control BLOCK pushes back on the anchors instead of
dropping); the main thread drains the queue, decodes, aligns, solves and publishes (no work
on Zenoh's threads). Steps of :func:`run_fusion`: open the session -> declare publishers,
the one subscriber and the liveliness token -> serve (wait, ingest, step, publish,
diagnostics) until ``stop`` -> flush what is pending and undeclare.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import zenoh

from diffpos_services.bus.session import ZenohSettings, open_session
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.core import FusionCore
from diffpos_services.kit import log_event
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key

__all__ = ["fusion_subscription", "run_fusion"]

_ACCOUNTED_BYTES = 2048  # samples above this size count against max_queued_bytes
_DRAIN_BUDGET = 20_000  # samples ingested between two solve steps at most
# queue items: (kind, key, value, receive wall time [ns])
_DATA, _ALIVE, _OVERSIZED = 0, 1, 2


def fusion_subscription(keys: Keys) -> str:
    """The one key expression the fusion subscribes to (:meth:`Keys.fusion_inputs`).

    One subscriber for states, ranges and range batches of every anchor, so each anchor's
    messages reach the fusion's queue in their publish order (with several subscribers an
    anchor's range could be queued before its state of the same instant, and the fusion then
    extrapolated the anchor from its previous state). It never matches ``truth/**`` (tested).
    Keys under ``anchor/`` that are not fusion inputs are counted as ``unexpected_key``.
    """
    (key_expr,) = keys.fusion_inputs()
    return key_expr


class _Inbox:
    """The bounded queue between Zenoh's threads and the fusion's thread.

    Bounded in samples (small ones) and in bytes (large ones, e.g. range batches): a full
    queue blocks Zenoh's thread, which paces BLOCK publishers. A sample over
    ``max_message_bytes`` is never copied nor queued (only its size): bounded memory whatever
    arrives.
    """

    def __init__(self, config: FusionConfig, stop: threading.Event) -> None:
        self.q: queue.Queue = queue.Queue(maxsize=config.queue_size)
        self.stop = stop
        self.max_bytes = config.max_message_bytes
        self.max_queued = config.max_queued_bytes
        self.queued = 0
        self.room = threading.Condition()

    def release(self, size: int) -> None:
        with self.room:
            self.queued -= size
            self.room.notify_all()

    def on_data(self, sample: zenoh.Sample) -> None:
        size = len(sample.payload)
        if size > self.max_bytes:
            self.q.put((_OVERSIZED, str(sample.key_expr), size, time.time_ns()))
            return
        if size > _ACCOUNTED_BYTES:
            with self.room:
                while (self.queued > 0 and self.queued + size > self.max_queued
                       and not self.stop.is_set()):
                    self.room.wait(0.1)
                self.queued += size
        self.q.put((_DATA, str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    def on_alive(self, sample: zenoh.Sample) -> None:
        self.q.put((_ALIVE, str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT,
                    time.time_ns()))


@dataclass
class _Endpoints:
    """What the fusion declared on its session."""

    session: Any
    diag_pub: Any
    subs: list[Any]
    live_sub: Any
    token: Any
    est_pubs: dict[str, Any]

    def publish(self, core: FusionCore, estimates: Iterable[M.PositionEstimate]) -> None:
        """Publish estimates, one publisher per node (declared on its first estimate)."""
        for est in estimates:
            pub = self.est_pubs.get(est.node_id)
            if pub is None:
                pub = self.est_pubs[est.node_id] = self.session.declare_publisher(
                    core.keys.node_estimate(est.node_id),
                    encoding=zenoh.Encoding.APPLICATION_JSON,
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
            pub.put(M.encode(est))
            core.published += 1


def _declare(session: Any, keys: Keys, inbox: _Inbox) -> _Endpoints:
    diag_pub = session.declare_publisher(
        keys.fusion_diagnostics(),
        encoding=zenoh.Encoding.APPLICATION_JSON,
        congestion_control=zenoh.CongestionControl.BLOCK,
    )
    # ONE subscriber: an anchor's states, ranges and batches keep their publish order
    subs = [session.declare_subscriber(fusion_subscription(keys), inbox.on_data)]
    live_sub = session.liveliness().declare_subscriber(
        keys.alive_anchors(), inbox.on_alive, history=True
    )
    token = session.liveliness().declare_token(keys.alive_fusion())
    return _Endpoints(session, diag_pub, subs, live_sub, token, {})


def _ingest(core: FusionCore, inbox: _Inbox, item: tuple, log: logging.Logger) -> None:
    """Hand one queued item to the core; a bug (not bad input) is counted and logged once."""
    kind, key, val, rx = item
    try:
        if kind == _DATA:
            if len(val) > _ACCOUNTED_BYTES:
                inbox.release(len(val))
            core.on_sample(key, val, time.time_ns())
        elif kind == _OVERSIZED:
            core.on_oversized(key, val)
        else:
            pk = parse_key(key)
            if pk is not None and pk.anchor_id is not None:
                core.on_liveliness(pk.anchor_id, bool(val), rx)
    except Exception as exc:  # a bug, not bad input: count, log once, go on
        core.rejected["internal_error"] += 1
        if core.rejected["internal_error"] == 1:
            log.exception("internal error while ingesting %s: %s", key, exc)


def _drain(core: FusionCore, inbox: _Inbox, item: tuple | None, linger_s: float,
           log: logging.Logger) -> None:
    """Ingest ``item`` and what is queued after it (bounded, so solving and diagnostics
    keep going). Epoch deadlines count from each sample's own ingestion, so neither a
    backlog nor a long drain releases epochs before their queued ranges were seen."""
    budget = _DRAIN_BUDGET
    while item is not None:
        _ingest(core, inbox, item, log)
        budget -= 1
        try:
            item = inbox.q.get_nowait() if budget > 0 else None
        except queue.Empty:
            # linger briefly: an anchor publishes its ranges to all nodes back to back, so
            # waiting ~1 ms batches them into one solve
            try:
                item = inbox.q.get(timeout=linger_s) if budget > 0 else None
            except queue.Empty:
                item = None


def _next_item(core: FusionCore, inbox: _Inbox, next_diag: int) -> tuple | None:
    """The next queued item, waiting at most until the next epoch deadline or diagnostics
    (not at all with a solve backlog, at most 0.1 s)."""
    now = time.time_ns()
    dl = core.book.next_deadline_wall_ns()
    wake = min(next_diag, dl if dl is not None else next_diag)
    timeout = 0.0 if core.backlog else min(max((wake - now) * 1e-9, 0.0), 0.1)
    try:
        return inbox.q.get(timeout=timeout)
    except queue.Empty:
        return None


def _serve(core: FusionCore, inbox: _Inbox, ends: _Endpoints, stop: threading.Event,
           log: logging.Logger) -> None:
    """Wait, ingest, solve and publish until ``stop``; diagnostics every period and on
    every liveliness change."""
    config = core.config
    period_ns = int(config.diagnostics_period_s * 1e9)
    next_diag = time.time_ns() + period_ns
    while not stop.is_set():
        _drain(core, inbox, _next_item(core, inbox, next_diag), config.linger_s, log)
        now = time.time_ns()
        ends.publish(core, core.step(now, limit=config.max_fixes_per_step))
        if now >= next_diag or core.changed:
            ends.diag_pub.put(M.encode(core.diagnostics(now)))
            next_diag = now + period_ns


def _close(core: FusionCore, ends: _Endpoints, log: logging.Logger) -> None:
    """Flush what is pending (nothing already received is lost), then undeclare."""
    for est in core.flush(time.time_ns()):
        ends.session.put(
            core.keys.node_estimate(est.node_id),
            M.encode(est),
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        core.published += 1
    ends.diag_pub.put(M.encode(core.diagnostics(time.time_ns())))
    ends.token.undeclare()
    ends.live_sub.undeclare()
    for s in ends.subs:
        s.undeclare()
    log_event(log, logging.INFO, "fusion stopped", solved=core.solved,
              published=core.published, rejected=dict(core.rejected))


def run_fusion(
    config: FusionConfig,
    zenoh_config: Any,
    stop: threading.Event,
    *,
    logger: logging.Logger | None = None,
    on_ready: Callable[[], None] | None = None,
) -> FusionCore:
    """Run the fusion on a Zenoh session until ``stop`` is set.

    ``zenoh_config`` is a :class:`~diffpos_services.bus.session.ZenohSettings` (opened with
    retries until ``stop``) or a ``zenoh.Config``. Returns the core (its counters).
    """
    log = logger or logging.getLogger("diffpos.fusion")
    core = FusionCore(config, logger=log)
    inbox = _Inbox(config, stop)
    core.warm_up()
    session = open_session(zenoh_config, stop, logger=log) if isinstance(
        zenoh_config, ZenohSettings) else zenoh.open(zenoh_config)
    if session is None:
        return core
    with session:
        ends = _declare(session, core.keys, inbox)
        log_event(log, logging.INFO, "fusion ready", site=config.site,
                  subscriptions=[fusion_subscription(core.keys)])
        if on_ready is not None:
            on_ready()
        try:
            _serve(core, inbox, ends, stop, log)
        finally:
            _close(core, ends, log)
    return core
