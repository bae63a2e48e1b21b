"""Regenerate the bad-input table of docs/bad_input.md by running every case.

    .venv/bin/python scripts/bad_input_table.py            # rewrite the table in the doc
    .venv/bin/python scripts/bad_input_table.py --check    # exit 1 if the doc is out of date
    .venv/bin/python scripts/bad_input_table.py --only 15.11 --doc /tmp/x.md   # a subset

Every case runs the real ``diffpos`` command (the one next to this Python, else the one on
PATH) in a fresh temporary directory with its stdin, and its row says what happens now: the
exit code, and for ``diffpos solve`` the status and message of each result (``position_m
null`` when no position is published), for other verbs the last line of stderr. The rows
replace everything between the markers ``<!-- generated: scripts/bad_input_table.py -->``
and ``<!-- /generated -->`` (added at the end of the doc if missing); the prose around them
is kept byte for byte, so the table is never hand-written.

Adding a case is one entry in :data:`CASES`::

    Case("15.12", "`replay --out` at an existing file", ("replay", "{tmp}/x.mcap", "--out",
         "{tmp}/taken"), "tests/services/test_cli.py::test_replay_out_exists",
         setup=lambda tmp: (tmp / "taken").write_text("x")),

``{tmp}`` in ``argv`` is the case's temporary directory (also its working directory);
``stdin`` is bytes, a function returning bytes, or a path (relative to the repository);
``setup(tmp)`` prepares files before the run.
"""

from __future__ import annotations

import argparse
import collections
import importlib.util
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "bad_input.md"
BEGIN = "<!-- generated: scripts/bad_input_table.py -->"
END = "<!-- /generated -->"
NASTY = ROOT / "tests" / "data" / "nasty"
MESSAGE_CHARS = 220
GOOD_STATUSES = ("ok", "ok_unverified")


@dataclass(frozen=True)
class Case:
    """One bad input: what was tried, how to run it, and the test that pins it."""

    item: str  # issue item ("15.10") or "corpus"
    tried: str  # markdown, one line
    argv: tuple[str, ...]  # after ``diffpos``; "{tmp}" is the case's temporary directory
    test: str  # file::test that pins the behaviour
    stdin: bytes | Path | Callable[[], bytes] = b""
    setup: Callable[[Path], object] | None = None
    timeout_s: float = 300.0


# ----------------------------------------------------------------------------- inputs
def _line(obj: object) -> bytes:
    return json.dumps(obj).encode() + b"\n"


GOOD = {"anchors_m": [[-15, -20, 1], [0, -15, 0], [0, -7, 4], [15, -20, 1]],
        "ranges_m": [32.233, 23.711, 15.058, 30.315], "sigmas_m": 0.005, "window_height_m": 1.0}


def _with(**changes: object) -> bytes:
    return _line({**GOOD, **changes})


def _anchor_at_y(y: float) -> bytes:
    anchors = [list(a) for a in GOOD["anchors_m"]]
    anchors[2][1] = y
    return _with(anchors_m=anchors)


def _random_anchors(m: int, seed: int = 1) -> bytes:
    """``m`` anchors with random ranges: every anchor looks faulty (the gating's worst case)."""
    rng = np.random.default_rng(seed)
    a = np.c_[rng.uniform(-30, 30, m), rng.uniform(-40, -5, m), rng.uniform(0, 30, m)]
    return _with(anchors_m=a.tolist(), ranges_m=rng.uniform(10, 60, m).tolist(),
                 sigmas_m=0.01)


