"""The recorder service: every data message of a site into an MCAP file.

A thin Zenoh wrapper around :class:`diffpos_services.recording.writer.McapSink`:

* one data subscriber on every data key of the site (:meth:`Keys.everything`) with a bounded
  ``FifoChannel`` handler, drained by a thread of ours (when the channel is full Zenoh blocks,
  and publishers using ``CongestionControl.BLOCK`` slow down instead of losing messages);
* one liveliness subscriber on every token of the site (:meth:`Keys.alive_all`,
  ``history=True``), whose rare events (anchor joined / left) go to the recorder's liveliness
  channel (:meth:`Keys.recorder_liveliness`);
* a flush thread closing the chunk in progress every ``flush_interval_s`` so that after a
  SIGKILL at most the last interval is lost (``diffpos recover`` rewrites the rest into a
  valid file);
* the recorder's own liveliness token (:meth:`Keys.alive_recorder`) is declared once both
  subscribers exist, so whoever waits for it knows recording has started;
* the services' heartbeats (:mod:`diffpos_services.bus.heartbeat`) are recorded like data,
  on ``heartbeat/<service>`` and ``heartbeat/anchor/<id>`` channels (schema
  ``heartbeat.v1``): a recording shows which process stalled and when (``diffpos inspect``
  summarises them); replay and ``to-rerun`` do not read them. The recorder's own heartbeat
  is not written into its own file (counted in ``own_heartbeats``): whatever it writes shows
  it was not stalled then, so it could never show its own stall, and its counters are in
  the ``recorder_stats`` metadata; another recorder's heartbeats are recorded;
* the stop is bounded: the main thread waits for ``stop`` and joins in signal-poll slices
  (:func:`diffpos_services.shutdown.wait_event`: a SIGTERM taken by another thread is acted on),
  and after the session closed the drain thread is waited for until its channel is drained
  (:meth:`_Drain.finish`: bounded even if the channel stayed open; before it gives up it
  writes what the channel still holds). Everything received before the stop is written and
  the file is finished; the one exception is a sample the drain thread holds while it has
  been stalled for all of ``DRAIN_IDLE_S`` with the channel left open (counted in
  ``after_stop_dropped``).

Foreign messages (issue 15 item 9, issue 36 item 4). When the recorder has the run's secret
token (:data:`diffpos_services.bus.integrity.RUN_TOKEN_ENV`, handed by ``diffpos emulate``
in the environment, never written anywhere), a message on an estimate or diagnostics key is
the run's own only if it carries a valid MAC under that token bound to the full zenoh id
stamped on it (:class:`~diffpos_services.bus.integrity.Verifier`): a copy or a forgery is
foreign. A heartbeat is the run's own only with a valid MAC too (heartbeats are signed, not
stamped). Without a token, a run configuration naming the run's fusion by a zenoh id prefix
(``emulate.fusion_id_prefix``, older runs) is used as before; with a list of the run's anchors
(``fusion.anchors``), a message on the key of an anchor outside that list is foreign too.
A *foreign* message it is not written to the recording (which replay,
``to-rerun`` and the dashboard read as the run) but kept apart, unchanged, in
``<stem>.foreign.mcap`` next to it (evidence of who else published), counted per key, and the
counts are written into the recording as metadata ``foreign``. Why: a user replaying or
drawing a run expects the run's own data, and someone investigating expects the intruder's
messages not to vanish. Without such a run configuration (a stand-alone ``diffpos
recorder``) every message is recorded as before.
"""

from __future__ import annotations

import json
import logging
import math
import os
import platform
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh
from zenoh import handlers

from diffpos_services.bus.commands import foreign_path, recorder_args
from diffpos_services.bus.heartbeat import HeartbeatThread, Progress, process_nonce
from diffpos_services.bus.integrity import Verifier, run_token
from diffpos_services.bus.session import ZenohSettings, open_session
from diffpos_services.recording.writer import McapSink, SinkStats
from diffpos_services.shutdown import SIGNAL_POLL_S, join_thread, wait_event
from diffpos_services.wire.keys import Keys, parse_key

