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

``--whole-process``: also the whole D-NLS replay (``diffpos replay REC --method dnls
--no-files --no-progress``) of each recording in fresh processes, ``--rounds`` times
alternating: numba's JIT kernel (this tree as it is) against the ahead-of-time module in a
process without numba. A process without numba is made for the measurement only: a stand-in
``numba`` package (``@njit`` leaves a function as it is; written into the work folder and put
first on the child's path) lets the kernel modules import, and ``dnls.fit_nb.dnls_batch`` is
the module's function; any other compiled function the replay called would run as Python
(none does: checked by the outputs). CPU (user + system), wall and peak RSS; the printed
reports compared line by line (the timing line apart) and the ``--write-mcap`` outputs message
by message (topic, receive time, payload).

Usage::

    python benchmarks/bench_dnls_aot.py --recording /work/rec/large30.mcap [REC ...] \\
        [--rounds 3] [--keep DIR] [--target-cpu host] [--whole-process]
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


#: the stand-in ``numba`` package of ``--whole-process`` (file -> text)
STAND_IN = {
    "numba/__init__.py": (
        '"""A stand-in for numba (bench_dnls_aot.py --whole-process only)."""\n'
        '__version__ = "stand-in"\n\n\n'
        "def njit(*args, **kwargs):\n"
        "    if len(args) == 1 and callable(args[0]) and not kwargs:\n"
        "        return args[0]\n"
        "    return lambda f: f\n"),
    "numba/core/__init__.py": "",
    "numba/core/event.py": ("class Listener:\n    pass\n\n\n"
                            "def register(kind, listener):\n    pass\n"),
}


def replay_aot_child(module_dir: str, *argv: str) -> None:
    """``diffpos replay ARGV`` in this process with the stand-in numba (first on the path)
    and ``dnls_batch`` from the ahead-of-time module in ``module_dir``."""
    import numba

    assert numba.__version__ == "stand-in", "the stand-in numba is not first on the path"
    from diffpos.estimators.dnls import fit_nb

    sys.path.insert(0, module_dir)
    fit_nb.dnls_batch = __import__(MODULE).dnls_batch
    from diffpos_services.cli import main as cli

    cli.main(list(argv))


def tree_env() -> dict[str, str]:
    """This environment with this tree (and its ``services``) first on ``PYTHONPATH``.

    (``common.tree_env``'s, restated: this process imports nothing of the project, because a
    child's peak RSS as ``os.wait4`` reports it includes the image of the process it was
    forked from, so the parent is kept small: ~20 MB.)"""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "services")])
    return env


def replay_process(kind: str, work: Path, argv: list[str]) -> tuple[dict, str]:
    """One whole replay in a fresh process (``jit``: this tree as it is; ``aot``: without
    numba); its CPU, wall, peak RSS and printed report (the timing line dropped)."""
    env = tree_env()
    if kind == "aot":
        env["PYTHONPATH"] = os.pathsep.join([str(work / "stand-in"), env["PYTHONPATH"]])
        cmd = [sys.executable, __file__, "--replay-aot-child", str(work), *argv]
    else:
        cmd = [sys.executable, "-m", "diffpos_services.cli.main", *argv]
    load = os.getloadavg()[0]
    with tempfile.TemporaryFile() as out:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=ROOT)
        _, status, ru = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        out.seek(0)
        text = out.read().decode(errors="replace")
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{text[-2000:]}")
    report = "\n".join(ln for ln in text.splitlines() if "of recording replayed in" not in ln)
    return {"cpu_s": ru.ru_utime + ru.ru_stime, "wall_s": wall, "rss_mb": ru.ru_maxrss / 1024,
            "load": load}, report


def compare_child(path_a: str, path_b: str) -> None:
    """Two MCAPs message by message (by topic: receive time and payload, in file order);
    prints a JSON line: topics, topics differing, replayed estimates."""
    from diffpos_services.recording.reader import McapScanner

    msgs = []
    for path in (path_a, path_b):
        out: dict[str, list] = {}
        for batch in McapScanner(path).iter_batches():
            for m in batch:
                out.setdefault(m.topic, []).append((m.log_ns, m.data))
        msgs.append(out)
    a, b = msgs
    print(json.dumps({"topics": len(b), "differ": sum(a.get(t) != b.get(t) for t in set(a) | set(b)),
                      "estimates": sum(len(v) for t, v in b.items() if "/replay/" in t)}))


