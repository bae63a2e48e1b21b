"""CPU per range of the fusion's ingest path (issue 16: decode + checks + alignment), per-range
messages and RangeBatch side by side.

A seeded synthetic run (``replay/synthetic.py``: 8 anchors x 50 nodes x 10 Hz by default,
5 % NLoS outliers) is generated in memory; its fusion inputs are fed to a
:class:`~diffpos_services.fusion.core.FusionCore` in receive order, the core stepped every
100 ms of receive time as the live service does. Only the ingest is timed
(``time.process_time`` around each run of ``on_sample`` calls between two steps, so the solve
steps are excluded), then divided by the ranges ingested. The decode alone is timed on the
same payloads with the fusion's decoders (best of 5 passes).

Run:  python benchmarks/bench_ingest.py [--anchors 8] [--nodes 50] [--duration 10] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

from diffpos_services.fusion.core import FusionCore
from diffpos_services.replay.synthetic import (
    FUSION_INPUT_KINDS,
    quiet_logger,
    synthetic_run,
)
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import parse_key

STEP_NS = 100_000_000


def _inputs(args: argparse.Namespace, batch: bool):
    run = synthetic_run(n_anchors=args.anchors, n_nodes=args.nodes, duration_s=args.duration,
                        rate_hz=10.0, outlier_probability=0.05, seed=3, range_batch=batch)
    msgs = [(rx, k, p) for items in run.epochs for rx, k, p in items
            if (pk := parse_key(k)) is not None and pk.kind in FUSION_INPUT_KINDS]
    return run, msgs


def ingest_cpu(run, msgs) -> tuple[float, int]:
    """CPU seconds of the ``on_sample`` calls (steps excluded) and ranges received."""
    core = FusionCore(run.config, logger=quiet_logger())
    for a in run.anchor_ids:
        core.on_liveliness(a, True, run.t0_ns - 10_000_000)
    cpu = 0.0
    i, n = 0, len(msgs)
    while i < n:
        until = msgs[i][0] + STEP_NS
        j = i
        while j < n and msgs[j][0] < until:
            j += 1
        c0 = time.process_time()
        for rx, k, p in msgs[i:j]:
            core.on_sample(k, p, rx)
        cpu += time.process_time() - c0
        core.step(msgs[j - 1][0])
        i = j
    return cpu, int(core.received["range"])


def decode_cpu(msgs) -> float:
    """Best-of-5 CPU seconds to decode every payload with the fusion's decoders."""
    dec = {"range": M.decoder(M.RangeMeasurement), "range_batch": M.decoder(M.RangeBatch),
           "anchor_state": M.decoder(M.AnchorState)}
    pairs = [(dec[parse_key(k).kind], p) for _, k, p in msgs]
    best = float("inf")
    for _ in range(5):
        c0 = time.process_time()
        for d, p in pairs:
            d(p)
        best = min(best, time.process_time() - c0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--anchors", type=int, default=8)
    ap.add_argument("--nodes", type=int, default=50)
    ap.add_argument("--duration", type=float, default=10.0, help="emulated seconds")
    ap.add_argument("--repeats", type=int, default=3, help="ingest runs (median reported)")
    args = ap.parse_args()
    print(f"{platform.machine()}, Python {platform.python_version()}, {os.cpu_count()} cores "
          f"(shared with other jobs); {args.anchors} anchors x {args.nodes} nodes x 10 Hz, "
          f"{args.duration:g} s\n")
    print("| messages | ranges | ingest CPU [s] | per range [us] | decode alone per range [us] |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for batch in (False, True):
        run, msgs = _inputs(args, batch)
        runs = [ingest_cpu(run, msgs) for _ in range(args.repeats)]
        cpu = statistics.median(c for c, _ in runs)
        ranges = runs[0][1]
        dec = decode_cpu(msgs)
        label = "RangeBatch (one per anchor epoch)" if batch else "per range"
        print(f"| {label} | {ranges:,} | {cpu:.3f} | {1e6 * cpu / ranges:.2f} | "
              f"{1e6 * dec / ranges:.2f} |")
    print(f"\nMedian of {args.repeats} ingest runs (CPU per run: time.process_time around the "
          f"on_sample calls only); load average {os.getloadavg()[0]:.1f} at the end.")


if __name__ == "__main__":
    main()
