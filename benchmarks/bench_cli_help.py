"""How long ``diffpos VERB --help`` takes on a fresh machine, for every verb; prints a table.

A fresh machine has no numba cache: each run gets ``NUMBA_CACHE_DIR`` pointed at a new empty
folder, so a verb whose help imported (and compiled) a kernel would pay for it here (before
issue 33: 71 s for ``diffpos replay --help``). Each row is a new interpreter running
``python -m diffpos_services.cli.main VERB --help`` (what the ``diffpos`` script runs), with
the environment of this process (PYTHONPATH included). Target: every verb under 3 s.

    python benchmarks/bench_cli_help.py [--repeat 3]

Columns: wall seconds (median and max of ``--repeat`` runs), the child's CPU seconds (user +
sys, median), and whether numba was imported (``-X importtime`` of one run).
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time

from diffpos_services.cli.main import COMMANDS

TARGET_S = 3.0


def _run(argv: list[str]) -> tuple[float, float, bool]:
    """(wall [s], child CPU [s], numba imported) of one ``diffpos ARGV`` with an empty cache."""
    with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        out = subprocess.run([sys.executable, "-X", "importtime", "-m", "diffpos_services.cli.main",
                              *argv], env=env, capture_output=True, text=True, check=False)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if out.returncode != 0:
        raise SystemExit(f"diffpos {' '.join(argv)} failed ({out.returncode}):\n{out.stderr}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    numba = any(line.rstrip().endswith("| numba") for line in out.stderr.splitlines())
    return wall, cpu, numba


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3, help="runs per verb (default 3)")
    args = ap.parse_args(argv)
    rows = [("(diffpos --help)", ["--help"])] + [(v, [v, "--help"]) for v in COMMANDS]
    print(f"{'verb':<18} {'wall median [s]':>15} {'wall max [s]':>12} {'CPU [s]':>8} "
          f"{'numba':>6}  < {TARGET_S:g} s")
    worst = 0.0
    for name, cmd in rows:
        runs = [_run(cmd) for _ in range(args.repeat)]
        walls = [r[0] for r in runs]
        worst = max(worst, max(walls))
        print(f"{name:<18} {statistics.median(walls):>15.2f} {max(walls):>12.2f} "
              f"{statistics.median(r[1] for r in runs):>8.2f} "
              f"{'yes' if any(r[2] for r in runs) else 'no':>6}  "
              f"{'ok' if max(walls) < TARGET_S else 'SLOW'}")
    print(f"slowest run: {worst:.2f} s (load average {os.getloadavg()[0]:.1f})")
    return 0 if worst < TARGET_S else 1


if __name__ == "__main__":
    sys.exit(main())
