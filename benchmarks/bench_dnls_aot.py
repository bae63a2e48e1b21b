"""The D-NLS kernel compiled ahead of time: bit for bit, and what a process saves (issue 37).

A feasibility measurement, not a product path: the whole-process D-NLS replay pays ~0.8 s of
CPU before its first fix for ``import numba``, numba's first-use set-up and the kernel's load
from numba's cache (docs/replay_speed.md, "Session 30"); a kernel compiled ahead of time
(numba's ``numba.pycc``, deprecated by numba but present) is a plain extension module that a
process imports without numba. This script

1. compiles this tree's ``dnls.fit_nb.dnls_batch`` (its one signature, the callees compiled
   in) into an extension module in ``--keep DIR`` (a temporary folder without it), for the
   generic x86-64 target (``numba.pycc``'s default) or ``--target-cpu`` (e.g. ``host``);
2. records every ``dnls_batch`` call of a D-NLS replay of each ``--recording`` (inputs as
   passed, outputs after: ``diffpos replay REC --method dnls`` in-process, the kernel
   wrapped);
3. runs, ``--rounds`` times alternating, two fresh processes per recording on those calls:
   the ahead-of-time module (imports: numpy, ``scipy.linalg``'s BLAS/LAPACK as the kernel's
   ``np.linalg`` calls load them, the module) and the JIT kernel (``import
   dnls.fit_nb``: numba, its set-up, the cache load; then the calls); CPU of each part, and
   whether the ahead-of-time outputs equal the JIT's bit for bit (positions, covariances,
   statuses, residuals, used anchors, reasons) and the process imported numba.

Usage::

    python benchmarks/bench_dnls_aot.py --recording /work/rec/large30.mcap [REC ...] \\
        [--rounds 3] [--keep DIR] [--target-cpu host]
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import pickle
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MODULE = "dnls_aot"


def build_child(out_dir: str, target_cpu: str) -> None:
    """Compile ``dnls_batch`` ahead of time into ``out_dir``; prints a JSON line (CPU s)."""
    from numba.pycc import CC

    from diffpos.estimators.dnls import fit_nb

    cc = CC(MODULE)
    cc.output_dir = out_dir
    if target_cpu:
        cc.target_cpu = target_cpu
    sig = fit_nb.dnls_batch.nopython_signatures[0]
    cc.export("dnls_batch", sig)(fit_nb.dnls_batch.py_func)
    t0 = time.process_time()
    cc.compile()
    print(json.dumps({"build_cpu_s": time.process_time() - t0}))


def capture_child(recording: str, out: str) -> None:
    """A D-NLS replay of ``recording`` in-process, every ``dnls_batch`` call recorded into
    ``out`` (pickle: inputs as passed, outputs after)."""
    from diffpos.estimators.dnls import fit_nb

    real, calls = fit_nb.dnls_batch, []

    def recorded(*args):
        before = [a.copy() for a in args]
        real(*args)
        calls.append((before, [a.copy() for a in args[12:]]))

    fit_nb.dnls_batch = recorded
    from diffpos_services.cli import main as cli

    with contextlib.redirect_stdout(sys.stderr), contextlib.suppress(SystemExit):
        cli.main(["replay", recording, "--method", "dnls", "--no-files", "--no-progress"])
    with open(out, "wb") as fh:
        pickle.dump(calls, fh)
    print(json.dumps({"calls": len(calls)}))


def run_child(kind: str, module_dir: str, calls_file: str) -> None:
    """One fresh process: the kernel (``aot``: the module in ``module_dir``; ``jit``: numba's)
    on the recorded calls; prints a JSON line (CPU of each part, differing outputs)."""
    import numpy as np

    t0 = time.process_time()
    if kind == "aot":
        import scipy.linalg.cython_blas
        import scipy.linalg.cython_lapack  # noqa: F401
        t1 = time.process_time()
        sys.path.insert(0, module_dir)
        kernel = __import__(MODULE).dnls_batch
    else:
        t1 = t0
        from diffpos.estimators.dnls import fit_nb

        kernel = fit_nb.dnls_batch
    t2 = time.process_time()
    with open(calls_file, "rb") as fh:
        calls = pickle.load(fh)
    t3 = time.process_time()
    differ = 0
    for before, after in calls:
        args = [a.copy() for a in before]
        kernel(*args)
        for x, y in zip(args[12:], after, strict=True):
            same = (np.array_equal(x.view(np.int64), y.view(np.int64)) if x.dtype.kind == "f"
                    else np.array_equal(x, y))
            differ += not same
    t4 = time.process_time()
    print(json.dumps({"scipy_s": t1 - t0, "module_s": t2 - t1, "calls_s": t4 - t3,
                      "calls": len(calls), "differ": differ, "numba": "numba" in sys.modules}))


def child(args: list[str], env: dict[str, str] | None = None) -> dict:
    """This script in a fresh process (a hidden mode); its JSON line and CPU (``os.wait4``).
    (``common`` is imported here, by the parent only: the children import nothing else.)"""
    from common import tree_env

    with tempfile.TemporaryFile() as out:
        proc = subprocess.Popen([sys.executable, __file__, *args], stdout=out,
                                stderr=subprocess.DEVNULL, env=env or tree_env(ROOT), cwd=ROOT)
        _, status, ru = os.wait4(proc.pid, 0)
        if os.waitstatus_to_exitcode(status) != 0:
            raise RuntimeError(f"{' '.join(args)} failed")
        out.seek(0)
        row = json.loads(out.read().decode().strip().splitlines()[-1])
    return row | {"process_cpu_s": ru.ru_utime + ru.ru_stime}


def measure(recordings: list[str], work: Path, rounds: int) -> dict[tuple[str, str], list]:
    """Each recording's calls, then ``rounds`` alternating fresh processes of each kind."""
    rows: dict[tuple[str, str], list] = {}
    for rec in recordings:
        calls = work / f"{Path(rec).stem}.calls.pkl"
        n = child(["--capture-child", rec, str(calls)])["calls"]
        print(f"{rec}: {n} kernel calls recorded", flush=True)
        for _ in range(rounds):
            for kind in ("aot", "jit"):
                row = child(["--run-child", kind, str(work), str(calls)])
                rows.setdefault((rec, kind), []).append(row | {"load": os.getloadavg()[0]})
    return rows


def report(rows: dict[tuple[str, str], list], build: dict, target: str) -> None:
    """The table: medians per recording and kind."""
    med = statistics.median
    print(f"\n{datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC; {platform.machine()}, "
          f"{os.cpu_count()} cores, Python {platform.python_version()}; ahead-of-time build "
          f"({target or 'generic x86-64'}): {build['build_cpu_s']:.1f} s CPU (LLVM), "
          f"{build['process_cpu_s']:.1f} s CPU the whole build process")
    print(f"{'recording / kernel':<40} {'start-up':>9} {'calls':>7} {'process':>8} "
          f"{'differ':>7} {'numba':>6} load")
    for (rec, kind), rs in rows.items():
        start = med(r["scipy_s"] + r["module_s"] for r in rs)
        print(f"{Path(rec).name + ' / ' + kind:<40} {start:>9.3f} "
              f"{med(r['calls_s'] for r in rs):>7.3f} {med(r['process_cpu_s'] for r in rs):>8.2f} "
              f"{max(r['differ'] for r in rs):>7} {any(r['numba'] for r in rs)!s:>6} "
              f"{min(r['load'] for r in rs):.1f}-{max(r['load'] for r in rs):.1f}")
    print("start-up: CPU s before the first call (aot: scipy.linalg's BLAS/LAPACK + the module; "
          "jit: import dnls.fit_nb: numba, its set-up, scipy.linalg, the cache load); calls: "
          "CPU s of the recorded calls; process: the whole child's CPU (numpy and the pickle "
          "included); differ: outputs not equal to the JIT's bit for bit (of calls x 7); "
          "medians of the rounds")


def main() -> None:
    modes = {"--build-child": build_child, "--capture-child": capture_child,
             "--run-child": run_child}
    if len(sys.argv) > 1 and sys.argv[1] in modes:
        modes[sys.argv[1]](*sys.argv[2:])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recording", nargs="+", required=True)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--keep", metavar="DIR", help="build and keep the module here")
    ap.add_argument("--target-cpu", default="", help="numba.pycc's target CPU (default: "
                    "generic x86-64; 'host': this machine's)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="dnls_aot_") as tmp:
        work = Path(args.keep or tmp)
        work.mkdir(parents=True, exist_ok=True)
        build = child(["--build-child", str(work), args.target_cpu])
        rows = measure(args.recording, work, args.rounds)
    report(rows, build, args.target_cpu)


if __name__ == "__main__":
    main()
