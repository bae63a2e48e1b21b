"""CPU per node-epoch of the whole fusion core, as it runs live, per method (issue 13's "usable
live: <= 2 ms per node-epoch on average with 8 anchors").

Usage::

    python benchmarks/bench_fusion_cost.py [--scenario large] [--duration 10] [--seed 0]

Records a lockstep run of the real system (``diffpos emulate SCENARIO --speed 0 --record``,
realistic emulated channel, the fusion's default method), then replays the recording in this
process with each method (:func:`diffpos_services.recording.replay.replay`: the same fusion
core as the live service, fed the recorded ranges in the recorded order) and divides the
replay's CPU time (``time.process_time``, imports and the first-call costs excluded: one warm-up
replay of the first seconds precedes the timed ones) by the node-epochs it solved. The figure
covers everything the live fusion does per node-epoch: ingest, alignment, the M-NLS snapshots
(every epoch until a track is confirmed, then every 1 s, every 10 s for a confident track), the
tracker's update, estimate building and the report. Side by side in one run: ``mnls`` (the
default: M-NLS + tracker) and ``dnls``.

Measured 2026-11-27 07:02 UTC (2-core x86_64 VM, Python 3.11.7, load average 0.8-2.1)::

    scenario              method  node-epochs  CPU s  ms/node-epoch  right floor (all)
    large (8 x 50), 10 s  mnls           5000   9.31          1.862  99.8 %   (<= 2 ms: met)
                          dnls           5000   1.99          0.398  44.6 %
    paper (4 x 6), 20 s   mnls           1200   1.77          1.476  94.1 %
                          dnls           1200   0.43          0.359  25.4 %

(``python benchmarks/bench_fusion_cost.py`` and ``... --scenario paper --duration 20``.) Before
this round's compiled SNR prediction, M-NLS LM steps and tracker kernels, the same large
replay took 3.4 ms per node-epoch (``diffpos replay``: 17.2 s for 5,000, same machine, load 2).
The snapshot fix alone costs more (3.1-3.8 ms with 8 anchors, benchmarks/
bench_estimator_cost.py): live it runs for a fraction of the node-epochs only.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from diffpos_services.recording.replay import replay

TARGET_MS = 2.0


def record(scenario: str, duration_s: float, seed: int, out: Path) -> None:
    """A lockstep run of the whole system, recorded."""
    exe = Path(sys.executable).with_name("diffpos")
    cmd = [str(exe), "emulate", scenario, "--speed", "0", "--duration", str(duration_s),
           "--seed", str(seed), "--dashboard", "off", "--no-progress", "--record", str(out)]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def cost(path: Path, method: str) -> tuple[float, int, dict]:
    """CPU seconds of one replay and the node-epochs it solved."""
    t = time.process_time()
    r = replay(path, method=method, keep_estimates=False)
    cpu = time.process_time() - t
    return cpu, int(r.report["fixes"]["total"]), r.report


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="large", help="scenario name or file (default large)")
    ap.add_argument("--duration", type=float, default=10.0, help="emulated seconds (default 10)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--recording", type=Path, help="replay this recording instead of making one")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-fusion-cost-") as tmp:
        rec = args.recording or Path(tmp) / "run.mcap"
        if args.recording is None:
            record(args.scenario, args.duration, args.seed, rec)
        cost(rec, "mnls")  # warm-up: imports, kernels, first calls
        rows = []
        for method in ("mnls", "dnls"):
            cpu, n, rep = cost(rec, method)
            rows.append((method, cpu, n, rep))
    print(f"bench_fusion_cost: {args.scenario}, {args.duration:g} s lockstep recording, seed "
          f"{args.seed}; machine {platform.machine()} {os.cpu_count()} cores, Python "
          f"{platform.python_version()}, load avg {os.getloadavg()[0]:.1f}")
    print(f"{'method':<8} {'node-epochs':>11} {'CPU s':>7} {'ms/node-epoch':>14} "
          f"{'floor':>6}  (floor: all node-epochs after 2 s)  target <= {TARGET_MS} ms (8 anchors)")
    for method, cpu, n, rep in rows:
        per = 1e3 * cpu / max(n, 1)
        floor = (rep.get("node_epochs") or {}).get("floor_accuracy_all")
        fl = f"{100 * floor:5.1f}%" if isinstance(floor, float) else "   -"
        ok = ("met" if per <= TARGET_MS else "NOT met") if method == "mnls" else ""
        print(f"{method:<8} {n:>11} {cpu:>7.2f} {per:>14.3f} {fl:>6}  {ok}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
