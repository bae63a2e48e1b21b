"""The paper's positioning study with M-NLS beside the other methods (prints a table).

Same channel, seed handling and estimator settings as ``diffpos reproduce`` (the logic of
services/cmd_reproduce.compute, without its CLI): the default scenario's 17,600 receivers,
the emulator's first arrivals with the radio's ranging error floor, seed 0. Every receiver
counts; a failed fix is a miss (infinite error, wrong floor).

    python benchmarks/study_mnls.py                 # all 17,600 receivers (tens of minutes)
    python benchmarks/study_mnls.py --nodes 1500    # a random subsample (seeded)
    python benchmarks/study_mnls.py --jobs 4        # receivers split over 4 processes

The receivers are independent fixes, so splitting them over processes (``--jobs``) gives the
same estimates as one process.

Measured at commit e3f5c9d (``--nodes 2000 --jobs 8``, seed 0; before the edge starts):

    method                               median      p80      p95   floor   ell95
    LLS                                   8.636   17.880   33.471   13.4%       -
    IPPA                                 11.100   16.252   20.289   29.5%       -
    D-NLS (Case-1)                        2.474    5.394   12.933   35.3%       -
    D-NLS (Case-2, Δ=1.5 m)               3.075    6.597   12.266   41.4%       -
    M-NLS (first-arrival model)           0.185    0.629    3.939   87.5%   89.5%
    PEB (diffraction model)               0.561    1.202    1.625

M-NLS on all 17,600 receivers at commit bf9ef03 (edge and edge + ceiling starts, 4 x 3 grid,
variance factor), ``diffpos reproduce --seed 0 --methods mnls`` (same channel and seed as
this script): 3D median / p80 / p95 0.18 / 0.55 / 3.66 m, z 0.08 / 0.24 / 3.00 m, right floor
91.6 % of all receivers, 95 % ellipsoid 95.2 %, 11.8 ms CPU per fix (2-core x86_64 VM,
Python 3.11.7, shared with other jobs: 950 s wall at load average ~29).
"""

from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.study import (
    FirstArrivalData,
    PositioningStudy,
    floor_starts_m,
    method_label,
    positioning_study,
)

METHODS = ("lls", "ippa", "dnls_case1", "dnls_case2", "mnls")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--nodes", type=int, default=0, help="random subsample size (0: all)")
    ap.add_argument("--methods", nargs="+", default=list(METHODS))
    ap.add_argument("--json", help="write the summary here")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes")
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
    t1 = time.perf_counter()
    parts = np.array_split(np.arange(len(nodes)), max(args.jobs, 1))
    with ProcessPoolExecutor(max_workers=max(args.jobs, 1)) as ex:
        studies = list(ex.map(_study_part, [(data.subset(p), tuple(args.methods))
                                           for p in parts]))
    study = _merge(studies)
    timing = {"channel": t1 - t0, "positioning": time.perf_counter() - t1}
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
    print("time [s]:", {k: round(v, 1) for k, v in timing.items()}, f"({args.jobs} jobs)")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"summary": s, "n": len(nodes), "seed": args.seed}, f, indent=1,
                      default=lambda v: None if isinstance(v, float) else str(v))


def _study_part(arg) -> PositioningStudy:
    data, methods = arg
    sc = default_scenario()
    return positioning_study(
        data, window_height_m=sc.building.window_height_m, edge_x_m=sc.building.edge_x_m,
        methods=methods, z_starts_m=floor_starts_m(sc.building),
        start_y_m=0.5 * sc.building.depth_m, building=sc.building, radio=sc.radio)


def _merge(parts: list[PositioningStudy]) -> PositioningStudy:
    """One study from studies of disjoint receiver subsets (in order)."""
    from diffpos.study import floor_accuracy

    sc = default_scenario()
    cat = lambda key, m: np.concatenate([getattr(p, key)[m] for p in parts])  # noqa: E731
    methods = parts[0].methods
    pos = {m: cat("positions_m", m) for m in methods}
    truth = np.concatenate([p.extra["truth_m"] for p in parts])
    covs = {m: np.concatenate([p.extra["covariance_m2"][m] for p in parts])
            for m in parts[0].extra["covariance_m2"]}
    n = len(truth)
    ok = {m: sum(p.extra["status_ok_fraction"][m] * len(p.peb_m) for p in parts) / n
          for m in methods}
    return PositioningStudy(
        positions_m=pos, error_3d_m={m: cat("error_3d_m", m) for m in methods},
        error_z_m={m: cat("error_z_m", m) for m in methods},
        peb_m=np.concatenate([p.peb_m for p in parts]),
        z_bound_m=np.concatenate([p.z_bound_m for p in parts]), methods=methods,
        delta_case2_m=parts[0].delta_case2_m,
        extra={"status_ok_fraction": ok, "covariance_m2": covs, "truth_m": truth,
               "floor_accuracy": {m: floor_accuracy(pos[m], truth, sc.building)
                                  for m in methods}})


if __name__ == "__main__":
    main()
