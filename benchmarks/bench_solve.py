"""Benchmark of the compiled D-NLS kernel and of ``diffpos solve`` (issue 16, "Single fix" and
"solve"): reference (numpy) and kernel side by side in one run.

Prints three markdown tables:

1. **Single fix, 8 anchors** (one ``dnls`` call per fix, default settings: multi-start over 11
   heights + LLS with screening, LM, RAIM gating): cold (multi-start), warm (one given start,
   as the fusion's tracked nodes) and failing (one anchor +10 m: RAIM solves every
   leave-one-out candidate from all starts). Median over fixes of this thread's CPU time and
   of the wall time per call, numpy reference (``kernel=False``) vs compiled kernel.
2. **Batched**: one call on ``--batch`` fixes (cold, warm, and 10 % of the links +0.5-10 m),
   per-fix time reference vs kernel.
3. **``diffpos solve`` whole process** on ``--fixes`` problem lines (a subprocess from start to
   exit: imports, kernel load from the numba cache, parsing, solving, writing), against a
   ``scipy.optimize.least_squares`` loop (MINPACK LM with the analytic Jacobian, the same 12
   starts per fix, lowest cost kept, no gating) timed on ``--scipy-subset`` fixes and
   extrapolated. Times are CPU (user + sys of the process) and wall.

The kernel's first compile happens before the tables (its cost is printed): the rows time
the compiled code loaded from the cache, as a second start of any service does.

Run:  python benchmarks/bench_solve.py [--quick] [--seed N] [--only-solve --runs 3]
      [--keep-io DIR]   (two versions' DIR/fixes.jsonl must be equal byte for byte)
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from common import SIGMA_M, W_M, scene, scipy_fix

from diffpos.estimators.dnls.fit import _lls_starts
from diffpos.estimators.dnls.fit_nb import warm_dnls
from diffpos.estimators.dnls.solver import dnls
from diffpos.estimators.starts import DEFAULT_Z_STARTS_M, grid_starts


def _per_call(fn, n: int) -> tuple[float, float]:
    """Median CPU and wall seconds of ``n`` calls of ``fn(i)``."""
    cpu, wall = [], []
    for i in range(n):
        t0, c0 = time.perf_counter(), time.thread_time()
        fn(i)
        cpu.append(time.thread_time() - c0)
        wall.append(time.perf_counter() - t0)
    return float(np.median(cpu)), float(np.median(wall))


def _problems(rng: np.random.Generator, n: int, m: int, fault: bool):
    anchors, nodes, p = scene(rng, n, m)
    r = p + SIGMA_M * rng.standard_normal(p.shape)
    if fault:
        r[:, 0] += 10.0
    return anchors, nodes, r


def _one_fix(a: np.ndarray, r: np.ndarray, x0: np.ndarray | None, kern: bool, i: int) -> None:
    kw = {} if x0 is None else {"x0_m": x0[i]}
    dnls(a[i], r[i], SIGMA_M, window_height_m=W_M, kernel=kern, **kw)


def single_table(rng: np.random.Generator, n: int) -> list[str]:
    rows = ["| fix (8 anchors, one call each) | reference CPU [ms] | kernel CPU [ms] | "
            "reference wall [ms] | kernel wall [ms] | speed-up (CPU) |",
            "| --- | ---: | ---: | ---: | ---: | ---: |"]
    for label, fault, warm in (("cold (multi-start)", False, False),
                               ("warm (given start)", False, True),
                               ("failing: one anchor +10 m", True, False)):
        a, nodes, r = _problems(rng, n, 8, fault)
        x0 = nodes + rng.normal(0.0, 0.3, nodes.shape)
        res = {}
        for kern in (False, True):
            fix = functools.partial(_one_fix, a, r, x0 if warm else None, kern)
            res[kern] = _per_call(fix, n if kern else max(n // 5, 20))
        (rc, rw), (kc, kw_) = res[False], res[True]
        rows.append(f"| {label} | {1e3 * rc:.3f} | {1e3 * kc:.3f} | {1e3 * rw:.3f} | "
                    f"{1e3 * kw_:.3f} | {rc / kc:.0f}x |")
    rows.append("")
    rows.append(f"Median over {n} fixes (reference: {max(n // 5, 20)}).")
    return rows


def batch_table(rng: np.random.Generator, n: int) -> list[str]:
    rows = ["| batch of fixes (8 anchors) | reference [us/fix] | kernel [us/fix] | speed-up |",
            "| --- | ---: | ---: | ---: |"]
    a, nodes, r = _problems(rng, n, 8, False)
    faulty = r + (rng.random(r.shape) < 0.1) * rng.uniform(0.5, 10.0, r.shape)
    x0 = nodes + rng.normal(0.0, 0.3, nodes.shape)
    for label, rr, kw in (("cold", r, {}), ("warm (given start)", r, {"x0_m": x0}),
                          ("cold, 10 % links +0.5-10 m", faulty, {})):
        t = {}
        for kern in (False, True):
            c0 = time.thread_time()
            dnls(a, rr, SIGMA_M, window_height_m=W_M, kernel=kern, **kw)
            t[kern] = (time.thread_time() - c0) / n
        rows.append(f"| {label}, {n:,} | {1e6 * t[False]:.1f} | {1e6 * t[True]:.1f} | "
                    f"{t[False] / t[True]:.0f}x |")
    rows.append("")
    rows.append("CPU time of one call on the whole batch, per fix.")
    return rows


def _write_lines(path: Path, a: np.ndarray, r: np.ndarray) -> None:
    with path.open("w") as f:
        for i in range(r.shape[0]):
            f.write(json.dumps({"id": i, "anchors_m": a[i].tolist(), "ranges_m": r[i].tolist(),
                                "sigmas_m": SIGMA_M, "window_height_m": W_M}) + "\n")


def _run_solve(inp: Path, keep: Path | None = None) -> tuple[float, float, int]:
    """CPU (user + sys) and wall seconds of a whole ``diffpos solve`` process; result lines
    (written to ``keep`` if given, else to a temporary file)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    with inp.open("rb") as fin, (keep.open("w+b") if keep else tempfile.TemporaryFile()) as fout:
        subprocess.run([sys.executable, "-m", "diffpos_services.cli.main", "solve"], stdin=fin,
                       stdout=fout, check=True)
        wall = time.perf_counter() - t0
        fout.seek(0)
        n_out = sum(1 for _ in fout)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, wall, n_out


