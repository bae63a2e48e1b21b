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


# ------------------------------------------------------------------ what the line and table say
# Reference: a made-up run of 50 static responders, 10 on each of 5 floors (the building's
# floor_index of their true height), counted by hand: 48 placed (two LOST), one on the wrong
# floor, the least sure at p = 0.62.
def _run_of_50():
    import types

    from diffpos_services.emulate.monitor import Monitor
    from diffpos_services.emulate.scoring import Scorer
    from diffpos_services.wire import messages as M

    from diffpos.scenario import default_scenario
    from diffpos.trajectory import Static

    b = default_scenario().building
    period, t0 = 100_000_000, 1_800_000_000_000_000_000
    nodes = [(f"n{i:02d}", Static((-15.0 + 0.6 * i, 5.0, 5.5 + 3.0 * (i % 5)))) for i in range(50)]
    sc = Scorer(nodes, b, t0, period_ns=period, end_ns=t0 + 50 * period)
    for k in range(50):
        for i, (nid, tr) in enumerate(nodes):
            pos = tuple(tr.position_m(0.0))
            floor = i % 5 if nid != "n07" else 4  # n07 is on F2, published on F4
            p = 0.62 if nid == "n33" else 0.97
            lost = nid in ("n10", "n11") and k >= 40
            probs = [0.0] * 5
            probs[floor] = p
            sc.add(M.PositionEstimateV2(
                node_id=nid, t_ns=t0 + k * period, epoch=t0 // period + k, seq=k,
                method="mnls+tracking", status="LOST" if lost else "TRACKING",
                position_m=None if lost else pos, covariance_m2=None, peb_m=None,
                z_bound_m=None, floor_index=None if lost else floor,
                floor_probabilities=[] if lost else probs, snapshot=None, links=[],
                used_anchors=[], residuals_m=[], excluded=[], message="", t_input_wall_ns=0,
                t_pub_wall_ns=0))
    mon = Monitor.__new__(Monitor)
    mon.o = types.SimpleNamespace(duration_s=5.0)
    mon.emu = types.SimpleNamespace(nodes=nodes)
    mon.tb = types.SimpleNamespace(t0_ns=t0)
    mon.scorer, mon.lockstep, mon.clock_k, mon.period_ns = sc, True, 49, period
    mon.end_ns = t0 + 50 * period
    return mon, sc


def test_status_line_says_who_is_placed_where_first_within_80_columns():
    mon, _ = _run_of_50()
    line = mon.status_line(latency_ms=25.4, width=100)
    assert line.endswith(" err 0.00m") and len(line) < 100
    line = mon.status_line(latency_ms=25.4, width=80)  # the median error left out, not cut
    assert len(line) < 80 and "err" not in line, line
    assert line.startswith("t 5.0/5s placed 48/50 ")
    # per floor: the published floor of the 48 placed (n10, n11 LOST; n07 published on F4)
    counts = {f"F{f}": 0 for f in range(5)}
    for i in range(50):
        nid = f"n{i:02d}"
        if nid in ("n10", "n11"):
            continue
        counts[f"F{4 if nid == 'n07' else i % 5}"] += 1
    assert " ".join(f"{f}:{n}" for f, n in counts.items()) in line
    assert "unsure n33 62%" in line and "lat 25ms" in line
    assert "x0.0" not in line and "x1.0" not in line


def test_summary_table_has_every_responder_and_flags_the_wrong_floor():
    from diffpos_services.emulate.scoring import format_summary

    _, sc = _run_of_50()
    s = sc.summary() | {"speed": 0.0, "duration_s": 5.0, "recording": "/r/run.mcap",
                        "notes": ["recording: /r/run.mcap", "another note"]}
    text = format_summary(s, width=100)
    lines = text.splitlines()
    assert max(map(len, lines)) <= 100
    assert "x0.0" not in text and "in lockstep" in text
    assert text.count("/r/run.mcap") == 1  # the recording row, not again as a note
    assert "another note" in text
    cells = [c for line in lines for c in line.split(" | ")]
    rows = {c.split()[0]: c.split() for c in cells if c[:1] == "n" and c.split()[0][1:].isdigit()}
    assert sorted(rows) == [f"n{i:02d}" for i in range(50)]
    assert rows["n07"][2:4] == ["F4", "97%"] and rows["n07"][-1] == "F2!"
    assert rows["n10"][1] == "LOST" and rows["n10"][4] == "1.0s"  # last fix at epoch 39 of 49
    assert rows["n12"][-1] == "0.00"  # right floor: no flag; error 0 (estimate = truth)
