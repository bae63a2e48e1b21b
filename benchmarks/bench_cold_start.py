"""First use on a fresh machine vs later runs: wall and CPU seconds of three commands; a table.

A fresh machine has no numba cache: each "fresh" row points ``NUMBA_CACHE_DIR`` at a new
empty folder (numba's cache also keys on the source files' path, so a new checkout is fresh
too); the "warm" row runs the same command again with that folder, now filled. Each command
is a new interpreter running ``python -m diffpos_services.cli.main ...`` (what the
``diffpos`` script runs) with this process's environment (PYTHONPATH included):

    diffpos replay --help
    diffpos emulate --speed 0 --duration 5 --dashboard off --record off   (lockstep, 5 s)
    diffpos replay REC --no-files --json        (REC: --recording, default recordings/sample.mcap)

    python benchmarks/bench_cold_start.py [--recording REC] [--only emulate]
    python benchmarks/bench_cold_start.py --groups     # each kernel group alone, fresh cache

Columns: wall seconds; CPU seconds of the command and every process it started (user + sys);
the kernels' share (emulate: the "compiled the solver kernels" seconds it logs, when it
compiled; replay: ``timing.kernels_s`` + ``timing.warm_up_s`` of its report, with the replay's
own ``wall_s`` and speed apart), with the CPU seconds of each compiling worker (on an idle
machine with a core per worker, the compile's wall seconds are about the largest of them); the 1-minute load average before the row (other processes
on the machine: on a busy machine wall seconds grow, CPU seconds much less). Target (issue
35): the fresh emulate row under 45 s wall on an idle 2-core machine.

``--groups`` prints the CPU seconds of each kernel group of
:data:`diffpos_services.fusion.prepare.GROUPS` compiled alone in a fresh cache (the
``cpu_s`` figures there come from it).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from diffpos_services.fusion.prepare import GROUPS

ROOT = Path(__file__).resolve().parents[1]
TARGET_S = 45.0


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _run(argv: list[str], cache: str) -> tuple[float, float, str, str]:
    """(wall [s], CPU of it and its children [s], stdout, stderr) of one command."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache)
    c0, t0 = _cpu(), time.perf_counter()
    out = subprocess.run(argv, env=env, capture_output=True, text=True, check=False,
                         cwd=tempfile.gettempdir())
    wall, cpu = time.perf_counter() - t0, _cpu() - c0
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(argv)} failed ({out.returncode}):\n{out.stderr[-3000:]}")
    return wall, cpu, out.stdout, out.stderr


def _note(name: str, stdout: str, stderr: str) -> str:
    if name == "emulate":
        m = re.search(r"compiled the solver kernels.*?seconds=([\d.]+)"
                      r"(?:.*?worker_cpu_s=\[([^]]*)\])?", stderr)
        if not m:
            return "kernels cached (< 5 s)"
        cpu = " + ".join(f"{float(x):.1f}" for x in (m.group(2) or "").split(",") if x)
        return f"kernels {float(m.group(1)):.1f} s" + (f" (workers' CPU {cpu} s)" if cpu else "")
    if name == "replay":
        t = json.loads(stdout[stdout.index("{"):])["timing"]
        cpu = " + ".join(f"{x:.1f}" for x in t["kernel_worker_cpu_s"])
        return (f"kernels {t['kernels_s']:.1f} s (workers' CPU {cpu} s) + warm-up "
                f"{t['warm_up_s']:.1f} s; replay {t['wall_s']:.1f} s ({t['speedup_x']:.1f}x "
                "real time)")
    return ""


def commands(recording: str) -> dict[str, list[str]]:
    cli = [sys.executable, "-m", "diffpos_services.cli.main"]
    return {
        "replay --help": [*cli, "replay", "--help"],
        "emulate": [*cli, "emulate", "--speed", "0", "--duration", "5", "--dashboard", "off",
                    "--record", "off", "--no-progress", "--log-format", "text"],
        "replay": [*cli, "replay", recording, "--no-files", "--json", "--no-progress"],
    }


def _groups() -> None:
    print(f"{'group':<10} {'wall [s]':>9} {'CPU [s]':>8} {'in GROUPS [s]':>14}")
    for name, g in GROUPS.items():
        with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
            code = ("import sys; from diffpos_services.fusion.prepare import compile_groups; "
                    "compile_groups(sys.argv[1])")
            spec = json.dumps([[name, g.calls]])
            wall, cpu, _, _ = _run([sys.executable, "-c", code, spec], cache)
        print(f"{name:<10} {wall:>9.1f} {cpu:>8.1f} {g.cpu_s:>14.1f}", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recording", default=str(ROOT / "recordings" / "sample.mcap"))
    ap.add_argument("--only", action="append", choices=["replay --help", "emulate", "replay"],
                    help="run only these commands (repeatable)")
    ap.add_argument("--groups", action="store_true", help="each kernel group alone instead")
    args = ap.parse_args(argv)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, {platform.system()} "
          f"{platform.release()}, Python {platform.python_version()}")
    if args.groups:
        _groups()
        return 0
    print(f"{'command':<14} {'cache':<6} {'load':>5} {'wall [s]':>9} {'CPU [s]':>8}  kernels / note")
    for name, cmd in commands(args.recording).items():
        if args.only and name not in args.only:
            continue
        with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
            for state in ("fresh", "warm"):
                load = os.getloadavg()[0]
                wall, cpu, out, err = _run(cmd, cache)
                print(f"{name:<14} {state:<6} {load:>5.1f} {wall:>9.1f} {cpu:>8.1f}  "
                      f"{_note(name.split()[0] if name != 'replay --help' else name, out, err)}",
                      flush=True)
    print(f"target: the fresh emulate row under {TARGET_S:g} s wall on an idle 2-core machine")
    return 0


if __name__ == "__main__":
    sys.exit(main())
