"""Row chunks of the compiled kernels on a small shared thread pool.

The heavy numba kernels (``channel_nb.channel_snr_kernel``, ``mnls_nb.lm_kernel``,
``tracking_nb.all_paths_kernel``, ``grid_nb.grid_cost_kernel``) loop over independent
rows (nodes, hypotheses, starts) and are compiled with ``nogil=True``: their Python wrappers
call :func:`run_rows` with a function that runs the kernel on the rows ``[lo, hi)`` (slices of
the row axis of every per-row input and output, C-contiguous like the whole arrays, so the
same compiled signature). Each row's arithmetic is that of the one-thread call and no output
is shared between rows, so every output is bit-identical whatever the thread count
(tests/core/test_kernel_threads.py).

The worker count is set once by the caller (:func:`set_threads`; the fusion service, replay
and the benchmarks from ``FusionConfig.kernel_threads``); it is 1 in the pure core until set,
and then every call runs on the calling thread as before. With ``n`` threads a call of at
least ``2 * min_rows`` rows is cut into up to ``CHUNKS_PER_THREAD * n`` chunks of at least
``min_rows`` rows; the calling thread and ``n - 1`` pool threads take chunks in turn until none
is left (so one slow chunk does not leave the other thread idle), and the caller then cancels
the helpers that have not started. Smaller calls stay on the calling thread: a split call of
two empty chunks costs ~10 us wall on the 2-core VM (benchmarks/bench_kernel_threads.py), a
waking thread more, and on a loaded machine a helper thread may wait for a core, so each
wrapper's ``min_rows`` is about 0.3-0.5 ms of its kernel's work. When the helpers have no
free core (a loaded machine: the caller finishes its chunks and then waits for a helper's),
splitting only adds hand-offs: after split calls whose caller waited more than
:data:`BACKOFF_WAIT_SHARE` of their wall time, the next :data:`BACKOFF_CALLS` calls stay on the
calling thread (:func:`_watch`; the outputs are the same either way).

The pool (a :class:`concurrent.futures.ThreadPoolExecutor`) is created lazily on the first
call that splits, and shut down by :func:`shutdown` (the fusion service at its end) or at
interpreter exit. A split call that finds the pool shut down (another thread's
:func:`shutdown` or :func:`set_threads` between its look-up and its hand-off, or a call during
interpreter exit) runs its chunks on the calling thread (counted in :func:`stats`). Threads
only: nothing here forks.
"""

from __future__ import annotations

import atexit
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

__all__ = ["CHUNKS_PER_THREAD", "GRID_MIN_CELL_LINKS", "LM_MIN_ROWS", "PATHS_MIN_LINKS",
           "SNR_MIN_PAIRS", "reset_stats", "run_rows", "set_threads", "shutdown", "stats",
           "threads"]

#: Chunks per thread of a call that is split (more than one: a chunk of slow rows, e.g. the
#: M-NLS starts still iterating, does not hold up the call while the other thread idles).
CHUNKS_PER_THREAD = 4

_lock = threading.Lock()
_state: dict[str, object] = {"threads": 1, "executor": None}
_STAT_KEYS = ("calls", "split_calls", "chunk_cpu_s", "critical_cpu_s", "backoffs", "refused")
#: Back-off: when the caller of a split call waited for the helpers more than this share of
#: the call's wall time (averaged over the recent split calls), the next
#: :data:`BACKOFF_CALLS` calls run on the calling thread: the helpers had no free core
#: (a loaded machine), where splitting only adds hand-offs. Outputs are the same either way.
BACKOFF_WAIT_SHARE = 0.25
BACKOFF_CALLS = 200
_guard = {"wait_share": 0.0, "skip": 0}
_stats: dict[str, float] = dict.fromkeys(_STAT_KEYS, 0.0)


def set_threads(n: int) -> None:
    """Use ``n`` >= 1 threads (the caller's included) for the kernels' rows from now on.
    A different count than before shuts the current pool down (a new one is made lazily)."""
    n = int(n)
    if n < 1:
        raise ValueError(f"kernel threads must be >= 1; got {n}")
    with _lock:
        _guard.update(wait_share=0.0, skip=0)
        if n == _state["threads"]:
            return
        old, _state["executor"] = _state["executor"], None
        _state["threads"] = n
    if old is not None:
        old.shutdown(wait=True)


def threads() -> int:
    """The thread count of :func:`set_threads` (1 until set)."""
    return int(_state["threads"])  # type: ignore[call-overload]


def shutdown() -> None:
    """Stop the pool's threads (idempotent; a later split call makes a new pool)."""
    with _lock:
        old, _state["executor"] = _state["executor"], None
    if old is not None:
        old.shutdown(wait=True)


atexit.register(shutdown)


def stats() -> dict[str, float]:
    """Counters since :func:`reset_stats`: ``calls`` of :func:`run_rows`, ``split_calls``,
    ``chunk_cpu_s`` (the CPU of every chunk on every thread) and ``critical_cpu_s`` (per call,
    the CPU of the busiest thread's chunks: with a free core per thread, the call's wall time
    is about this; a whole run's wall is then its process CPU - ``chunk_cpu_s`` +
    ``critical_cpu_s``, the "free-core wall" of bench_fusion_cost ``--threads``), ``backoffs``
    (:func:`_watch`) and ``refused`` (split calls whose helpers the pool refused, shut down
    meanwhile: their chunks ran on the calling thread)."""
    return dict(_stats)


def reset_stats() -> None:
    """Zero the :func:`stats` counters."""
    _stats.update(dict.fromkeys(_STAT_KEYS, 0.0))