__all__ = [
    "Provenance",
    "RecorderOptions",
    "build_command",
    "default_output_path",
    "record",
]

log = logging.getLogger("diffpos.recorder")

#: after the session closed, how long the drain thread may wait in ``recv()`` with nothing
#: taken before the recorder stops waiting for it [s]: its channel is then empty, so every
#: sample received before the stop is written (see :meth:`_Drain.finish`)
DRAIN_IDLE_S = 1.0


def default_output_path(
    scenario: str, *, directory: str | os.PathLike[str] = "recordings", now_ns: int | None = None
) -> Path:
    """``<directory>/<scenario>-<UTC YYYYmmddTHHMMSSZ>.mcap``.

    Parameters
    ----------
    scenario : str
        Scenario name (file stem); characters outside ``[A-Za-z0-9_-]`` become ``_``.
    now_ns : int [ns], optional
        Time stamp to use (default: now).
    """
    t = time.time_ns() if now_ns is None else now_ns
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(t / 1e9))
    safe = "".join(c if c.isalnum() or c in "_-" else "_" for c in scenario) or "run"
    return Path(directory) / f"{safe}-{stamp}.mcap"


@dataclass(frozen=True)
class RecorderOptions:
    """How :func:`record` runs.

    Attributes
    ----------
    site : str
        Site whose ``diffpos/<site>/**`` is recorded.
    flush_interval_s : float [s]
        Chunk flush period: at most this much is lost on SIGKILL.
    queue_size : int
        Slots of the Zenoh FIFO between the network and the drain thread.
    duration_s : float or None [s]
        Stop on its own after this long (``None``: until ``stop`` is set).
    """

    site: str
    flush_interval_s: float = 0.2
    queue_size: int = 65536
    duration_s: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        Keys(self.site)  # validates the site id
        if not self.flush_interval_s > 0:
            raise ValueError(f"flush_interval_s={self.flush_interval_s} must be > 0 [s]")
        if self.queue_size < 1:
            raise ValueError(f"queue_size={self.queue_size} must be >= 1")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError(f"duration_s={self.duration_s} must be > 0 [s]")


StatusCallback = Callable[[str, dict[str, Any]], None]

#: key kinds only the run's fusion publishes
_FUSION_KINDS = frozenset({"estimate", "diagnostics"})
#: key kinds an anchor publishes (its id in the key)
_ANCHOR_KINDS = frozenset({"anchor_state", "range", "range_batch"})


