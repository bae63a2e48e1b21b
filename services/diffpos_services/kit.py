"""What every diffpos command shares: errors, typed config, structured logs, clean shutdown.

Standard library and msgspec only (no zenoh: the bus health check is
:mod:`diffpos_services.bus.health`).

- :class:`DiffposError` is the one base of the errors a person sees; its ``exit_code`` is
  what the CLI returns (mapped in one place, :func:`diffpos_services.cli.main.main`).
- :func:`build_config` turns plain options into a typed, validated ``msgspec.Struct`` and
  raises :class:`ConfigError` naming the bad field (the CLI prints it, no traceback).
- :func:`setup_logging` writes one JSON object per line to stderr (``--log-format text`` for
  humans); :func:`log_event` attaches key/value fields; :class:`LogOnce` logs a recurring
  problem once per (key, reason); :data:`STATUS` is the one live status line of a terminal
  (log records print above it: the handler clears and redraws it).
- :class:`Shutdown` turns SIGINT/SIGTERM into an event the main loop waits on, so sessions
  are closed by their ``with`` blocks and buffers are flushed before exit; a main thread
  waits and joins only in slices (:meth:`Shutdown.wait`, :func:`wait_event`,
  :func:`join_thread`: a signal taken by another thread runs its handler); :func:`run_main`
  runs a service body; :func:`stop_process_groups` and :func:`free_tcp_port` help the
  commands that start processes (``diffpos emulate``, tests, benchmarks).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import ctypes.util
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

import msgspec

__all__ = [
    "STATUS",
    "ConfigError",
    "DiffposError",
    "LogOnce",
    "Shutdown",
    "StatusLine",
    "add_logging_arguments",
    "build_config",
    "child_env",
    "die_with_parent",
    "free_tcp_port",
    "join_thread",
    "load_json_option",
    "log_event",
    "run_main",
    "setup_logging",
    "stop_process_groups",
    "wait_event",
]

#: environment variable naming the parent process a service must not outlive
#: (:func:`child_env` sets it, :class:`Shutdown` acts on it)
PARENT_PID_ENV = "DIFFPOS_PARENT_PID"
_PR_SET_PDEATHSIG = 1

T = TypeVar("T")


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (bind to port 0)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def stop_process_groups(
    procs: list[subprocess.Popen],
    *,
    timeout_s: float,
    on_kill: Callable[[subprocess.Popen], None] | None = None,
) -> list[int]:
    """Stop processes started with ``start_new_session=True``: SIGTERM each process group,
    wait until ``timeout_s`` [s] after that (one shared deadline), SIGKILL the groups still
    running (``on_kill(proc)`` is called first, e.g. to log it). Returns the exit codes.

    Signalling the group, not just the process, also stops its children.
    """
    for p in procs:
        if p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    codes = []
    for p in procs:
        try:
            codes.append(p.wait(max(deadline - time.monotonic(), 0.05)))
        except subprocess.TimeoutExpired:
            if on_kill is not None:
                on_kill(p)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            codes.append(p.wait())
    return codes


def child_env(env: Mapping[str, str] | None = None) -> dict[str, str]:
    """The environment of a child service that must die with this process: ``env`` (default
    ``os.environ``) plus :data:`PARENT_PID_ENV` = this process's pid (see
    :func:`die_with_parent`). Nothing runs between fork and exec (no ``preexec_fn``), so it
    is safe after ``zenoh.open()``."""
    return dict(os.environ if env is None else env, **{PARENT_PID_ENV: str(os.getpid())})


def die_with_parent(sig: int = signal.SIGTERM) -> bool:
    """If :data:`PARENT_PID_ENV` is set: ask the kernel for ``sig`` when the parent dies
    (``prctl(PR_SET_PDEATHSIG)``, Linux; it survives ``exec``), even by SIGKILL. Returns
    False if the parent is already gone (the caller stops at once), else True.

    The signal comes when the *thread* that started this process ends: parents start their
    children from threads that outlive them (``diffpos emulate``: the main thread and the
    supervisor, joined after the children are stopped).
    """
    want = os.environ.get(PARENT_PID_ENV)
    if not want:
        return True
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0)
    # the parent may have died before prctl: then we were re-parented already
    return str(os.getppid()) == want


class DiffposError(Exception):
    """Base of every error diffpos reports to a person: the message says what to fix.

    ``exit_code`` is the process exit code the CLI returns for it (one place:
    :func:`diffpos_services.cli.main.main`); subclasses set their own.
    """

    exit_code: int = 1


class ConfigError(DiffposError, ValueError):
    """Invalid service configuration; the message names the field and what to fix."""

    exit_code = 2


def build_config(kind: type[T], values: Mapping[str, Any]) -> T:
    """Validate ``values`` into the typed config struct ``kind``.

    Raises
    ------
    ConfigError
        With msgspec's path to the offending field, e.g.
        ``invalid fusion config: Expected `float` >= 0.0 - at `$.deadline_s```.
    """
    try:
        cfg = msgspec.convert(dict(values), type=kind, strict=False)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"invalid {kind.__name__}: {exc}") from None
    check = getattr(cfg, "check", None)
    if check is not None:
        try:
            check()
        except ValueError as exc:
            raise ConfigError(f"invalid {kind.__name__}: {exc}") from None
    return cfg


def load_json_option(option: str, path: str) -> Any:
    """The JSON document in the file ``path`` given to the command-line ``option``.

    Raises
    ------
    ConfigError
        Naming the option and the file, e.g. ``--config run.json: cannot read it (No such
        file or directory)`` or ``... not valid JSON (...)``.
    """
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except OSError as exc:
        raise ConfigError(f"{option} {path}: cannot read it ({exc.strerror})") from None
    except ValueError as exc:
        raise ConfigError(f"{option} {path}: not valid JSON ({exc})") from None


# ----------------------------------------------------------------------------- logging
class _JsonFormatter(logging.Formatter):
    def __init__(self, service: str) -> None:
        super().__init__()
        self.service = service

    def format(self, record: logging.LogRecord) -> str:
        out = {
            "ts": round(record.created, 6),
            "level": record.levelname.lower(),
            "service": self.service,
            "pid": record.process,
            "msg": record.getMessage(),
        }
        fields = getattr(record, "fields", None)
        if fields:
            out.update(fields)
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


class _TextFormatter(logging.Formatter):
    def __init__(self, service: str) -> None:
        super().__init__()
        self.service = service

    def format(self, record: logging.LogRecord) -> str:
        fields = getattr(record, "fields", None) or {}
        extra = " ".join(f"{k}={v}" for k, v in fields.items())
        stamp = time.strftime("%H:%M:%S", time.localtime(record.created))
        line = f"{stamp} {record.levelname.lower():<7} {self.service}: {record.getMessage()}"
        if extra:
            line += " " + extra
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        return line


class StatusLine:
    """One live status line at the bottom of a terminal, with log records printed above it.

    :meth:`show` (re)draws the line in place (``\\r`` + erase to end of line), cut to the
    terminal's width so it never wraps; the log handler of :func:`setup_logging` erases it,
    writes the record on its own line and draws it again (:meth:`above`), so a warning is
    never glued to the status. On a stream that is not a terminal nothing is drawn (callers
    log their progress instead). Thread-safe.

    Parameters
    ----------
    stream : file, optional
        Default: ``sys.stderr`` at the time of each write (so redirections are honoured).
    """

    ERASE = "\r\x1b[K"

    def __init__(self, stream: Any = None) -> None:
        self._stream = stream
        self.text = ""
        self._lock = threading.RLock()

    @property
    def stream(self) -> Any:
        return self._stream if self._stream is not None else sys.stderr

    def active(self) -> bool:
        """A line is shown (and the stream is a terminal)."""
        return bool(self.text) and _isatty(self.stream)

    @staticmethod
    def width() -> int:
        """Columns available for the line (the terminal's width minus one, at least 20)."""
        return max(20, shutil.get_terminal_size((80, 24)).columns - 1)

    def fit(self, text: str) -> str:
        """``text`` cut to :meth:`width` (an ellipsis marks the cut)."""
        w = self.width()
        return text if len(text) <= w else text[: w - 1] + "\u2026"

    def show(self, text: str) -> None:
        """Draw ``text`` as the status line (replacing the previous one)."""
        with self._lock:
            self.text = text
            if _isatty(self.stream):
                self.stream.write(self.ERASE + self.fit(text))
                self.stream.flush()

    def done(self) -> None:
        """Leave the last line on screen and end it (later output starts on a new line)."""
        with self._lock:
            if self.active():
                self.stream.write("\n")
                self.stream.flush()
            self.text = ""

    @contextlib.contextmanager
    def above(self) -> Any:
        """Erase the line, let the caller write full lines, draw the line again."""
        with self._lock:
            active = self.active()
            if active:
                self.stream.write(self.ERASE)
            try:
                yield
            finally:
                if active:
                    self.stream.write(self.fit(self.text))
                    self.stream.flush()


def _isatty(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # closed or not a file
        return False


#: the process's one status line (``diffpos emulate``'s progress)
STATUS = StatusLine()


class _StatusAwareHandler(logging.StreamHandler):
    """A stderr handler that prints each record above :data:`STATUS`."""

    def emit(self, record: logging.LogRecord) -> None:
        with STATUS.above():
            super().emit(record)


def add_logging_arguments(parser: argparse.ArgumentParser) -> None:
    """``--log-level`` and ``--log-format`` options."""
    g = parser.add_argument_group("logging")
    g.add_argument(
        "--log-level",
        default=os.environ.get("DIFFPOS_LOG_LEVEL", "info"),
        choices=["debug", "info", "warning", "error"],
        help="log verbosity (default info, env DIFFPOS_LOG_LEVEL)",
    )
    g.add_argument(
        "--log-format",
        default=os.environ.get("DIFFPOS_LOG_FORMAT", "json"),
        choices=["json", "text"],
        help="json: one object per line on stderr (default, env DIFFPOS_LOG_FORMAT); text: human",
    )


def setup_logging(service: str, *, level: str = "info", fmt: str = "json") -> logging.Logger:
    """Configure the root logger for a service process; return the service's logger."""
    handler = _StatusAwareHandler(sys.stderr)
    handler.setFormatter(_JsonFormatter(service) if fmt == "json" else _TextFormatter(service))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())
    return logging.getLogger(f"diffpos.{service}")


def log_event(logger: logging.Logger, level: int, msg: str, **fields: Any) -> None:
    """Log ``msg`` with structured key/value ``fields``."""
    if logger.isEnabledFor(level):
        logger.log(level, msg, extra={"fields": fields})


class LogOnce:
    """Log a recurring problem once per ``(key, reason)``; count every occurrence."""

    def __init__(self, logger: logging.Logger, *, max_keys: int = 10_000) -> None:
        self.logger = logger
        self.max_keys = max_keys
        self.seen: dict[tuple[str, str], int] = {}

    def __call__(self, key: str, reason: str, detail: str = "", level: int = logging.WARNING) -> None:
        k = (key, reason)
        n = self.seen.get(k, 0)
        if n == 0 and len(self.seen) < self.max_keys:
            log_event(self.logger, level, f"{reason} on {key}", key=key, reason=reason, detail=detail[:300])
        if n or len(self.seen) < self.max_keys:
            self.seen[k] = n + 1


# ----------------------------------------------------------------------------- shutdown
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
    (:func:`child_env`) gets SIGTERM when its parent dies (:func:`die_with_parent`), and the
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
