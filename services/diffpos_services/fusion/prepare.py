"""The compiled (numba) kernels a run needs, prepared once, in parallel, with a progress line.

On a fresh machine (an empty numba cache) the kernels compile for over a minute of CPU;
afterwards every process loads them from numba's on-disk cache (``cache=True``) in about a
second. :func:`prepare_kernels` compiles the :data:`GROUPS` a run needs, each in its own
worker processes (``python -c``: a worker imports only its groups' kernel modules, compiles
them and writes numba's cache), one per core, the groups shared out longest first
(:func:`bins`); the caller and the services it starts then load the kernels from the cache.
When every group is cached already this takes about a second (each worker loads its groups
and exits); with ``skip_cached`` (``diffpos replay``) not even that: a stamp written after the
workers succeeded (:func:`cache_stamp`) says which groups numba's cache holds for these
sources, and a run that finds its groups there starts no worker (the caller's own import
loads the kernels, as it would after the workers).

Which groups a run needs: :func:`groups_for` (the method's solvers, and what the fusion's
imports compile whatever its method: nothing, see :data:`IMPORTED`; the anchors' emulated
channel needs the SNR kernels).

The progress callback gets a :class:`Progress` every ``interval_s``: the groups done, the
seconds so far and an estimate of the seconds left, made from the CPU seconds each group
took on the reference machine (:data:`GROUPS`) and the CPU the workers have used so far
(read from ``/proc``; on a busy machine the estimate grows with the wall time per CPU
second measured, instead of promising the idle machine's figure).

Nothing here imports numba or a kernel module: the workers do.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.metadata
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from diffpos_services.errors import DiffposError
from diffpos_services.logs import STATUS

__all__ = ["GROUPS", "GROUP_METHODS", "IMPORTED", "Group", "KernelError", "Prepared", "Progress", "bins",
           "cache_stamp", "cached_groups", "compile_groups", "groups_for", "prepare_kernels",
           "progress_display"]


@dataclass(frozen=True)
class Group:
    """One worker's share: what it compiles, and its compile CPU on the reference machine."""

    label: str
    cpu_s: float
    #: ``module:function`` calls run in order (a bare module: compiled when imported)
    calls: tuple[str, ...]


#: The kernel groups; ``cpu_s``: one group alone on an empty numba cache, CPU seconds on the
#: 2-core reference VM (benchmarks/bench_cold_start.py --groups measures them).
GROUPS: dict[str, Group] = {
    "dnls": Group("D-NLS solver", 44.0, ("diffpos.estimators.dnls.fit_nb:warm_dnls",)),
    "mnls": Group("M-NLS solver", 21.0, ("diffpos.estimators.mnls.solver_nb",
                                         "diffpos.estimators.mnls.starts_nb")),
    "paths": Group("path model", 3.0, ("diffpos.paths.model_nb:warm_paths",)),
    "channel": Group("SNR prediction", 11.5, ("diffpos.channel.snr_nb:warm_channel",)),
    "tracking": Group("tracker", 24.5, ("diffpos.tracking.tracker:warm_tracking",)),
}

#: Groups compiled whenever the fusion is imported, whatever its method: the groups of the
#: kernel modules that compile on import (explicit signatures) and that the fusion's process
#: (service or replay) imports at module level. None: M-NLS's start kernels (``starts_nb``,
#: which compile on import) are imported with the M-NLS solver, which the fusion imports
#: where mnls runs (``fusion/core.py`` -> ``tracked.py``, ``warm.py``'s ``warm_model``, the
#: pool's worker process); the solvers' own kernels (``mnls/solver_nb``, ``dnls/fit_nb``) when
#: they first solve (tests/services/test_kernel_prepare.py checks it).
IMPORTED: tuple[str, ...] = ()

#: What each method solves with (:func:`groups_for` adds :data:`IMPORTED`, compiled anyway;
#: ``mnls``'s group holds M-NLS's start kernels, ``starts_nb``, which its solver imports).
_METHOD_GROUPS = {"mnls": ("mnls", "paths", "channel", "tracking"), "dnls": ("dnls",),
                  "lls": (), "ippa": ()}
#: The methods :func:`groups_for` knows.
GROUP_METHODS = tuple(_METHOD_GROUPS)