@dataclass(frozen=True)
class Provenance:
    """Which messages belong to the run (see the module docstring).

    Attributes
    ----------
    fusion_id_prefix : str or None
        Zenoh id prefix of the run's fusion (``None``: any publisher's estimates belong);
        only used without a ``verifier``.
    anchors : frozenset of str or None
        The run's anchors (``None``: any anchor belongs).
    verifier : Verifier or None
        The run token's verifier: the fusion's messages must carry its MAC.
    """

    fusion_id_prefix: str | None = None
    anchors: frozenset[str] | None = None
    verifier: Verifier | None = None

    @classmethod
    def from_run_config(cls, run_config: dict[str, Any] | None,
                        token: bytes | None = None) -> Provenance | None:
        """From a run configuration (``{"fusion": {...}, "emulate": {...}}``, values possibly
        JSON text as in MCAP metadata) and the run's token; ``None`` if they name nothing."""
        verifier = Verifier(token) if token else None
        if not run_config:
            return cls(verifier=verifier) if verifier else None
        fusion, emu = (run_config.get(k) or {} for k in ("fusion", "emulate"))
        fusion, emu = (json.loads(v) if isinstance(v, str) else v for v in (fusion, emu))
        prefix = emu.get("fusion_id_prefix") if isinstance(emu, dict) else None
        anchors = fusion.get("anchors") if isinstance(fusion, dict) else None
        if not prefix and not anchors and verifier is None:
            return None
        return cls(str(prefix) if prefix else None,
                   frozenset(map(str, anchors)) if anchors else None, verifier)

    def foreign(self, key: str, sample: Any) -> bool:
        """True if the message on ``key`` (a zenoh sample) is not the run's own."""
        pk = parse_key(key)
        if pk is None:
            return False
        if pk.kind in _FUSION_KINDS and self.verifier is not None:
            return not self.verifier.ours(sample)
        if pk.kind in _FUSION_KINDS and self.fusion_id_prefix is not None:
            ts = sample.timestamp
            return ts is None or not str(ts.get_id()).startswith(self.fusion_id_prefix)
        if pk.kind == "heartbeat":
            if self.verifier is not None:  # signed like the fusion's, but not stamped
                return not self.verifier.ours(sample, stamped=False)
            return (pk.anchor_id is not None and self.anchors is not None
                    and pk.anchor_id not in self.anchors)
        if pk.kind in _ANCHOR_KINDS and self.anchors is not None:
            return pk.anchor_id not in self.anchors
        return False


class _ForeignSink:
    """The foreign messages of a recording: counted per key and written, unchanged, to
    :func:`foreign_path` (opened on the first one)."""

    def __init__(self, out: Path | None, compression: str = "zstd") -> None:
        self.path = foreign_path(out) if out is not None else None
        self.compression = compression
        self.sink: McapSink | None = None
        self.counts: dict[str, int] = {}
        self.lock = threading.Lock()

    def write(self, key: str, payload: bytes, rx_ns: int) -> None:
        with self.lock:
            self.counts[key] = self.counts.get(key, 0) + 1
            if self.path is None:
                return
            if self.sink is None:
                k = 1
                while self.path.exists():  # never over an existing file
                    self.path = foreign_path(self.path.with_name(
                        self.path.name.replace(".foreign", f"-{k}", 1)))
                    k += 1
                self.sink = McapSink(self.path, compression=self.compression)
                self.sink.add_metadata("foreign", {
                    "what": "messages on the run's keys that were not the run's own (not "
                            "from the run's fusion, or from an anchor outside the run): kept "
                            "apart from the recording, unchanged"})
            self.sink.write(key, payload, rx_ns)

    @property
    def count(self) -> int:
        return sum(self.counts.values())

    def flush(self) -> None:
        with self.lock:
            if self.sink is not None:
                self.sink.flush()

    def close(self, main: McapSink) -> dict[str, Any]:
        """Close the foreign file; record the counts in ``main`` (metadata ``foreign``)."""
        with self.lock:
            if self.sink is not None:
                self.sink.close()
        info = {"count": self.count, "file": self.path.name if self.sink is not None else "",
                "keys": dict(sorted(self.counts.items(), key=lambda kv: -kv[1])[:50])}
        if self.count:
            main.add_metadata("foreign", info)
        return info


def _run_config_of(sink: McapSink) -> dict[str, Any] | None:
    """The ``run_config`` metadata the sink was given (it repeats it in every part)."""
    for what, args in getattr(sink, "_side", ()):
        if what == "metadata" and args[0] == "run_config":
            return dict(args[1])
    return None


