"""Structured logs and the terminal's one status line.

:func:`setup_logging` writes one JSON object per line to stderr (``--log-format text`` for
humans, :func:`add_logging_arguments`); :func:`log_event` attaches key/value fields;
:class:`LogOnce` logs a recurring problem once per (key, reason); :data:`STATUS` is the one
live status line of a terminal (log records print above it: the handler clears and redraws it).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import shutil
import sys
import threading
import time
from typing import Any

__all__ = ["STATUS", "LogOnce", "StatusLine", "add_logging_arguments", "log_event",
           "setup_logging"]


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
