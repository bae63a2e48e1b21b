"""Clean shutdown: signals -> an event the main loop waits on, in slices.

:class:`Shutdown` turns SIGINT/SIGTERM/SIGHUP into an event the main loop waits on, so sessions
are closed by their ``with`` blocks and buffers are flushed before exit; a main thread waits
and joins only in slices (:meth:`Shutdown.wait`, :func:`wait_event`, :func:`join_thread`: a
signal taken by another thread runs its handler); :func:`run_main` runs a service body.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

from diffpos_services.errors import DiffposError
from diffpos_services.logs import log_event
from diffpos_services.processes import PARENT_PID_ENV, die_with_parent

__all__ = ["ORPHAN_STOP_S", "SIGNAL_POLL_S", "Shutdown", "join_thread", "run_main", "wait_event"]


#: The longest a :meth:`Shutdown.wait` (and :func:`wait_event`, :func:`join_thread`) blocks
#: before it lets Python run pending signal handlers [s].
SIGNAL_POLL_S = 0.25


def wait_event(event: threading.Event, timeout: float | None = None) -> bool:
    """``event.wait(timeout)`` ([s], None: until set) in slices of :data:`SIGNAL_POLL_S`.

    A service's main thread must never block in one unbounded wait: a process-directed
    signal may be delivered to any thread (a Zenoh thread), and Python runs its handler only
    when the main thread next runs bytecode; a main thread blocked without a timeout then
    never wakes (a router child of a SIGKILLed ``diffpos emulate`` was left running this
    way under load, and a recorder whose main thread waited on ``Shutdown.event`` did not
    stop on SIGTERM). Returns whether the event is set.
    """
    if timeout is None:
        while not event.wait(SIGNAL_POLL_S):
            pass
        return True
    deadline = time.monotonic() + timeout
    while (left := deadline - time.monotonic()) > 0:
        if event.wait(min(left, SIGNAL_POLL_S)):
            return True
    return event.is_set()


def join_thread(thread: threading.Thread, timeout: float | None = None) -> bool:
    """``thread.join(timeout)`` ([s], None: until it ends) in slices of :data:`SIGNAL_POLL_S`
    (see :func:`wait_event`); returns whether the thread has ended."""
    deadline = None if timeout is None else time.monotonic() + timeout
    while thread.is_alive():
        left = SIGNAL_POLL_S if deadline is None else deadline - time.monotonic()
        if left <= 0:
            return False
        thread.join(min(left, SIGNAL_POLL_S))
    return True


class _SignalSafeEvent(threading.Event):
    """A ``threading.Event`` a signal handler may set: its condition's lock is re-entrant.

    Python runs a handler in the main thread between two bytecodes, possibly while that
    thread is inside ``Event.wait`` holding the event's lock (it takes it on every entry:
    with waits in slices, four times a second); ``set()`` on a plain Event would then wait
    forever for a lock its own thread holds.
    """

    def __init__(self) -> None:
        super().__init__()
        self._cond = threading.Condition(threading.RLock())


#: How long a child of a diffpos process (:data:`PARENT_PID_ENV` set) may take to stop once
#: asked while its parent is gone [s]; then it exits at once (``os._exit(1)``, said on stderr).
#: A repeated SIGTERM no longer interrupts a stop (:class:`Shutdown`) and an orphan has no
#: supervisor left to escalate with SIGKILL, so an orphan whose stop hung would stay forever.
#: Measured stops take 0.1-0.4 s (the recorder beside busy loops, load ~5; its drain waits
#: at most ~1 s idle): 15 s is far beyond them and below the 30 s in which
#: tests/system/test_emulate_faults.py wants every child of a SIGKILLed emulate gone.
ORPHAN_STOP_S = 15.0


def _orphan_watch(event: threading.Event, parent_pid: str, stop_s: float) -> None:
    """The daemon thread of a supervised child's :class:`Shutdown`: once ``event`` is set and
    ``stop_s`` [s] have passed, exit the process as soon as the parent is gone (while the
    parent lives, stopping its child is the parent's job: it escalates itself)."""
    event.wait()
    deadline = time.monotonic() + stop_s
    while (left := deadline - time.monotonic()) > 0:
        time.sleep(min(left, 1.0))
    told = False
    while str(os.getppid()) == parent_pid:
        if not told:  # os.write: no lock the stuck main thread may hold (logging's)
            os.write(2, b"diffpos: still stopping; the parent process is alive: its call\n")
            told = True
        time.sleep(min(stop_s, 1.0))
    os.write(2, f"diffpos: still stopping {stop_s:g} s after the stop was asked and the parent "
                f"process is gone: exiting now\n".encode())
    os._exit(1)


class Shutdown:
    """SIGINT/SIGTERM/SIGHUP -> ``event``; the main loop waits on it and exits its ``with``
    blocks (a closed terminal stops a service cleanly instead of killing it mid-write).

    A second SIGINT while shutting down raises ``KeyboardInterrupt`` (the escape hatch of a
    person pressing Ctrl-C twice; when the program set the event itself, e.g. a recorder's
    duration ran out, the first Ctrl-C after that is the one that waits for the stop). A repeated SIGTERM or SIGHUP is ignored: the stop is
    under way, and a supervisor escalates with SIGKILL. Why: a child of a diffpos process
    (:func:`~diffpos_services.processes.child_env`) gets SIGTERM when its parent dies (:func:`die_with_parent`), and the
    kernel sends it again each time the orphan is handed to another thread of the dying
    parent (measured: 1-8 SIGTERMs per child of a SIGKILLed 9-thread parent; ``getppid()``
    is the parent's pid until the last); those interrupted the child's own orderly stop
    (closing its session, finishing its file) at a random point. A child whose parent is
    already gone stops at once; one whose parent is gone exits ``orphan_stop_s`` [s] after
    its stop was asked if it has not stopped by then (:data:`ORPHAN_STOP_S`: no supervisor
    is left to SIGKILL a hung stop). Must be created in the main thread.
    """

    def __init__(self, logger: logging.Logger | None = None,
                 orphan_stop_s: float = ORPHAN_STOP_S) -> None:
        self.event: threading.Event = _SignalSafeEvent()
        self.signal_name: str | None = None
        self._logger = logger
        self._sigint_waited = False  # a SIGINT came after the program stopped on its own
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, self._handle)
        parent = os.environ.get(PARENT_PID_ENV)
        if parent:  # started here, not in the handler (no thread start between bytecodes)
            threading.Thread(target=_orphan_watch, args=(self.event, parent, orphan_stop_s),
                             name="orphan-watch", daemon=True).start()
        if not die_with_parent(signal.SIGTERM):
            if logger is not None:
                log_event(logger, logging.WARNING, "parent process gone: stopping")
            self.signal_name = "parent-death"
            self.event.set()

    def _handle(self, signum: int, _frame: Any) -> None:
        name = signal.Signals(signum).name
        if self.event.is_set():
            if signum == signal.SIGINT:
                if self.signal_name is not None or self._sigint_waited:
                    raise KeyboardInterrupt(name)
                # the program set the event itself (a recorder's --duration ran out) and is
                # finishing: a first Ctrl-C waits for that, a second one escapes
                self._sigint_waited = True
            return  # SIGTERM/SIGHUP again (e.g. the parent's death, repeated): keep stopping
        self.signal_name = name
        if self._logger is not None:
            log_event(self._logger, logging.INFO, "shutdown requested", signal=name)
        self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the event (``timeout`` [s], None: until set), waking at least every
        :data:`SIGNAL_POLL_S` (:func:`wait_event`: why). A loop given ``event`` itself
        must wait on it the same way."""
        return wait_event(self.event, timeout)

    def set(self) -> None:
        self.event.set()


def run_main(fn: Callable[[], int], logger: logging.Logger) -> int:
    """Run a service body; an unexpected exception is logged with its traceback (exit 1).

    A :class:`DiffposError` (and ``KeyboardInterrupt``) goes up to the CLI, which maps it
    to its exit code with a one-line message (:func:`diffpos_services.cli.main.main`).
    """
    try:
        return int(fn() or 0)
    except (DiffposError, KeyboardInterrupt):
        raise
    except Exception as exc:  # pragma: no cover - last resort, logged with traceback
        logger.exception("fatal: %s", exc)
        return 1
