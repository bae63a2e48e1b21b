"""Per-fix time of M-NLS vs D-NLS, single fix and batched, 4 and 8 anchors (prints a table).

Emulated first arrivals (ranges with the radio's error floor, SNR) on the paper's building for
random receivers on every floor; 4 anchors = the paper's UAVs, 8 = the large scenario's UAV
positions at t = 0. M-NLS gets the SNR and the radio (its full model: SNR-aware search), D-NLS
its defaults (Case-1, gating on). The live target: <= 2 ms per node-epoch on average with 8
anchors, batched.

    python benchmarks/bench_mnls.py [--batch 256] [--repeat 5]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from diffpos.channel import emulate_channel, first_arrival
from diffpos.estimators import dnls, mnls
from diffpos.scenario import default_scenario

EIGHT = np.array([[-15.0, -20.0, 1.5], [0.0, -15.0, 1.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.5],
                  [-25.0, -11.0, 3.0], [25.0, -19.0, 3.0], [-20.0, -10.0, 2.0],
                  [-10.0, -25.0, 0.5]])


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
    args = ap.parse_args()
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


if __name__ == "__main__":
    main()
