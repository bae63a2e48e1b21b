"""Where a replay's start-up goes in numba: each compiled kernel it loads, its signatures, and
the milliseconds of loading them from numba's on-disk cache; a table.

This script is the fresh process: it installs a timer around ``numba``'s
``Dispatcher.compile`` (the one place a kernel signature is loaded from the cache or
compiled: a lazy first call, an eager ``@njit("sig")`` at import and a callee during a
caller's compile all go through it), then runs ``diffpos replay REC --no-files`` in-process
(its output discarded) and prints, per dispatcher that was loaded or compiled:

- ``hit`` / ``miss``: signatures loaded from the cache / compiled (on a warmed cache every row
  should be all hits; a miss there is a kernel compiled each run; ``--json`` lists them);
- ``load ms``: wall milliseconds inside that dispatcher's ``compile`` minus those of the
  dispatchers compiled inside it (exclusive), split into ``index`` (the cache index read),
  ``unpickle`` (the cached data file) and ``link`` (rebuilding the compile result: LLVM
  object code to machine code, the callees' libraries linked);
- ``when``: ``start-up`` if the dispatcher was first loaded before the fusion's warm-up
  returned, ``run`` if during the replay itself (``--no-warm`` skips the warm-up: the rows are
  then exactly the kernels the replay calls);
- ``import``: signatures loaded while a module was being imported (explicit signatures).

Then the totals, the process's CPU seconds, the seconds until the replay's own clock started
(``timing.warm_up_s`` of its report, when it gives it), and the 1-minute load average.

    python benchmarks/bench_kernel_load.py [--recording /work/rec/large30.mcap] [--method dnls]
        [--no-warm] [--json]

Figures and their reading: docs/startup.md.

From a git worktree put the tree first (``PYTHONPATH=$PWD:$PWD/services``). Run it twice after
a source change: the first run compiles (misses) and fills the cache.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import resource
import sys
import time
from collections import defaultdict
from pathlib import Path

import numba.core.caching as caching
import numba.core.dispatcher as dispatcher

_STATS: dict[str, dict] = defaultdict(lambda: {"hit": 0, "miss": 0, "ms": 0.0, "index": 0.0,
                                               "unpickle": 0.0, "link": 0.0, "import": 0,
                                               "sigs": [], "phase": ""})
_PHASE = ["start-up"]  # "start-up" until the replay's warm-up returns, then "run"
_STACK: list[list] = []  # [name, child ms] per compile in progress


def _name(disp) -> str:
    f = disp.py_func
    return f"{f.__module__}.{f.__qualname__}"


def _importing() -> bool:
    """True while an ``import`` runs (importlib's frame on the stack)."""
    frame = sys._getframe(2)
    while frame is not None:
        if frame.f_code.co_name == "_call_with_frames_removed":
            return True
        frame = frame.f_back
    return False


def _install() -> None:
    compile_ = dispatcher.Dispatcher.compile

    def compile(self, sig):
        name = _name(self)
        before = len(self.overloads)
        _STACK.append([name, 0.0])
        t0 = time.perf_counter()
        try:
            return compile_(self, sig)
        finally:
            ms = (time.perf_counter() - t0) * 1e3
            _, child = _STACK.pop()
            if _STACK:
                _STACK[-1][1] += ms
            if len(self.overloads) > before:
                s = _STATS[name]
                hits = sum(self._cache_hits.values())
                s["hit"], s["miss"] = hits, sum(self._cache_misses.values())
                s["ms"] += ms - child
                s["import"] += _importing()
                s["sigs"] += [str(k) for k in list(self.overloads)[before:]]
                s["phase"] = s["phase"] or _PHASE[0]

    def timed(part: str, fn):
        def wrapper(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                if _STACK:
                    _STATS[_STACK[-1][0]][part] += (time.perf_counter() - t0) * 1e3
        return wrapper

    dispatcher.Dispatcher.compile = compile
    f = caching.IndexDataCacheFile
    f._load_index = timed("index", f._load_index)
    f._load_data = timed("unpickle", f._load_data)
    caching.CompileResultCacheImpl.rebuild = timed("link", caching.CompileResultCacheImpl.rebuild)


def _watch_warm_up(skip: bool) -> None:
    """Mark the end of the fusion's warm-up (rows loaded later: ``run``); ``skip``: no
    warm-up at all, so the rows are exactly the kernels the replay calls."""
    from diffpos_services.fusion import core  # after the timers
    warm = core.FusionCore.warm_up

    def warm_up(self) -> None:
        if not skip:
            warm(self)
        _PHASE[0] = "run"
    core.FusionCore.warm_up = warm_up


def measure(recording: str, method: str | None, *, no_warm: bool = False) -> dict:
    """Run the replay in this process with the timers installed; the rows and totals."""
    _install()
    t0 = time.perf_counter()
    _watch_warm_up(no_warm)
    from diffpos_services.cli.main import main  # after the timers
    argv = ["replay", recording, "--no-files", "--json"] + (["--method", method] if method else [])
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(argv)
    wall = time.perf_counter() - t0
    try:
        timing = json.loads(out.getvalue()).get("timing", {})
    except ValueError:
        timing = {}
    ru = resource.getrusage(resource.RUSAGE_SELF)
    rows = sorted(({"kernel": k, **v} for k, v in _STATS.items()), key=lambda r: -r["ms"])
    return {"rc": rc, "rows": rows, "wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime,
            "timing": timing, "load1": os.getloadavg()[0],
            "kernels": sorted(m for m in sys.modules if m.startswith("diffpos") and
                              m.endswith("_nb"))}


def table(res: dict) -> str:
    lines = [f"{'kernel':62s} {'when':>8s} {'hit':>4s} {'miss':>4s} {'import':>6s} {'load ms':>8s} "
             f"{'index':>6s} {'unpkl':>6s} {'link':>7s}"]
    tot = defaultdict(float)
    for r in res["rows"]:
        lines.append(f"{r['kernel'][-62:]:62s} {r['phase']:>8s} {r['hit']:4d} {r['miss']:4d} {r['import']:6d} "
                     f"{r['ms']:8.1f} {r['index']:6.1f} {r['unpickle']:6.1f} {r['link']:7.1f}")
        for k in ("hit", "miss", "import", "ms", "index", "unpickle", "link"):
            tot[k] += r[k]
    lines.append(f"{'total (' + str(len(res['rows'])) + ' dispatchers)':71s} {int(tot['hit']):4d} "
                 f"{int(tot['miss']):4d} {int(tot['import']):6d} {tot['ms']:8.1f} "
                 f"{tot['index']:6.1f} {tot['unpickle']:6.1f} {tot['link']:7.1f}")
    t = res["timing"]
    lines.append(f"process: wall {res['wall_s']:.2f} s, CPU {res['cpu_s']:.2f} s; replay "
                 f"warm_up_s {t.get('warm_up_s', float('nan')):.2f}, kernels_s "
                 f"{t.get('kernels_s') or 0:.2f}, replay wall_s {t.get('wall_s', float('nan')):.2f}"
                 f"; load average (1 min) {res['load1']:.1f}; exit {res['rc']}")
    lines.append("kernel modules imported: " + ", ".join(res["kernels"]))
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--recording", default=str(Path("/work/rec/large30.mcap")))
    ap.add_argument("--method", default=None, help="e.g. dnls (default: the recorded one)")
    ap.add_argument("--json", action="store_true", help="the rows as JSON")
    ap.add_argument("--no-warm", action="store_true",
                    help="skip the fusion's warm-up: the rows are the kernels the replay calls")
    a = ap.parse_args()
    res = measure(a.recording, a.method, no_warm=a.no_warm)
    print(json.dumps(res, indent=1) if a.json else table(res))


if __name__ == "__main__":
    main()