def record(
    settings: ZenohSettings,
    sink: McapSink,
    options: RecorderOptions,
    *,
    stop: threading.Event,
    on_status: StatusCallback | None = None,
) -> SinkStats:
    """Record until ``stop`` is set (or ``options.duration_s`` elapses).

    The sink is flushed but not closed (the caller closes it, adding final metadata).

    Parameters
    ----------
    settings : ZenohSettings
        How to join the bus.
    sink : McapSink
        Where messages go.
    options : RecorderOptions
    stop : threading.Event
        Set it (e.g. from a signal handler) to end recording.
    on_status : callable, optional
        ``on_status(event, fields)`` with events ``ready`` (subscribed), ``flush`` (after each
        flush that wrote something, fields ``flushed``, ``flushed_written``, ``received``,
        ``written``, ``gaps`` and ``by_kind``, written messages per kind) and
        ``stopped``. Called from the recorder's threads; keep it short.

    Returns
    -------
    stats : SinkStats
    """
    keys = Keys(options.site)
    emit = on_status or (lambda _e, _f: None)
    provenance = Provenance.from_run_config(_run_config_of(sink), run_token())
    foreign = _ForeignSink(sink.path)
    t_end = None if options.duration_s is None else time.monotonic() + options.duration_s
    session = open_session(settings, stop, logger=log)
    if session is None:  # stopped while waiting for the router
        return sink.stats
    with session:
        sub = session.declare_subscriber(
            keys.everything(), handlers.FifoChannel(options.queue_size)
        )
        live_sub = session.liveliness().declare_subscriber(
            keys.alive_all(), _liveliness_writer(sink, options.site), history=True
        )
        drainer = _Drain(sub, sink, stop, provenance, foreign,
                         own_heartbeat=(keys.heartbeat("recorder"), process_nonce()))
        drainer.start()
        flush_thread = threading.Thread(target=_flush_loop,
                                        args=(sink, options, stop, emit, foreign),
                                        name="recorder-flush", daemon=True)
        flush_thread.start()
        token = session.liveliness().declare_token(keys.alive_recorder())
        beat = HeartbeatThread(session, keys.heartbeat("recorder"), "recorder",
                               lambda: Progress(progress=drainer.taken,
                                                published=sink.stats.written),
                               logger=log).start()
        emit("ready", {"key": keys.everything(), "path": str(sink.path or "")})
        try:
            # never one unbounded wait in the main thread (kit.wait_event: a SIGTERM
            # delivered to another thread would not run the handler that sets ``stop``)
            wait_event(stop, None if t_end is None else max(0.0, t_end - time.monotonic()))
        finally:
            stop.set()
            beat.stop()
            join_thread(flush_thread)  # ends after the flush in progress
            live_sub.undeclare()  # first: our own token's DELETE is not an event
            token.undeclare()
    # leaving the with block closed the session: recv() drains what is queued, then raises
    # (or, should the channel stay open, waits with nothing queued: finish() stops there)
    if not drainer.finish(DRAIN_IDLE_S):
        log.warning("the subscriber's channel stayed open %.1f s after the session closed, "
                    "with nothing queued: stopped waiting for it", DRAIN_IDLE_S)
    foreign_info = foreign.close(sink)
    flushed = sink.flush()
    st = sink.stats
    emit(
        "stopped",
        {
            "flushed": flushed,
            "flushed_written": st.flushed_written,
            "received": st.received,
            "written": st.written,
            "gaps": st.gaps,
            "deletes_ignored": drainer.deletes,
            "after_stop_dropped": drainer.late,
            "foreign": foreign_info,
        },
    )
    return st


