"""The compiled kernels' row chunks on 1 vs 2 threads (diffpos._kernels.pool): where a split
pays, per kernel wrapper, and what handing a chunk to a thread costs.

Usage::

    python benchmarks/bench_kernel_threads.py [--repeat 30]

For each wrapper (``pair_snr_db`` = channel_snr_kernel, ``all_paths``, ``grid_starts`` and an
M-NLS batch = lm_kernel) and a range of row counts, the median wall time of a call with 1
thread and with 2 threads (the wrapper's row threshold forced to 1 row, so every call splits),
and their ratio; first the pool's own cost (a call of 2 empty chunks vs a direct call). The
wrappers' thresholds (``diffpos._kernels.pool``: ``SNR_MIN_PAIRS`` ...) are set where the
ratio stays above ~1.2 with some margin: a call below twice the threshold stays on the
calling thread. Wall times on a shared machine: run it twice and read the load average.

2026-11-27 10:56 UTC, 2-core VM shared with four other jobs (load average 3.5): a split call
of 2 empty chunks 9.6 us wall (direct 0.14 us). With no free core the 2-thread ratios were
0.55-1.65 (noise around 1: the second thread had nowhere to run), so the thresholds are set
from the one-thread cost per unit of this run instead (~0.3-0.5 ms of work per chunk):
pair_snr_db 2.2-3.8 us per node-anchor pair, all_paths 0.5-0.9 us per (hypothesis, anchor)
link, grid_starts ~3 ms per node (2 floors, 16 anchors).
"""

from __future__ import annotations

import argparse
import importlib
import os
import platform
import statistics
import sys
import time

import numpy as np

import diffpos.tracking.initialisation as tracking_init
import diffpos.tracking.links as tracking_paths
from diffpos._kernels import pool
from diffpos.channel import snr_nb as channel_nb
from diffpos.channel.emulator import pair_snr_db
from diffpos.estimators.mnls.solver import mnls
from diffpos.scenario import default_scenario
from diffpos.tracking.initialisation import grid_starts
from diffpos.tracking.links import Links, all_paths
from diffpos.tracking.state import TrackerConfig

mnls_mod = importlib.import_module("diffpos.estimators.mnls.solver")
SC = default_scenario()
B, RADIO = SC.building, SC.radio


def _median_wall(fn, repeat: int) -> float:
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return statistics.median(out)


def _inputs(n: int, m: int, h: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    x0, x1 = B.edge_x_m
    floor = rng.integers(0, B.n_floors, n)
    nodes = np.stack([rng.uniform(x0 + 1, x1 - 1, n), rng.uniform(0.5, B.depth_m - 1, n),
                      B.floor_z_m(floor) + 1.2], -1)
    anc = np.stack([rng.uniform(x0 - 10, x1 + 10, (n, m)), rng.uniform(-30, -3, (n, m)),
                    rng.uniform(0, 20, (n, m))], -1)
    rho = np.linalg.norm(anc - nodes[:, None], axis=-1) + rng.uniform(0, 3, (n, m))
    links = Links.from_arrays(anc, rho, np.full((n, m), 0.1), np.ones((n, m), bool), 0.03)
    pos = np.broadcast_to(nodes[:, None], (n, h, 3)).copy()
    fl = np.broadcast_to(floor[:, None], (n, h)).copy()
    return anc, nodes, links, pos, fl, rho


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--anchors", type=int, default=16)
    args = ap.parse_args(argv)
    m, h = args.anchors, 4
    cfg = TrackerConfig()
    # no thresholds: every call with >= 2 rows splits
    for mod, name in ((channel_nb, "SNR_MIN_PAIRS"), (mnls_mod, "LM_MIN_ROWS"),
                      (tracking_paths, "PATHS_MIN_LINKS"), (tracking_init, "GRID_MIN_CELL_LINKS")):
        setattr(mod, name, 1)
    print(f"bench_kernel_threads: {platform.machine()} {os.cpu_count()} cores, load avg "
          f"{os.getloadavg()[0]:.2f}, {m} anchors, {h} hypotheses, median of {args.repeat}")
    pool.set_threads(2)
    pool.run_rows(lambda lo, hi: None, 2)  # the pool's threads exist
    t_pool = _median_wall(lambda: pool.run_rows(lambda lo, hi: None, 2), 200)
    t_direct = _median_wall(lambda: (lambda lo, hi: None)(0, 2), 200)
    print(f"pool: a call of 2 empty chunks {1e6 * t_pool:.1f} us wall, direct "
          f"{1e6 * t_direct:.2f} us")
    print(f"{'wrapper':<12} {'rows':>5} {'work':>8} {'1 thr ms':>9} {'2 thr ms':>9} "
          f"{'ratio':>6}")
    cases = []
    for n in (1, 2, 4, 8, 16, 32, 64, 200):
        anc, nodes, links, pos, fl, rho = _inputs(n, m, h)
        floors = np.stack([np.maximum(fl[:, 0] - 1, 0), fl[:, 0]], -1)
        cases += [
            ("snr", n, f"{n * m}pr", lambda a=anc, x=nodes: pair_snr_db(
                a, x, building=B, radio=RADIO)),
            ("all_paths", n, f"{n * h * m}ln", lambda p=pos, lk=links, f=fl: all_paths(
                p, lk, f, B, 0.2)),
            ("grid_starts", n, f"{n}x2fl", lambda lk=links, f=floors: grid_starts(
                lk, f, B, cfg)),
            ("mnls", n, f"{n}fix", lambda a=anc, r=rho: mnls(a, r, 0.1, building=B)),
        ]
    for name, n, work, fn in sorted(cases, key=lambda c: (c[0], c[1])):
        res = []
        for thr in (1, 2):
            pool.set_threads(thr)
            fn()  # compiled, pool up
            res.append(_median_wall(fn, args.repeat if name != "mnls" else
                                    max(args.repeat // 5, 3)))
        print(f"{name:<12} {n:>5} {work:>8} {1e3 * res[0]:>9.3f} {1e3 * res[1]:>9.3f} "
              f"{res[0] / res[1]:>6.2f}")
    pool.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
