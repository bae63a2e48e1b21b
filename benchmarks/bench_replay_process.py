"""Whole-process `diffpos replay` before/after a change, side by side in one run (issue 37).

Each replay is the command a user types, in a fresh process:
``python -m diffpos_services.cli.main replay REC --no-files --json --compare --no-progress
[--method M]``, once with a *before* tree (``--before-commit``: that commit of this
repository, extracted by ``git archive`` into a temporary folder; or ``--before-tree DIR``)
and once with this tree, alternating, ``--rounds`` times. Each tree first replays once
untimed, so its numba cache is warm (a separate tree has its own cache: the first run there
compiles for minutes).

Per replay: wall seconds of the whole process (interpreter start, imports, kernels, replay,
report), its CPU (user + system, child processes included: ``os.wait4``; the median and, the
better guide on a loaded machine, the least of the rounds), peak RSS (``ru_maxrss``), the
seconds ``-X importtime`` reports for its imports (wall), and from the JSON report the
replay's own timing and the comparison with the recorded live estimates (positions identical
/ with positions). ``--bytecode-cache DIR`` keeps both trees' compiled bytecode there (an
installed package has it; the project's environment sets ``PYTHONDONTWRITEBYTECODE``, so by
default every process compiles the project's sources again). "x real" is the run's
emulated length (the truth's span: a lockstep recording's receive times span a different
time than the run) over the wall seconds; "x cpu" over the CPU seconds, the better guide on a
shared machine. "us/ne": CPU microseconds per node-epoch (published estimate).

Usage::

    python benchmarks/bench_replay_process.py --recording /work/rec/large30.mcap \\
        --before-commit c52d72c --methods default dnls --rounds 3
    python benchmarks/bench_replay_process.py --recording /work/rec/large30.mcap \\
        --before-tree /tmp/before --rounds 0 --split --split-rounds 5   # the split only

``--floor``: the start-up floor, each tree's fresh processes that only import (the
interpreter, numpy, numba, numba with ``scipy.linalg`` as numba's BLAS check imports it, the
D-NLS kernel module: numba's set-up and the kernel's load from its cache, the replay's own
module) and each method's replay of the recording's first 8 s (``--end 8``: start-up, the
kernels, the first epochs), ``--floor-rounds`` times alternating: CPU (user + system) and wall,
medians. What a whole replay costs beyond its start-up, and what a process that does not
import numba would save (docs/replay_speed.md, "Session 31").

``--split``: in-process CPU per step (``time.process_time`` around the fusion's ingest, its
step and the step's parts, the report's parts; one ``cli.main`` replay in a child process per
tree and method), us per node-epoch side by side: which part a change moved, within the noise
of a shared machine (the whole process's CPU varies more than the change).

The machine, Python and load (1-minute average, before each replay) are printed with the
table.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

from common import tree_env

ROOT = Path(__file__).resolve().parent.parent


def extract_commit(commit: str, dest: Path) -> Path:
    """``commit`` of this repository's history as a plain folder (``git archive``)."""
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryFile() as fh:
        subprocess.run(["git", "-C", str(ROOT), "archive", commit], stdout=fh, check=True)
        fh.seek(0)
        with tarfile.open(fileobj=fh) as tar:
            tar.extractall(dest, filter="data")
    return dest


def import_seconds(stderr: str) -> float:
    """The seconds ``python -X importtime`` reports for the top-level imports (cumulative
    time of each module imported at the top level, summed): every import of the process,
    those inside functions included (the fusion's, loaded when the replay starts)."""
    total = 0
    for line in stderr.splitlines():
        if not line.startswith("import time:"):
            continue
        parts = line.split("|")
        if len(parts) == 3 and parts[2].startswith(" ") and not parts[2].startswith("  "):
            with contextlib.suppress(ValueError):
                total += int(parts[1])
    return total / 1e6


