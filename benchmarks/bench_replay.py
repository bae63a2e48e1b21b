"""Replay speed, memory and live-equivalence (issue 16 item 3, issue 15 item 3).

Prints one table, ratios side by side, each replay in a fresh child process (its own peak
RSS, ``ru_maxrss``):

* realistic: a recording of ``diffpos emulate scenarios/large.toml --speed 0 --duration D
  --record R`` (8 anchors x 50 nodes x 10 Hz on the O2I emulator channel, the live fusion's
  decision record inside), replayed as now (by the decision record, report as a stream) and
  as before (recorder order, every estimate kept): speed vs real time, bit-identity with the
  live fixes (statuses, positions), peak RSS.
* flat memory: synthetic RangeBatch recordings (8 x 50 x 10 Hz, a live fusion's estimates
  recorded; ``replay/synthetic.py``, ideal channel: the cheap way to get an hour) of two
  lengths, replayed now: peak RSS must not follow the length.
* ``--profile``: where a replay of the realistic recording spends its time (cProfile, top
  functions by own time).

Usage::

    python benchmarks/bench_replay.py                          # defaults below
    python benchmarks/bench_replay.py --realistic r.mcap       # reuse a recording
    python benchmarks/bench_replay.py --emulate-s 600 --minutes 10 60 --profile
    python benchmarks/bench_replay.py --realistic r600.mcap --synthetic s10.mcap s60.mcap
    python benchmarks/bench_replay.py --realistic r.mcap --minutes --methods default dnls
    python benchmarks/bench_replay.py --realistic r.mcap --synthetic s10.mcap s60.mcap --methods mnls

A split recording (``r.mcap``, ``r_0001.mcap``, ...: the recorder splits long runs) is given
by its first part and replayed whole.

The machine and Python are printed with the table (shared machines: say so next to any
figure quoted from it).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import platform
import pstats
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import msgspec
from diffpos_services.heap import keep_heap
from diffpos_services.replay.run import replay
from diffpos_services.wire import messages as M

ROOT = Path(__file__).resolve().parent.parent


def _env() -> dict[str, str]:
    path = os.pathsep.join([str(ROOT), str(ROOT / "services"), os.environ.get("PYTHONPATH", "")])
    return dict(os.environ, PYTHONPATH=path)


def child_replay(path: str, mode: str, method: str = "default") -> dict:
    """One replay in this (fresh) process; the figures as a dict. ``method``: the fusion's
    estimator (``default``: the recorded one, the only one that can be identical to live).
    ``cpu_s`` is the whole process's CPU (imports included), ``fusion_cpu_s`` the replay
    call's own (``time.process_time`` around it)."""
    new = mode == "now"
    keep_heap()  # as `diffpos replay` (diffpos_services.heap)
    c0, t0 = time.process_time(), time.perf_counter()
    r = replay(path, keep_estimates=not new, use_decisions=new,
               method=None if method == "default" else method)
    wall = time.perf_counter() - t0
    fusion_cpu = time.process_time() - c0
    rep = r.report
    c = rep["compare"] or {}
    out = {
        "mode": mode,
        # the run's length in emulated time (truth span): a lockstep recording's receive
        # times span longer than the run
        "recording_s": rep["truth_s"] or rep["recording_s"],
        "wall_s": wall,
        "cpu_s": time.process_time(),
        "fusion_cpu_s": fusion_cpu,
        "method": method,
        "speed_x": (rep["truth_s"] or rep["recording_s"]) / wall if wall > 0 else None,
        "fixes": rep["fixes"]["total"],
        "live": c.get("live"),
        "only_live": c.get("only_live"),
        "only_replayed": c.get("only_replayed"),
        "status_agree": c.get("status_agree"),
        "identical_positions": c.get("identical_positions"),
        "with_positions": c.get("with_positions"),
        "max_diff_m": (c.get("position_diff_m") or {}).get("max"),
        "decisions": rep["decisions"],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "parts": len(rep.get("parts") or [path]),
        "load": os.getloadavg()[0],
    }
    if not new and r.live_estimates:  # before: every field of every fix
        def bare(e):
            return M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0))
        out["all_fields_equal"] = (sorted(map(bare, r.live_estimates))
                                   == sorted(map(bare, r.estimates)))
    return out


def child_profile(path: str, top: int) -> None:
    prof = cProfile.Profile()
    prof.enable()
    replay(path, keep_estimates=False)
    prof.disable()
    st = pstats.Stats(prof)
    total = sum(v[2] for v in st.stats.values())
    rows = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:top]
    print(f"\nprofile of one replay (own time, {total:.1f} s total under cProfile):")
    for (file, line, fn), (_cc, nc, tt, _ct, _callers) in rows:
        where = f"{Path(file).parent.name}/{Path(file).name}:{line}" if line else file
        print(f"  {100 * tt / total:5.1f} %  {tt:7.2f} s  {nc:>9}  {fn}  ({where})")


