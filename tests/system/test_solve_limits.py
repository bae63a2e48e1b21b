"""`diffpos solve` bounds the work of every line: a hostile stream cannot exhaust memory or time.

Each case runs the real ``diffpos solve`` process on a stream and measures that process alone
(``os.wait4``: its own CPU time and peak RSS, not those of other children of the test run). As
a safety net for the shared test machine the child's address space is capped at 2 GiB
(``RLIMIT_AS``): a filter that held what it should not runs out of memory there instead of
swapping the machine, and the test fails on the exit code or the traceback.

Measured on the 2-core test machine with the limits in place (2026-11-27): a process solving
one good line costs 1.2 s CPU and peaks at 171 MB (start-up: imports and numba's compiled
kernels); one line with 1000 anchors is refused within that, 1.7 s and 171 MB in all (before
the limits: 102 s and 3.9 GB); 8 of the worst problems the default limits allow (32 anchors,
random ranges, gating excluding down to 3 anchors, 32 starts) cost 2.0 s and 171 MB in all
(earlier, before the numba kernels: ~0.5 s per line, ~120 MB).

A system test (real processes, ~25 s CPU): the same limits through ``cli.main`` in the test
process, without the CPU and memory measurements, are the fast loop's
tests/services/test_solve_limit_options.py.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from diffpos_services.wire.solve_io import DEFAULT_MAX_ANCHORS, DEFAULT_MAX_STARTS
from test_solve_limit_options import GOOD_LINE, problem_line

pytestmark = pytest.mark.system

EXE = Path(sys.executable).parent / "diffpos"
AS_LIMIT = 2 << 30  # [bytes] the child's address space (a safety net, not the assertion)
MIB = 1 << 20


@dataclass
class Child:
    rc: int
    records: list[dict]
    stderr: str
    cpu_s: float
    rss_mb: float


#: ``diffpos solve`` in a process that reports its own peak RSS (VmHWM of its address space
#: after exec) on stderr at exit. ``wait4``'s ``ru_maxrss`` is no good here: Linux carries the
#: forked pytest's high-water mark (hundreds of MB late in a run) across the exec.
_HWM_TAG = "\nVmHWM_kB "
_REPORT_HWM = (
    "import atexit, sys\n"
    "from diffpos_services.cli.main import main\n"
    "def _hwm():\n"
    "    kb = [ln.split()[1] for ln in open('/proc/self/status') if ln.startswith('VmHWM:')]\n"
    f"    sys.stderr.write({_HWM_TAG!r} + kb[0] + '\\n')\n"
    "atexit.register(_hwm)\n"
    "sys.exit(main(sys.argv[1:]))\n"
)


def _cap_memory() -> None:  # runs in the child before exec
    resource.setrlimit(resource.RLIMIT_AS, (AS_LIMIT, AS_LIMIT))


def run_solve(chunks: Iterator[bytes], *argv: str) -> Child:
    """Feed ``chunks`` to ``diffpos solve ARGV`` on stdin (from a thread, never all in memory
    here); the results and the child's own CPU time and peak RSS."""
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen([sys.executable, "-c", _REPORT_HWM, "solve", *argv],
                                stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=err, preexec_fn=_cap_memory)

        def feed() -> None:
            try:
                for c in chunks:
                    proc.stdin.write(c)
            except BrokenPipeError:  # the child died: the assertions below say how
                pass
            finally:
                try:
                    proc.stdin.close()
                except BrokenPipeError:
                    pass

        writer = threading.Thread(target=feed, daemon=True)
        writer.start()
        out = proc.stdout.read()
        proc.stdout.close()
        writer.join(timeout=60)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        err.seek(0)
        text = err.read().decode(errors="replace")
    text, _, hwm = text.rpartition(_HWM_TAG)
    return Child(rc=proc.returncode, records=[json.loads(x) for x in out.splitlines()],
                 stderr=text, cpu_s=usage.ru_utime + usage.ru_stime,
                 rss_mb=int(hwm.split()[0]) / 1024)


# ----------------------------------------------------------------------------- per problem
def test_a_thousand_anchor_line_is_refused_at_once_naming_the_option():
    """Before: this one line cost 102 s CPU and 3.9 GB, now it is refused in well under a
    second and the lines around it are solved."""
    bad = problem_line(1000, 1, random_ranges=True)
    child = run_solve(iter([GOOD_LINE, bad, GOOD_LINE]))
    assert child.rc == 0, child.stderr
    assert [r["status"] for r in child.records] == ["ok", "invalid_input", "ok"]
    msg = child.records[1]["message"]
    assert msg.startswith(f"anchors_m has 1000 anchors; at most {DEFAULT_MAX_ANCHORS} per "
                          "problem"), msg
    assert f"--max-anchors, default {DEFAULT_MAX_ANCHORS}, at most 1024" in msg
    assert child.cpu_s < 15 and child.rss_mb < 250, (child.cpu_s, child.rss_mb)


