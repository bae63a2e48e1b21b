"""`diffpos solve`'s per-line limits in this process (the fast loop): a line beyond a limit is
``invalid_input`` naming the option that raises it, the options are in ``--help`` with their
defaults, and an option out of range is exit 2 naming the option.

The same verb, run through ``cli.main.main`` with stdin replaced; what only a separate process
can show (its own CPU time and peak RSS on hostile streams, the exit code a user sees) is
tests/system/test_solve_limits.py, which reuses the lines built here.
"""

from __future__ import annotations

import io
import json
import sys

import numpy as np
import pytest
from diffpos_services.cli import main as cli
from diffpos_services.wire.solve_io import DEFAULT_MAX_ANCHORS, DEFAULT_MAX_STARTS

from diffpos.geometry import window_edge_path

NODE = [2.0, 5.0, 10.5]
GOOD = {"anchors_m": [[-15, -20, 1], [0, -15, 0], [0, -7, 4], [15, -20, 1]],
        "ranges_m": [32.233, 23.711, 15.058, 30.315], "sigmas_m": 0.005,
        "window_height_m": 1.0}
GOOD_LINE = json.dumps(GOOD).encode() + b"\n"


def problem_line(m: int, seed: int, **extra) -> bytes:
    """A line with ``m`` anchors outside the facade seeing the node at :data:`NODE`;
    ``random_ranges`` makes every anchor look faulty (the gating then refits every
    leave-one-out subset, round after round: the worst case)."""
    rng = np.random.default_rng(seed)
    a = np.c_[rng.uniform(-30, 30, m), rng.uniform(-40, -5, m), rng.uniform(0, 30, m)]
    if extra.pop("random_ranges", False):
        r = rng.uniform(10, 60, m)
    else:
        r = window_edge_path(a, np.array(NODE), window_height_m=1.0).length_m
    prob = {"anchors_m": a.tolist(), "ranges_m": r.tolist(), "sigmas_m": 0.01,
            "window_height_m": 1.0, **extra}
    return json.dumps(prob).encode() + b"\n"


def _solve(data: bytes, argv, monkeypatch, capsys):
    monkeypatch.setattr(sys, "stdin", io.TextIOWrapper(io.BytesIO(data), encoding="utf-8"))
    rc = cli.main(["solve", *argv])
    out, err = capsys.readouterr()
    return rc, [json.loads(x) for x in out.splitlines()], err


def test_a_thousand_anchor_line_is_refused_naming_the_option(monkeypatch, capsys):
    bad = problem_line(1000, 1, random_ranges=True)
    rc, recs, err = _solve(GOOD_LINE + bad + GOOD_LINE, [], monkeypatch, capsys)
    assert rc == 0 and "Traceback" not in err
    assert [r["status"] for r in recs] == ["ok", "invalid_input", "ok"]
    msg = recs[1]["message"]
    assert msg.startswith(f"anchors_m has 1000 anchors; at most {DEFAULT_MAX_ANCHORS} per "
                          "problem"), msg
    assert f"--max-anchors, default {DEFAULT_MAX_ANCHORS}, at most 1024" in msg


def test_anchor_and_start_limits_are_options_with_their_defaults_in_help(monkeypatch, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["solve", "--help"])
    assert info.value.code == 0
    flat = " ".join(capsys.readouterr().out.split())
    assert f"--max-anchors N a problem with more anchors is answered with invalid_input " \
           f"(default {DEFAULT_MAX_ANCHORS}" in flat
    assert f"(default {DEFAULT_MAX_STARTS}, at most 1000)" in flat
    assert "--max-line-bytes N longer lines" in flat
    # both over-limit lines refused at the defaults, both solved when the options allow them
    m = DEFAULT_MAX_ANCHORS + 1
    lines = problem_line(m, 2) + problem_line(
        5, 3, z_starts_m=[float(z) for z in range(DEFAULT_MAX_STARTS + 1)])
    rc, refused, _ = _solve(lines, [], monkeypatch, capsys)
    assert rc == 0 and [r["status"] for r in refused] == ["invalid_input", "invalid_input"]
    assert "--max-anchors" in refused[0]["message"]
    assert "--max-starts, default 32, at most 1000" in refused[1]["message"]
    rc, allowed, _ = _solve(lines, ["--max-anchors", str(m), "--max-starts", "64"],
                            monkeypatch, capsys)
    assert rc == 0 and [r["status"] for r in allowed] == ["ok", "ok"], allowed
    assert np.allclose(allowed[1]["position_m"], NODE, atol=1e-6)


@pytest.mark.parametrize(("argv", "needle"), [
    (["--max-anchors", "2000"], "--max-anchors must be an integer in [3, 1024], got 2000"),
    (["--max-anchors", "2"], "--max-anchors must be an integer in [3, 1024], got 2"),
    (["--max-starts", "0"], "--max-starts must be an integer in [1, 1000], got 0"),
    (["--max-line-bytes", "8"], "--max-line-bytes must be an integer in [16, 1073741824]"),
    (["--batch", "0"], "--batch must be >= 1, got 0"),
])
def test_limit_options_out_of_range_exit_2_naming_the_option(argv, needle, monkeypatch, capsys):
    rc, recs, err = _solve(GOOD_LINE, argv, monkeypatch, capsys)
    assert rc == 2 and recs == []
    assert f"diffpos solve: error: {needle}" in err and "Traceback" not in err