def _run_child(*argv: str) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", *argv], env=_env(),
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _emulate(path: Path, seconds: float) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "diffpos_services.cli.main", "emulate",
                    str(ROOT / "scenarios" / "large.toml"), "--speed", "0", "--duration",
                    str(seconds), "--dashboard", "off", "--no-progress", "--record", str(path)],
                   env=_env(), check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def _synthetic(path: Path, minutes: float) -> None:
    code = ("import sys; from diffpos_services.replay.synthetic import "
            "write_synthetic_recording as w; "
            f"w(sys.argv[1], n_anchors=8, n_nodes=50, duration_s={minutes * 60}, "
            "rate_hz=10.0, range_batch=True, outlier_probability=0.05, seed=3)")
    subprocess.run([sys.executable, "-c", code, str(path)], env=_env(), check=True)


def _fmt(v, spec: str = "") -> str:
    if v is None:
        return "-"
    return format(v, spec) if spec else str(v)


def _row(name: str, r: dict) -> str:
    ident = (f"{r['identical_positions']}/{r['with_positions']}"
             if r.get("with_positions") is not None else "-")
    cpu_x = r["recording_s"] / r["cpu_s"] if r.get("cpu_s") else None
    own_x = r["recording_s"] / r["fusion_cpu_s"] if r.get("fusion_cpu_s") else None
    return (f"{name:<34} {r['recording_s']:>8.1f} {r['wall_s']:>8.1f} "
            f"{_fmt(r['speed_x'], '.2f'):>8} {_fmt(cpu_x, '.2f'):>8} {_fmt(own_x, '.2f'):>8} "
            f"{r['fixes']:>8} {_fmt(r['status_agree'], '.4f'):>7} "
            f"{ident:>15} {_fmt(r['max_diff_m'], '.3g'):>9} {r['peak_rss_mb']:>8.0f} "
            f"{r.get('parts', 1):>5} {r.get('load', 0):>5.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--realistic", help="an existing emulate recording (else one is made)")
    ap.add_argument("--emulate-s", type=float, default=600.0,
                    help="emulated seconds of the realistic recording to make (default 600)")
    ap.add_argument("--minutes", type=float, nargs="*", default=[10.0, 60.0],
                    help="lengths of the synthetic recordings for the flat-memory check")
    ap.add_argument("--synthetic", nargs="*", default=None, metavar="MCAP",
                    help="existing synthetic recordings for the flat-memory check (instead of "
                         "making --minutes ones)")
    ap.add_argument("--before", action="store_true",
                    help="also replay the realistic recording as before (every estimate kept)")
    ap.add_argument("--methods", nargs="+", default=["default"], metavar="METHOD",
                    help="replay the realistic and the synthetic recordings with each fusion "
                         "method (default: the recorded one, mnls in emulate's recordings, "
                         "dnls in the synthetic ones; e.g. --methods default mnls)")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="print the top N functions of a profiled realistic replay")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        if args.child[0] == "profile":
            child_profile(args.child[1], int(args.child[2]))
        else:
            print(json.dumps(child_replay(*args.child)))
        return
    tmp = Path(tempfile.mkdtemp(prefix="bench_replay_"))
    rows: list[tuple[str, dict]] = []
    notes = []
    real = Path(args.realistic) if args.realistic else tmp / "realistic.mcap"
    if not args.realistic:
        wall = _emulate(real, args.emulate_s)
        notes.append(f"made {real.name}: diffpos emulate scenarios/large.toml --speed 0 "
                     f"--duration {args.emulate_s:g} --record ... ({wall:.0f} s wall)")
    for method in args.methods:
        label = "" if method == "default" else f", {method}"
        rows.append((f"realistic, now{label} (decision record)",
                     _run_child(str(real), "now", method)))
    if args.before:
        rows.append(("realistic, before (recorder order)", _run_child(str(real), "before")))
    synthetic = [] if args.synthetic is None else [(p, Path(p).name) for p in args.synthetic]
    for minutes in [] if args.synthetic is not None else args.minutes:
        p = tmp / f"synthetic_{minutes:g}min.mcap"
        t0 = time.perf_counter()
        _synthetic(p, minutes)
        notes.append(f"made {p.name} ({time.perf_counter() - t0:.0f} s wall)")
        synthetic.append((str(p), f"{minutes:g} min"))
    for p, name in synthetic:  # each method on each length (default: the recorded D-NLS)
        for method in args.methods:
            label = "" if method == "default" else f", {method}"
            rows.append((f"synthetic {name}, now{label}", _run_child(p, "now", method)))
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python "
          f"{platform.python_version()} (shared with other jobs: absolute times vary)")
    for n in notes:
        print("  " + n)
    print("\nx cpu: recording length / CPU of the whole replay process (imports included); "
          "x own: / CPU of the replay call alone")
    print(f"\n{'replay':<34} {'rec [s]':>8} {'wall [s]':>8} {'x real':>8} {'x cpu':>8} {'x own':>8} "
          f"{'fixes':>8} {'status=':>7} {'identical pos':>15} {'max d [m]':>9} {'RSS [MB]':>8} "
          f"{'parts':>5} {'load':>5}")
    for name, r in rows:
        print(_row(name, r))
    for name, r in rows:
        if r.get("decisions"):
            print(f"  {name}: decisions {r['decisions']}")
        if "all_fields_equal" in r:
            print(f"  {name}: every field of every fix equal to live: {r['all_fields_equal']}")
    if args.profile:
        subprocess.run([sys.executable, __file__, "--child", "profile", str(real),
                        str(args.profile)], env=_env(), check=True)


if __name__ == "__main__":
    main()
