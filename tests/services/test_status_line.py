"""The live status line: log records print above it, never glued to it, and it never wraps.

Reference: the exact bytes a terminal receives (a fake tty stream), checked by hand:
erase-line (``\\r\\x1b[K``), the record on its own line, the status drawn again."""

from __future__ import annotations

import io
import logging

import pytest
from diffpos_services import logs


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def _render(raw: str) -> list[str]:
    """What a terminal shows: ``\\r`` returns to column 0, ``\\x1b[K`` erases the rest."""
    lines, cur = [], ""
    i = 0
    while i < len(raw):
        if raw.startswith("\x1b[K", i):
            i += 3
            continue
        ch = raw[i]
        if ch == "\r":
            cur = ""
        elif ch == "\n":
            lines.append(cur)
            cur = ""
        else:
            cur += ch
        i += 1
    return [*lines, cur]


def test_log_records_print_above_the_status_line(monkeypatch):
    tty = _Tty()
    status = logs.StatusLine(tty)
    monkeypatch.setattr(logs, "STATUS", status)
    monkeypatch.setenv("COLUMNS", "80")
    handler = logs._StatusAwareHandler(tty)
    handler.setFormatter(logs._TextFormatter("emulate"))
    log = logging.getLogger("test.status")
    log.handlers[:] = [handler]
    log.propagate = False
    log.setLevel(logging.INFO)
    status.show("t 1.0/20 s  avail 50.0%")
    log.warning("anchor uav3 lost")
    status.show("t 1.5/20 s  avail 60.0%")
    status.done()
    screen = _render(tty.getvalue())
    assert screen[0].endswith("warning emulate: anchor uav3 lost")
    assert "avail" not in screen[0]  # not glued to the status
    assert screen[1] == "t 1.5/20 s  avail 60.0%" and screen[2] == ""


@pytest.mark.parametrize("columns", [40, 80])
def test_status_line_is_cut_to_the_terminal_width(monkeypatch, columns):
    tty = _Tty()
    status = logs.StatusLine(tty)
    monkeypatch.setenv("COLUMNS", str(columns))
    status.show("x" * 300)
    shown = _render(tty.getvalue())[-1]
    assert len(shown) == columns - 1 and shown.endswith("\u2026")


def test_nothing_is_drawn_on_a_pipe():
    pipe = io.StringIO()
    status = logs.StatusLine(pipe)
    status.show("t 1.0/20 s")
    with status.above():
        pipe.write("record\n")
    status.done()
    assert pipe.getvalue() == "record\n"