def _heavy_lines(n: int = 24) -> bytes:
    """``n`` lines just under 1 MiB that decode to ~30 MB of Python objects each, then a good
    line."""
    unit = b"[[]],"
    body = b'{"id": [' + unit * (((1 << 20) - 32) // len(unit)) + b'0]}\n'
    return body * n + _line(GOOD)


def _deep_lines() -> bytes:
    return b"[" * ((1 << 20) - 2) + b"\n" + b'{"a":' * 200_000 + b"\n" + _line(GOOD)


SOLVE_CORPUS_TEST = ("tests/services/test_bad_input.py::"
                     "test_solve_answers_every_nasty_line_and_every_good_one")
LIMITS = "tests/system/test_solve_limits.py::"
SOLVE_CLI = "tests/services/test_solve_cli.py::"


def _corpus_cases() -> list[Case]:
    """One case per line of the committed solve corpus (described in make_corpus.py)."""
    spec = importlib.util.spec_from_file_location("make_corpus", NASTY / "make_corpus.py")
    corpus = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(corpus)
    return [Case("corpus", f"`solve/{name}`: {what}", ("solve", "--max-line-bytes", "65536"),
                 SOLVE_CORPUS_TEST, stdin=NASTY / "solve" / name)
            for name, _needle, what, _data in corpus.SOLVE]


# ----------------------------------------------------------------------------- issue 36 item 5
SCEN = "tests/services/test_scenario_file_limits.py::"
DAMAGE = "tests/services/test_recording_damage.py::"
SAMPLE = ROOT / "recordings" / "sample.mcap"
_ANCHOR = '[[anchors]]\nid = "u{i}"\nposition_m = [{x}.0, {y}.0, 1.0]\n'


def _scenario_with_anchors(tmp: Path, n: int, name: str) -> None:
    paper = (ROOT / "scenarios" / "paper.toml").read_text()
    head, tail = paper[: paper.index("[[anchors]]")], paper[paper.index("[nodes"):]
    body = "".join(_ANCHOR.format(i=i, x=i % 1000, y=-20 - i // 1000) for i in range(n))
    (tmp / name).write_text(head + body + tail)


def _chunk_offsets(data: bytes) -> list[tuple[int, int]]:
    out, off = [], 8
    while off + 9 <= len(data):
        op, ln = struct.unpack_from("<BQ", data, off)
        if op == 0x06:
            out.append((off, ln))
        if op == 0x02:
            break
        off += 9 + ln
    return out


def _damaged_sample(tmp: Path, how: str) -> None:
    data = bytearray(SAMPLE.read_bytes())
    off, ln = _chunk_offsets(bytes(data))[len(_chunk_offsets(bytes(data))) // 4]
    if how == "length":
        struct.pack_into("<Q", data, off + 1, ln + 12345)
    elif how == "opcode":
        data[off] = 0x33
    elif how == "crc":
        at = off + 9 + 24
        struct.pack_into("<I", data, at, struct.unpack_from("<I", data, at)[0] ^ 1)
    (tmp / f"{how}.mcap").write_bytes(bytes(data))


def _foreign_mcap(tmp: Path) -> None:
    from mcap.writer import Writer  # the script's only use of mcap

    with open(tmp / "foreign.mcap", "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("foo.AnchorState", "protobuf", b"\x00")
        cid = w.register_channel("diffpos/demo/anchor/uav1/state", "protobuf", sid)
        for i in range(100):
            w.add_message(cid, log_time=i, data=b"\x08\x01", publish_time=i)
        w.finish()


ITEM5_CASES: list[Case] = [
    Case("36.5", "`emulate`: a scenario with 5,000 anchors (was > 120 s CPU, SIGTERM ignored)",
         ("emulate", "{tmp}/many.toml", "--duration", "1"),
         SCEN + "test_five_thousand_anchor_file_names_the_anchor_limit",
         setup=lambda tmp: _scenario_with_anchors(tmp, 5000, "many.toml")),
    Case("36.5", "`emulate`: a scenario with 10^6 anchors, 50 MB (was 23.7 GB, killed by the "
         "kernel)", ("emulate", "{tmp}/million.toml", "--duration", "1"),
         SCEN + "test_oversized_file_is_refused_without_reading_it_all",
         setup=lambda tmp: _scenario_with_anchors(tmp, 1_000_000, "million.toml")),
    Case("36.5", "`emulate`: a scenario nested 100,000 deep (was a RecursionError traceback)",
         ("emulate", "{tmp}/deep.toml", "--duration", "1"),
         SCEN + "test_deep_nesting_is_refused_naming_the_limit",
         setup=lambda tmp: (tmp / "deep.toml").write_text("a = " + "[" * 100_000
                                                          + "]" * 100_000)),
    Case("36.5", "`recover`: one chunk length field of `recordings/sample.mcap` corrupted "
         "(was: the remaining 73 % dropped)", ("recover", "{tmp}/length.mcap", "--out",
                                                "{tmp}/fixed.mcap"),
         DAMAGE + "test_recover_reads_a_chunk_by_its_contents_when_its_length_field_is_corrupt",
         setup=lambda tmp: _damaged_sample(tmp, "length")),
    Case("36.5", "`recover`: one record opcode corrupted", ("recover", "{tmp}/opcode.mcap",
                                                            "--out", "{tmp}/fixed.mcap"),
         DAMAGE + "test_recover_resyncs_past_an_unreadable_record",
         setup=lambda tmp: _damaged_sample(tmp, "opcode")),
    Case("36.5", "`to-rerun`: a chunk failing its CRC", ("to-rerun", "{tmp}/crc.mcap", "-o",
                                                         "{tmp}/x.rrd"),
         DAMAGE + "test_every_reader_logs_a_crc_failure_naming_file_and_byte",
         setup=lambda tmp: _damaged_sample(tmp, "crc")),
    Case("36.5", "`inspect`: a chunk failing its CRC", ("inspect", "{tmp}/crc.mcap"),
         DAMAGE + "test_every_reader_logs_a_crc_failure_naming_file_and_byte",
         setup=lambda tmp: _damaged_sample(tmp, "crc")),
    Case("36.5", "`to-rerun`: a protobuf MCAP on a diffpos-looking topic (was an .rrd, exit 0)",
         ("to-rerun", "{tmp}/foreign.mcap", "-o", "{tmp}/x.rrd"),
         DAMAGE + "test_foreign_mcap_with_diffpos_looking_topics_is_refused",
         setup=_foreign_mcap),
    Case("36.5", "`replay`: the same foreign MCAP (was `fixes: 0`, exit 0)",
         ("replay", "{tmp}/foreign.mcap", "--no-files"),
         DAMAGE + "test_foreign_mcap_with_diffpos_looking_topics_is_refused",
         setup=_foreign_mcap),
]


#: Every case, in table order. One entry per case.
CASES: list[Case] = [
    # issue 15, item 10: bounded work per line
    Case("15.10", "`solve`: one line with 1000 anchors, random ranges (was 102 s CPU, 3.9 GB)",
         ("solve",), LIMITS + "test_a_thousand_anchor_line_is_refused_at_once_naming_the_option",
         stdin=lambda: _random_anchors(1000)),
    Case("15.10", "`solve`: 33 anchors (one above the default `--max-anchors`)", ("solve",),
         LIMITS + "test_anchor_and_start_limits_are_options_with_their_defaults_in_help",
         stdin=lambda: _random_anchors(33)),
    Case("15.10", "`solve --max-anchors 40`: the same 33 anchors", ("solve", "--max-anchors", "40"),
         LIMITS + "test_anchor_and_start_limits_are_options_with_their_defaults_in_help",
         stdin=lambda: _random_anchors(33)),
    Case("15.10", "`solve`: 33 `z_starts_m`", ("solve",),
         LIMITS + "test_anchor_and_start_limits_are_options_with_their_defaults_in_help",
         stdin=lambda: _with(z_starts_m=[float(z) for z in range(33)])),
    Case("15.10", "`solve --max-anchors 2000`", ("solve", "--max-anchors", "2000"),
         LIMITS + "test_limit_options_out_of_range_exit_2_naming_the_option",
         stdin=_line(GOOD)),
    Case("15.10", "`solve`: 24 lines of 1 MiB decoding to 30 MB each, then a good line",
         ("solve",), LIMITS + "test_hostile_stream_cannot_exhaust_memory_or_time[many-huge-lines]",
         stdin=_heavy_lines),
    Case("15.10", "`solve`: one 5 MiB line, then a good line (the test: 512 MiB)", ("solve",),
         LIMITS + "test_hostile_stream_cannot_exhaust_memory_or_time[one-giant-line]",
         stdin=lambda: b'{"id": "' + b"x" * (5 << 20) + b'"}\n' + _line(GOOD)),
    Case("15.10", "`solve`: 1 MiB of `[`, 200,000 nested `{\"a\":`, then a good line",
         ("solve",), LIMITS + "test_hostile_stream_cannot_exhaust_memory_or_time[deep-nesting]",
         stdin=_deep_lines),
    # issue 15, item 11: anchors outside, no untrustworthy positions, blank lines
    Case("15.11", "`solve`: anchor 2 inside the building (y = 5)", ("solve",),
         SOLVE_CLI + "test_anchor_not_outside_is_invalid_naming_the_anchor",
         stdin=lambda: _anchor_at_y(5.0)),
    Case("15.11", "`solve`: anchor 2 on the facade (y = 0)", ("solve",),
         SOLVE_CLI + "test_anchor_not_outside_is_invalid_naming_the_anchor",
         stdin=lambda: _anchor_at_y(0.0)),
    Case("15.11", "`solve`: four anchors at one point (not identifiable)", ("solve",),
         SOLVE_CLI + "test_statuses_without_a_trustworthy_position_publish_none",
         stdin=lambda: _with(anchors_m=[[0, -5, 1]] * 4, ranges_m=[10.0] * 4, sigmas_m=0.01)),
    Case("15.11", "`solve`: a fix below `gating.z_range_m` (gating_failed)", ("solve",),
         SOLVE_CLI + "test_statuses_without_a_trustworthy_position_publish_none",
         stdin=lambda: _with(gating={"z_range_m": [12.0, 30.0]})),
    Case("15.11", "`solve`: good line, blank, spaces, tab, good line", ("solve",),
         SOLVE_CLI + "test_blank_lines_are_skipped_as_help_and_docs_say",
         stdin=lambda: _line(GOOD) + b"\n   \n\t\n" + _line(GOOD)),
    # the committed corpus of nasty solve lines
    *_corpus_cases(),
    *ITEM5_CASES,
]


# ----------------------------------------------------------------------------- running
def diffpos_exe() -> str:
    here = Path(sys.executable).parent / "diffpos"
    return str(here) if here.exists() else (shutil.which("diffpos") or "diffpos")


def _stdin_bytes(case: Case) -> bytes:
    if isinstance(case.stdin, Path):
        return (case.stdin if case.stdin.is_absolute() else ROOT / case.stdin).read_bytes()
    return case.stdin() if callable(case.stdin) else case.stdin


def run_case(case: Case, exe: str) -> str:
    """Run one case; the "now" cell of its row."""
    with tempfile.TemporaryDirectory(prefix="bad-input-") as tmp:
        if case.setup is not None:
            case.setup(Path(tmp))
        argv = [a.replace("{tmp}", tmp) for a in case.argv]
        env = dict(os.environ, DIFFPOS_LOG_FORMAT="text", COLUMNS="200", NO_COLOR="1")
        try:
            proc = subprocess.run([exe, *argv], input=_stdin_bytes(case), capture_output=True,
                                  cwd=tmp, env=env, timeout=case.timeout_s, check=False)
        except subprocess.TimeoutExpired:
            return f"**timed out** after {case.timeout_s:g} s"
        out = proc.stdout.decode(errors="replace").replace(tmp, "{tmp}")
        err = proc.stderr.decode(errors="replace").replace(tmp, "{tmp}")
    return describe(case, proc.returncode, out, err)


def describe(case: Case, rc: int, out: str, err: str) -> str:
    """Exit code plus the results (``solve``) or the last stderr line (other verbs)."""
    parts = [f"exit {rc}"]
    records = _records(out) if case.argv[:1] == ("solve",) else None
    if records:
        parts.append(_records_text(records))
    else:
        last = [ln.strip() for ln in err.splitlines() if ln.strip()]
        if last:
            parts.append(_clip(last[-1]))
    if "Traceback" in err:
        parts.append("**traceback**")
    return "; ".join(parts)


def _records(out: str) -> list[dict] | None:
    try:
        return [json.loads(ln) for ln in out.splitlines() if ln.strip()]
    except json.JSONDecodeError:
        return None


def _record_text(rec: dict) -> str:
    status = rec.get("status")
    text = f"`{status}`"
    if status not in GOOD_STATUSES and status != "invalid_input":
        text += ", position_m " + ("null" if rec.get("position_m") is None else "PUBLISHED")
    return f"{text}: {_clip(rec.get('message') or '')}"


def _records_text(records: list[dict]) -> str:
    if len(records) == 1:
        return _record_text(records[0])
    counts = collections.Counter(r.get("status") for r in records)
    lines = _spans([int(r.get("line") or 0) for r in records])
    text = f"{len(records)} results (lines {lines}): " + ", ".join(
        f"{n} `{s}`" for s, n in counts.items())
    first_bad = next((r for r in records if r.get("status") not in GOOD_STATUSES), None)
    return text + (f"; first: {_record_text(first_bad)}" if first_bad else "")


def _spans(numbers: Sequence[int]) -> str:
    """``[1, 2, 3, 5]`` -> ``"1-3, 5"``."""
    spans: list[list[int]] = []
    for n in numbers:
        if spans and n == spans[-1][1] + 1:
            spans[-1][1] = n
        else:
            spans.append([n, n])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in spans)


def _clip(text: str) -> str:
    text = " ".join(text.split()).replace("|", "\\|")
    return text if len(text) <= MESSAGE_CHARS else text[:MESSAGE_CHARS - 3] + "..."


# ----------------------------------------------------------------------------- the doc
def table(cases: Sequence[Case], exe: str, *, progress: bool = False) -> str:
    rows = ["| item | tried | now | test |", "| --- | --- | --- | --- |"]
    for k, case in enumerate(cases, start=1):
        if progress:
            print(f"[{k}/{len(cases)}] {case.item}: {case.tried}", file=sys.stderr)
        rows.append(f"| {case.item} | {case.tried} | {run_case(case, exe)} | `{case.test}` |")
    return "\n".join(rows)


def splice(doc: str, body: str) -> str:
    """``doc`` with the text between the markers replaced by ``body`` (markers appended at the
    end if missing)."""
    if BEGIN not in doc or END not in doc:
        doc = doc.rstrip("\n") + f"\n\n{BEGIN}\n{END}\n"
    head, rest = doc.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{BEGIN}\n{body}\n{END}{tail}"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--doc", type=Path, default=DOC, help="the markdown file to update")
    parser.add_argument("--check", action="store_true",
                        help="do not write; exit 1 if the doc's table is out of date")
    parser.add_argument("--only", metavar="TEXT",
                        help="only the cases whose item or description contains TEXT")
    args = parser.parse_args(argv)
    cases = [c for c in CASES if not args.only or args.only in f"{c.item} {c.tried}"]
    doc = args.doc.read_text(encoding="utf-8")
    new = splice(doc, table(cases, diffpos_exe(), progress=True))
    if args.check:
        if new != doc:
            print(f"{args.doc} is out of date: run scripts/bad_input_table.py", file=sys.stderr)
            return 1
        return 0
    if new != doc:
        tmp = args.doc.with_name(args.doc.name + ".tmp")
        tmp.write_text(new, encoding="utf-8")
        tmp.replace(args.doc)
    print(f"{args.doc}: {len(cases)} cases", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
