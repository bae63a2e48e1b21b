"""Can the published floor probability be trusted? Its calibration over a set of recordings.

Usage::

    python benchmarks/bench_floor_calibration.py /tmp/geo14/rec40/*.mcap /tmp/geo14/rec40s1/*.mcap
    python benchmarks/bench_floor_calibration.py --top 5 --json out.json REC.mcap ...
    python benchmarks/bench_floor_calibration.py --trace r02 REC.mcap   # one node, every 1 s

Every recording is scored as ``bench_accuracy.py`` scores it (:func:`bench_accuracy.
score_recording`: every node-epoch after the first 2 s, the recorded live estimate of each,
a missing position is a miss) and its floor probabilities as :mod:`diffpos.floor_calibration`
measures them. The recorded live estimates are used: ``diffpos replay`` of the same file gives
the same estimates bit for bit (its report shows the same calibration; checked on the worst
geometry in docs/floor_calibration.md), without re-running the fusion (~0.1 s CPU per 20 s
recording instead of ~3 s: the replay of rand-0-38 took 2.7 s user CPU, the 80 replays ~3.8 s
wall each, docs/floor_calibration.md).

Prints: one row per recording (node-epochs, floor accuracy over all node-epochs, ECE, log
score, Brier, confidently wrong = a wrong floor published at p >= 0.95, count and share of all
node-epochs), the reliability table pooled over all recordings (counts and sums per bin added:
the pooled figures are those of one scorer over every node-epoch), and the ``--top``
recordings with the most confidently wrong node-epochs: their geometry (``rand-S-i`` names are
re-made by ``heldout.random_scenario``) and their confidently wrong episodes (a node's
consecutive node-epochs on one wrong floor at p >= 0.95; ``t+a-b s`` counts from the first
scored node-epoch, 2 s into the run).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from common import machine, score_recording
from heldout import family, random_scenario, summary

from diffpos.floor_calibration import CONFIDENT, FloorCalibration, format_calibration


def pool(calibs: list[dict[str, Any] | None], *,
         uncalibrated: list[tuple[int, int]] = ()) -> dict[str, Any] | None:
    """The calibration of the union of the node-epochs of ``calibs`` (each a
    :func:`diffpos.floor_calibration.floor_calibration` result with the default bins, or None)
    and of ``uncalibrated``: ``(node_epochs, fixes)`` of each recording whose estimates report
    no floor probabilities (estimate v1, whose calibration is None): its node-epochs count in
    the denominator of "confidently wrong" (ALL node-epochs) and its fixes as without
    probabilities, as one scorer over the union counts them."""
    acc = FloorCalibration()
    for n, fixes in uncalibrated:
        acc.node_epochs += n
        acc.without += fixes
    for c in calibs:
        if c is None:
            continue
        for i, r in enumerate(c["reliability"]):
            acc.count[i] += r["count"]
            if r["count"]:
                acc.sum_p[i] += r["mean_probability"] * r["count"]
                acc.right[i] += round(r["fraction_right"] * r["count"])
        k = c["with_probabilities"]
        acc.node_epochs += c["node_epochs"]
        acc.without += c["without_probabilities"]
        acc.confidently_wrong += c["confidently_wrong_count"]
        acc.log_score_sum += c["log_score"] * k
        acc.brier_sum += c["brier"] * k
    return acc.result()


def episodes(rows: list[tuple], *, confident: float = CONFIDENT) -> list[dict[str, Any]]:
    """Runs of consecutive node-epochs of one node published on one wrong floor at
    p >= ``confident`` (rows of :func:`bench_accuracy.score_recording`'s ``rows_out``)."""
    out: list[dict[str, Any]] = []
    by: dict[str, list[tuple]] = {}
    for r in rows:
        by.setdefault(r[0], []).append(r)
    t0 = min((r[1] for r in rows), default=0)
    for node, rs in by.items():
        rs.sort(key=lambda r: r[1])
        cur: list[tuple] = []
        for r in [*rs, None]:
            bad = r is not None and r[3] >= 0 and r[3] != r[2] and r[4] >= confident
            if bad and cur and (r[2], r[3]) == (cur[-1][2], cur[-1][3]):
                cur.append(r)
                continue
            if cur:
                ps = [c[4] for c in cur]
                out.append({"node": node, "t_s": [round((cur[0][1] - t0) * 1e-9, 1),
                                                  round((cur[-1][1] - t0) * 1e-9, 1)],
                            "true_floor": cur[0][2], "published_floor": cur[0][3],
                            "node_epochs": len(cur), "p_min": min(ps), "p_max": max(ps),
                            "true_z_m": [round(min(c[5] for c in cur), 2),
                                         round(max(c[5] for c in cur), 2)]})
            cur = [r] if bad else []
    return sorted(out, key=lambda e: -e["node_epochs"])


def where(rows: list[tuple], *, confident: float = CONFIDENT,
          near_s: float = 1.0) -> dict[str, int]:
    """Confidently wrong node-epochs: how many at a floor change (the node's true floor differs
    within +-``near_s``: the stairs), how many published below the true floor."""
    out = {"confidently_wrong": 0, "at_floor_change": 0, "below_truth": 0}
    by: dict[str, list[tuple]] = {}
    for r in rows:
        by.setdefault(r[0], []).append(r)
    for rs in by.values():
        t = np.array([r[1] for r in rs], np.int64)
        tf = np.array([r[2] for r in rs])
        for r in rs:
            if r[3] >= 0 and r[3] != r[2] and r[4] >= confident:
                near = tf[np.abs(t - r[1]) <= round(near_s * 1e9)]
                out["confidently_wrong"] += 1
                out["at_floor_change"] += int(near.min() != near.max())
                out["below_truth"] += int(r[3] < r[2])
    return out


def trace(rows: list[tuple], node: str, *, every: int = 10) -> list[str]:
    """One node's published floor over time (every ``every``-th node-epoch): its probability
    and the log-odds of the published floor against the true one, ``ln(p_pub / p_true)``
    (0 when right; how sure the wrong floor is when not)."""
    rs = sorted((r for r in rows if r[0] == node), key=lambda r: r[1])
    t0 = rs[0][1] if rs else 0
    out = []
    for r in rs[::every]:
        lo = math.log(r[4] / max(r[6], 1e-300)) if r[3] >= 0 and r[6] == r[6] else math.nan
        out.append(f"t+{(r[1] - t0) * 1e-9:4.1f} s  true {r[2]}  published {r[3]:2d}  "
                   f"p {r[4]:.4f}  ln(p_pub/p_true) {lo:+.1f}")
    return out


def _geometry(name: str) -> str:
    m = re.fullmatch(r"rand-(\d+)-(\d+)", name)
    if not m:
        return "(shipped scenario or variant: benchmarks/bench_accuracy.py)"
    s, i = int(m.group(1)), int(m.group(2))
    return f"{family(i)}: {summary(random_scenario(s, i))}"


def _row(name: str, r: dict[str, Any]) -> str:
    c = r["floor_calibration"]
    fl = f"{100 * r['floor']:6.1f}%"
    if c is None:
        return f"{name:22s} {r['node_epochs']:6d} {fl}  (no floor probabilities)"
    hi = c["reliability"][-1]
    right = "-" if not hi["count"] else f"{100 * hi['fraction_right']:.1f}%"
    return (f"{name:22s} {r['node_epochs']:6d} {fl} {c['ece']:7.4f} {c['log_score']:7.4f} "
            f"{c['brier']:7.4f} {c['confidently_wrong_count']:6d} "
            f"{100 * c['confidently_wrong']:6.2f}% {hi['count']:6d} {right:>7s}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recordings", nargs="+", help="MCAP recordings of diffpos emulate")
    ap.add_argument("--top", type=int, default=5, help="recordings shown in detail")
    ap.add_argument("--json", metavar="FILE", help="also write every result as JSON")
    ap.add_argument("--trace", metavar="NODE",
                    help="also print this node's published floor every 1 s, per recording")
    args = ap.parse_args(argv)
    results: dict[str, dict[str, Any]] = {}
    eps: dict[str, list] = {}
    spots = {"confidently_wrong": 0, "at_floor_change": 0, "below_truth": 0}
    cpu = time.process_time()
    for path in args.recordings:
        name = Path(path).stem
        rows: list = []
        results[name] = score_recording(path, rows_out=rows)
        eps[name] = episodes(rows)
        if args.trace:
            print(f"{name} {args.trace}:\n  " + "\n  ".join(trace(rows, args.trace)) + "\n")
        for k, v in where(rows).items():
            spots[k] += v
    cpu = time.process_time() - cpu
    print("bench_floor_calibration: the recorded live estimates of each recording, every "
          "node-epoch after the first 2 s (diffpos.floor_calibration; confidently wrong = "
          f"wrong floor at p >= {CONFIDENT:g}, share of ALL node-epochs)")
    print(f"command: python benchmarks/bench_floor_calibration.py "
          f"{' '.join(argv if argv is not None else sys.argv[1:])}")
    print(f"machine: {machine()}; {len(results)} recordings scored in {cpu:.1f} s CPU\n")
    print(f"{'run':22s} {'N':>6s} {'floor':>7s} {'ECE':>7s} {'log':>7s} {'Brier':>7s} "
          f"{'confwr':>6s} {'%':>7s} {'>=.99':>6s} {'right':>7s}")
    for name, r in results.items():
        print(_row(name, r))
    pooled = pool([r["floor_calibration"] for r in results.values()],
                  uncalibrated=[(r["node_epochs"], round(r["availability"] * r["node_epochs"]))
                                for r in results.values() if r["floor_calibration"] is None])
    print(f"\npooled over {len(results)} recordings:")
    print("\n".join(format_calibration(pooled)))
    print(f"  of the {spots['confidently_wrong']} confidently wrong: {spots['at_floor_change']} "
          f"at a floor change (the node's true floor differs within +-1 s: the stairs), "
          f"{spots['below_truth']} published below the true floor")
    worst = sorted(results, key=lambda k: -((results[k]["floor_calibration"] or {})
                                             .get("confidently_wrong_count", 0)))
    worst = [k for k in worst[:args.top]
             if (results[k]["floor_calibration"] or {}).get("confidently_wrong_count")]
    for name in worst:
        c = results[name]["floor_calibration"]
        print(f"\n{name}: {c['confidently_wrong_count']} confidently wrong node-epochs "
              f"({100 * c['confidently_wrong']:.2f} %), floor {100 * results[name]['floor']:.1f} "
              f"%\n  {_geometry(name)}")
        for e in eps[name][:6]:  # t: after the first scored node-epoch (2 s into the run)
            print(f"  {e['node']}: t+{e['t_s'][0]}-{e['t_s'][1]} s, true floor "
                  f"{e['true_floor']} (z {e['true_z_m'][0]}-{e['true_z_m'][1]} m), published "
                  f"{e['published_floor']} at p {e['p_min']:.3f}-{e['p_max']:.4f}, "
                  f"{e['node_epochs']} node-epochs")
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": machine(), "results": results,
                                               "pooled": pooled, "episodes": eps},
                                              indent=1, default=float))
    n_cw = np.sum([(r["floor_calibration"] or {}).get("confidently_wrong_count", 0)
                   for r in results.values()])
    print(f"\nrecordings with any confidently wrong node-epoch: "
          f"{sum(bool((r['floor_calibration'] or {}).get('confidently_wrong_count')) for r in results.values())}"
          f" of {len(results)} ({int(n_cw)} node-epochs)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
