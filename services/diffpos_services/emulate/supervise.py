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

The thread outlives every child it started (it waits for :meth:`Supervisor.close` after the
children are stopped): a child's parent-death signal (:func:`diffpos_services.processes.
die_with_parent`) comes when the thread that started it ends.
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
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

__all__ = ["MAX_RESTARTS", "MIN_FREE_BYTES", "Fault", "NotRestarted", "Supervisor", "disk_full",
           "format_faults", "recover_in_place"]

#: restarts per service and run (a service that keeps dying is not restarted forever)
MAX_RESTARTS = 3
#: restarted when they die
RESTARTABLE = ("fusion", "recorder")
#: a recorder is not restarted where less than this is free [bytes] (a full disk)
MIN_FREE_BYTES = 16 << 20


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
        When, since the run started (negative: before the run control).
    exit_code : int
        Its exit code (negative: killed by that signal).
    restarted_s : float or None [s]
        When it was started again (``None``: not restarted).
    note : str
        What happened to its data (the recorder's recovered file, the new file).
    """

    service: str
    died_s: float
    exit_code: int
    restarted_s: float | None = None
    note: str = ""

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
                 period_s: float = 0.1) -> None:
        self.procs, self.restart, self.log = procs, restart, logger
        self.period_s = period_s
        self.faults: list[Fault] = []
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

    def check(self) -> None:
        """One poll: every child that exited since the last poll becomes a fault."""
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

    def _fault(self, name: str, rc: int) -> None:
        fault = Fault(service=name, died_s=round(time.monotonic() - self.t0, 3), exit_code=rc)
        self.faults.append(fault)
        log_event(self.log, logging.ERROR, "service died", service=name, exit_code=rc,
                  at_s=fault.died_s)
        n = self.restarts.get(name, 0)
        if name not in RESTARTABLE:
            fault.note = "not restarted"
            return
        if n >= MAX_RESTARTS:
            fault.note = f"not restarted (already restarted {n} times)"
            return
        try:
            fault.note = self.restart(name, n + 1)
        except NotRestarted as exc:
            fault.note = f"not restarted: {exc}"
            log_event(self.log, logging.ERROR, "service not restarted", service=name,
                      why=str(exc))
            return
        self.restarts[name] = n + 1
        fault.restarted_s = round(time.monotonic() - self.t0, 3)
        log_event(self.log, logging.WARNING, "service restarted", service=name,
                  at_s=fault.restarted_s, note=fault.note)

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
        when = f"died at {f['died_s']:.1f} s (exit code {f['exit_code']})"
        again = (f", restarted at {f['restarted_s']:.1f} s" if f.get("restarted_s") is not None
                 else "")
        note = f"; {f['note']}" if f.get("note") else ""
        lines.append(f"  {f['service']}: {when}{again}{note}")
    return "\n".join(lines)
