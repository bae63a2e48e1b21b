"""Heartbeats: each service says, every half second, how far its work has come.

Liveliness alone does not tell a working process from a stopped one: a SIGSTOPped process
keeps its token for the whole lease (10 s by default) and a stuck one keeps it forever.
:class:`HeartbeatThread` publishes a :class:`~diffpos_services.wire.messages.Heartbeat` on
:meth:`~diffpos_services.wire.keys.Keys.heartbeat` from a thread of its own, with the
service's progress counter (work done, only grows) and the work waiting; ``diffpos
emulate``'s supervisor (:mod:`diffpos_services.emulate.supervise`) judges from them.

Every heartbeat carries :func:`process_nonce` (random per process start), which the anchors
also attach to every message they publish: two processes under one anchor key are told apart
(:class:`diffpos_services.bus.integrity.PublisherGuard`). With a run token
(:func:`diffpos_services.bus.integrity.run_token`) the heartbeat is signed like the fusion's
estimates.
"""

from __future__ import annotations

import functools
import logging
import os
import secrets
import threading
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import zenoh

from diffpos_services.bus.integrity import Signer
from diffpos_services.logs import log_event
from diffpos_services.wire import messages as M

__all__ = ["HEARTBEAT_PERIOD_S", "HeartbeatThread", "Progress", "process_nonce"]

#: heartbeat period [s]
HEARTBEAT_PERIOD_S = 0.5


@functools.cache
def process_nonce() -> str:
    """16 hex digits, random, fixed for this process (a new one after every start)."""
    return secrets.token_hex(8)


class Progress(NamedTuple):
    """What a service reports in its heartbeat (see :class:`~diffpos_services.wire.
    messages.Heartbeat`)."""

    progress: int
    pending: int = 0
    last_epoch: int | None = None
    published: int = 0


class HeartbeatThread:
    """Publish ``service``'s heartbeat on ``key`` every ``period_s`` until :meth:`stop`.

    Parameters
    ----------
    session : zenoh.Session
    key : str
        :meth:`Keys.heartbeat` of the service.
    service : str
        ``fusion``, ``recorder``, ``anchor`` or ``dashboard``.
    progress : callable
        ``progress() -> Progress``, called from this thread (read counters only).
    anchor_id : str, optional
    """

    def __init__(self, session: Any, key: str, service: str, progress: Callable[[], Progress],
                 *, anchor_id: str | None = None, period_s: float = HEARTBEAT_PERIOD_S,
                 logger: logging.Logger | None = None) -> None:
        self.key, self.service, self.progress = key, service, progress
        self.anchor_id, self.period_s = anchor_id, period_s
        self.log = logger or logging.getLogger("diffpos")
        self.pub = session.declare_publisher(key, encoding=zenoh.Encoding.APPLICATION_JSON,
                                             congestion_control=zenoh.CongestionControl.BLOCK)
        self.signer = Signer.for_session(session)
        self.seq = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"{service}-heartbeat",
                                        daemon=True)

    def start(self) -> HeartbeatThread:
        self._thread.start()
        return self

    def beat(self) -> None:
        """Publish one heartbeat now."""
        p = self.progress()
        msg = M.Heartbeat(service=self.service, instance=process_nonce(), pid=os.getpid(),
                          seq=self.seq, t_wall_ns=time.time_ns(),
                          period_ns=round(self.period_s * 1e9), progress=max(int(p.progress), 0),
                          pending=max(int(p.pending), 0), last_epoch=p.last_epoch,
                          published=max(int(p.published), 0), anchor_id=self.anchor_id)
        self.seq += 1
        data = M.encode(msg)
        self.pub.put(data, attachment=self.signer.attachment(self.key, data))

    def _loop(self) -> None:
        failed = False
        while True:
            try:
                self.beat()
            except Exception as exc:  # the session is closing, or a bug: said once
                if not failed and not self._stop.is_set():
                    log_event(self.log, logging.WARNING, "heartbeat not sent", error=str(exc))
                failed = True
            if self._stop.wait(self.period_s):
                return

    def stop(self) -> None:
        """End the thread and undeclare the publisher (before the session closes)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        try:
            self.pub.undeclare()
        except Exception:  # pragma: no cover - session already closed
            pass