def child_env(tree: Path, bytecode_dir: str | None) -> dict[str, str]:
    """The replay's environment: ``tree`` first on the path; with ``bytecode_dir``, compiled
    bytecode kept there (``PYTHONPYCACHEPREFIX``, as an installed package has it) instead of
    every process compiling the project's sources again (``PYTHONDONTWRITEBYTECODE``)."""
    env = tree_env(tree)
    if bytecode_dir is not None:
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        env["PYTHONPYCACHEPREFIX"] = bytecode_dir
    return env


def run_replay(tree: Path, recording: str, method: str, bytecode_dir: str | None = None) -> dict:
    """One whole-process replay with ``tree``'s code; its figures."""
    env = child_env(tree, bytecode_dir)
    cmd = [sys.executable, "-X", "importtime", "-m", "diffpos_services.cli.main", "replay",
           recording, "--no-files", "--json", "--compare", "--no-progress"]
    if method != "default":
        cmd += ["--method", method]
    load = os.getloadavg()[0]
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=out, stderr=err, cwd=tree)
        _, status, ru = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        if proc.returncode != 0:
            err.seek(0)
            raise RuntimeError(f"{' '.join(cmd)} (in {tree}) failed with {proc.returncode}:\n"
                               + err.read().decode(errors="replace")[-3000:])
        out.seek(0)
        rep = json.loads(out.read())
        err.seek(0)
        imports = import_seconds(err.read().decode(errors="replace"))
    c = rep.get("compare") or {}
    run_s = rep["truth_s"] or rep["recording_s"]
    cpu = ru.ru_utime + ru.ru_stime
    fixes = rep["fixes"]["total"]
    return {"wall_s": wall, "cpu_s": cpu, "rss_mb": ru.ru_maxrss / 1024, "run_s": run_s,
            "fixes": fixes, "x_real": run_s / wall, "x_cpu": run_s / cpu,
            "us_per_ne": 1e6 * cpu / max(fixes, 1), "load": load,
            "replay_wall_s": rep["timing"]["wall_s"], "kernels_s": rep["timing"].get("kernels_s"),
            "imports_s": imports,
            "identical": c.get("identical_positions"), "with_positions": c.get("with_positions"),
            "status_agree": c.get("status_agree")}


# ------------------------------------------------------------------ in-process split
#: (label, module, attribute path) of the steps timed in-process (``--split``); a step a
#: tree does not have is skipped. Nested: "fusion step" holds gather .. estimates.
SPLIT_STEPS = [
    ("ingest (FusionCore.on_sample)", "diffpos_services.fusion.core", "FusionCore.on_sample"),
    ("fusion step (FusionCore.step + flush)", "diffpos_services.fusion.core", "FusionCore.step"),
    ("fusion step (FusionCore.step + flush)", "diffpos_services.fusion.core", "FusionCore.flush"),
    ("  gather", "diffpos_services.fusion.core", "gather"),
    ("  gather", "diffpos_services.fusion.core", "_gather"),
    ("  prepare", "diffpos_services.fusion.core", "prepare"),
    ("  solve (kernels)", "diffpos_services.fusion.core", "solve_batch"),
    ("  solve (kernels)", "diffpos_services.fusion.core", "solve_mnls"),
    ("  estimates", "diffpos_services.fusion.core", "v1_estimates"),
    ("  estimates", "diffpos_services.fusion.core", "v2_builder"),
    ("report: truth + live estimates (Recorded.take)", "diffpos_services.replay.report_stream",
     "Recorded.take"),
    ("report: scoring (Recorded.advance)", "diffpos_services.replay.report_stream",
     "Recorded.advance"),
    ("report: replayed estimates in (_Outputs.emit)", "diffpos_services.replay.run",
     "_Outputs.emit"),
    ("report: final (_report)", "diffpos_services.replay.run", "_report"),
]