def groups_for(method: str, *, tracking: bool = True, channel: bool = False) -> list[str]:
    """The groups a run of the fusion with ``method`` needs (``tracking``: mnls with its
    tracker; ``channel``: the emulated channel of ``diffpos emulate``'s anchors), the
    longest first."""
    need = set(IMPORTED) | set(_METHOD_GROUPS[method])
    if method == "mnls" and not tracking:
        need.discard("tracking")
    if channel:
        need.add("channel")
    return sorted(need, key=lambda g: -GROUPS[g].cpu_s)


def compile_groups(spec: str) -> None:
    """Compile (or load from numba's cache) the kernels of the groups in ``spec`` (JSON:
    ``[[name, [call, ...]], ...]``, the calls of :class:`Group`) in turn, printing
    ``done NAME`` after each: a worker's job."""
    for name, calls in json.loads(spec):
        for call in calls:
            module, _, func = call.partition(":")
            mod = importlib.import_module(module)
            if func:
                getattr(mod, func)()
        print(f"done {name}", flush=True)


def bins(groups: list[str], workers: int) -> list[list[str]]:
    """``groups`` shared among at most ``workers`` workers, the longest first, each to the
    least loaded (by :data:`GROUPS` ``cpu_s``); one process per worker: a cached group then
    costs no interpreter start of its own."""
    loads: list[tuple[float, list[str]]] = [(0.0, []) for _ in range(max(1, workers))]
    for g in sorted(groups, key=lambda g: -GROUPS[g].cpu_s):
        i = min(range(len(loads)), key=lambda k: loads[k][0])
        loads[i] = (loads[i][0] + GROUPS[g].cpu_s, [*loads[i][1], g])
    return [b for _, b in loads if b]


class KernelError(DiffposError):
    """A worker failed: the group, its exit code and the end of its error output."""


@dataclass(frozen=True)
class Progress:
    """Where the preparation is: ``done`` of ``total`` groups, ``elapsed_s`` so far and
    ``left_s`` (the estimate of what is left; ``None`` until it can be made)."""

    done: int
    total: int
    elapsed_s: float
    left_s: float | None
    running: tuple[str, ...]
    finished: bool = False  # the last call: every worker has ended

    def line(self) -> str:
        """``compiling solver kernels (first run; cached after): 14 s, about 20 s left,
        2/5 parts [tracker, M-NLS solver]``: what moves first (a terminal line is cut at its
        width)."""
        what = ", ".join(GROUPS[g].label for g in self.running)
        left = "" if self.left_s is None else f", about {max(1, round(self.left_s))} s left"
        return (f"compiling solver kernels (first run; cached after): {self.elapsed_s:.0f} s"
                f"{left}, {self.done}/{self.total} parts{f' [{what}]' if what else ''}")