def whole_process(recordings: list[str], work: Path, rounds: int) -> None:
    """``--whole-process``: per recording, the written outputs compared message by message,
    then ``rounds`` alternating whole replays of each kind; a table of medians."""
    for rel, text in STAND_IN.items():
        (work / "stand-in" / rel).parent.mkdir(parents=True, exist_ok=True)
        (work / "stand-in" / rel).write_text(text)
    print("\nwhole process: diffpos replay REC --method dnls --no-files --no-progress; CPU s "
          "(user + system), wall s, peak RSS MB, medians; reports: printed reports equal but "
          "the timing line; messages: --write-mcap outputs, topics differing")
    print(f"{'recording / kernel':<40} {'CPU s':>7} {'min':>7} {'wall s':>7} {'RSS MB':>7} "
          f"{'reports':>8} {'messages':>20} load")
    for rec in recordings:
        base = ["replay", rec, "--method", "dnls", "--no-files", "--no-progress"]
        outs = [work / f"{Path(rec).stem}.{kind}.mcap" for kind in ("aot", "jit")]
        for kind, out in zip(("aot", "jit"), outs, strict=True):
            replay_process(kind, work, [*base, "--write-mcap", str(out)])
        c = child(["--compare-child", *map(str, outs)])
        for out in outs:
            out.unlink()
        same = f"{c['differ']} of {c['topics']} ({c['estimates']} est.)"
        rows: dict[str, list] = {"aot": [], "jit": []}
        reports: dict[str, set] = {"aot": set(), "jit": set()}
        for _ in range(rounds):
            for kind in ("aot", "jit"):
                row, report = replay_process(kind, work, base)
                rows[kind].append(row)
                reports[kind].add(report)
        equal = "equal" if reports["aot"] == reports["jit"] and len(reports["jit"]) == 1 \
            else "DIFFER"
        for kind, rs in rows.items():
            med = statistics.median
            print(f"{Path(rec).name + ' / ' + kind:<40} {med(r['cpu_s'] for r in rs):>7.2f} "
                  f"{min(r['cpu_s'] for r in rs):>7.2f} {med(r['wall_s'] for r in rs):>7.2f} "
                  f"{max(r['rss_mb'] for r in rs):>7.0f} {equal:>8} {same:>20} "
                  f"{min(r['load'] for r in rs):.1f}-{max(r['load'] for r in rs):.1f}")


def child(args: list[str], env: dict[str, str] | None = None) -> dict:
    """This script in a fresh process (a hidden mode); its JSON line and CPU (``os.wait4``)."""
    with tempfile.TemporaryFile() as out:
        proc = subprocess.Popen([sys.executable, __file__, *args], stdout=out,
                                stderr=subprocess.DEVNULL, env=env or tree_env(), cwd=ROOT)
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
             "--run-child": run_child, "--replay-aot-child": replay_aot_child,
             "--compare-child": compare_child}
    if len(sys.argv) > 1 and sys.argv[1] in modes:
        modes[sys.argv[1]](*sys.argv[2:])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recording", nargs="+", required=True)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--keep", metavar="DIR", help="build and keep the module here")
    ap.add_argument("--target-cpu", default="", help="numba.pycc's target CPU (default: "
                    "generic x86-64; 'host': this machine's)")
    ap.add_argument("--whole-process", action="store_true",
                    help="also whole D-NLS replays: the JIT kernel vs the module without numba")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="dnls_aot_") as tmp:
        work = Path(args.keep or tmp)
        work.mkdir(parents=True, exist_ok=True)
        build = child(["--build-child", str(work), args.target_cpu])
        rows = measure(args.recording, work, args.rounds)
        report(rows, build, args.target_cpu)
        if args.whole_process:
            whole_process(args.recording, work, args.rounds)


if __name__ == "__main__":
    main()
