"""Row-parallel process pool for the fusion's heavy per-node work (``FusionConfig.workers``).

Why: live, the fusion of the ``16 anchors x 200 nodes x 10 Hz`` soak is one saturated core
(2026-11-27: fusion 0.95 of a core, ~0.6 of the machine's second core idle) and ~79 % of its
CPU is per-node work whose rows are independent bit for bit: the tracker update
(:func:`diffpos.tracking.tracker.update`, 64 %) and the M-NLS snapshot fixes
(:func:`diffpos.estimators.mnls.solver`, 15 %). :class:`RowPool` splits such a call's rows into
contiguous shares balanced by an estimated cost, sends ``workers - 1`` shares to worker
processes (pickled numpy over a :func:`multiprocessing.Pipe`, the arrays of a worker's first
request in flight through a mapped file: :mod:`diffpos_services.fusion.shm`; the process
side is :mod:`diffpos_services.fusion.worker_proc`), computes the first share in the
calling process meanwhile (no idle main) and concatenates the results in row order: the numbers
are those of one call, whatever the number of workers (tests/services/test_fusion_workers.py).

- Processes are started with the ``spawn`` context (fork + exec: nothing of the parent's
  Zenoh session or threads is copied; safe after ``zenoh.open()``); each imports the core,
  warms the numba kernels (:func:`diffpos_services.fusion.warm.warm_model`) and only then says
  ``ready``; :meth:`RowPool.wait_ready` is called before the service declares itself ready.
- A worker dies with the fusion: it asks the kernel for SIGKILL when its parent dies
  (``prctl(PR_SET_PDEATHSIG)``, as :func:`diffpos_services.processes.die_with_parent`) and a closed
  pipe (EOF) ends it too. Linux sends that signal when the *thread* that started the worker
  ends: a pool is started and used by one thread that outlives it (the service's
  ``run_fusion`` thread, replay's caller), a worker restarted by :meth:`RowPool.map_rows`
  belongs to the calling thread.
- A worker that dies, times out or raises loses nothing: its share is computed in the calling
  process, the failure is logged and counted (:attr:`RowPool.failures`); a dead one is restarted
  (at most :data:`MAX_RESTARTS` times each, then the pool runs with fewer workers). A restarted
  worker is used again once it said ``ready`` (polled, never waited for on the hot path).
- Calls cheaper than :data:`MIN_PARALLEL_COST` stay in the calling process (the IPC and the
  per-call cost of the tracker would exceed the gain).
- Each worker runs in a session of its own (``setsid``): Linux's autogroup scheduling shares
  the CPU per session, so in the fusion's session the worker only split the fusion's one
  share on a busy machine (soak, 2026-11-27, before: 36-40k estimates with 2 workers vs
  58-60k with 1; after: on a par, below).

Measured (2026-11-27, 2-core VM; the soak's commands and figures in README.md, "What is still short"):
the split costs ~+2.5 % CPU on the soak's 200-row calls, +35-45 % on 50-row ones
(``benchmarks/bench_workers.py``); the soak with 2 workers vs 1 is in ``bench_soak.py``.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import logging
import math
import multiprocessing as mp
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from diffpos_services.fusion import shm
from diffpos_services.fusion.worker_proc import TASKS, _dumps, worker_main
from diffpos_services.logs import log_event

__all__ = ["INIT_COST", "MIN_PARALLEL_COST", "Pending", "RowPool", "start_workers"]

#: Cost of a row the tracker initialises (UNINITIALISED or LOST with enough ranges: the grid
#: snapshot of :func:`diffpos.tracking.model.snapshot_init`) in units of one row's update: an
#: initialisation costs ~5 ms with 8 anchors, an update ~0.6 ms (tracked.py's measurements):
#: a share of new nodes is balanced against ~8 updates each.
INIT_COST = 8.0
#: Smallest call (in cost units: one per updated row, :data:`INIT_COST` per initialisation,
#: one per M-NLS fix times :data:`MNLS_COST`) split across the workers. Below it a call stays
#: local: ~24 rows of update is ~14 ms of CPU, against ~1 ms of pickling and pipe transfer
#: both ways and the tracker's fixed per-call cost (~2.6 ms) paid once more per share.
MIN_PARALLEL_COST = 24.0
#: Cost of one M-NLS snapshot fix in update units (~3.5 ms vs ~0.6 ms with 8 anchors).
MNLS_COST = 6.0
#: Restarts of one worker slot after it died; after that the pool runs without it.
MAX_RESTARTS = 3
#: Seconds a share may take before its worker is presumed hung (killed, share done locally):
#: a fixed part plus a part per cost unit (an initialisation ~5 ms; 0.1 s per unit is ~20x
#: that, for a loaded machine).
TIMEOUT_BASE_S = 30.0
TIMEOUT_PER_COST_S = 0.1
#: Memory of the measured worker speed (:attr:`RowPool.speed`): weight of the previous value.
SPEED_MEMORY = 0.8
LATENCY_MAX_S = 0.05  #: cap of :attr:`RowPool.latency_s` [s] (beyond +-1 s: clock not shared)


# ------------------------------------------------------------------------ the pool
@dataclasses.dataclass
class _Slot:
    proc: Any = None
    conn: Any = None
    ready: bool = False
    restarts: int = 0
    pid: int | None = None
    shm: Any = None  # the worker's :class:`.shm.Regions` (None: everything through the pipe)
    #: requests sent and not answered yet, oldest first (a worker answers in order)
    pending: collections.deque = dataclasses.field(default_factory=collections.deque)


@dataclasses.dataclass
class Pending:
    """A request to a worker (or done here: ``slot`` None): see :meth:`RowPool.result`."""

    kind: str
    args: tuple
    cost: float  # in update units (the share balancing of later calls counts it)
    units: float = 0.0  # rows of ``kind`` (cost / the kind's unit cost when sent)
    slot: _Slot | None = None
    sent: bool = True  # False: deferred (:meth:`RowPool.submit`), sent with the next call
    done: bool = False
    ok: bool = False
    value: Any = None
    busy_s: float = 0.0
    alone: bool = False  # the worker had nothing else pending when this was sent
    t_done_s: float | None = None  # the worker's perf_counter at the task's end (None: unknown)


class RowPool:
    """``workers - 1`` worker processes plus the calling process (see the module docstring).

    Parameters
    ----------
    workers : int
        Processes sharing a call's rows, the calling one included (1: no process started,
        every call local).
    model : tuple
        (building, radio or None, window_height_m, first_floor_z_m): what the workers warm
        up on; ``building`` is the one every task uses.
    logger : logging.Logger, optional
    """

    def __init__(self, workers: int, model: tuple, *, logger: logging.Logger | None = None
                 ) -> None:
        self.n = max(1, int(workers))
        self.model = model
        self.building = model[0]
        self.log = logger or logging.getLogger("diffpos.fusion")
        self.failures: collections.Counter[str] = collections.Counter()
        #: calls kept local / split; rows sent to workers; where the time goes [s]: the
        #: caller's own share (wall, and its thread's CPU), the caller's thread CPU in split
        #: calls in all (the rest is slicing, pickling, pipes, concatenation), the wait for
        #: the workers after the own share (wall), the workers' task time (wall)
        self.calls: collections.Counter[str] = collections.Counter()
        #: a worker's speed relative to the calling process (share weights), measured: each
        #: split call's (own wall per cost) / (worker task wall per cost), averaged in log
        #: (EWMA :data:`SPEED_MEMORY`), within [1/4, 4]. The caller also ingests, decodes and
        #: publishes, and on a loaded machine its share ran ~1.5x slower than the worker's
        #: (soak, 2026-11-27): equal shares left the worker waiting.
        self.speed = 1.0
        #: a worker's latency [s] beyond its task time (how late its task ends after the
        #: caller's own share started, less the task: request transfer, unpickling, wake-up;
        #: not the reply's pickling and transfer; EWMA, :meth:`_learn_latency`): the shares
        #: are balanced as if each worker had that much work already (live soak: the caller
        #: waited ~5 ms per split call)
        self.latency_s = 0.0
        #: a worker's seconds per row of each kind (EWMA; :meth:`unit_cost`)
        self._unit_s: dict[str, float] = {}
        #: requests submitted and not sent yet (:meth:`submit`)
        self._deferred: list[Pending] = []
        self._ctx = mp.get_context("spawn")
        self._slots = [_Slot() for _ in range(self.n - 1)]
        try:
            for s in self._slots:
                self._start(s)
        except BaseException:  # no pool to close: the ones started would outlive the call
            self.close(0.0)
            raise

    # ---------------------------------------------------------------- processes
    def _start(self, s: _Slot) -> None:
        with contextlib.suppress(OSError, ValueError):
            s.shm = shm.Regions.create()
        parent, child = self._ctx.Pipe(duplex=True)
        try:
            proc = self._ctx.Process(
                target=worker_main, args=(child, os.getpid(), self.model,
                                          None if s.shm is None else shm.PassFd(s.shm.fd)),
                name="diffpos-fusion-worker", daemon=True)
            proc.start()
        except BaseException:
            self._drop_shm(s)
            raise
        if s.shm is not None:
            s.shm.close_fd()  # the worker has its copy (passed at its start)
        child.close()
        s.proc, s.conn, s.ready, s.pid = proc, parent, False, proc.pid

    @staticmethod
    def _drop_shm(s: _Slot) -> None:
        if s.shm is not None:
            with contextlib.suppress(Exception):
                s.shm.close()
            s.shm = None

    def _poll_ready(self, s: _Slot, timeout_s: float = 0.0) -> None:
        if s.ready or s.conn is None:
            return
        try:
            if s.conn.poll(timeout_s):
                msg = s.conn.recv()
                s.ready = msg[0] == "ready"
                if s.shm is not None and not (s.ready and len(msg) > 2 and msg[2]):
                    self._drop_shm(s)  # the worker did not map it: its pipe only
        except (EOFError, OSError):
            self._failed(s, "died")

    def wait_ready(self, timeout_s: float = 300.0) -> int:
        """Wait until every worker warmed up (at most ``timeout_s`` [s] in all; a worker
        still starting is used once ready). Returns the number of ready workers."""
        deadline = time.monotonic() + timeout_s
        for s in self._slots:
            self._poll_ready(s, max(deadline - time.monotonic(), 0.0))
        return sum(s.ready for s in self._slots)

    @property
    def pids(self) -> list[int]:
        """Process ids of the live worker processes."""
        return [s.pid for s in self._slots if s.conn is not None and s.pid is not None]

    def _failed(self, s: _Slot, why: str, detail: str = "") -> None:
        """Count and log a failure; a dead or hung worker is killed and restarted (or
        dropped after :data:`MAX_RESTARTS`); one that raised stays."""
        self.failures[why] += 1
        log_event(self.log, logging.WARNING, "fusion worker failed: its share computed locally",
                  why=why, pid=s.pid, failures=dict(self.failures), detail=detail[-2000:])
        if why == "error":
            return
        self._kill(s)
        if s.restarts < MAX_RESTARTS:
            s.restarts += 1
            self._start(s)
        else:
            log_event(self.log, logging.WARNING, "fusion worker dropped after restarts",
                      restarts=s.restarts, workers_left=1 + len(self.pids))

    def _kill(self, s: _Slot) -> None:
        while s.pending:  # their shares are computed by the caller
            s.pending.popleft().done = True
        if s.proc is not None:
            with contextlib.suppress(Exception):
                s.proc.kill()
                s.proc.join(5.0)
                s.proc.close()  # its sentinel descriptor now, not when collected
        if s.conn is not None:
            with contextlib.suppress(Exception):
                s.conn.close()
        s.proc = s.conn = s.pid = None
        s.ready = False
        self._drop_shm(s)

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the workers: ``stop``, join with one shared ``timeout_s`` [s], then kill."""
        for s in self._slots:
            if s.conn is not None:
                with contextlib.suppress(Exception):
                    s.conn.send(("stop", ()))
        deadline = time.monotonic() + timeout_s
        for s in self._slots:
            if s.proc is not None:
                s.proc.join(max(deadline - time.monotonic(), 0.05))
            self._kill(s)

    def __enter__(self) -> RowPool:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # ---------------------------------------------------------------- calls
    def _run_here(self, kind: str, local: Callable[..., Any] | None, args: tuple,
                  shared: tuple) -> Any:
        return (local(*args, *shared) if local is not None
                else TASKS[kind](self.model, *args, *shared))

    def _send(self, s: _Slot, kind: str, args: tuple, cost: float, units: float) -> Pending:
        """Send ``(kind, args)`` to ``s``; a send that fails gives a failed (done) request."""
        return self._dispatch(s, Pending(kind, args, cost, units))

    def _dispatch(self, s: _Slot, p: Pending) -> Pending:
        p.slot, p.sent = s, True
        p.alone = not s.pending
        try:  # an argument that cannot be pickled: nothing sent, the worker stays
            # through the worker's request region when it is free (nothing pending), with
            # the reply in its reply region (:mod:`.shm`); else through the pipe
            ref = (shm.pack(s.shm.request, p.args, reply=True)
                   if s.shm is not None and p.alone else None)
            payload = _dumps((p.kind, p.args if ref is None else ref))
            self.calls["via_shm"] += ref is not None
        except Exception as exc:
            self._failed(s, "error", f"request not pickled: {exc!r}")
            p.done = True
            return p
        try:
            s.conn.send_bytes(payload)
            s.pending.append(p)
        except (OSError, ValueError) as exc:
            self._failed(s, "died", repr(exc))
            p.done = True
        return p

    def unit_cost(self, kind: str) -> float:
        """Cost of one row of ``kind`` in update units: ``update`` 1, ``mnls`` measured
        (the workers' task time per M-NLS row over that per update unit; :data:`MNLS_COST`
        until both were seen: with 16 anchors a snapshot fix costs ~15 updates, with 8 ~6)."""
        if kind != "mnls":
            return 1.0
        u, m = self._unit_s.get("update"), self._unit_s.get("mnls")
        return MNLS_COST if u is None or m is None or u <= 0 else min(max(m / u, 1.0), 100.0)

    def submit(self, kind: str, args: tuple, n_units: float,
               local: Callable[..., Any] | None = None, *, shared: tuple = ()) -> Pending:
        """``TASKS[kind](model, *args, *shared)`` on a worker, not waited for
        (:meth:`result`), or here at once without a ready worker; ``n_units``: its size in
        rows of ``kind``. Deferred: sent by the next :meth:`map_rows` after its shares, to
        the least loaded worker, whose share it shrinks (or by :meth:`result`)."""
        for s in self._slots:
            self._poll_ready(s)
        ready = [s for s in self._slots if s.ready]
        if not ready:
            self.calls["local"] += 1
            return Pending(kind, args, 0.0, done=True, ok=True,
                           value=self._run_here(kind, local, args, shared))
        self.calls["submitted"] += 1
        p = Pending(kind, (*args, *shared), n_units * self.unit_cost(kind), n_units, sent=False)
        self._deferred.append(p)
        return p

    def _flush(self, ready: list[_Slot]) -> None:
        """Send the deferred requests to the least loaded of ``ready`` (none ready: they
        fail, computed by the caller when collected)."""
        todo, self._deferred = self._deferred, []
        if not todo:
            return
        if not ready:
            for p in todo:
                p.done = True
            return
        s = min(ready, key=lambda x: sum(q.cost for q in x.pending))
        for p in todo:
            self._dispatch(s, p)

    def result(self, p: Pending, local: Callable[..., Any] | None = None, *,
               shared: tuple = ()) -> Any:
        """The value of a :meth:`submit`; computed here (same numbers) if its worker
        failed."""
        if not p.sent:
            for s in self._slots:
                self._poll_ready(s)
            self._flush([s for s in self._slots if s.ready])
        self._wait(p)
        if p.ok:
            return p.value
        args = p.args[:len(p.args) - len(shared)] if shared else p.args
        return self._run_here(p.kind, local, args, shared)

    def map_rows(self, kind: str, args: tuple, cost: np.ndarray,
                 local: Callable[..., Any] | None = None, *, shared: tuple = ()) -> Any:
        """``TASKS[kind](model, *rows of args, *shared)`` split over the ready workers by
        ``cost`` (one value per row; a worker's requests still pending count as cost it
        already has): ``args`` are arrays / dataclasses of arrays with the rows on axis 0
        (:func:`take_rows`), ``shared`` is passed whole; ``local(*args, *shared)`` computes a
        share here (default: the task itself). Returns the result of one call on all rows
        (the shares' results concatenated in row order)."""
        for s in self._slots:
            self._poll_ready(s)
        ready = [s for s in self._slots if s.ready]
        cost = np.asarray(cost, dtype=np.float64)
        if not ready or cost.size == 0 or float(cost.sum()) < MIN_PARALLEL_COST:
            self._flush(ready)  # an idle worker: small requests, sent without blocking
            self.calls["local"] += 1
            return self._run_here(kind, local, args, shared)
        self.calls["split"] += 1
        # here, not at the top: ``rows`` imports the tracker, which a process that imports
        # this module without running mnls (the D-NLS fusion service) never loads
        from diffpos_services.fusion.rows import concat_rows, preloaded_bounds, take_rows

        c0 = time.thread_time()
        preload = [sum(q.cost for q in s.pending) for s in ready]
        if self._deferred:  # they go after the shares to the least loaded worker
            k = int(np.argmin(preload))
            preload[k] += sum(p.cost for p in self._deferred)
            ready = [ready[k], *ready[:k], *ready[k + 1:]]
            preload = [preload[k], *preload[:k], *preload[k + 1:]]
        lat = self.latency_cost()
        shares = preloaded_bounds(cost, [1.0] + [self.speed] * len(ready),
                                  [0.0, *(x + lat for x in preload)])
        if not any(preload) and all(sl.stop == sl.start for sl in shares[1:]):
            self._forget()  # idle workers left out by what was learned: measure them again
        unit = self.unit_cost(kind)
        # the shares first: a big message to a worker busy with an earlier request would
        # block this process in send() until the worker reads it
        sent = [(self._send(s, kind, (*take_rows(args, sl), *shared), float(cost[sl].sum()),
                            float(cost[sl].sum()) / unit)
                 if sl.stop > sl.start else None, sl)
                for s, sl in zip(ready, shares[1:], strict=True)]
        self._flush(ready[:1])
        parts: list[Any] = []
        t0, c1 = time.perf_counter(), time.thread_time()
        try:
            if shares[0].stop > shares[0].start:
                parts.append(self._run_here(kind, local, take_rows(args, shares[0]), shared))
        finally:  # even if the local share raises: no reply is left in a pipe
            t1, c2 = time.perf_counter(), time.thread_time()
            for p, _ in sent:
                if p is not None:
                    self._wait(p)
            done = [p for p, _ in sent if p is not None and p.ok]
            self._account(t1 - t0, c2 - c1, time.perf_counter() - t1, [p.busy_s for p in done])
            self._learn_latency(t0, done)
            self.calls["rows_sent"] += sum(sl.stop - sl.start for p, sl in sent if p)
        if shares[0].stop > shares[0].start:
            self._learn(t1 - t0, float(cost[shares[0]].sum()), [p.busy_s for p in done],
                        [p.cost for p in done])
        for p, sl in sent:
            if p is None:
                continue
            # the worker failed: its share here, same numbers
            parts.append(p.value if p.ok else self._run_here(kind, local,
                                                             take_rows(args, sl), shared))
        out = concat_rows(parts)
        self.calls["caller_cpu_s"] += time.thread_time() - c0
        return out

    def _account(self, own_s: float, own_cpu_s: float, wait_s: float, busy: list[float]) -> None:
        self.calls["own_share_s"] += own_s
        self.calls["own_cpu_s"] += own_cpu_s
        self.calls["wait_s"] += wait_s
        self.calls["worker_busy_s"] += sum(busy)

    def _learn(self, own_s: float, own_cost: float, busy: list[float], costs: list[float]
               ) -> None:
        """Update :attr:`speed` from one split call (workers that failed: skipped)."""
        rates = [c / b for b, c in zip(busy, costs, strict=True) if b > 0 and c > 0]
        if not rates or own_s <= 0 or own_cost <= 0:
            return
        ratio = float(np.mean(rates)) / (own_cost / own_s)
        log_speed = (SPEED_MEMORY * math.log(self.speed)
                     + (1 - SPEED_MEMORY) * math.log(min(max(ratio, 0.25), 4.0)))
        self.speed = math.exp(log_speed)

    def _forget(self) -> None:
        """Move :attr:`speed` and :attr:`latency_s` one EWMA step (:data:`SPEED_MEMORY`)
        towards their priors (1 and 0 s). Called by a split call that gave idle workers (no
        request pending or deferred) no rows: both are learned only from shares, so without
        this one bad sample kept a worker out for good (2026-11-28 04:18 UTC, ``python
        benchmarks/bench_soak.py --load 16x200 --duration 60 --warmup 10 --method mnls
        --workers 2 --log-dir D``, the fusion log's ``fusion workers stopped`` counters: one 30
        ms latency sample at the start, then 29 rows sent to the worker in 1,111 split calls,
        the fusion's process alone at 0.72 of a core). A worker that is
        really slow or late is measured so again by the share it then gets: a share every
        few calls, sized by the regressed estimates."""
        self.latency_s *= SPEED_MEMORY
        self.speed = math.exp(SPEED_MEMORY * math.log(self.speed))
        self.calls["forgot"] += 1

    def latency_cost(self) -> float:  # latency_s in update rows of a worker (0: unknown)
        u = self._unit_s.get("update")
        return self.latency_s / u if u is not None and u > 0 else 0.0

    def _learn_latency(self, t0: float, done: list[Pending]) -> None:
        """:attr:`latency_s` (EWMA :data:`SPEED_MEMORY`) from the shares of a split call
        whose worker had nothing else to do first: the task's end (the worker's clock) -
        ``t0`` (the caller's own share's start) - its time, within [0, LATENCY_MAX_S]."""
        for p in done:
            if not p.alone or p.t_done_s is None:
                continue
            lat = p.t_done_s - t0 - p.busy_s
            if abs(lat) > 1.0:
                continue
            lat = min(max(lat, 0.0), LATENCY_MAX_S)
            self.latency_s = SPEED_MEMORY * self.latency_s + (1 - SPEED_MEMORY) * lat
            self.calls["latency_n"] += 1
            self.calls["latency_s"] += lat

    def _wait(self, p: Pending) -> None:
        """Receive the replies of ``p``'s worker in order until ``p``'s (each one stored in
        its request); a worker that dies or times out fails every request it holds."""
        s = p.slot
        while not p.done:
            head = s.pending[0]
            try:
                if not s.conn.poll(TIMEOUT_BASE_S + TIMEOUT_PER_COST_S * head.cost):
                    self._failed(s, "timeout", f"{head.kind}, cost {head.cost:.0f}")
                    continue
                tag, value, busy_s, *stamp = s.conn.recv()
                if isinstance(value, shm.ShmRef):
                    value = shm.unpack(s.shm.reply, value)
            except (EOFError, OSError) as exc:
                self._failed(s, "died", repr(exc))
                continue
            except Exception as exc:  # read but not decoded: the pipe is still in step
                s.pending.popleft().done = True
                self._failed(s, "error", f"reply not unpickled: {exc!r}")
                continue
            s.pending.popleft()
            head.done, head.ok, head.busy_s = True, tag == "ok", busy_s
            head.t_done_s = stamp[0] if stamp else None
            if head.ok:
                head.value = value
                if busy_s > 0 and head.units > 0:  # the worker's seconds per row of the kind
                    old = self._unit_s.get(head.kind)
                    new = busy_s / head.units
                    self._unit_s[head.kind] = new if old is None else (
                        SPEED_MEMORY * old + (1 - SPEED_MEMORY) * new)
            else:
                self._failed(s, "error", str(value))


def start_workers(core: Any, log: logging.Logger | None = None, *,
                  max_processes: int | None = None) -> RowPool | None:
    """The pool of ``core.config.workers`` (> 1; mnls + tracking; at most ``max_processes``,
    e.g. a replay on a machine with fewer cores than the recording's: the estimates are the
    same for any count) for a :class:`FusionCore
    <diffpos_services.fusion.core.FusionCore>`, attached to its tracker bank (not waited
    for: :meth:`RowPool.wait_ready`), or None (1 worker, or no tracker)."""
    n = core.config.workers if max_processes is None else min(core.config.workers,
                                                               max(int(max_processes), 1))
    if n <= 1 or core.bank is None:
        return None
    cfg = core.config
    rows = RowPool(n, (core.building, core.model[1], cfg.window_height_m,
                                 cfg.first_floor_z_m), logger=log or core.log)
    core.bank.pool = rows
    return rows
