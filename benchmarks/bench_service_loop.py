"""The live fusion's main-thread loop after a stall: how long a backlog delays solving.

A synthetic run (8 anchors x 50 nodes x 10 Hz, per-node ranges, seeded) is queued at once on
the fusion's real inbox, as after a stall of the fusion's thread (e.g. a GC pause or a
machine under load), and :class:`~diffpos_services.fusion.service.ServiceLoop` works it
off. Printed per rule, in the same run:

- ``first fix``: wall time from the start to the first published estimate [ms];
- ``max gap``: longest wall time between two consecutive solve steps that published [ms]
  (what a newly arrived epoch may wait for its solve);
- ``max step``: longest solve step [ms];
- ``turns``, ``total``: loop turns and wall time to publish every node-epoch [s].

Rules: ``time-bounded`` (this code: ingest <= 5 ms per turn, solve steps sized to ~20 ms by
the measured cost) and ``unbounded`` (the same loop with no time bounds: ingest the whole
queue, then solve up to ``max_fixes_per_step`` epochs per step, like the former 20,000-sample
drain budget with a backlog of this size).

    python benchmarks/bench_service_loop.py                 # 20 s of backlog (~80,000 messages)
    python benchmarks/bench_service_loop.py --seconds 5     # quicker
"""

from __future__ import annotations

import argparse
import logging
import threading
import time

import msgspec
from diffpos_services.fusion.core import FusionCore
from diffpos_services.fusion.service import _ALIVE, _DATA, ServiceLoop, _Inbox
from diffpos_services.replay.synthetic import synthetic_run
from diffpos_services.wire.keys import Keys, parse_key


def _run(seconds: float, *, bounded: bool, seed: int) -> dict[str, float]:
    run = synthetic_run(n_anchors=8, n_nodes=50, duration_s=seconds, seed=seed)
    items = [m for ep in run.epochs for m in ep if parse_key(m[1]).kind not in ("truth_node",)]
    cfg = msgspec.structs.replace(run.config, queue_size=len(items) + 100)
    core = FusionCore(cfg, logger=logging.getLogger("bench.quiet"))
    core.warm_up()
    inbox = _Inbox(cfg, threading.Event())
    keys = Keys(cfg.site)
    now = time.time_ns()
    for a in run.anchor_ids:
        inbox.q.put((_ALIVE, keys.alive_anchor(a), True, now))
    for _, key, payload in items:
        inbox.q.put((_DATA, key, payload, now))
    published: list[int] = []
    kw = {} if bounded else {"ingest_budget_s": 1e9, "solve_budget_s": 1e9}
    loop = ServiceLoop(core, inbox, lambda e: published.append(e.t_pub_wall_ns),
                       lambda d: None, logging.getLogger("bench.quiet"), **kw)
    want = len(run.node_ids) * (round(seconds * 10) - 1)
    t0 = time.time_ns()
    turns, steps, last_end, max_gap = 0, [], None, 0
    while len(published) < want and turns < 1_000_000:
        t = loop.turn()
        turns += 1
        if t.published:
            steps.append(t.solve_end_wall_ns - t.solve_start_wall_ns)
            if last_end is not None:
                max_gap = max(max_gap, t.solve_start_wall_ns - last_end)
            last_end = t.solve_end_wall_ns
    return {"first fix [ms]": (published[0] - t0) * 1e-6, "max gap [ms]": max_gap * 1e-6,
            "max step [ms]": max(steps) * 1e-6, "turns": turns,
            "total [s]": (time.time_ns() - t0) * 1e-9, "messages": len(items)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="backlog length [s of run]")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rows = [(name, _run(args.seconds, bounded=b, seed=args.seed))
            for name, b in (("time-bounded", True), ("unbounded", False))]
    cols = list(rows[0][1])
    print(f"backlog: {args.seconds:g} s of 8 anchors x 50 nodes x 10 Hz "
          f"({rows[0][1]['messages']:.0f} messages) queued at once")
    print("| rule | " + " | ".join(c for c in cols if c != "messages") + " |")
    print("| --- " * len(cols) + "|")
    for name, r in rows:
        print(f"| {name} | " + " | ".join(f"{r[c]:.1f}" if isinstance(r[c], float) else
                                          str(r[c]) for c in cols if c != "messages") + " |")


if __name__ == "__main__":
    main()
