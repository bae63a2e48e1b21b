"""Fusion latency second by second from a recording (e.g. ``bench_soak.py --log-dir D``'s
``D/<site>.mcap``, or ``diffpos emulate --record R.mcap``): for every estimate, its publish
wall time minus the newest input publish time of its ranges (``t_pub_wall_ns -
t_input_wall_ns``, the fusion's own stamps: no clock of another process involved), grouped by
the second of that input time since the first estimate's; prints per second the estimates,
p50, p99 and max [ms].

Usage::

    python benchmarks/latency_by_second.py D/soak16x200.mcap

Shows what a run's one p99 hides: on the 16 x 200 soak (2026-11-28 morning) a run either kept
up from second 3 on (p50 ~48-50 ms, p99 60-90 ms every second) or, after the start-up, spent
stretches of ~10 s one epoch behind (p50 100-120 ms, p99 200-260 ms) before it caught up.
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import numpy as np
from diffpos_services.recording.reader import McapScanner
from diffpos_services.recording.topics import parse_topic
from diffpos_services.wire import messages as M


def latency_by_second(path: Path) -> dict[int, np.ndarray]:
    """Latencies [ms] of the recording's estimates by second of their input time."""
    dec = M.estimate_decoder()
    rows = []
    for batch in McapScanner(path).iter_batches():
        for m in batch:
            if parse_topic(m.topic)[0] == "estimate":
                e = dec(m.data)
                rows.append((e.t_input_wall_ns, (e.t_pub_wall_ns - e.t_input_wall_ns) / 1e6))
    if not rows:
        return {}
    t0 = min(t for t, _ in rows)
    by: dict[int, list[float]] = collections.defaultdict(list)
    for t, lat in rows:
        by[(t - t0) // 1_000_000_000].append(lat)
    return {s: np.asarray(v) for s, v in sorted(by.items())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path)
    args = ap.parse_args(argv)
    by = latency_by_second(args.recording)
    if not by:
        print(f"{args.recording}: no estimates", file=sys.stderr)
        return 1
    print(f"{'second':>6} {'estimates':>9} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8}")
    for s, v in by.items():
        print(f"{s:>6} {v.size:>9} {np.percentile(v, 50):>8.1f} {np.percentile(v, 99):>8.1f} "
              f"{v.max():>8.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
