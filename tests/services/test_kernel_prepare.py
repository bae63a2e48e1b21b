"""The kernels prepared before a run (issue 35, first use): the right groups for each method,
shared out among parallel workers, an estimate that follows the machine, failures that say
what failed, and a progress display that is quiet when the kernels are cached.

Not timed (benchmarks/bench_cold_start.py measures the seconds); the workers here run cheap
stand-in groups (stdlib imports), not the kernels.
"""

from __future__ import annotations

import ast
import io
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from diffpos_services.fusion import prepare
from diffpos_services.fusion.prepare import (
    GROUPS,
    IMPORTED,
    STAMP_NAME,
    Group,
    KernelError,
    Progress,
    bins,
    groups_for,
    prepare_kernels,
    progress_display,
)

ROOT = Path(__file__).resolve().parents[2]

#: the kernel modules a process imports with ``modules`` (numba off: nothing compiles meanwhile)
PROBE = """
import json, sys
for m in sys.argv[1:]:
    __import__(m)
print(json.dumps(sorted(m for m in sys.modules
                        if m.startswith("diffpos.") and m.endswith("_nb"))))
"""


def _kernel_modules(*modules: str) -> list[str]:
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    out = subprocess.run([sys.executable, "-c", PROBE, *modules], env=env, capture_output=True,
                         text=True, timeout=300, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _compiles_on_import(module: str) -> bool:
    """A kernel module with an ``@njit(SIGNATURE, ...)``: numba compiles it when imported."""
    tree = ast.parse((ROOT / (module.replace(".", "/") + ".py")).read_text(encoding="utf-8"))
    return any(isinstance(d, ast.Call) and getattr(d.func, "id", "") == "njit" and d.args
               for f in ast.walk(tree) if isinstance(f, ast.FunctionDef) for d in f.decorator_list)


def _group_of(module: str) -> str:
    return next(g for g, grp in GROUPS.items()
                if any(c.partition(":")[0] == module for c in grp.calls))


def test_imported_groups_are_what_the_fusion_compiles_on_import():
    """:data:`IMPORTED` is exactly the groups of the kernel modules that a fusion process (the
    live service, a replay) imports and that compile when imported (whatever the method): an
    eager import there makes this fail (and IMPORTED grows); none now, so a D-NLS run prepares
    D-NLS only."""
    for process in ("diffpos_services.fusion.service", "diffpos_services.replay.run"):
        mods = _kernel_modules(process)
        eager = [m for m in mods if _compiles_on_import(m)]
        assert {_group_of(m) for m in eager} == set(IMPORTED), (process, mods)
        # the solvers import their own kernels when they first solve (a D-NLS fusion or
        # replay loads neither M-NLS's nor, until it solves, D-NLS's)
        assert not {"diffpos.estimators.mnls.solver_nb", "diffpos.estimators.mnls.starts_nb",
                    "diffpos.estimators.dnls.fit_nb"} & set(mods), (process, mods)
    # the probe sees an eager module where one is imported: mnls's path (fusion/tracked.py
    # -> mnls/solver.py -> mnls/starts.py -> starts_nb), in the groups mnls prepares
    mnls = [m for m in _kernel_modules("diffpos_services.fusion.tracked") if _compiles_on_import(m)]
    assert mnls and {_group_of(m) for m in mnls} <= set(groups_for("mnls")) - set(IMPORTED), mnls


def test_each_method_prepares_its_own_groups():
    mnls = {"mnls", "paths", "channel", "tracking"}
    assert set(groups_for("mnls")) == set(IMPORTED) | mnls
    assert set(groups_for("mnls", tracking=False)) == set(IMPORTED) | mnls - {"tracking"}
    for m, own in (("dnls", {"dnls"}), ("lls", set()), ("ippa", set())):
        assert set(groups_for(m)) == set(IMPORTED) | own
        assert set(groups_for(m, channel=True)) == set(IMPORTED) | own | {"channel"}
    got = groups_for("mnls")
    assert got == sorted(got, key=lambda g: -GROUPS[g].cpu_s)  # the longest first


def test_bins_share_the_groups_longest_first():
    groups = groups_for("mnls")
    for workers in (1, 2, 3):
        b = bins(groups, workers)
        assert sorted(g for x in b for g in x) == sorted(groups) and len(b) <= workers
        loads = [sum(GROUPS[g].cpu_s for g in x) for x in b]
        # longest-first to the least loaded: loads differ by at most the longest group
        assert max(loads) - min(loads) <= max(GROUPS[g].cpu_s for g in groups)
    assert bins(["dnls"], 4) == [["dnls"]]


@pytest.fixture
def fake_groups(monkeypatch, tmp_path):
    """Cheap stand-ins (stdlib imports and calls) for the kernel groups; their cache stamp
    goes to ``tmp_path`` (numba's cache folder there), not the tree's real one."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    fake = {"a": Group("part A", 3.0, ("json", "gc:collect")),
            "b": Group("part B", 2.0, ("decimal",)),
            "c": Group("part C", 1.0, ("fractions",)),
            "bad": Group("broken part", 1.0, ("no_such_module_for_this_test",))}
    monkeypatch.setattr(prepare, "GROUPS", fake)
    return fake


def test_workers_run_every_group_and_report_the_end(fake_groups):
    seen: list[Progress] = []
    took = prepare_kernels(["a", "b", "c"], workers=2, progress=seen.append, interval_s=0.05)
    assert took.wall_s > 0 and len(took.worker_cpu_s) == 2 and seen[-1].finished
    assert (seen[-1].done, seen[-1].total, seen[-1].running) == (3, 3, ())
    assert all(not p.finished for p in seen[:-1])


def _real_stamp() -> bytes | None:
    """The tree's own cache stamp (numba's default cache folder of the core package)."""
    try:
        return (ROOT / "diffpos" / "__pycache__" / STAMP_NAME).read_bytes()
    except FileNotFoundError:
        return None


def test_stand_in_groups_stamp_only_the_tests_cache(fake_groups, tmp_path):
    before = _real_stamp()
    (tmp_path / "k.nbi").write_bytes(b"")  # a cache file to stamp (none: nothing stamped)
    prepare_kernels(["a", "b"], workers=2, interval_s=0.05)
    assert _real_stamp() == before  # the real stamp names no stand-in group
    assert set(json.loads((tmp_path / STAMP_NAME).read_text())["groups"]) == {"a", "b"}


def test_a_failing_worker_names_its_group_and_error(fake_groups):
    with pytest.raises(KernelError, match=r"broken part.*(?s:.*)no_such_module_for_this_test"):
        prepare_kernels(["a", "bad"], workers=2, interval_s=0.05)
    with pytest.raises(ValueError, match="unknown kernel groups"):
        prepare_kernels(["nope"])


class _Stub:
    def __init__(self, groups, done, cpu_s, left_s):
        self.groups, self.done, self.cpu_s, self._left = groups, done, cpu_s, left_s

    def left_s(self):
        return self._left


def test_the_estimate_follows_the_machine(monkeypatch):
    """Left = the most reference CPU a worker has left x the wall seconds per CPU second seen
    so far: on an idle machine the reference figure, on a busy one (2 wall s per CPU s)
    twice that."""
    t = {"now": 100.0}
    monkeypatch.setattr(prepare.time, "monotonic", lambda: t["now"])
    workers = [_Stub(["dnls"], [], 10.0, 30.0), _Stub(["mnls", "paths"], ["mnls"], 8.0, 3.0)]
    t["now"] = 110.0  # 10 s wall, 10 s CPU: idle
    p = prepare._progress(workers, 3, 100.0)
    assert p.left_s == pytest.approx(30.0) and p.done == 1 and p.running == ("dnls", "paths")
    t["now"] = 120.0  # 20 s wall for the same 10 s CPU: a busy machine
    assert prepare._progress(workers, 3, 100.0).left_s == pytest.approx(60.0)
    assert p.line() == ("compiling solver kernels (first run; cached after): 10 s, about 30 s "
                        "left, 1/3 parts [D-NLS solver, path model]")


class _Stream(io.StringIO):
    def isatty(self):
        return False


def test_the_display_is_quiet_when_cached_and_says_the_end_otherwise():
    out = _Stream()
    show = progress_display(out, quiet_s=2.0)
    show(Progress(0, 5, 0.5, None, ("dnls",)))
    show(Progress(5, 5, 1.0, 0.0, (), finished=True))
    assert out.getvalue() == ""  # cached: about a second, nothing said
    out = _Stream()
    show = progress_display(out, quiet_s=2.0)
    for s in (3.0, 3.5, 4.0):
        show(Progress(1, 5, s, 20.0, ("dnls",)))
    show(Progress(5, 5, 30.0, 0.0, (), finished=True))
    lines = out.getvalue().splitlines()
    assert len(lines) == 2  # one line when it started taking long, one at the end
    assert "(first run; cached after): 3 s, about 20 s left" in lines[0]
    assert lines[1] == "compiled the solver kernels in 30 s (cached for later runs)"


def test_a_stop_ends_the_workers_without_calling_it_a_failure(fake_groups):
    """Ctrl-C reaches the workers too (they die with KeyboardInterrupt): with the run's stop
    event set, that is not reported as a compile failure."""
    stop = threading.Event()
    stop.set()
    got = prepare_kernels(["bad", "a"], workers=2, stop=stop, interval_s=0.05)
    assert got.wall_s >= 0 and len(got.worker_cpu_s) == 2