class _Drain(threading.Thread):
    """The thread moving samples from the Zenoh FIFO into the sink (heartbeats too, but its
    own; DELETEs are counted, not recorded; foreign messages go to ``foreign``, see :class:`Provenance`). Ends when the
    session is closed and every queued sample is written; :meth:`finish` waits for that,
    bounded."""

    def __init__(self, sub: Any, sink: McapSink, stop: threading.Event,
                 provenance: Provenance | None, foreign: _ForeignSink, *,
                 own_heartbeat: tuple[str, str] | None = None) -> None:
        super().__init__(name="recorder-drain", daemon=True)
        self.sub, self.sink, self.stop = sub, sink, stop
        self.provenance, self.foreign = provenance, foreign
        # (key, process nonce) of this recorder's heartbeat: not written (module docstring)
        self.own_key, self.own_tag = (None, b"") if own_heartbeat is None else (
            own_heartbeat[0], f'"instance":"{own_heartbeat[1]}"'.encode())
        self.own_heartbeats = 0
        self.deletes = 0
        self.taken = 0         # samples taken from the channel
        self.waiting = False   # in recv() (blocks there only while the channel is empty)
        self.late = 0          # samples taken after finish() gave up (not written)
        self._given_up = False
        self._lock = threading.Lock()  # a write vs finish() giving up

    def run(self) -> None:
        recv, lock = self.sub.recv, self._lock
        try:
            while True:
                self.waiting = True
                sample = recv()
                self.waiting = False
                self.taken += 1
                with lock:
                    if self._given_up:  # the sink is being closed: after the stop
                        self.late += 1
                    else:
                        self._put(sample)
        except zenoh.ZError:
            return  # channel closed: session closed and every queued sample drained
        except Exception:  # pragma: no cover - never let the drain thread die silently
            log.exception("recorder drain thread failed")
            self.stop.set()

    def _put(self, sample: Any) -> None:
        """One sample into the sink (a DELETE counted, a foreign message to ``foreign``);
        under ``_lock``."""
        if sample.kind != zenoh.SampleKind.PUT:
            self.deletes += 1
            return
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        if key == self.own_key and self.own_tag in payload:
            self.own_heartbeats += 1
            return
        if self.provenance is not None and self.provenance.foreign(key, sample):
            self.foreign.write(key, payload, time.time_ns())
        else:
            self.sink.write(key, payload, time.time_ns())

    def _take_queued(self) -> int:
        """Under ``_lock``: write what the channel still holds (``try_recv``, never blocks);
        returns how many samples there were."""
        n = 0
        try:
            while (sample := self.sub.try_recv()) is not None:
                n += 1
                self._put(sample)
        except zenoh.ZError:
            pass  # closed meanwhile: the thread ends on its own
        return n

    def finish(self, idle_s: float) -> bool:
        """Wait (bounded, in signal-poll slices) until the thread has ended, i.e. recv()
        raised after the session closed, every queued sample written. Should the channel
        stay open (a sender kept alive: zenoh-c #1240 / zenoh-pico #1120 describe session
        drops that do not close at once), stop waiting once the thread has looked idle in
        recv() (nothing taken) for ``idle_s`` [s] *and* over at least
        ``max(2, idle_s / SIGNAL_POLL_S)`` consecutive slices of this thread's own waiting:
        a process that was frozen (stopped, descheduled, a paused VM) for longer than
        ``idle_s`` does not count as idle on its first look after, when the drain thread
        has not run yet. Before giving up, whatever the channel still holds is taken and
        written here (a drain thread stalled right after a ``recv()`` would otherwise leave
        the queue behind it unwritten); if there was any, the thread was not idle and the
        wait goes on. What remains unavoidable: a sample the thread holds between its
        ``recv()`` and its next step while it has been stalled over all those slices is
        counted in ``late``, not written, as is any sample taken after this gives up.
        Returns True if the thread ended."""
        slices = max(2, math.ceil(idle_s / SIGNAL_POLL_S))
        last, since, idle = self.taken, time.monotonic(), 0
        while not join_thread(self, SIGNAL_POLL_S):
            if self.taken != last or not self.waiting:
                last, since, idle = self.taken, time.monotonic(), 0
                continue
            idle += 1
            if idle >= slices and time.monotonic() - since >= idle_s:
                with self._lock:
                    if self.taken != last:
                        continue
                    if self._take_queued():
                        last, since, idle = self.taken, time.monotonic(), 0
                        continue
                    self._given_up = True
                    return False
        return True