def split_child(recording: str, method: str) -> None:
    """One in-process replay (``cli.main.main``) with CPU timers (``time.process_time``)
    around :data:`SPLIT_STEPS`; prints a JSON line: seconds per step, after the import."""
    import functools
    import importlib
    t_imp = time.process_time()
    from diffpos_services.cli import main as cli
    importlib.import_module("diffpos_services.replay.run")
    spent: dict[str, float] = {}

    def wrap(label: str, fn, returns_fn: bool = False):
        @functools.wraps(fn)
        def timed(*a, **k):
            t0 = time.process_time()
            try:
                out = fn(*a, **k)
            finally:
                spent[label] = spent.get(label, 0.0) + time.process_time() - t0
            return wrap(label, out) if returns_fn else out
        return timed

    for label, mod, path in SPLIT_STEPS:
        obj = importlib.import_module(mod)
        *owner, name = path.split(".")
        for part in owner:
            obj = getattr(obj, part)
        fn = getattr(obj, name, None)
        if fn is not None:
            setattr(obj, name, wrap(label, fn, returns_fn=name == "v2_builder"))
    t0 = time.process_time()
    argv = ["replay", recording, "--no-files", "--no-progress"]
    if method != "default":
        argv += ["--method", method]
    with contextlib.redirect_stdout(sys.stderr):
        cli.main(argv)
    spent["everything after the import"] = time.process_time() - t0
    spent["import of replay.run"] = t0 - t_imp
    print(json.dumps(spent))


def run_split(tree: Path, recording: str, method: str) -> dict[str, float]:
    env = child_env(tree, None)
    out = subprocess.run([sys.executable, __file__, "--split-child", recording, method],
                         env=env, cwd=tree, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def print_split(trees: list[tuple[str, Path]], recording: str, methods: list[str],
                fixes: int, rounds: int = 1) -> None:
    """The in-process split, every tree and method side by side (us per node-epoch; the
    median of ``rounds`` replays each, alternating)."""
    runs: dict[tuple[str, str], list[tuple[dict[str, float], float]]] = {}
    for _ in range(rounds):
        for method in methods:
            for name, tree in trees:
                load = os.getloadavg()[0]
                runs.setdefault((method, name), []).append(
                    (run_split(tree, recording, method), load))
    cols = []
    for (method, name), rs in runs.items():
        med = {k: statistics.median(r[0].get(k, 0.0) for r in rs) for k in rs[0][0]}
        cols.append((f"{method} {name.split(' ')[0]}", med, statistics.median(r[1] for r in rs)))
    labels = list(dict.fromkeys([lab for lab, _, _ in SPLIT_STEPS]
                                + ["everything after the import", "import of replay.run"]))
    print(f"\nin-process CPU per step [us per node-epoch; {fixes} node-epochs], the median "
          f"of {rounds} replay(s) per column, alternating (median load before them: last row)")
    print(f"{'step':<48}" + "".join(f"{c[0]:>16}" for c in cols))
    for lab in labels:
        print(f"{lab:<48}" + "".join(
            f"{1e6 * c[1][lab] / fixes:>16.1f}" if lab in c[1] else f"{'-':>16}" for c in cols))
    print(f"{'load':<48}" + "".join(f"{c[2]:>16.1f}" for c in cols))


# ------------------------------------------------------------------ the start-up floor
#: (label, python -c code) of the import-only processes of ``--floor``
FLOOR_IMPORTS = [
    ("python -c pass", "pass"),
    ("import numpy", "import numpy"),
    ("import numba", "import numba"),
    ("import numba, scipy.linalg", "import numba, scipy.linalg"),
    ("import dnls.fit_nb (numba set-up, kernel load)", "import diffpos.estimators.dnls.fit_nb"),
    ("import replay.run", "import diffpos_services.replay.run"),
]


def run_process(tree: Path, args: list[str], bytecode_dir: str | None = None) -> dict:
    """One fresh ``python ARGS`` process with ``tree``'s code: its CPU (user + system) [s]
    and wall [s] (``os.wait4``; its peak RSS is not reported: the child is forked from this
    process, whose image counts until the exec)."""
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, *args], env=child_env(tree, bytecode_dir),
                            cwd=tree, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, ru = os.wait4(proc.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"python {' '.join(args)} (in {tree}) failed")
    return {"cpu_s": ru.ru_utime + ru.ru_stime, "wall_s": time.perf_counter() - t0,
            "load": load}


