"""Live Rerun dashboard: a Zenoh subscriber process that streams the bus into Rerun.

The service is deliberately *outside* the fusion hot path:

* it subscribes (as its own Zenoh client) only to what it draws: anchor states, estimates,
  node truth, fusion diagnostics and liveliness tokens (never the high-rate range messages);
* the Zenoh callbacks only append ``(kind, payload)`` to a bounded ring buffer
  (``collections.deque(maxlen=N)``, O(1), never blocks): when the viewer or this process falls
  behind, the *oldest* undrawn messages are dropped and counted, the publishers are never
  slowed down;
* a drain loop wakes every ``drain_period_s``, decodes the batch and logs it with
  ``send_columns`` through :class:`diffpos_services.dashboard.stream.Dashboard` (one call per entity
  per batch, not per message).

Like every service it publishes a heartbeat (:mod:`diffpos_services.bus.heartbeat`) on
:meth:`Keys.heartbeat` ``("dashboard")``: its progress is the number of messages taken out of
the ring buffer by the drain loop, its pending work the messages waiting in it. ``diffpos
emulate``'s supervisor judges it from them: a dashboard stopped (no heartbeat) or stuck (the
drain loop not taking what waits, e.g. blocked in the Rerun SDK) for its stall time is a
hung fault.

Rerun output (``RerunTarget``): ``spawn`` a native viewer (needs a display), ``serve`` a gRPC
server plus the web viewer over HTTP, ``save`` an .rrd file, ``off`` (count only; for tests
and benchmarks). ``auto`` picks spawn when a display is available, otherwise serve.
"""

from __future__ import annotations

import collections
import logging
import os
import shutil
import sys
import threading
import time
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import rerun as rr
import zenoh  # this module is the dashboard process's service (liveliness sample kinds)

from diffpos_services.bus.heartbeat import HeartbeatThread, Progress
from diffpos_services.bus.integrity import Verifier, run_token
from diffpos_services.dashboard.blueprint import default_blueprint
from diffpos_services.dashboard.building import BuildingOutline
from diffpos_services.dashboard.columns import EventColumns
from diffpos_services.dashboard.common import APP_ID
from diffpos_services.dashboard.decode import VIEW_DECODERS
from diffpos_services.dashboard.events import end_text, is_normal_end, lost_text
from diffpos_services.dashboard.stream import Dashboard
from diffpos_services.logs import log_event
from diffpos_services.processes import free_tcp_port
from diffpos_services.wire.keys import Keys, parse_key

__all__ = [
    "DashboardService",
    "RerunTarget",
    "ServiceStats",
    "describe_target",
    "display_available",
    "open_rerun",
    "web_viewer_url",
]

Mode = Literal["auto", "spawn", "serve", "save", "off"]


