"""Benchmark of the batched estimators: speed against scipy, gating against robust losses.

Prints three markdown tables:

1. **Speed.** D-NLS (default settings: multi-start over 11 floor heights and the LLS position
   with screening, LM, RAIM gating) on 4 and 8 anchors: fixes per second for batches of 1, 100 and 100,000
   fixes, against ``scipy.optimize.least_squares`` (MINPACK LM, analytic Jacobian) solving the
   same fixes one by one with the same model and the same 12 starts (11 heights + the LLS
   position; keeping the lowest cost; no screening, no gating). The batch-of-1 row also gives
   the latency of a failing fix (one anchor +10 m: the exclusion candidates are solved from
   all starts). The scipy loop is timed on a subset and extrapolated to 100,000 (stated
   in the table). Accuracy is compared on the subset: RMSE of both against the truth and the
   largest difference between the two estimates.
2. **Gating vs robust loss.** One anchor of 6 given a positive bias of k sigma: how often
   RAIM excludes it, how often it excludes another anchor, and the 3D RMSE of plain least
   squares, gated D-NLS, Huber and soft-L1 (no gating).
3. **Baselines on diffraction data.** LLS, IPPA (authors' settings), D-NLS Case-1 and
   Case-2 on ranges generated with a true offset Delta = 1.5 m.

Run:  /work/venv/bin/python benchmarks/bench_estimators.py [--quick] [--seed N]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from common import SIGMA_M, W_M, scene, scipy_fix

from diffpos.estimators.dnls.fit import _lls_starts
from diffpos.estimators.dnls.solver import dnls
from diffpos.estimators.ippa import ippa
from diffpos.estimators.lls import lls
from diffpos.estimators.result import ExclusionReason
from diffpos.estimators.starts import DEFAULT_Z_STARTS_M, grid_starts
from diffpos.geometry import window_edge_path


def rate(anchors: np.ndarray, ranges: np.ndarray, *, repeat: int = 1) -> tuple[float, float]:
    """Fixes per second of default D-NLS on one batch (median over ``repeat`` calls), by wall
    clock and by this thread's CPU time (less sensitive to other processes on the machine)."""
    wall, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.thread_time()
        dnls(anchors, ranges, SIGMA_M, window_height_m=W_M)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
    n = ranges.reshape(-1, ranges.shape[-1]).shape[0]
    return n / float(np.median(wall)), n / float(np.median(cpu))


def speed_table(rng: np.random.Generator, big: int, subset: int) -> list[str]:
    rows = ["| anchors | batch | D-NLS+gating fixes/s | scipy loop fixes/s | speed-up | note |",
            "| ---: | ---: | ---: | ---: | ---: | --- |"]
    acc = ["| anchors | fixes | RMSE D-NLS (no gating) [m] | RMSE scipy [m] | max |D-NLS - scipy| [m] |",
           "| ---: | ---: | ---: | ---: | ---: |"]
    zs = np.asarray(DEFAULT_Z_STARTS_M)
    for m in (4, 8):
        anchors, nodes, p = scene(rng, big, m)
        r = p + SIGMA_M * rng.standard_normal(p.shape)
        # scipy per-fix loop on a subset
        sub = slice(0, subset)
        full_mask = np.ones((subset, m), bool)
        starts = grid_starts(anchors[sub], full_mask, zs, 3.0)
        starts = np.concatenate([starts, _lls_starts(anchors[sub], r[sub], full_mask, starts)], 1)
        t0 = time.perf_counter()
        x_sp = np.array([scipy_fix(anchors[i], r[i], SIGMA_M, starts[i]) for i in range(subset)])
        sp_rate = subset / (time.perf_counter() - t0)
        # D-NLS, batches of 1, 100 and `big`
        one, one_cpu = rate(anchors[0], r[0], repeat=300)
        # a failing fix: anchor 0 biased by +10 m (exclusion candidates solved from all starts)
        bad = r[:300].copy()
        bad[:, 0] += 10.0
        bad_cpu = [rate(anchors[i], bad[i])[1] for i in range(300)]
        hundred, _ = rate(anchors[:100], r[:100], repeat=20)
        many, _ = rate(anchors, r)
        for batch, fps in ((1, one), (100, hundred), (big, many)):
            if batch == 1:
                note = (f"single-fix latency {1e3 / fps:.2f} ms wall, {1e3 / one_cpu:.2f} ms "
                        "CPU (median of 300 calls); one anchor +10 m: "
                        f"{1e3 * np.median(1.0 / np.asarray(bad_cpu)):.2f} ms CPU (median of "
                        "300 fixes)")
            elif batch > subset:
                note = f"scipy timed on {subset} fixes, extrapolated"
            else:
                note = ""
            rows.append(f"| {m} | {batch:,} | {fps:,.0f} | {sp_rate:,.1f} | "
                        f"{fps / sp_rate:,.0f}x | {note} |")
        nog = dnls(anchors[sub], r[sub], SIGMA_M, window_height_m=W_M, gating=None)
        rmse_d = np.sqrt(np.mean(np.sum((nog.position_m - nodes[sub]) ** 2, axis=1)))
        rmse_s = np.sqrt(np.mean(np.sum((x_sp - nodes[sub]) ** 2, axis=1)))
        diff = np.max(np.linalg.norm(nog.position_m - x_sp, axis=1))
        acc.append(f"| {m} | {subset} | {rmse_d:.4f} | {rmse_s:.4f} | {diff:.2e} |")
    return [*rows, "", *acc]