def solve_table(rng: np.random.Generator, n: int, subset: int, runs: int = 3,
                keep_io: Path | None = None) -> list[str]:
    a, _, r = _problems(rng, n, 8, False)
    zs = np.asarray(DEFAULT_Z_STARTS_M)
    sub = slice(0, subset)
    full = np.ones((subset, 8), bool)
    st = grid_starts(a[sub], full, zs, 3.0)
    st = np.concatenate([st, _lls_starts(a[sub], r[sub], full, st)], axis=1)
    c0, t0 = time.process_time(), time.perf_counter()
    for i in range(subset):
        scipy_fix(a[i], r[i], SIGMA_M, st[i])
    sp_cpu = (time.process_time() - c0) / subset * n
    sp_wall = (time.perf_counter() - t0) / subset * n
    with tempfile.TemporaryDirectory() as tmp:
        inp = (keep_io or Path(tmp)) / "problems.jsonl"
        _write_lines(inp, a, r)
        meas = [_run_solve(inp, keep_io / "fixes.jsonl" if keep_io and k == 0 else None)
                for k in range(runs)]
    assert all(k[2] == n for k in meas), f"diffpos solve wrote {[k[2] for k in meas]} for {n}"
    cpu, wall = float(np.median([k[0] for k in meas])), float(np.median([k[1] for k in meas]))
    each = ", ".join(f"{k[0]:.1f}/{k[1]:.1f}" for k in meas)
    return [
        "| fixes (8 anchors) | scipy loop CPU [s] | diffpos solve CPU [s] | ratio (CPU) | "
        "scipy loop wall [s] | diffpos solve wall [s] | ratio (wall) |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        f"| {n:,} | {sp_cpu:,.0f} | {cpu:,.1f} | {sp_cpu / cpu:.0f}x | {sp_wall:,.0f} | "
        f"{wall:,.1f} | {sp_wall / wall:.0f}x |",
        "",
        f"scipy loop timed on {subset} fixes and extrapolated to {n:,}; diffpos solve measured "
        f"whole-process (start to exit) on all of them, median of {runs} runs (CPU/wall s: "
        f"{each}); load average {os.getloadavg()[0]:.1f} at the end.",
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fixes", type=int, default=100_000, help="diffpos solve lines")
    ap.add_argument("--batch", type=int, default=10_000, help="batched table size")
    ap.add_argument("--scipy-subset", type=int, default=200)
    ap.add_argument("--runs", type=int, default=3, help="diffpos solve runs (median reported)")
    ap.add_argument("--only-solve", action="store_true", help="only the diffpos solve table")
    ap.add_argument("--keep-io", type=Path, metavar="DIR",
                    help="keep diffpos solve's input (DIR/problems.jsonl) and the first run's "
                         "output (DIR/fixes.jsonl), e.g. to compare two versions byte for byte")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    warm_dnls()  # compiled (or loaded from numba's cache) when dnls_nb was imported
    print(f"{platform.machine()}, Python {platform.python_version()}, {os.cpu_count()} cores "
          "(shared with other jobs); the kernel is loaded before the tables (numba's cache: "
          "the first compile on a machine costs ~45-52 s CPU, a cached load ~0.7 s CPU)\n")
    n_single = 100 if args.quick else 500
    if args.only_solve:
        print("\n".join(solve_table(rng, args.fixes, args.scipy_subset, args.runs,
                                    args.keep_io)))
        return
    print("## Single fix\n")
    print("\n".join(single_table(rng, n_single)))
    print("\n## Batched\n")
    print("\n".join(batch_table(rng, 2000 if args.quick else args.batch)))
    print("\n## diffpos solve vs a scipy least_squares loop\n")
    print("\n".join(solve_table(rng, 10_000 if args.quick else args.fixes,
                                50 if args.quick else args.scipy_subset, args.runs,
                                args.keep_io)))


if __name__ == "__main__":
    main()
