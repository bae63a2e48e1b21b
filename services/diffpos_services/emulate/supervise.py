"""Faults of an emulated run: a child that dies is reported, and the fusion and the recorder
are restarted.

:class:`Supervisor` watches the processes of an :class:`~diffpos_services.emulate.Emulation`
from its own thread while the run lasts. A process that exits is a :class:`Fault` (what
died, when, its exit code); the fusion is started again on the same command line (it
resumes from the bus: it needs nothing but the anchors' messages) and the recorder with a
new file (``<stem>-restart<k>.mcap``) while the dead recorder's truncated file is recovered
in place (:func:`diffpos_services.recording.repair.recover`: every complete chunk, indexed).
An anchor that ends the run on its own (exit code 0) is not a fault. A recorder is not
restarted onto a full disk (less than :data:`MIN_FREE_BYTES` free where it writes: the fault
says "disk full"), and a recovery that fails (e.g. no room for the rewritten file) says so
in the fault's note, keeping the file as it is.

Progress, not only liveliness (issue 36 item 1): every service publishes a heartbeat with its
progress (:mod:`diffpos_services.bus.heartbeat`); :meth:`Supervisor.on_heartbeat` keeps, per
process, when its progress last advanced. A process whose progress has not advanced for
:data:`STALL_S` although it has work pending, or that has sent no heartbeat for that long
(a SIGSTOPped process keeps its liveliness token for the whole lease, 10 s by default), is
**hung**: a fault like a crash, reported with how long it had made no progress; a hung fusion
or recorder is killed (SIGKILL to its process group) and restarted as if it had died, a hung
anchor is reported (anchors are not restarted; one that resumes is taken back, the fault says
when). A process is judged only from its first heartbeat on (start-up is the readiness
timeout's business), and nobody is judged while the bus itself is silent (the router died,
or no heartbeat from anyone arrives: the router's fault, reported as such).

A fusion that cannot be restarted (it died more than :data:`MAX_RESTARTS` times) ends the
run: :attr:`Supervisor.fatal` says why, the monitor stops, the summary says it and the exit
code is that of lost data (3); before, the run went on without a fusion, silently.

The thread outlives every child it started (it waits for :meth:`Supervisor.close` after the
children are stopped): a child's parent-death signal (:func:`diffpos_services.processes.
die_with_parent`) comes when the thread that started it ends.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import shutil
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from diffpos_services.errors import DiffposError
from diffpos_services.logs import log_event
from diffpos_services.recording.repair import recover
from diffpos_services.recording.writer import existing_parts

__all__ = ["MAX_RESTARTS", "MIN_FREE_BYTES", "STALL_S", "Fault", "NotRestarted", "Supervisor", "disk_full",
           "format_faults", "fusion_name", "recover_in_place", "service_role"]

#: restarts per service and run (a service that keeps dying is not restarted forever)
MAX_RESTARTS = 3
#: restarted when they die
RESTARTABLE = ("fusion", "recorder")
#: a recorder is not restarted where less than this is free [bytes] (a full disk)
MIN_FREE_BYTES = 16 << 20
#: a process whose progress has not advanced for this long (with work pending, or without
#: any heartbeat) is hung [s]: 10 heartbeat periods, half the default 10 s lease
STALL_S = 5.0
#: the service that the run cannot go on without
ESSENTIAL = ("fusion",)


def fusion_name(shard: int, shards: int) -> str:
    """The process name of fusion shard ``shard`` of ``shards`` (``fusion`` without shards,
    ``fusion-K`` with)."""
    return "fusion" if shards == 1 else f"fusion-{shard}"


def service_role(name: str) -> str:
    """The role of process ``name``: ``fusion`` for every fusion shard (``fusion-K``), else
    the name (what :data:`RESTARTABLE` and :data:`ESSENTIAL` list)."""
    return "fusion" if name.startswith("fusion-") else name


class NotRestarted(DiffposError):
    """Raised by a restart callback that declines (its message is the fault's note)."""

    exit_code = 3  # never reaches the CLI: the supervisor catches it


def disk_full(path: str | os.PathLike[str]) -> str | None:
    """``"disk full: N bytes free on DIR"`` when the file system holding ``path`` has less
    than :data:`MIN_FREE_BYTES` free (a recorder restarted there would write 0-byte files),
    else None."""
    d = Path(path).resolve().parent
    try:
        free = shutil.disk_usage(d).free
    except OSError:
        return None
    if free >= MIN_FREE_BYTES:
        return None
    return f"disk full: {free} bytes free on {d} (No space left on device)"


@dataclass
class Fault:
    """One child that died during the run.

    Attributes
    ----------
    service : str
        ``fusion``, ``recorder``, ``anchor-<id>``, ``router``, ``dashboard``.
    died_s : float [s]
        When it died or was found hung, since the run started (negative: before the run
        control).
    exit_code : int or None
        Its exit code (negative: killed by that signal; ``None``: a hung anchor, left
        running).
    restarted_s : float or None [s]
        When it was started again (``None``: not restarted).
    note : str
        What happened to its data (the recorder's recovered file, the new file).
    kind : str
        ``died`` (it exited), ``hung`` (no progress while alive), ``duplicate publisher``
        (two processes under one anchor key, reported by the fusion).
    detected_after_s : float or None [s]
        A hang: how long it had made no progress when it was found.
    """

    service: str
    died_s: float
    exit_code: int | None
    restarted_s: float | None = None
    note: str = ""
    kind: str = "died"
    detected_after_s: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def recover_in_place(path: str | os.PathLike[str]) -> str:
    """Recover a dead recorder's file set in place: its last part (the only one that can be
    truncated) is rewritten complete and indexed. Returns what was done, for the report."""
    first = Path(path)
    parts = existing_parts(first)
    if not parts:
        return f"{first}: not written (the recorder died before its first message)"
    last = parts[-1]
    tmp = last.with_name(last.stem + ".recovering.mcap")
    try:
        rep = recover(last, tmp)
        os.replace(tmp, last)
    except (DiffposError, OSError) as exc:
        tmp.unlink(missing_ok=True)
        why = (os.strerror(exc.errno) if isinstance(exc, OSError) and exc.errno else str(exc))
        full = " (disk full)" if getattr(exc, "errno", None) == errno.ENOSPC else ""
        return (f"{last}: RECOVERY FAILED{full}: {why}; kept as it is, truncated (run diffpos "
                f"recover {last} --out <a file on a disk with room>)")
    d = rep.damage
    return (f"{last}: recovered in place ({rep.messages} messages kept; dropped "
            f"{d.unread_bytes} bytes of an incomplete record, {d.bad_chunks} bad chunks)")


class Supervisor:
    """Watch the children of ``emu`` (see module docstring).

    Parameters
    ----------
    procs : callable
        Returns the current ``(name, popen)`` pairs (the orchestrator's list).
    restart : callable
        ``restart(name) -> note``: start service ``name`` again; the note says what it did.
    logger : logging.Logger
    period_s : float [s]
        How often the children are polled.
    """

    def __init__(self, procs: Callable[[], list[tuple[str, Any]]],
                 restart: Callable[[str, int], str], logger: logging.Logger, *,
                 period_s: float = 0.1, stall_s: float = STALL_S) -> None:
        self.procs, self.restart, self.log = procs, restart, logger
        self.period_s, self.stall_s = period_s, stall_s
        self.faults: list[Fault] = []
        #: why the run cannot go on (a fusion that cannot be restarted), else None
        self.fatal: str | None = None
        # pid -> [progress, pending, last heartbeat, last advance] (monotonic [s])
        self._beats: dict[int, list] = {}
        self._hung_anchors: dict[int, Fault] = {}  # hung anchors left running, by pid
        self.t0 = time.monotonic()
        self.restarts: dict[str, int] = {}
        self._seen: set[int] = set()
        self._stopping = threading.Event()  # no more restarts: the run is ending
        self._done = threading.Event()      # every child stopped: the thread may end
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._loop, name="emulate-supervisor",
                                        daemon=True)

    def start(self, t0: float | None = None) -> None:
        if t0 is not None:
            self.t0 = t0
        self._thread.start()

    def stopping(self) -> None:
        """The run is ending: children exiting from now on are expected."""
        with self._lock:
            self._stopping.set()

    def close(self) -> None:
        """Every child is stopped: end the thread."""
        self._stopping.set()
        self._done.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)

    def on_heartbeat(self, pid: int, progress: int, pending: int,
                     now: float | None = None) -> None:
        """A heartbeat of process ``pid`` (any thread): when its progress last advanced."""
        now = time.monotonic() if now is None else now
        with self._lock:
            b = self._beats.get(pid)
            if b is None:
                self._beats[pid] = [progress, pending, now, now]
                return
            if progress != b[0]:
                b[0], b[3] = progress, now
            b[1], b[2] = pending, now

    def heard(self, pids: list[int]) -> bool:
        """True once every process of ``pids`` sent a heartbeat (a fusion's first one follows
        its liveliness token: with several fusion shards on the one ``alive/fusion`` key, the
        run waits for each shard's heartbeat)."""
        with self._lock:
            return all(p in self._beats for p in pids)

    def check(self, now: float | None = None) -> None:
        """One poll: every child that exited since the last poll becomes a fault, and so
        does every child found hung (:meth:`_check_stalled`)."""
        for name, popen in self.procs():
            rc = popen.poll()
            if rc is None or id(popen) in self._seen:
                continue
            with self._lock:
                if self._stopping.is_set():
                    return
                self._seen.add(id(popen))
                if name.startswith("anchor-") and rc == 0:
                    continue  # an anchor ends the run on its own
                self._fault(name, rc)
        self._check_stalled(time.monotonic() if now is None else now)

    def _stalled_for(self, pid: int, now: float) -> float | None:
        """How long process ``pid`` has made no progress, if that makes it hung: no advance
        for :attr:`stall_s` with work pending or without any heartbeat since; else None."""
        b = self._beats.get(pid)
        if b is None:
            return None
        quiet, silent = now - b[3], now - b[2]
        if quiet > self.stall_s and (b[1] > 0 or silent > self.stall_s):
            return quiet
        return None

    def _bus_silent(self, now: float) -> bool:
        """No heartbeat from anyone for :attr:`stall_s`, or the router is gone: the silence
        is the bus's (a dead or hung router), not each process's."""
        if any(name == "router" and popen.poll() is not None for name, popen in self.procs()):
            return True
        with self._lock:
            latest = max((b[2] for b in self._beats.values()), default=None)
        return latest is not None and now - latest > self.stall_s

    def _check_stalled(self, now: float) -> None:
        if self._bus_silent(now):
            return
        for name, popen in self.procs():
            if popen.poll() is not None or id(popen) in self._seen:
                continue
            with self._lock:
                if self._stopping.is_set():
                    return
                quiet = self._stalled_for(popen.pid, now)
                hung = self._hung_anchors.get(popen.pid)
                if hung is not None and quiet is None:  # a hung anchor resumed
                    del self._hung_anchors[popen.pid]
                    hung.note += f"; resumed at {now - self.t0:.1f} s (used again)"
                    log_event(self.log, logging.WARNING, "service resumed", service=name)
                if quiet is None or hung is not None:
                    continue
                self._hung(name, popen, quiet, now)

    def _hung(self, name: str, popen: Any, quiet: float, now: float) -> None:
        """Report a hung child; kill and restart it (an anchor: report only)."""
        b = self._beats[popen.pid]
        what = (f"no progress for {quiet:.1f} s while alive (last heartbeat "
                f"{now - b[2]:.1f} s ago, {b[1]} items pending)")
        log_event(self.log, logging.ERROR, "service hung", service=name, pid=popen.pid,
                  no_progress_s=round(quiet, 1), last_heartbeat_s=round(now - b[2], 1))
        if name.startswith("anchor-"):
            fault = Fault(service=name, died_s=round(now - self.t0, 3), exit_code=None,
                          note=f"hung: {what}; not restarted (anchors are not), left running",
                          kind="hung", detected_after_s=round(quiet, 2))
            self.faults.append(fault)
            self._hung_anchors[popen.pid] = fault
            return
        self._seen.add(id(popen))
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(popen.pid, signal.SIGKILL)
        with contextlib.suppress(Exception):
            popen.wait(timeout=10.0)
        self._fault(name, popen.returncode, kind="hung", detected_after_s=round(quiet, 2),
                    what=f"hung: {what}; killed")

    def _fault(self, name: str, rc: int | None, *, kind: str = "died",
               detected_after_s: float | None = None, what: str = "") -> None:
        fault = Fault(service=name, died_s=round(time.monotonic() - self.t0, 3), exit_code=rc,
                      kind=kind, detected_after_s=detected_after_s)
        self.faults.append(fault)
        if kind == "died":
            log_event(self.log, logging.ERROR, "service died", service=name, exit_code=rc,
                      at_s=fault.died_s)
        pre = f"{what}; " if what else ""
        n = self.restarts.get(name, 0)
        if service_role(name) not in RESTARTABLE:
            fault.note = f"{pre}not restarted"
            return
        if n >= MAX_RESTARTS:
            fault.note = f"{pre}not restarted (already restarted {n} times)"
            self._end_run(name, fault, f"it died {n + 1} times, restarted {n} times "
                          f"(at most {MAX_RESTARTS})")
            return
        try:
            fault.note = pre + self.restart(name, n + 1)
        except NotRestarted as exc:
            fault.note = f"{pre}not restarted: {exc}"
            log_event(self.log, logging.ERROR, "service not restarted", service=name,
                      why=str(exc))
            self._end_run(name, fault, str(exc))
            return
        self.restarts[name] = n + 1
        fault.restarted_s = round(time.monotonic() - self.t0, 3)
        log_event(self.log, logging.WARNING, "service restarted", service=name,
                  restart=n + 1, at_s=fault.restarted_s, note=fault.note)

    def _end_run(self, name: str, fault: Fault, why: str) -> None:
        """An essential service that is not restarted ends the run (:attr:`fatal`)."""
        if service_role(name) not in ESSENTIAL or self.fatal is not None:
            return
        self.fatal = f"the run ended early: the {name} is gone ({why}); no estimates without it"
        fault.note += f"; {self.fatal}"
        log_event(self.log, logging.ERROR, "run cannot go on", service=name, why=why)

    def _loop(self) -> None:
        while not self._done.wait(self.period_s):
            if not self._stopping.is_set():
                try:
                    self.check()
                except Exception as exc:  # pragma: no cover - never let the watcher die
                    log_event(self.log, logging.ERROR, "supervisor error", error=str(exc))


def format_faults(faults: list[dict[str, Any]]) -> str:
    """The summary's faults block (empty string when nothing died)."""
    if not faults:
        return ""
    lines = [f"faults: {len(faults)} (the run lost data)"]
    for f in faults:
        kind = f.get("kind", "died")
        if kind == "died":
            when = f"died at {f['died_s']:.1f} s (exit code {f['exit_code']})"
        elif kind == "hung":
            when = (f"hung, found at {f['died_s']:.1f} s after {f['detected_after_s']:.1f} s "
                    f"without progress" + ("" if f["exit_code"] is None
                                           else f" (killed: exit code {f['exit_code']})"))
        else:
            when = kind
        again = (f", restarted at {f['restarted_s']:.1f} s" if f.get("restarted_s") is not None
                 else "")
        note = f"; {f['note']}" if f.get("note") else ""
        lines.append(f"  {f['service']}: {when}{again}{note}")
    return "\n".join(lines)