def display_available() -> bool:
    """True if a native viewer can open a window (X11/Wayland display, or macOS/Windows)."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


@dataclass(frozen=True)
class RerunTarget:
    """Where the dashboard goes.

    Attributes
    ----------
    mode : {"auto", "spawn", "serve", "save", "off"}
    path : str, optional
        Output .rrd for ``save``.
    grpc_port, web_port : int
        Ports of ``serve`` (0 = pick a free port).
    bind : str
        Host name printed in the web-viewer URL.
    memory_limit : str
        Memory budget of the gRPC server / spawned viewer (oldest data dropped beyond it).
    """

    mode: Mode = "auto"
    path: str | None = None
    grpc_port: int = 9876
    web_port: int = 9090
    bind: str = "127.0.0.1"
    memory_limit: str = "1GiB"

    def __post_init__(self) -> None:
        if self.mode not in ("auto", "spawn", "serve", "save", "off"):
            raise ValueError(f"rerun mode {self.mode!r}: use spawn, serve, save PATH or off")
        if self.mode == "save" and not self.path:
            raise ValueError("rerun mode save needs a PATH, e.g. --rerun save out/live.rrd")
        for name in ("grpc_port", "web_port"):
            port = getattr(self, name)
            if not 0 <= port < 65536:
                raise ValueError(f"{name}={port} must be a TCP port (0 = any free port)")


def _ensure_viewer_on_path() -> None:
    """``spawn`` runs the ``rerun`` executable from PATH; the one of this Python environment
    (rerun-sdk's wheel) is used when the venv is not activated (``/path/venv/bin/diffpos``)."""
    if shutil.which("rerun"):
        return
    here = Path(sys.executable).parent
    if (here / "rerun").exists():
        os.environ["PATH"] = f"{here}{os.pathsep}{os.environ.get('PATH', '')}"
        return
    raise RuntimeError(
        "--rerun spawn needs the `rerun` viewer executable (it comes with rerun-sdk); it is "
        "not on PATH: activate the virtual environment, or use --rerun serve / save PATH"
    )


def web_viewer_url(url: str, *, host: str, web_port: int) -> str:
    """URL of the hosted web viewer that connects to the gRPC server ``url``."""
    return f"http://{host}:{web_port}/?url={urllib.parse.quote(url, safe='')}"


def describe_target(target: RerunTarget) -> str:
    """The sentence telling a user how to open the dashboard (nothing is opened).

    ``diffpos emulate`` can print this for the dashboard process it starts. For ``serve``
    the ports must be explicit (not 0) for the URL to be known in advance.
    """
    mode = target.mode
    if mode == "auto":
        mode = "spawn" if display_available() else "serve"
    if mode == "spawn":
        return "Rerun viewer spawned (native window)"
    if mode == "serve":
        url = f"rerun+http://{target.bind}:{target.grpc_port}/proxy"
        view = web_viewer_url(url, host=target.bind, web_port=target.web_port)
        return (
            f"Rerun web viewer: open {view} in a browser, or run `rerun {url}` "
            "for the native viewer"
        )
    if mode == "save":
        return f"Rerun recording saved to {target.path} (open it with `rerun {target.path}`)"
    return "Rerun output off"


def open_rerun(
    target: RerunTarget, *, recording_id: str | None = None
) -> tuple[rr.RecordingStream, str]:
    """A recording stream connected to ``target``, and a sentence saying how to view it.

    Never spawns a viewer without a display (``auto`` falls back to ``serve``; an explicit
    ``spawn`` without a display raises ``RuntimeError`` with what to do instead).
    """
    if target.mode == "off":  # a disabled stream: every log call is a cheap no-op
        return rr.RecordingStream(APP_ID, recording_id=recording_id, default_enabled=False), (
            "Rerun output off"
        )
    rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
    bp = default_blueprint()
    mode = target.mode
    if mode == "auto":
        mode = "spawn" if display_available() else "serve"
    if mode == "spawn":
        if not display_available():
            raise RuntimeError(
                "--rerun spawn needs a display (DISPLAY/WAYLAND_DISPLAY is not set); use "
                "--rerun serve (web viewer) or --rerun save PATH instead"
            )
        _ensure_viewer_on_path()
        rec.spawn(memory_limit=target.memory_limit, default_blueprint=bp)
        return rec, "Rerun viewer spawned (native window)"
    if mode == "serve":
        grpc_port = target.grpc_port or free_tcp_port()
        web_port = target.web_port or free_tcp_port()
        url = rec.serve_grpc(
            grpc_port=grpc_port, default_blueprint=bp, server_memory_limit=target.memory_limit
        )
        rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=url)
        view = web_viewer_url(url, host=target.bind, web_port=web_port)
        return rec, (
            f"Rerun web viewer: open {view} in a browser, or run `rerun {url}` "
            "for the native viewer"
        )
    if mode == "save":
        path = Path(str(target.path))
        path.parent.mkdir(parents=True, exist_ok=True)
        rec.save(str(path), default_blueprint=bp)
        return rec, f"Rerun recording saved to {path} (open it with `rerun {path}`)"
    raise AssertionError(f"unhandled rerun mode {mode!r}")  # pragma: no cover