def gating_table(rng: np.random.Generator, n: int) -> list[str]:
    anchors6 = np.array([[-20.0, -20.0, 2.0], [-5.0, -12.0, 0.0], [0.0, -7.0, 6.0],
                         [12.0, -18.0, 3.0], [25.0, -25.0, 15.0], [-10.0, -30.0, 25.0]])
    sig = 0.01
    nodes = np.stack([rng.uniform(-10, 10, n), rng.uniform(2, 12, n),
                      1.5 + 3.0 * rng.integers(0, 7, n)], axis=-1)
    a = np.broadcast_to(anchors6, (n, 6, 3))
    p = window_edge_path(a, nodes[:, None, :], window_height_m=W_M).length_m
    noise = sig * rng.standard_normal(p.shape)
    rows = ["| bias [sigma] | RAIM excludes the biased anchor | excludes another anchor | "
            "RMSE plain [m] | RMSE gated [m] | RMSE Huber [m] | RMSE soft-L1 [m] |",
            "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for lo, hi in ((0, 0), (5, 6), (8, 10), (10, 20), (5, 20)):
        j = rng.integers(0, 6, n)
        r = p + noise
        r[np.arange(n), j] += rng.uniform(lo, hi, n) * sig
        fits = {
            "plain": dnls(a, r, sig, window_height_m=W_M, gating=None),
            "gated": dnls(a, r, sig, window_height_m=W_M),
            "huber": dnls(a, r, sig, window_height_m=W_M, gating=None, loss="huber"),
            "soft_l1": dnls(a, r, sig, window_height_m=W_M, gating=None, loss="soft_l1"),
        }
        g = fits["gated"]
        raim = g.exclusion_reason == ExclusionReason.RAIM
        if hi == 0:
            hit, other = "-", f"{np.mean(np.any(g.excluded, axis=1)):.4f} (false exclusions)"
        else:
            biased = np.zeros((n, 6), dtype=bool)
            biased[np.arange(n), j] = True
            hit = f"{np.mean(raim[biased]):.3f}"
            other = f"{np.mean(np.any(g.excluded & ~biased, axis=1)):.3f}"
        rmse = {k: np.sqrt(np.mean(np.sum((f.position_m - nodes) ** 2, axis=1)))
                for k, f in fits.items()}
        label = "none" if hi == 0 else f"{lo}-{hi}"
        rows.append(f"| {label} | {hit} | {other} | {rmse['plain']:.4f} | {rmse['gated']:.4f} | "
                    f"{rmse['huber']:.4f} | {rmse['soft_l1']:.4f} |")
    rows.append("")
    rows.append(f"{n} trials per row, 6 anchors, sigma = {sig} m, P_fa = 1e-3 (chi-square, 3 dof).")
    return rows


def baseline_table(rng: np.random.Generator, n: int) -> list[str]:
    anchors = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0],
                        [15.0, -20.0, 1.0], [5.0, -30.0, 20.0]])
    nodes = np.stack([rng.uniform(-10, 10, n), rng.uniform(1, 12, n),
                      1.5 + 3.0 * rng.integers(0, 8, n)], axis=-1)
    a = np.broadcast_to(anchors, (n, 5, 3))
    r = window_edge_path(a, nodes[:, None, :], window_height_m=W_M, delta_m=1.5).length_m
    r = r + 0.03 * rng.standard_normal(r.shape)
    los = np.linalg.norm(nodes[:, None, :] - a, axis=-1)
    mean_bias = np.mean(r - los, axis=0)  # genie: per-anchor mean NLoS bias of this data set
    fits = {
        "LLS (LoS model)": lls(a, r, 0.03),
        "IPPA (all NLoS, 20 updates)": ippa(a, r),
        "IPPA (all NLoS, genie mean bias subtracted)": ippa(a, r, nlos_bias_m=mean_bias),
        "D-NLS Case-1 (Delta = 0, mismatched)": dnls(a, r, 0.03, window_height_m=W_M,
                                                     gating=None),
        "D-NLS Case-2 (Delta = 1.5 m)": dnls(a, r, 0.03, window_height_m=W_M, delta_m=1.5,
                                            gating=None),
    }
    rows = ["| method | 3D RMSE [m] | median 3D error [m] | z RMSE [m] |",
            "| --- | ---: | ---: | ---: |"]
    for name, f in fits.items():
        e = np.linalg.norm(f.position_m - nodes, axis=1)
        ez = f.position_m[:, 2] - nodes[:, 2]
        rows.append(f"| {name} | {np.sqrt(np.nanmean(e**2)):.3f} | {np.nanmedian(e):.3f} | "
                    f"{np.sqrt(np.nanmean(ez**2)):.3f} |")
    rows.append("")
    rows.append(f"{n} nodes on 8 floors, 5 anchors, ranges from the upper-edge diffraction path "
                "with true Delta = 1.5 m, sigma = 0.03 m.")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes (10,000 fixes)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scipy-subset", type=int, default=200,
                    help="fixes solved by the scipy loop (default 200)")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    big = 10_000 if args.quick else 100_000
    print("## Speed (D-NLS with gating vs scipy.optimize.least_squares per fix)\n")
    print("\n".join(speed_table(rng, big, args.scipy_subset)))
    print("\n## Gating (RAIM FDE) vs robust loss\n")
    print("\n".join(gating_table(rng, 1000 if args.quick else 4000)))
    print("\n## Baselines on diffraction data\n")
    print("\n".join(baseline_table(rng, 1000 if args.quick else 4000)))


if __name__ == "__main__":
    main()