def _count(total_s: float, critical_s: float, split: bool) -> None:
    with _lock:
        _stats["calls"] += 1
        _stats["split_calls"] += split
        _stats["chunk_cpu_s"] += total_s
        _stats["critical_cpu_s"] += critical_s


def _executor(n_workers: int) -> ThreadPoolExecutor:
    with _lock:
        ex = _state["executor"]
        if ex is None:
            ex = ThreadPoolExecutor(max_workers=n_workers, thread_name_prefix="diffpos-kernel")
            _state["executor"] = ex
        return ex  # type: ignore[return-value]


def _bounds(n_rows: int, n_chunks: int) -> list[tuple[int, int]]:
    """``n_chunks`` contiguous row ranges covering ``[0, n_rows)``, sizes differing by <= 1."""
    q, r = divmod(n_rows, n_chunks)
    out, lo = [], 0
    for c in range(n_chunks):
        hi = lo + q + (1 if c < r else 0)
        out.append((lo, hi))
        lo = hi
    return out


def run_rows(fn: Callable[[int, int], None], n_rows: int, *, min_rows: int = 1) -> float:
    """Call ``fn(lo, hi)`` on row ranges covering ``[0, n_rows)`` exactly once each.

    ``fn`` must write only rows ``[lo, hi)`` of its outputs and read no output row of another
    range (the kernels' rows are independent). On one thread, or when ``n_rows < 2 *
    min_rows``, this is ``fn(0, n_rows)`` on the calling thread. Returns the CPU seconds the
    chunks took on their threads (``time.thread_time``), for the callers' cost counters. The
    first exception of a chunk is raised once every started chunk has ended. A pool shut
    down meanwhile takes no chunk: the calling thread runs them all.
    """
    n_thr = threads()
    min_rows = max(int(min_rows), 1)
    backing_off = _guard["skip"] > 0
    if n_thr <= 1 or n_rows < 2 * min_rows or backing_off:
        if backing_off and n_thr > 1 and n_rows >= 2 * min_rows:
            _guard["skip"] -= 1
        c0 = time.thread_time()
        fn(0, n_rows)
        dt = time.thread_time() - c0
        _count(dt, dt, False)
        return dt
    n_chunks = min(CHUNKS_PER_THREAD * n_thr, n_rows // min_rows)
    chunks = _bounds(n_rows, n_chunks)
    take = threading.Lock()
    nxt = [0]
    cpu: list[float] = []  # per thread

    def drain() -> None:
        c0 = time.thread_time()
        try:
            while True:
                with take:
                    c = nxt[0]
                    if c >= n_chunks:
                        return
                    nxt[0] = c + 1
                fn(*chunks[c])
        finally:
            dt = time.thread_time() - c0
            with take:
                cpu.append(dt)

    t0 = time.perf_counter()
    helpers = []
    try:
        ex = _executor(n_thr - 1)
        for _ in range(min(n_thr - 1, n_chunks - 1)):
            helpers.append(ex.submit(drain))
    except RuntimeError:  # the pool was shut down meanwhile (another thread's shutdown or
        with _lock:  # set_threads, or the interpreter exiting): the caller drains every
            _stats["refused"] += 1  # chunk left itself (the same outputs)
    error: BaseException | None = None
    try:
        drain()
    except BaseException as exc:  # re-raised below, after the helpers ended
        error = exc
        with take:
            nxt[0] = n_chunks  # the helpers take no further chunk
    t1 = time.perf_counter()
    for f in helpers:
        if f.cancel():  # not started: the caller did its chunks
            continue
        try:
            f.result()
        except BaseException as exc:
            error = error or exc
    if error is not None:
        raise error
    _count(sum(cpu), max(cpu), True)
    _watch(time.perf_counter() - t1, time.perf_counter() - t0)
    return sum(cpu)


def _watch(wait_s: float, call_s: float) -> None:
    """The back-off rule (:data:`BACKOFF_WAIT_SHARE`): the caller's wait for its helpers
    after its own chunks, as a share of the split call's wall time, averaged over ~10 calls."""
    share = _guard["wait_share"] = 0.9 * _guard["wait_share"] + 0.1 * (
        wait_s / call_s if call_s > 0 else 0.0)
    if share > BACKOFF_WAIT_SHARE:
        _guard["skip"], _guard["wait_share"] = BACKOFF_CALLS, 0.0
        _stats["backoffs"] += 1


# ---- the wrappers' thresholds: a chunk of at least ~0.3-0.5 ms of kernel work (one thread's
# cost per unit from benchmarks/bench_kernel_threads.py, 2026-11-27, 16 anchors; a split call
# costs ~10 us wall more than a direct one with the pool's threads up). A call below twice
# the threshold stays on the calling thread.
#: ``channel_nb.eval_snr_kernel``: node-anchor pairs (18 slots each, ~2-4 us per pair).
SNR_MIN_PAIRS = 128
#: ``mnls._lm_compiled``: rows (starts) of ``mnls_nb.lm_kernel`` per chunk (~20-60 us each).
LM_MIN_ROWS = 8
#: ``tracking_paths.all_paths``: (hypothesis, anchor) links of ``all_paths_kernel`` (18 slots,
#: ~0.5-1 us per link).
PATHS_MIN_LINKS = 512
#: ``tracking_init.grid_starts``: (floor, cell, anchor) evaluations of ``grid_cost_kernel``
#: (~30 ns each; one node on one floor is ~3,600 cells x its anchors).
GRID_MIN_CELL_LINKS = 16384