def print_floor(trees: list[tuple[str, Path]], recording: str, methods: list[str],
                rounds: int, bytecode_dir: str | None) -> None:
    """The start-up floor (``--floor``), every tree side by side: CPU and wall, the
    median of ``rounds`` fresh processes each, alternating."""
    cases = [(label, ["-c", code]) for label, code in FLOOR_IMPORTS]
    for method in methods:
        cmd = ["-m", "diffpos_services.cli.main", "replay", recording, "--no-files",
               "--no-progress", "--end", "8"]
        cases.append((f"replay --end 8 ({method})",
                      cmd + ([] if method == "default" else ["--method", method])))
    runs: dict[tuple[str, str], list[dict]] = {}
    for _ in range(rounds):
        for label, args in cases:
            for name, tree in trees:
                runs.setdefault((label, name), []).append(run_process(tree, args, bytecode_dir))
    print(f"\nstart-up floor: fresh processes, CPU s (user + system), the median of {rounds} "
          "each, alternating / wall s (the same median; it moves with the load)")
    print(f"{'process':<48}" + "".join(f"{n.split(' ')[0]:>20}" for n, _ in trees))
    for label, _ in cases:
        cells = []
        for name, _ in trees:
            rs = runs[(label, name)]
            cells.append(f"{_median(rs, 'cpu_s'):>12.2f} / {_median(rs, 'wall_s'):>5.2f}")
        print(f"{label:<48}" + "".join(f"{c:>20}" for c in cells))
    loads = [r["load"] for rs in runs.values() for r in rs]
    print(f"{'load (1-minute average before each)':<48}{min(loads):>12.1f} - {max(loads):.1f}")


def _median(rows: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in rows)


def _line(label: str, rows: list[dict]) -> str:
    ident = {f"{r['identical']}/{r['with_positions']}" for r in rows}
    return (f"{label:<22} {_median(rows, 'wall_s'):>7.2f} {_median(rows, 'x_real'):>7.2f} "
            f"{_median(rows, 'cpu_s'):>7.2f} {min(r['cpu_s'] for r in rows):>7.2f} "
            f"{_median(rows, 'x_cpu'):>7.2f} "
            f"{_median(rows, 'us_per_ne'):>7.0f} {max(r['rss_mb'] for r in rows):>7.0f} "
            f"{_median(rows, 'imports_s'):>8.2f} "
            f"{_median(rows, 'kernels_s'):>8.2f} {_median(rows, 'replay_wall_s'):>8.2f} "
            f"{','.join(sorted(ident)):>13} "
            f"{min(r['load'] for r in rows):>4.1f}-{max(r['load'] for r in rows):<4.1f}")