@dataclass
class ServiceStats:
    """Counters of the dashboard service.

    Attributes
    ----------
    received : int
        Messages put in the ring buffer by the Zenoh callbacks.
    drawn : int
        Messages decoded and logged.
    dropped : int
        Messages pushed out of the full ring buffer before they were drawn.
    undecodable : int
        Payloads that were not valid messages.
    batches : int
        Drain cycles that logged something.
    max_batch : int
        Largest batch.
    lag_ms : float [ms]
        Wall time from the newest estimate's publish to the end of its batch's logging.
    foreign : int
        Estimates and diagnostics not drawn because another publisher than the expected
        fusion sent them (``estimates_from``).
    """

    received: int = 0
    drawn: int = 0
    dropped: int = 0
    undecodable: int = 0
    batches: int = 0
    max_batch: int = 0
    log_time_s: float = 0.0
    lag_ms: float = 0.0
    per_kind: dict[str, int] = field(default_factory=dict)
    foreign: int = 0


class DashboardService:
    """Subscribe to a diffpos site and stream it into a Rerun recording stream.

    Parameters
    ----------
    session : zenoh.Session
        An open session (the caller owns it).
    rec : rerun.RecordingStream
    site : str
    building : BuildingOutline, optional
    ring_size : int
        Capacity of the ring buffer [messages]; the oldest are dropped beyond it.
    drain_period_s : float [s]
        How often the buffer is drained into Rerun.
    estimates_from : str, optional
        Draw only estimates and diagnostics whose sample timestamp names a zenoh id starting
        with this (``diffpos emulate`` gives its fusion such an id); others are counted as
        ``foreign``. ``None``: draw every publisher's. With the run's secret token in the
        environment (:data:`~diffpos_services.bus.integrity.RUN_TOKEN_ENV`, as ``diffpos
        emulate`` starts it) the prefix is not trusted: only publications with a valid MAC
        under the token (bound to the full zenoh id stamped on them) are drawn.
    logger : logging.Logger, optional
    """

    #: the bus kinds drawn, and their fast view decoders (see ``dashboard.VIEW_DECODERS``)
    _DECODERS: ClassVar[dict[str, Any]] = {
        k: VIEW_DECODERS[k].decode
        for k in ("anchor_state", "estimate", "truth_node", "diagnostics")
    }

    def __init__(
        self,
        session: Any,
        rec: rr.RecordingStream,
        *,
        site: str,
        building: BuildingOutline | None = None,
        ring_size: int = 200_000,
        drain_period_s: float = 0.5,
        logger: logging.Logger | None = None,
        estimates_from: str | None = None,
    ) -> None:
        if ring_size < 1:
            raise ValueError("ring_size must be >= 1")
        if drain_period_s <= 0:
            raise ValueError("drain_period_s must be > 0")
        self.session = session
        self.rec = rec
        self.keys = Keys(site)
        self.dashboard = Dashboard(rec, building=building)
        self.ring: collections.deque[tuple[str, bytes, int]] = collections.deque(maxlen=ring_size)
        self.ring_size = ring_size
        self.estimates_from = estimates_from
        token = run_token() if estimates_from is not None else None
        self.verifier = Verifier(token) if token else None
        self.drain_period_s = drain_period_s
        self.stats = ServiceStats()
        self.log = logger or logging.getLogger("diffpos.dashboard")
        self._kind_cache: dict[str, str | None] = {}
        self._subs: list[Any] = []
        self._deferred: list[Any] = []
        self._truth_t_ns: int | None = None
        self._clock_offset_ns: int | None = None  # measurement time - wall time
        self._pending_live: list[tuple[int, str, bool]] = []
        self._leaves: list[tuple[int, str]] = []  # left, not yet known whether lost
        self._last_data_wall: int | None = None
        self._lock = threading.Lock()
        self._received_cv = threading.Condition()
        self._want_received: int | None = None  # set while wait_received() waits
        self._taken = 0  # messages the drain loop took out of the ring (heartbeat progress)
        self._beat: HeartbeatThread | None = None

    # -- zenoh side (never blocks) -------------------------------------------------------
    def _on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        kind = self._kind_cache.get(key)
        if kind is None and key not in self._kind_cache:
            pk = parse_key(key)
            kind = pk.kind if pk is not None and pk.kind in self._DECODERS else None
            self._kind_cache[key] = kind
        if kind is None:
            return
        if self.estimates_from is not None and kind in ("estimate", "diagnostics"):
            ts = sample.timestamp
            if (not self.verifier.ours(sample) if self.verifier is not None else
                    ts is None or not str(ts.get_id()).startswith(self.estimates_from)):
                self.stats.foreign += 1
                return
        ring = self.ring
        if len(ring) == self.ring_size:
            self.stats.dropped += 1
        ring.append((kind, sample.payload.to_bytes(), time.time_ns()))
        self.stats.received += 1
        want = self._want_received
        if want is not None and self.stats.received >= want:
            with self._received_cv:
                self._received_cv.notify_all()

    def wait_received(self, n: int, *, timeout_s: float) -> bool:
        """Block until ``n`` data samples were received in total (or ``timeout_s`` [s]
        passed); True if they were. For tests and benchmarks that must not stop the service
        before what they published has arrived."""
        with self._received_cv:
            self._want_received = n
            try:
                return self._received_cv.wait_for(lambda: self.stats.received >= n,
                                                  timeout=timeout_s)
            finally:
                self._want_received = None

    def _on_liveliness(self, sample: Any) -> None:
        key = str(sample.key_expr)
        pk = parse_key(key)
        if pk is None or pk.kind not in ("alive_anchor", "alive_fusion"):
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        who = f"anchor {pk.anchor_id}" if pk.kind == "alive_anchor" else "fusion"
        with self._lock:
            self._pending_live.append((time.time_ns(), who, alive))

    def start(self) -> None:
        """Declare the subscribers (data keys and liveliness), then the dashboard's own
        liveliness token (:meth:`Keys.alive_dashboard`): who waits for it (``diffpos
        emulate``) knows from then on every published sample reaches the Rerun sink."""
        k = self.keys
        for expr in (
            k.anchor_states(),
            k.estimates(),
            k.truth_node("*"),  # every node's truth (wire/keys has no truth_nodes() pattern)
            k.fusion_diagnostics(),
        ):
            self._subs.append(self.session.declare_subscriber(expr, self._on_sample))
        self._subs.append(
            self.session.liveliness().declare_subscriber(
                k.alive_all(), self._on_liveliness, history=True
            )
        )
        self._subs.append(self.session.liveliness().declare_token(k.alive_dashboard()))
        self._beat = HeartbeatThread(self.session, k.heartbeat("dashboard"), "dashboard",
                                     self.progress, logger=self.log).start()

    def progress(self) -> Progress:
        """The heartbeat's figures: messages taken from the ring buffer (only grows), messages
        waiting in it, messages drawn (read from the heartbeat thread)."""
        return Progress(progress=self._taken, pending=len(self.ring), published=self.stats.drawn)

    def close(self) -> None:
        """Stop the heartbeat, undeclare the subscribers, draw what is left, flush the
        recording."""
        if self._beat is not None:
            self._beat.stop()
            self._beat = None
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception:  # session already closed
                pass
        self._subs.clear()
        self.drain(final=True)
        if self.rec.is_enabled():
            self.rec.flush()

    # -- drain side ----------------------------------------------------------------------
    def drain(self, *, final: bool = False) -> int:
        """Decode and log everything in the ring buffer; returns the number of messages."""
        ring = self.ring
        n = len(ring)
        items = [ring.popleft() for _ in range(n)]
        self._taken += n
        by_kind: dict[str, list[Any]] = {k: [] for k in self._DECODERS}
        bad = 0
        for kind, payload, _ in items:
            try:
                by_kind[kind].append(self._DECODERS[kind](payload))
            except ValueError:
                bad += 1
        self.stats.undecodable += bad
        for kind, msgs in by_kind.items():
            if msgs:
                self.stats.per_kind[kind] = self.stats.per_kind.get(kind, 0) + len(msgs)
        anchors = by_kind["anchor_state"]
        if anchors:
            last = max(anchors, key=lambda a: a.t_ns)
            self._clock_offset_ns = last.t_ns - last.t_pub_wall_ns
        truth = by_kind["truth_node"]
        if truth:
            newest = max(t.t_ns for t in truth)
            self._truth_t_ns = newest if self._truth_t_ns is None else max(self._truth_t_ns, newest)
        # new estimates wait (at most one drain period) for the truth of their time, so the
        # error series compare like with like; what was deferred last time goes out now
        new = by_kind["estimate"]
        estimates, self._deferred = self._deferred, []
        if self._truth_t_ns is not None and not final:
            estimates += [e for e in new if e.t_ns <= self._truth_t_ns]
            self._deferred = [e for e in new if e.t_ns > self._truth_t_ns]
        else:
            estimates += new
        walls = [m.t_pub_wall_ns for m in (*anchors, *new) if m.t_pub_wall_ns]
        events = self._liveliness_events(max(walls) if walls else None, final=final)
        t0 = time.perf_counter()
        self.dashboard.add(
            anchor_states=anchors,
            truth=truth,
            estimates=estimates,
            diagnostics=by_kind["diagnostics"],
            events=events,
        )
        done_wall = time.time_ns()
        self.stats.log_time_s += time.perf_counter() - t0
        if estimates:
            self.stats.lag_ms = (done_wall - max(e.t_pub_wall_ns for e in estimates)) / 1e6
        if n:
            self.stats.batches += 1
            self.stats.max_batch = max(self.stats.max_batch, n)
            self.stats.drawn += n - bad
        return n

    def _liveliness_events(self, data_wall_ns: int | None, *, final: bool = False
                           ) -> EventColumns | None:
        """Joined events now; a service that left is held until it is known whether the run
        went on without it (data published :data:`~.events.END_GRACE_NS` after it left: a
        WARN, lost) or ended with it (no data since, or the dashboard stopping: one INFO
        "run ended" event for all of them). ``data_wall_ns``: newest publish wall time of
        this batch's data."""
        with self._lock:
            pending, self._pending_live = self._pending_live, []
        if self._clock_offset_ns is None:
            if pending:
                with self._lock:  # keep until the clock offset is known
                    self._pending_live = pending + self._pending_live
            return None
        if data_wall_ns is not None:
            self._last_data_wall = max(self._last_data_wall or 0, data_wall_ns)
        off = self._clock_offset_ns
        parts = [EventColumns([w + off for w, _, a in pending if a],
                              [f"{who} joined" for _, who, a in pending if a],
                              ["INFO" for _, _, a in pending if a])]
        self._leaves += [(w, who) for w, who, a in pending if not a]
        last = self._last_data_wall or 0
        lost = [(w, who) for w, who in self._leaves if not is_normal_end(w, last)]
        self._leaves = [x for x in self._leaves if x not in lost]
        parts.append(EventColumns([w + off for w, _ in lost], [lost_text(who) for _, who in lost],
                                  ["WARN"] * len(lost)))
        if final and self._leaves:
            parts.append(EventColumns([max(w for w, _ in self._leaves) + off],
                                      [end_text([who for _, who in self._leaves])], ["INFO"]))
            self._leaves = []
        events = EventColumns.concat(parts)
        return events if events.t_ns.size else None

    def run(self, stop: threading.Event | Any, *, report_every_s: float = 10.0) -> ServiceStats:
        """Drain periodically until ``stop`` is set; then close. Returns the final stats."""
        self.start()
        next_report = time.monotonic() + report_every_s
        try:
            while not stop.wait(self.drain_period_s):
                self.drain()
                if time.monotonic() >= next_report:
                    next_report += report_every_s
                    self._report()
        finally:
            self.close()
            self._report(final=True)
        return self.stats

    def _report(self, *, final: bool = False) -> None:
        s = self.stats
        log_event(
            self.log,
            logging.INFO,
            "dashboard stopped" if final else "dashboard running",
            received=s.received,
            drawn=s.drawn,
            dropped=s.dropped,
            undecodable=s.undecodable,
            batches=s.batches,
            max_batch=s.max_batch,
            log_time_s=round(s.log_time_s, 3),
            lag_ms=round(s.lag_ms, 1),
            per_kind=s.per_kind,
            foreign=s.foreign,
        )
