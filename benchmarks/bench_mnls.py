"""Per-fix time of M-NLS vs D-NLS (prints a table); ``--stages``: M-NLS's work per search stage.

Default mode: emulated first arrivals (ranges with the radio's error floor, SNR) on the
paper's building for random receivers on every floor; 4 anchors = the paper's UAVs, 8 = the
large scenario's UAV positions at t = 0. M-NLS gets the SNR and the radio (its full model:
SNR-aware search), D-NLS its defaults (Case-1, gating on). The live target: <= 2 ms per
node-epoch on average with 8 anchors, batched.

``--stages``: the inputs of ``bench_estimator_cost.py`` (its 8-anchor layout, nodes uniform
over the floor plans at random heights, seed 0), M-NLS batched with its live arguments, and
per stage of the search (``starts``, ``screen``, ``rescore``, ``refine``, ``final``; see
:data:`diffpos.estimators.mnls.solver.STAGE_STATS`) the node-anchor pairs through the path model and
through ``diffpos.channel.emulator.pair_snr_db`` and the CPU time (of the stage, and of those two calls
in it), per fix; then the accuracy of the same fixes (median / p80 3D error, right floor,
95 % ellipsoid coverage). ``--save FILE.npz`` keeps the fixes (position, floor, covariance,
truth) for a paired before/after comparison (``--compare A.npz B.npz``).

    python benchmarks/bench_mnls.py [--batch 256] [--repeat 5]
    python benchmarks/bench_mnls.py --stages [--batch 128] [--anchors 8] [--save out.npz]
    python benchmarks/bench_mnls.py --compare before.npz after.npz

Measured 2026-11-27 (``--stages --batch 128``, 8 anchors, seed 0; 2-core x86_64 VM shared
with other jobs, load average 5.5-7, so the CPU figures move by +-20 % between runs; the
pair counts are exact). Per fix, before (commit 0807c4b: the search as it was, with the
counters) -> after (this branch):

    stage     path pairs      SNR pairs    CPU ms (two runs each)
    screen    2,870 -> 1,920  480 -> 263   14.4, 15.9 -> 7.8, 9.6
    rescore      80 -> 70      80 -> 64     1.6, 1.8 -> 1.1, 1.6
    refine      117 -> 179     14 -> 19     0.8, 0.8 -> 0.7, 1.1
    final        71 -> 62      23 -> 20     0.6, 0.6 -> 0.6, 0.8
    sum       3,138 -> 2,231  597 -> 366   17.7, 19.4 -> 10.4, 13.4
    accuracy: median 3D 0.140 -> 0.133 m, p80 0.414 -> 0.343 m, right floor 98.4 -> 99.2 %,
    95 % ellipsoid 89.8 -> 91.4 %

The SNR prediction (``pair_snr_db``) is still ~70 % of the CPU, the path model ~15 %.
(That was before the compiled SNR prediction.)

``--reference``: M-NLS's numpy/numba reference steps (``kernel=False``). Measured
2026-11-27 06:35 UTC (``--stages --batch 128``, 8 anchors, seed 0; load 4.5-4.9), before =
commit adf3856 (compiled SNR, numpy steps) -> after (compiled starts and LM); per fix:

    stage     path pairs      SNR pairs   CPU ms        of it compiled LM
    starts        0 -> 0        0 -> 0     0.30 -> 0.19
    screen    1,920 -> 1,806  263 -> 263   5.45 -> 3.03  2.0 (SNR 0.87 -> 0.88)
    rescore      70 -> 120     64 -> 64    0.34 -> 0.42
    refine      179 -> 225     19 -> 19    0.25 -> 0.26  0.15
    final        62 -> 70      20 -> 20    0.14 -> 0.18  0.04
    sum       2,231 -> 2,220  366 -> 366   6.48 -> 4.07
    accuracy (the same fixes, bitwise): median 3D 0.133 m, p80 0.343 m, right floor 99.2 %,
    95 % ellipsoid 91.4 %

Path pairs after: the compiled LM evaluates the linked pairs only (screen -6 %) and the
terms at the returned points once more (rescore: the kept rows the re-scoring leaves out;
refine, final: once per run).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.estimators.dnls.solver import dnls
from diffpos.estimators.mnls.solver import mnls
from diffpos.scenario import default_scenario

_mn = sys.modules["diffpos.estimators.mnls.solver"]
EIGHT = np.array([[-15.0, -20.0, 1.5], [0.0, -15.0, 1.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.5],
                  [-25.0, -11.0, 3.0], [25.0, -19.0, 3.0], [-20.0, -10.0, 2.0],
                  [-10.0, -25.0, 0.5]])
STAGES = ("starts", "screen", "rescore", "refine", "final")
CHI2_3_95 = 7.814727903251178  # 95 % quantile of chi-square with 3 degrees of freedom


def _data(anchors, n, rng):
    sc = default_scenario()
    b = sc.building
    x0, x1 = b.edge_x_m
    k = rng.integers(0, b.n_floors, n)
    nodes = np.column_stack([rng.uniform(x0 + 0.5, x1 - 0.5, n), rng.uniform(0.5, 20, n),
                             b.floor_z_m(k) + b.nominal_node_height_m])
    ch = emulate_channel(anchors, nodes, building=b, radio=sc.radio)
    fa = first_arrival(ch, radio=sc.radio, rng=rng)
    a = np.broadcast_to(anchors, (n, *anchors.shape))
    return sc, a, np.where(fa.detected, fa.range_m, 0.0), fa


def _time(fn, repeat):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--stages", action="store_true", help="M-NLS work per search stage")
    ap.add_argument("--anchors", type=int, choices=(4, 8), default=8, help="with --stages")
    ap.add_argument("--seed", type=int, default=0, help="with --stages")
    ap.add_argument("--save", help="with --stages: write the fixes to this .npz")
    ap.add_argument("--reference", action="store_true",
                    help="with --stages: M-NLS's numpy/numba reference steps (kernel=False)")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"), help="paired comparison")
    args = ap.parse_args()
    if args.compare:
        compare(*args.compare)
        return
    if args.stages:
        stages(args)
        return
    rng = np.random.default_rng(0)
    sc = default_scenario()
    print(f"{'anchors':>7s} {'mode':>8s} {'dnls [ms/fix]':>14s} {'mnls [ms/fix]':>14s}")
    for anchors in (sc.anchor_positions_m(), EIGHT):
        for mode, sl, n in (("single", slice(0, 1), 1), ("batched", slice(None), args.batch)):
            td, tm = _bench(anchors, sl, args, rng)
            print(f"{len(anchors):7d} {mode:>8s} {1e3 * td / n:14.2f} {1e3 * tm / n:14.2f}")


def _bench(anchors, sl, args, rng) -> tuple[float, float]:
    """Best-of-repeat wall time of one dnls and one mnls call over the fixes ``sl`` [s]."""
    sc, a, r, fa = _data(anchors, args.batch, rng)
    sig = np.where(fa.detected, fa.sigma_m, 1.0)
    td = _time(lambda: dnls(a[sl], r[sl], sig[sl], mask=fa.detected[sl],
                            window_height_m=sc.building.window_height_m,
                            edge_x_m=sc.building.edge_x_m), args.repeat)
    tm = _time(lambda: mnls(a[sl], r[sl], sig[sl], mask=fa.detected[sl], building=sc.building,
                            snr_db=fa.snr_db[sl], radio=sc.radio), args.repeat)
    return td, tm


def stages(args) -> None:
    """The per-stage table of one batched M-NLS call (module docstring)."""
    from bench_estimator_cost import EXTRA_ANCHORS_M, measurements, nodes_on_floors, solvers

    sc = default_scenario()
    rng = np.random.default_rng(args.seed)
    anchors = sc.anchor_positions_m()
    if args.anchors == 8:
        anchors = np.concatenate([anchors, EXTRA_ANCHORS_M])
    nodes = nodes_on_floors(sc, rng, args.batch)
    meas = measurements(sc, anchors, nodes, rng)
    run = solvers(sc, kernel=not args.reference)["mnls"]
    run(meas, slice(0, 1))  # warm-up (imports, compiled kernels)
    _mn.STAGE_STATS = {}
    c0 = time.thread_time()
    try:
        res = run(meas, slice(None))
        cpu = time.thread_time() - c0
        st = _mn.STAGE_STATS
    finally:
        _mn.STAGE_STATS = None
    n = args.batch
    how = "reference steps, kernel=False" if args.reference else "compiled LM, kernel=True"
    print(f"## M-NLS per stage ({n} fixes batched, {len(anchors)} anchors, seed {args.seed}, "
          f"{how})\n")
    print("| stage | path-model pairs/fix | SNR pairs/fix | CPU ms/fix | of it path model | "
          "of it SNR | of it compiled LM |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    tot = dict.fromkeys(("paths", "snr", "cpu_s", "paths_cpu_s", "snr_cpu_s", "kernel_cpu_s"),
                        0.0)
    for name in [*STAGES, *(k for k in st if k not in STAGES)]:
        d = st.get(name, tot | {k: 0.0 for k in tot})
        for k in tot:
            tot[k] += d.get(k, 0.0)
        print(_stage_row(name, d, n))
    print(_stage_row("**sum**", tot, n))
    print(f"\nwhole mnls call: {1e3 * cpu / n:.2f} ms CPU per fix (thread time; the rest is "
          "the result assembly)\n")
    acc = accuracy(res, nodes, sc.building)
    print("| median 3D [m] | p80 3D [m] | right floor | 95 % ellipsoid |")
    print("| ---: | ---: | ---: | ---: |")
    print(f"| {acc['median']:.3f} | {acc['p80']:.3f} | {100 * acc['floor']:.1f}% | "
          f"{100 * acc['ell95']:.1f}% |")
    if args.save:
        np.savez(args.save, position_m=res.position_m, covariance_m2=res.covariance_m2,
                 floor=res.floor, truth_m=nodes,
                 truth_floor=sc.building.floor_index(nodes[:, 2]))


def _stage_row(name, d, n) -> str:
    return (f"| {name} | {d['paths'] / n:,.0f} | {d['snr'] / n:,.0f} | "
            f"{1e3 * d['cpu_s'] / n:.2f} | {1e3 * d['paths_cpu_s'] / n:.2f} | "
            f"{1e3 * d['snr_cpu_s'] / n:.2f} | {1e3 * d.get('kernel_cpu_s', 0.0) / n:.2f} |")


def accuracy(res, nodes, building) -> dict[str, float]:
    """Median / p80 3D error (a failed fix is infinite), right floor, 95 % ellipsoid coverage."""
    err = np.linalg.norm(res.position_m - nodes, axis=1)
    err = np.where(np.isfinite(err), err, np.inf)
    d = res.position_m - nodes
    with np.errstate(invalid="ignore"):
        m2 = np.einsum("bi,bi->b", d, np.linalg.solve(res.covariance_m2, d[..., None])[..., 0])
    ok = np.isfinite(m2)
    return {"median": float(np.median(err)), "p80": float(np.percentile(err, 80)),
            "floor": float(np.mean(res.floor == building.floor_index(nodes[:, 2]))),
            "ell95": float(np.mean(m2[ok] <= CHI2_3_95)) if ok.any() else float("nan")}


def compare(path_a: str, path_b: str) -> None:
    """Paired comparison of two saved runs on the same fixes (``--save``)."""
    a, b = np.load(path_a), np.load(path_b)
    if not np.array_equal(a["truth_m"], b["truth_m"]):
        raise SystemExit("the two files hold different fixes")
    ea = np.linalg.norm(a["position_m"] - a["truth_m"], axis=1)
    eb = np.linalg.norm(b["position_m"] - b["truth_m"], axis=1)
    same = np.linalg.norm(a["position_m"] - b["position_m"], axis=1) < 1e-3
    fa, fb = a["floor"] == a["truth_floor"], b["floor"] == b["truth_floor"]
    print(f"{len(ea)} fixes: same position (< 1 mm) {np.mean(same):.1%}; floor right in A "
          f"only {np.sum(fa & ~fb)}, in B only {np.sum(fb & ~fa)}; 3D error B - A: "
          f"median {np.median(eb - ea):+.4f} m, worse by > 0.1 m {np.sum(eb - ea > 0.1)}, "
          f"better by > 0.1 m {np.sum(ea - eb > 0.1)}")


if __name__ == "__main__":
    main()