def _cpu_s(pid: int) -> float | None:
    """CPU seconds (user + system) of a running process, from ``/proc`` (``None``: unknown)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            fields = fh.read().rsplit(b")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


class _Worker:
    """One worker process, its groups, the ones it finished (read from its output) and its
    CPU seconds so far."""

    def __init__(self, groups: list[str]) -> None:
        self.groups = groups
        self.done: list[str] = []
        self.cpu_s = 0.0
        self.err = tempfile.TemporaryFile()  # a file, not a pipe: numba's warnings never block
        code = ("import sys; from diffpos_services.fusion.prepare import compile_groups; "
                "compile_groups(sys.argv[1])")
        spec = json.dumps([[g, GROUPS[g].calls] for g in groups])
        self.proc = subprocess.Popen([sys.executable, "-c", code, spec],
                                     stdout=subprocess.PIPE, stderr=self.err, text=True)
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:  # type: ignore[union-attr]
            if line.startswith("done "):
                self.done.append(line.split()[1])

    def poll(self) -> bool:
        """True while running (its CPU seconds updated)."""
        cpu = _cpu_s(self.proc.pid)
        if self.proc.poll() is None:
            self.cpu_s = self.cpu_s if cpu is None else cpu
            return True
        self.reader.join()
        return False

    def left_s(self) -> float:
        """Reference CPU seconds it still has to spend (at least a tenth of the running
        group's: an estimate never says 0 while work is left)."""
        todo = [g for g in self.groups if g not in self.done]
        spent = self.cpu_s - sum(GROUPS[g].cpu_s for g in self.done)
        left = sum(GROUPS[g].cpu_s for g in todo) - max(spent, 0.0)
        return max(left, 0.1 * GROUPS[todo[0]].cpu_s) if todo else 0.0

    def failure(self) -> str | None:
        if self.proc.returncode == 0:
            return None
        self.err.seek(0)
        tail = "\n".join(self.err.read().decode(errors="replace").strip().splitlines()[-12:])
        todo = [GROUPS[g].label for g in self.groups if g not in self.done]
        return (f"compiling the {', '.join(todo)} kernels failed (exit {self.proc.returncode})"
                f":\n{tail}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        self.err.close()


def _progress(workers: list[_Worker], total: int, t0: float) -> Progress:
    """The estimate: the most reference CPU seconds a worker has left, times the wall seconds
    per CPU second measured so far (1 on an idle machine; more on a busy one)."""
    elapsed = time.monotonic() - t0
    used = max((w.cpu_s for w in workers), default=0.0)
    per_cpu = max(elapsed / used, 1.0) if used > 1.0 else 1.0
    left = max((w.left_s() for w in workers), default=0.0) * per_cpu
    running = tuple(next(g for g in w.groups if g not in w.done) for w in workers
                    if len(w.done) < len(w.groups))
    return Progress(sum(len(w.done) for w in workers), total, elapsed,
                    left if elapsed > 2.0 else None, running)


@dataclass(frozen=True)
class Prepared:
    """What :func:`prepare_kernels` took: ``wall_s``, and each worker's CPU seconds (as last
    read while it ran; on an idle machine with a core per worker the wall seconds are about
    the largest of them)."""

    wall_s: float
    worker_cpu_s: tuple[float, ...]
    #: every group was in the cache stamp: no worker was started (``skip_cached``)
    cached: bool = False


#: The core package whose kernels numba caches (its sources and their ``__pycache__``).
_CORE = Path(__file__).resolve().parents[3] / "diffpos"
#: The stamp's file name (in numba's cache folder of the core package).
STAMP_NAME = "diffpos-kernels-prepared.json"


def _stamp_path() -> Path:
    """Where the stamp lives: ``$NUMBA_CACHE_DIR`` when set (numba's cache is there), else the
    core package's ``__pycache__`` (numba's default place for its kernels' cache)."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    return Path(env) / STAMP_NAME if env else _CORE / "__pycache__" / STAMP_NAME


def _cache_files() -> list[str]:
    """numba's index and data files of the core package's kernels (sorted names)."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    root = Path(env) if env else _CORE
    if not root.is_dir():
        return []
    return sorted(str(p.relative_to(root)) for p in root.rglob("*.nb[ic]")
                  if env or p.parent.name == "__pycache__")


def _fingerprint() -> str:
    """What numba's cache of the kernels depends on: every core source file's path and
    content (a kernel's callees live in other files, so all of them), and the modification
    time and size of each file that can define a kernel (one that names numba: numba's
    cache index of a kernel is valid for its own file's mtime and size only); the Python and
    numba versions, the ``NUMBA_*`` settings, the machine and its CPU flags. By content, not
    mtime: a merge or checkout that rewrites files without changing a kernel's file (the
    usual merge) keeps the stamp, and the next run starts no worker processes (it started
    them, 1.6-3.2 s, after every merge)."""
    h = hashlib.sha256()
    try:
        numba_version = importlib.metadata.version("numba")
    except importlib.metadata.PackageNotFoundError:
        numba_version = "none"
    h.update(repr((sys.version, numba_version, platform.machine(), str(_CORE),
                   sorted((k, v) for k, v in os.environ.items() if k.startswith("NUMBA_")))
                  ).encode())
    try:
        with open("/proc/cpuinfo", "rb") as fh:
            h.update(next((ln for ln in fh if ln.startswith(b"flags")), b""))
    except OSError:
        pass
    for p in sorted(_CORE.rglob("*.py")):
        data = p.read_bytes()
        h.update(f"{p.relative_to(_CORE)}:{len(data)}:".encode())
        h.update(hashlib.sha256(data).digest())
        if b"numba" in data:  # numba's own cache stamp of the kernels defined here
            st = p.stat()
            h.update(f":{st.st_mtime_ns}:{st.st_size}".encode())
        h.update(b";")
    return h.hexdigest()


def cached_groups() -> set[str]:
    """The groups the stamp says numba's cache holds for the current sources (empty: no
    stamp, another fingerprint, or a cache file it named is gone)."""
    try:
        stamp = json.loads(_stamp_path().read_text(encoding="utf-8"))
        if stamp.get("fingerprint") != _fingerprint():
            return set()
        have = set(_cache_files())
        return {g for g, files in stamp.get("groups", {}).items() if set(files) <= have}
    except (OSError, ValueError, AttributeError, TypeError):
        return set()


def cache_stamp(groups: list[str], since: str | None = None) -> None:
    """Record that the workers prepared ``groups`` (numba's cache holds them now): the
    fingerprint of the sources and the cache files present, kept with the groups stamped
    before under the same fingerprint. ``since``: the fingerprint when the workers started
    (a source edited meanwhile: nothing is stamped). Best effort: an unwritable place writes
    nothing."""
    path = _stamp_path()
    fp = _fingerprint()
    files = _cache_files()
    if not files or (since is not None and since != fp):
        return
    try:
        old = json.loads(path.read_text(encoding="utf-8"))
        known = old.get("groups", {}) if old.get("fingerprint") == fp else {}
    except (OSError, ValueError, AttributeError):
        known = {}
    known = {g: f for g, f in known.items() if isinstance(f, list)}
    known.update({g: files for g in groups})
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
        tmp.write_text(json.dumps({"fingerprint": fp, "groups": known}), encoding="utf-8")
        os.replace(tmp, path)
    except OSError:
        pass


def prepare_kernels(groups: list[str], *, workers: int | None = None,
                    progress: Callable[[Progress], None] | None = None,
                    interval_s: float = 0.5, stop: threading.Event | None = None,
                    skip_cached: bool = False) -> Prepared:
    """Compile (or load from numba's cache) the kernels of ``groups`` in worker processes
    (:func:`bins`; default: one per core); ``progress`` is called every ``interval_s`` and
    once at the end. Returns what it took (``stop`` set: the workers are ended, and it
    returns at once). ``skip_cached``: no worker when the stamp (:func:`cached_groups`) holds
    every group (the caller then loads the kernels itself, from the cache). A successful
    preparation stamps its groups (:func:`cache_stamp`).

    Raises
    ------
    KernelError
        A worker failed (its error output's end is in the message).
    """
    unknown = sorted(set(groups) - set(GROUPS))
    if unknown:
        raise ValueError(f"unknown kernel groups {unknown}; known: {sorted(GROUPS)}")
    t0 = time.monotonic()
    if skip_cached and set(groups) <= cached_groups():
        return Prepared(time.monotonic() - t0, (), cached=True)
    since = _fingerprint()
    wake = stop or threading.Event()
    running = [_Worker(b) for b in bins(groups, workers or os.cpu_count() or 1)]
    try:
        while True:
            alive = [w.poll() for w in running]
            if stop is not None and stop.is_set():  # e.g. Ctrl-C, which also ends the workers
                return Prepared(time.monotonic() - t0, tuple(w.cpu_s for w in running))
            for w, up in zip(running, alive, strict=True):
                why = None if up else w.failure()
                if why is not None:  # at once: the other workers are ended below
                    raise KernelError(why)
            if not any(alive):
                break
            if progress is not None:
                progress(_progress(running, len(groups), t0))
            wake.wait(interval_s)
    finally:
        for w in running:
            w.stop()
    cache_stamp(groups, since)
    took = time.monotonic() - t0
    if progress is not None:
        progress(Progress(len(groups), len(groups), took, 0.0, (), finished=True))
    return Prepared(took, tuple(round(w.cpu_s, 1) for w in running))


def progress_display(stream: TextIO | None = None, *, quiet_s: float = 2.0,
                     say_done: bool = True) -> Callable[[Progress], None]:
    """A ``progress`` callback for :func:`prepare_kernels`: on a terminal, the moving status
    line (:data:`~diffpos_services.logs.STATUS`) once it took ``quiet_s`` (a cached run, which
    takes about a second, shows nothing), erased at the end; elsewhere one line when it took
    ``quiet_s``; then (``say_done``) one line with the seconds it took."""
    out = stream if stream is not None else sys.stderr
    said = {"start": False}

    def show(p: Progress) -> None:
        if p.elapsed_s < quiet_s and not p.finished:
            return
        tty = out.isatty()
        if p.finished:
            if said["start"] and tty:
                STATUS.show("")
            if said["start"] and say_done:
                print(f"compiled the solver kernels in {p.elapsed_s:.0f} s (cached for later "
                      "runs)", file=out, flush=True)
            return
        if tty:
            STATUS.show(p.line())
        elif not said["start"]:
            print(p.line(), file=out, flush=True)
        said["start"] = True

    return show
