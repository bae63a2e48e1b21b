"""The D-NLS kernel on a replay's own calls: CPU of its warm and cold fixes, and what an option
of ``dnls`` changes there (issue 37 item 1; docs/performance.md, "Session 23: D-NLS replay").

Every ``dnls`` call of ``diffpos replay R.mcap --method dnls`` is captured once (the fusion's
warm batches: one start, the track's predicted position; and its cold ones: the height grid
and the LLS position), then solved again in this process with the default options and with
the options given, alternately, ``--rounds`` times; the least CPU of each (this thread's
clock) and the fixes whose used anchors, status or position changed.

Run:  PYTHONPATH=.:services python benchmarks/bench_dnls_replay_calls.py --replay R.mcap \
          [--set exclusion_starts=local] [--rounds 3] [--save CALLS.pkl | --calls CALLS.pkl]
"""

from __future__ import annotations

import argparse
import json
import pickle
import time

import numpy as np
from diffpos_services.replay.run import replay

import diffpos.estimators.dnls.solver as dnls_solver


def capture(recording: str) -> list:
    """The arguments of every ``dnls`` call of a ``--method dnls`` replay of ``recording``."""
    calls: list = []
    orig = dnls_solver.dnls

    def capturing(*a, **k):
        calls.append((a, k))
        return orig(*a, **k)

    dnls_solver.dnls = capturing
    try:
        replay(recording, method="dnls", keep_estimates=False)
    finally:
        dnls_solver.dnls = orig
    return calls


def solve(calls: list, over: dict) -> tuple[float, list]:
    """CPU seconds of solving ``calls`` with ``over`` added to each one's options, and the
    results."""
    t0 = time.thread_time()
    out = [dnls_solver.dnls(*a, **{**k, **over}) for a, k in calls]
    return time.thread_time() - t0, out


def changes(old: list, new: list) -> tuple[int, int, int]:
    """Fixes whose used anchors, status or position (> 1 cm, or solved in one only) differ."""
    used = status = moved = 0
    for o, n in zip(old, new, strict=True):
        used += int((o.used != n.used).any(axis=1).sum())
        status += int((o.status != n.status).sum())
        d = np.linalg.norm(np.nan_to_num(o.position_m - n.position_m, nan=1e9), axis=1)
        moved += int((d > 0.01).sum())
    return used, status, moved


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--replay", metavar="R.mcap", help="capture the calls of this replay")
    src.add_argument("--calls", metavar="CALLS.pkl", help="calls captured before (--save)")
    ap.add_argument("--save", metavar="CALLS.pkl", help="keep the captured calls")
    ap.add_argument("--set", action="append", default=[], metavar="OPTION=JSON",
                    help='a dnls option, e.g. exclusion_starts="local" (repeatable)')
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    if args.replay:
        calls = capture(args.replay)
        if args.save:
            with open(args.save, "wb") as f:
                pickle.dump(calls, f)
    else:
        with open(args.calls, "rb") as f:
            calls = pickle.load(f)
    over = {}
    for s in args.set:
        key, _, val = s.partition("=")
        try:
            over[key] = json.loads(val)
        except json.JSONDecodeError:
            over[key] = val
    groups = {"warm": [c for c in calls if c[1].get("x0_m") is not None],
              "cold": [c for c in calls if c[1].get("x0_m") is None]}
    print(f"| fixes | default CPU [s] (least of {args.rounds}) | with {over or 'the defaults'} "
          "| ratio | used sets / statuses / positions > 1 cm changed |")
    print("| --- | ---: | ---: | ---: | --- |")
    for name, sel in groups.items():
        if not sel:
            continue
        solve(sel[:2], {})
        solve(sel[:2], over)
        cpu: dict[str, list[float]] = {"a": [], "b": []}
        for _ in range(args.rounds):
            ta, out_a = solve(sel, {})
            tb, out_b = solve(sel, over)
            cpu["a"].append(ta)
            cpu["b"].append(tb)
        n = sum(len(a[1]) for a, _ in sel)
        a, b = min(cpu["a"]), min(cpu["b"])
        u, s, m = changes(out_a, out_b)
        print(f"| {name}: {len(sel)} calls, {n:,} fixes | {a:.3f} | {b:.3f} | {b / a:.2f} | "
              f"{u} / {s} / {m} |")


if __name__ == "__main__":
    main()
