"""The paper's positioning study with M-NLS beside the other methods (prints a table).

Same channel, seed handling and estimator settings as ``diffpos reproduce`` (the logic of
services/cmd_reproduce.compute, without its CLI): the default scenario's 17,600 receivers,
the emulator's first arrivals with the radio's ranging error floor, seed 0. Every receiver
counts; a failed fix is a miss (infinite error, wrong floor).

    python benchmarks/study_mnls.py                 # all 17,600 receivers (tens of minutes)
    python benchmarks/study_mnls.py --nodes 1500    # a random subsample (seeded)
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from diffpos.channel import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.study import FirstArrivalData, floor_starts_m, method_label, positioning_study

METHODS = ("lls", "ippa", "dnls_case1", "dnls_case2", "mnls")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--nodes", type=int, default=0, help="random subsample size (0: all)")
    ap.add_argument("--methods", nargs="+", default=list(METHODS))
    ap.add_argument("--json", help="write the summary here")
    args = ap.parse_args()
    sc = default_scenario()
    sub_rng, noise_rng = (np.random.default_rng(s)
                          for s in np.random.SeedSequence(args.seed).spawn(2))
    nodes, anchors = sc.node_positions_m(), sc.anchor_positions_m()
    if 0 < args.nodes < len(nodes):
        nodes = nodes[np.sort(sub_rng.choice(len(nodes), args.nodes, replace=False))]
    t0 = time.perf_counter()
    ch = emulate_channel(anchors, nodes, building=sc.building, radio=sc.radio)
    fa = first_arrival(ch, radio=sc.radio, rng=noise_rng)
    data = FirstArrivalData.from_channel(fa, anchors, nodes)
    timing = {}

    def progress(m, done, total):
        timing[m] = time.perf_counter() - t0

    study = positioning_study(
        data, window_height_m=sc.building.window_height_m, edge_x_m=sc.building.edge_x_m,
        methods=tuple(args.methods), z_starts_m=floor_starts_m(sc.building),
        start_y_m=0.5 * sc.building.depth_m, building=sc.building, radio=sc.radio,
        progress=progress)
    s = study.summary()
    print(f"{len(nodes)} receivers x {len(anchors)} anchors, seed {args.seed}, "
          f"range error floor {sc.radio.range_error_floor_m} m")
    print(f"{'method':34s} {'median':>8s} {'p80':>8s} {'p95':>8s} {'floor':>7s} {'ell95':>7s}")
    for m in args.methods:
        r = s[m]
        ell = r.get("ellipsoid95_coverage")
        print(f"{method_label(m):34s} {r['3d']['median']:8.3f} {r['3d']['p80']:8.3f} "
              f"{r['3d']['p95']:8.3f} {100 * r['floor_accuracy']:6.1f}% "
              + (f"{100 * ell:6.1f}%" if ell is not None else "      -"))
    print(f"{'PEB':34s} {s['peb']['3d']['median']:8.3f} {s['peb']['3d']['p80']:8.3f} "
          f"{s['peb']['3d']['p95']:8.3f}")
    print("cumulative time [s]:", {k: round(v, 1) for k, v in timing.items()})
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"summary": s, "n": len(nodes), "seed": args.seed}, f, indent=1,
                      default=lambda v: None if isinstance(v, float) else str(v))


if __name__ == "__main__":
    main()