def test_anchor_and_start_limits_are_options_with_their_defaults_in_help():
    help_text = subprocess.run([str(EXE), "solve", "--help"], capture_output=True, text=True,
                               check=True, timeout=60).stdout
    flat = " ".join(help_text.split())
    assert f"--max-anchors N a problem with more anchors is answered with invalid_input " \
           f"(default {DEFAULT_MAX_ANCHORS}" in flat
    assert f"(default {DEFAULT_MAX_STARTS}, at most 1000)" in flat
    assert "--max-line-bytes N longer lines" in flat
    # one process per option setting: both over-limit lines refused at the defaults, both
    # solved when the options allow them (two lines per process instead of one each)
    m = DEFAULT_MAX_ANCHORS + 1
    many_anchors = problem_line(m, 2)
    starts = {"z_starts_m": [float(z) for z in range(DEFAULT_MAX_STARTS + 1)]}
    many_starts = problem_line(5, 3, **starts)
    refused = run_solve(iter([many_anchors, many_starts]))
    assert [r["status"] for r in refused.records] == ["invalid_input", "invalid_input"]
    assert "--max-anchors" in refused.records[0]["message"]
    assert "--max-starts, default 32, at most 1000" in refused.records[1]["message"]
    allowed = run_solve(iter([many_anchors, many_starts]), "--max-anchors", str(m),
                        "--max-starts", "64")
    assert [r["status"] for r in allowed.records] == ["ok", "ok"], allowed.records


@pytest.mark.parametrize(("argv", "needle"), [
    (["--max-anchors", "2000"], "--max-anchors must be an integer in [3, 1024], got 2000"),
    (["--max-anchors", "2"], "--max-anchors must be an integer in [3, 1024], got 2"),
    (["--max-starts", "0"], "--max-starts must be an integer in [1, 1000], got 0"),
    (["--max-line-bytes", "8"], "--max-line-bytes must be an integer in [16, 1073741824]"),
    (["--batch", "0"], "--batch must be >= 1, got 0"),
])
def test_limit_options_out_of_range_exit_2_naming_the_option(argv, needle):
    proc = subprocess.run([str(EXE), "solve", *argv], input=GOOD_LINE, capture_output=True,
                          timeout=60, check=False)
    err = proc.stderr.decode()
    assert proc.returncode == 2 and proc.stdout == b""
    assert f"diffpos solve: error: {needle}" in err and "Traceback" not in err


def test_worst_problems_the_defaults_allow_are_bounded_per_line():
    """32 anchors, 32 starts, every anchor faulty, gating allowed to exclude down to 3: the
    most work one line can ask for at the defaults; a batch of them is solved in chunks."""
    extra = {"random_ranges": True, "z_starts_m": [float(z) for z in range(32)],
             "gating": {"max_exclusions": 29}}
    n = 8
    child = run_solve(problem_line(32, 100 + k, **dict(extra)) for k in range(n))
    assert child.rc == 0, child.stderr
    assert len(child.records) == n
    assert child.cpu_s < 3 + 4 * n, child.cpu_s  # measured 2.0 s for all 8 (1.2 s start-up)
    assert child.rss_mb < 400, child.rss_mb  # measured 171 MB (the start-up's peak)


# ----------------------------------------------------------------------------- streams
def _heavy_lines(n: int) -> Iterator[bytes]:
    """Lines just under the default 1 MiB that decode to ~30 MB of Python objects each
    (a list of empty lists as the id): a batch of them must never be held at once."""
    unit = b"[[]],"
    body = b'{"id": [' + unit * ((MIB - 32) // len(unit)) + b'0]}\n'
    assert len(body) < MIB
    for _ in range(n):
        yield body
    yield GOOD_LINE


def _giant_line(size: int) -> Iterator[bytes]:
    """One line of ``size`` bytes (never complete in memory anywhere), then a good line."""
    piece = b"x" * MIB
    yield b'{"id": "'
    for _ in range(size // MIB):
        yield piece
    yield b'"}\n' + GOOD_LINE


def _deep_lines(n: int) -> Iterator[bytes]:
    """Lines nested as deep as a line allows: arrays, objects, and just under the decoder's
    recursion limit (valid JSON, refused by the field checks)."""
    for k in range(n):
        if k % 3 == 0:
            yield b"[" * (MIB - 2) + b"\n"
        elif k % 3 == 1:
            yield b'{"a":' * ((MIB - 2) // 5) + b"\n"
        else:
            yield b"[" * 900 + b"]" * 900 + b"\n"
    yield GOOD_LINE


def _many_blank_and_short(n: int) -> Iterator[bytes]:
    """Many tiny junk lines and blank lines: per-line overhead, not per-line size."""
    for _ in range(n):
        yield b"{}\n\n   \nnull\n"
    yield GOOD_LINE


STREAMS: list[tuple[str, Callable[[], Iterator[bytes]], int]] = [
    # (case, stream, expected number of results)
    ("many-huge-lines", lambda: _heavy_lines(24), 25),
    ("one-giant-line", lambda: _giant_line(512 * MIB), 2),
    ("deep-nesting", lambda: _deep_lines(60), 61),
    ("many-short-lines", lambda: _many_blank_and_short(20000), 40001),
]


@pytest.mark.parametrize(("case", "stream", "n_results"), STREAMS, ids=[s[0] for s in STREAMS])
def test_hostile_stream_cannot_exhaust_memory_or_time(case, stream, n_results):
    """Default options (1 MiB lines, batches of 256): every non-blank line is answered, the
    good line at the end is solved, and the process stays small and quick."""
    child = run_solve(stream())
    assert child.rc == 0 and "Traceback" not in child.stderr, (child.rc, child.stderr[-2000:])
    assert len(child.records) == n_results
    assert all(r["status"] == "invalid_input" for r in child.records[:-1])
    assert child.records[-1]["status"] == "ok"
    # 24 decoded heavy lines held at once would be ~720 MB (2.4x the bound; 64 lines cost
    # 2.7x the time for no stronger check); a giant line held whole 512 MB
    assert child.rss_mb < 300, (case, child.rss_mb)
    assert child.cpu_s < 60, (case, child.cpu_s)