def _liveliness_writer(sink: McapSink, site: str) -> Callable[[Any], None]:
    """Liveliness subscriber callback: token PUT / DELETE -> the sink's liveliness channel."""

    def on_liveliness(sample) -> None:
        alive = sample.kind == zenoh.SampleKind.PUT
        sink.write_liveliness(site, str(sample.key_expr), alive, time.time_ns())

    return on_liveliness


def _flush_loop(sink: McapSink, options: RecorderOptions, stop: threading.Event,
                emit: StatusCallback, foreign: _ForeignSink) -> None:
    """Flush every ``flush_interval_s`` until ``stop``; a ``flush`` status after each flush
    that wrote something."""
    last = -1
    while not stop.wait(options.flush_interval_s):
        foreign.flush()
        flushed = sink.flush()
        if flushed != last:
            last = flushed
            st = sink.stats
            emit(
                "flush",
                {
                    "flushed": flushed,
                    "flushed_written": st.flushed_written,
                    "received": st.received,
                    "written": st.written,
                    "gaps": st.gaps,
                    "by_kind": sink.counts_by_kind(),
                    "foreign": foreign.count,
                },
            )


def run_metadata(
    settings: ZenohSettings,
    options: RecorderOptions,
    *,
    scenario: str | None,
    argv: list[str] | None = None,
) -> dict[str, Any]:
    """The ``run`` metadata record written at the start of every recording."""
    return {
        "site": options.site,
        "scenario": scenario or "",
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "started_ns": time.time_ns(),
        "host": platform.node(),
        "pid": os.getpid(),
        "argv": list(sys.argv if argv is None else argv),
        "zenoh": settings.to_json(),
        "flush_interval_s": options.flush_interval_s,
        "recorder": "diffpos recorder (mcap, jsonschema + json channels, zstd chunks)",
        **options.extra,
    }


def build_command(
    *,
    site: str,
    out: str | os.PathLike[str],
    connect: list[str] | tuple[str, ...],
    scenario: str | os.PathLike[str] | None = None,
    run_config: str | os.PathLike[str] | None = None,
    flush_interval_s: float = 0.2,
    status: bool = True,
    python: str | None = None,
    split_duration_s: float | None = None,
    split_size_mb: float | None = None,
) -> list[str]:
    """argv that starts the recorder as a subprocess (tests, benchmarks): ``python -m
    diffpos_services.cli.main`` + :func:`diffpos_services.bus.commands.recorder_args` (the
    one recorder command line, also ``diffpos emulate``'s).

    Run it in its own process group (``start_new_session=True``) and stop it with SIGTERM
    (SIGINT also works): it then writes the footer and exits 0. With ``status`` it prints
    JSON lines to stdout: ``{"event": "ready", ...}`` once subscribed, ``{"event": "flush",
    "flushed": N, ...}`` after each flush and ``{"event": "closed", ...}`` at the end.

    Parameters
    ----------
    site : str
    out : path
        MCAP file to write.
    connect : list of str
        Router endpoints.
    scenario : path, optional
        Scenario TOML, attached to the recording.
    run_config : path, optional
        JSON file with the run configuration, attached to the recording.
    split_duration_s, split_size_mb : float, optional
        ``--split-duration`` / ``--split-size`` (default: the recorder's defaults; 0 = off).
    """
    return [python or sys.executable, "-m", "diffpos_services.cli.main",
            *recorder_args(site=site, out=out, connect=connect, scenario=scenario,
                           run_config=run_config, flush_interval_s=flush_interval_s,
                           split_duration_s=split_duration_s, split_size_mb=split_size_mb,
                           status=status)]


def status_printer(stream=None) -> StatusCallback:
    """An ``on_status`` callback printing one JSON object per line (flushed at once)."""
    out = sys.stdout if stream is None else stream
    lock = threading.Lock()

    def emit(event: str, fields: dict[str, Any]) -> None:
        line = json.dumps({"event": event, "t_wall_ns": time.time_ns(), **fields})
        with lock:
            out.write(line + "\n")
            out.flush()

    return emit