def _more_options(ap: argparse.ArgumentParser) -> None:
    """The options of the in-process split and the start-up floor."""
    ap.add_argument("--split", action="store_true",
                    help="also the in-process split (CPU per step, one replay per tree and "
                         "method, --split-rounds times alternating: the median)")
    ap.add_argument("--split-rounds", type=int, default=1)
    ap.add_argument("--floor", action="store_true",
                    help="also the start-up floor (import-only processes and each method's "
                         "replay of the first 8 s, --floor-rounds times alternating)")
    ap.add_argument("--floor-rounds", type=int, default=3)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--recording", required=True, help="an emulate recording (lockstep large)")
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--before-commit", help="the commit to compare with (git archive)")
    g.add_argument("--before-tree", help="a checkout to compare with")
    ap.add_argument("--methods", nargs="+", default=["default", "dnls"],
                    help="default (the recorded method) and/or a --method of replay")
    ap.add_argument("--rounds", type=int, default=3,
                    help="timed replays per tree and method (0: none, e.g. with --split)")
    ap.add_argument("--bytecode-cache", metavar="DIR",
                    help="keep the compiled bytecode of both trees in DIR (PYTHONPYCACHEPREFIX) "
                         "instead of the environment's setting (PYTHONDONTWRITEBYTECODE=1 "
                         "makes every process compile the project's sources again)")
    _more_options(ap)
    ap.add_argument("--split-child", nargs=2, help=argparse.SUPPRESS)
    if "--split-child" in sys.argv:
        i = sys.argv.index("--split-child")
        split_child(sys.argv[i + 1], sys.argv[i + 2])
        return
    args = ap.parse_args()
    bc = args.bytecode_cache
    tmp = None
    if args.before_commit:
        tmp = tempfile.TemporaryDirectory(prefix="bench_before_")
        before = extract_commit(args.before_commit, Path(tmp.name) / "before")
        before_name = f"before ({args.before_commit})"
    else:
        before, before_name = Path(args.before_tree), f"before ({args.before_tree})"
    trees = [(before_name, before), ("after (this tree)", ROOT)]
    rows: dict[tuple[str, str], list[dict]] = {}
    warm = []
    for method in args.methods:  # untimed: each tree's numba cache warm
        for _, tree in trees:
            warm.append(run_replay(tree, args.recording, method, bc))
    for _ in range(args.rounds):
        for method in args.methods:
            for name, tree in trees:
                rows.setdefault((method, name), []).append(
                    run_replay(tree, args.recording, method, bc))
    print(f"{datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC; machine: "
          f"{platform.machine()}, {os.cpu_count()} cores, {platform.processor() or '?'}, "
          f"Python {platform.python_version()}; shared with other jobs: the load column is "
          "the 1-minute load average before each replay")
    first = warm[0]
    print(f"recording {args.recording}: {first['run_s']:.1f} s emulated, {first['fixes']} "
          f"estimates; medians of {args.rounds} whole-process replays each, alternating")
    print("command: python -X importtime -m diffpos_services.cli.main replay REC --no-files "
          "--json --compare --no-progress [--method M]; bytecode: "
          + (f"cached in {bc}" if bc else "as the environment says (PYTHONDONTWRITEBYTECODE="
             f"{os.environ.get('PYTHONDONTWRITEBYTECODE', '')!r})"))
    if rows:
        print(f"\n{'method / tree':<22} {'wall s':>7} {'x real':>7} {'CPU s':>7} {'min':>7} {'x cpu':>7} "
              f"{'us/ne':>7} {'RSS MB':>7} {'imports':>8} {'kernels':>8} {'replay':>8} "
              f"{'identical':>13} load")
        for method in args.methods:
            for name, _ in trees:
                print(_line(f"{method}: {name.split(' ')[0]}", rows[(method, name)]))
            b, a = rows[(method, trees[0][0])], rows[(method, trees[1][0])]
            print(f"{method}: after/before      x real {_median(a, 'x_real') / _median(b, 'x_real'):.2f}, "
                  f"CPU {_median(a, 'cpu_s') / _median(b, 'cpu_s'):.2f} (least "
                  f"{min(r['cpu_s'] for r in a) / min(r['cpu_s'] for r in b):.2f}), "
                  f"RSS {max(r['rss_mb'] for r in a) / max(r['rss_mb'] for r in b):.2f}")
    if rows:
        print("\nimports: -X importtime's top-level imports summed (wall, the fusion's included); "
              "kernels: the report's kernels_s (kernel preparation + the fusion's import, wall); "
              "replay: the report's wall_s (feed + report); identical: live positions reproduced "
              "bit for bit / with positions (--compare)")
    if args.split:
        print_split(trees, args.recording, args.methods, first["fixes"], args.split_rounds)
    if args.floor:
        print_floor(trees, args.recording, args.methods, args.floor_rounds, bc)
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
