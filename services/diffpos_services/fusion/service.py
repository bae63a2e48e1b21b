"""The fusion process: :class:`~diffpos_services.fusion.core.FusionCore` on a Zenoh session.

Zenoh's callbacks only put raw samples on a bounded queue (:class:`_Inbox`; a full queue
blocks Zenoh, which with congestion control BLOCK pushes back on the anchors instead of
dropping); the main thread drains the queue, decodes, aligns, solves and publishes (no work
on Zenoh's threads). Steps of :func:`run_fusion`: open the session -> declare publishers,
the one subscriber and the liveliness token -> serve (:class:`ServiceLoop`: wait, ingest,
step, publish, diagnostics) until ``stop`` -> flush what is pending and undeclare.

Timing (issue 16 item 2): each turn ingests for at most :data:`INGEST_BUDGET_S`, or
:data:`INGEST_SHARE` times the previous solve step if longer (a backlog of any size never delays
a solve step by more, and ingest keeps up with the input however slow the solve), solves a
number of epochs that adapts to the measured solve cost (:class:`StepCost`: a fixed cost per
step plus a cost per epoch, so a step takes about :data:`SOLVE_BUDGET_S`, or
:data:`BEHIND_BUDGET_S` while ready epochs are left over: fewer, larger steps amortise the
per-call cost of the tracker when the fusion is behind; ingesting and solving alternate every
few ms instead of long ingests followed by huge solves), and stamps each estimate's
``t_pub_wall_ns`` just before it is handed to the bus, after its solve: the published and
diagnosed latency is anchor publish -> fusion publish, solve included. The step's epoch limit
also bounds its track initialisations and snapshot fixes (mnls + tracking,
:func:`diffpos_services.fusion.tracked.heavy_budget`), and the decision record keeps it, so a
replay re-issues the same steps.

Heartbeat and integrity (issue 36): a thread publishes the fusion's heartbeat (progress =
samples ingested + epochs solved, pending = queued samples + epochs waiting; the newest epoch
solved and the estimates published). With a run token (``diffpos emulate`` hands one in the
environment, :func:`diffpos_services.bus.integrity.run_token`) every estimate, diagnostics and
heartbeat carries the fusion's zenoh id and a MAC (:class:`~diffpos_services.bus.integrity.
Signer`): the recorder, the dashboard and emulate tell the run's fusion from a forger by it.
Every anchor message passes :class:`~diffpos_services.bus.integrity.PublisherGuard` on
Zenoh's thread: while two processes publish under one anchor key the anchor's messages are
dropped (counted) and the core is told the anchor is lost, until one publisher remains; the
diagnostics name the contested anchors and count the detections.
"""

from __future__ import annotations

import gc
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgspec
import zenoh

from diffpos._kernels import pool as kernel_pool
from diffpos_services.bus.heartbeat import HeartbeatThread, Progress, process_nonce
from diffpos_services.bus.integrity import PublisherGuard, Signer
from diffpos_services.bus.session import ZenohSettings, open_session
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.core import FusionCore
from diffpos_services.fusion.workers import start_workers
from diffpos_services.heap import keep_heap
from diffpos_services.logs import log_event
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key

__all__ = ["ServiceLoop", "StepCost", "Turn", "freeze_heap", "fusion_subscription",
           "ingest_rest", "run_fusion", "stamp_published"]

_ACCOUNTED_BYTES = 2048  # samples above this size count against max_queued_bytes
#: longest ingest between two solve steps [s]: a backlog never delays a solve by more
INGEST_BUDGET_S = 0.005
#: target duration of one solve step [s] (its epoch limit adapts to the measured cost): about
#: the end-to-end latency goal of an estimate (50 ms, issue 16). An epoch's node-epochs are
#: ready together (the anchors range every node at once); in two steps the second half waits
#: for both plus a second per-call cost, in one step none waits for another step. A step that
#: cannot take them all within the budget (a burst of new tracks) publishes what fits on time
#: and leaves the rest to the next step instead of making every estimate of the epoch late.
#: Measured on `large` live (8 x 50 on 2 cores shared with the anchors, 2-3 runs each): 0.02 s
#: (25 epochs per step): 78-130 of the 8,950 estimates after the first 2 s over 50 ms,
#: 67-106 of the 1,050 before; 0.05 s: 3-11 and 86-130; 0.05 s taking all ready epochs
#: when they exceed the limit by <= 25 %: 0-143 and 190-214 (whole start-up epochs late).
SOLVE_BUDGET_S = 0.05
#: target duration of a solve step while the previous one left ready epochs [s]: the fusion
#: is behind, its latency already large; larger steps pay the per-call costs (the tracker's
#: ~2.6 ms, batch assembly) over more epochs (kept below INGEST_MAX_S)
BEHIND_BUDGET_S = 0.08
#: epochs the first solve step may take (before any cost is measured)
MIN_STEP_EPOCHS = 64
#: epochs a solve step may always take once the cost is measured (a slow estimator, e.g. mnls
#: with the tracker at ~20 ms per fix, still solves in batches)
MIN_MEASURED_STEP_EPOCHS = 8
#: ingest budget of a turn as a multiple of the previous solve step's duration (at least
#: INGEST_BUDGET_S; a turn's ingest stops earlier when the queue is empty, as it usually is):
#: ingest (cheaper per epoch than the solve) keeps up with the input however long the steps
#: get, so an overloaded fusion sees the newest epochs and supersedes the old ones
#: (FusionConfig.max_backlog_s) instead of letting the input queue up unseen (measured: 16 x 200 on a
#: machine at load 12, share 0.5: shed 7,306 node-epochs and still 6-8 s behind)
INGEST_SHARE = 2.0
#: longest ingest of a turn whatever the previous step took [s] (a descheduled step must not
#: let the next turn drain a whole backlog)
INGEST_MAX_S = 0.1
#: estimate publishers declared per loop turn at most (~1 ms each)
DECLARES_PER_TURN = 8
# queue items: (kind, key, value, receive wall time [ns])
_DATA, _ALIVE, _OVERSIZED = 0, 1, 2


class _SeqOnly(msgspec.Struct):
    """The sequence number of an anchor message (the guard's copy check)."""

    seq: int | None = None


_SEQ_DECODER = msgspec.json.Decoder(_SeqOnly)


def _seq_of(payload: bytes) -> int | None:
    try:
        return _SEQ_DECODER.decode(payload).seq
    except (msgspec.DecodeError, msgspec.ValidationError):
        return None


def fusion_subscription(keys: Keys) -> str:
    """The one key expression the fusion subscribes to (:meth:`Keys.fusion_inputs`).

    One subscriber for states, ranges and range batches of every anchor, so each anchor's
    messages reach the fusion's queue in their publish order (with several subscribers an
    anchor's range could be queued before its state of the same instant, and the fusion then
    extrapolated the anchor from its previous state). It never matches ``truth/**`` (tested).
    Keys under ``anchor/`` that are not fusion inputs are counted as ``unexpected_key``.
    """
    (key_expr,) = keys.fusion_inputs()
    return key_expr


class _Inbox:
    """The bounded queue between Zenoh's threads and the fusion's thread.

    Bounded in samples (small ones) and in bytes (large ones, e.g. range batches): a full
    queue blocks Zenoh's thread, which paces BLOCK publishers. A sample over
    ``max_message_bytes`` is never copied nor queued (only its size): bounded memory whatever
    arrives.
    """

    def __init__(self, config: FusionConfig, stop: threading.Event) -> None:
        self.q: queue.Queue = queue.Queue(maxsize=config.queue_size)
        self.stop = stop
        self.max_bytes = config.max_message_bytes
        self.max_queued = config.max_queued_bytes
        self.queued = 0
        self.room = threading.Condition()
        self.log = logging.getLogger("diffpos.fusion")
        self.guard = PublisherGuard()
        self.contested_dropped = 0  # anchor messages dropped while two publishers shared a key
        self.token_alive: dict[str, bool] = {}
        self.keys: Keys | None = None

    def release(self, size: int) -> None:
        with self.room:
            self.queued -= size
            self.room.notify_all()

    def _guarded(self, sample: zenoh.Sample, key: str) -> bool:
        """False if the sample is an anchor message to drop: its anchor is contested (two
        publishers under its key, :class:`PublisherGuard`); a change of that state is queued
        for the core as the anchor lost / alive again, and logged."""
        pk = parse_key(key)
        if pk is None or pk.anchor_id is None:
            return True
        att = sample.attachment
        nonce = att.to_bytes() if att is not None else None
        now = time.time_ns()
        use, event = self.guard.check(pk.anchor_id, nonce,
                                      _seq_of(sample.payload.to_bytes()), now)
        if event is not None and self.keys is not None:
            alive_key = self.keys.alive_anchor(pk.anchor_id)
            if event == "contested":
                log_event(self.log, logging.ERROR, "two publishers under one anchor key: not "
                          "using the anchor until one remains", anchor=pk.anchor_id,
                          publishers=self.guard.publishers(pk.anchor_id))
                self.q.put((_ALIVE, alive_key, False, now))
            else:
                log_event(self.log, logging.WARNING, "one publisher left under the anchor's "
                          "key: using it again", anchor=pk.anchor_id)
                if self.token_alive.get(pk.anchor_id, True):
                    self.q.put((_ALIVE, alive_key, True, now))
        if not use:
            self.contested_dropped += 1
        return use

    def on_data(self, sample: zenoh.Sample) -> None:
        size = len(sample.payload)
        if not self._guarded(sample, str(sample.key_expr)):
            return
        if size > self.max_bytes:
            self.q.put((_OVERSIZED, str(sample.key_expr), size, time.time_ns()))
            return
        if size > _ACCOUNTED_BYTES:
            with self.room:
                while (self.queued > 0 and self.queued + size > self.max_queued
                       and not self.stop.is_set()):
                    self.room.wait(0.1)
                self.queued += size
        self.q.put((_DATA, str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    def on_alive(self, sample: zenoh.Sample) -> None:
        key, alive = str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT
        pk = parse_key(key)
        if pk is not None and pk.anchor_id is not None:
            self.token_alive[pk.anchor_id] = alive
            if not alive:
                self.guard.forget(pk.anchor_id)  # a restarted anchor is not a second one
            elif pk.anchor_id in self.guard.contested():
                return  # not trusted while contested (told when one publisher remains)
        self.q.put((_ALIVE, key, alive, time.time_ns()))


@dataclass
class _Endpoints:
    """What the fusion declared on its session."""

    session: Any
    diag_pub: Any
    subs: list[Any]
    live_sub: Any
    token: Any
    keys: Keys
    est_pubs: dict[str, Any]
    signer: Signer | None = None
    #: (K, N) of ``diffpos fusion --shard K/N`` ((0, 1): one fusion), in every diagnostics
    shard: tuple[int, int] = (0, 1)

    def _att(self, key: str, data: bytes) -> bytes | None:
        return None if self.signer is None else self.signer.attachment(key, data)

    def put_diagnostics(self, diag: Any, inbox: _Inbox) -> None:
        """Publish the core's diagnostics with the process instance, its shard and the
        integrity state (contested anchors, detections), signed."""
        diag = msgspec.structs.replace(
            diag, instance=process_nonce(), duplicate_publishers=inbox.guard.detections(),
            contested_anchors=inbox.guard.contested(), shard=self.shard[0],
            shards=self.shard[1])
        data = M.encode(diag)
        self.diag_pub.put(data, attachment=self._att(self.keys.fusion_diagnostics(), data))

    def _publisher(self, node_id: str) -> Any:
        pub = self.est_pubs[node_id] = self.session.declare_publisher(
            self.keys.node_estimate(node_id),
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        return pub

    def declare_nodes(self, node_ids: Any, limit: int | None = None) -> bool:
        """Declare the estimate publishers of ``node_ids`` not declared yet, at most
        ``limit`` of them (~1 ms each: a few per loop turn when nodes are first ingested, not
        200 in one turn or in their first estimate's publish). True when all are declared."""
        todo = [nid for nid in node_ids if nid not in self.est_pubs]
        for nid in todo[:limit]:
            self._publisher(nid)
        return limit is None or len(todo) <= limit

    def put_estimate(self, est: Any) -> None:
        """Publish one estimate on its node's publisher (a session put while the publisher
        is not declared yet: same key, encoding and congestion control)."""
        pub = self.est_pubs.get(est.node_id)
        key = self.keys.node_estimate(est.node_id)
        data = M.encode(est)
        if pub is None:
            self.session.put(key, data, encoding=zenoh.Encoding.APPLICATION_JSON,
                             congestion_control=zenoh.CongestionControl.BLOCK,
                             attachment=self._att(key, data))
        else:
            pub.put(data, attachment=self._att(key, data))


def _declare(session: Any, keys: Keys, inbox: _Inbox,
             nodes: tuple[str, ...] | None = None) -> _Endpoints:
    """The fusion's publishers, subscribers and, last, its liveliness token: with an
    allow-list of ``nodes`` every node's estimate publisher is declared before it (~1 ms
    each; a run started on the token must not wait for them in its first epochs)."""
    inbox.keys = keys
    diag_pub = session.declare_publisher(
        keys.fusion_diagnostics(),
        encoding=zenoh.Encoding.APPLICATION_JSON,
        congestion_control=zenoh.CongestionControl.BLOCK,
    )
    # ONE subscriber: an anchor's states, ranges and batches keep their publish order
    subs = [session.declare_subscriber(fusion_subscription(keys), inbox.on_data)]
    live_sub = session.liveliness().declare_subscriber(
        keys.alive_anchors(), inbox.on_alive, history=True
    )
    ends = _Endpoints(session, diag_pub, subs, live_sub, None, keys, {},
                      Signer.for_session(session))
    if nodes is not None:
        ends.declare_nodes(nodes)
    ends.token = session.liveliness().declare_token(keys.alive_fusion())
    return ends


def _ingest(core: FusionCore, inbox: _Inbox, item: tuple, log: logging.Logger) -> None:
    """Hand one queued item to the core; a bug (not bad input) is counted and logged once."""
    kind, key, val, rx = item
    try:
        if kind == _DATA:
            if len(val) > _ACCOUNTED_BYTES:
                inbox.release(len(val))
            core.on_sample(key, val, time.time_ns())
        elif kind == _OVERSIZED:
            core.on_oversized(key, val)
        else:
            pk = parse_key(key)
            if pk is not None and pk.anchor_id is not None:
                core.on_liveliness(pk.anchor_id, bool(val), rx)
    except Exception as exc:  # a bug, not bad input: count, log once, go on
        core.rejected["internal_error"] += 1
        if core.rejected["internal_error"] == 1:
            log.exception("internal error while ingesting %s: %s", key, exc)


def _drain(core: FusionCore, inbox: _Inbox, item: tuple | None, linger_s: float,
           log: logging.Logger, until_ns: int) -> int:
    """Ingest ``item`` and what is queued after it until the queue is empty or the
    monotonic clock reaches ``until_ns`` (bounded in time, so a backlog never delays the
    next solve step and the diagnostics by more than the ingest budget). Epoch deadlines
    count from each sample's own ingestion, so neither a backlog nor a long drain releases
    epochs before their queued ranges were seen. Returns the number of items ingested."""
    n = 0
    clock = time.monotonic_ns
    while item is not None:
        _ingest(core, inbox, item, log)
        n += 1
        left_ns = until_ns - clock()
        if left_ns <= 0:
            break
        try:
            item = inbox.q.get_nowait()
        except queue.Empty:
            # linger briefly: an anchor publishes its ranges to all nodes back to back, so
            # waiting ~1 ms batches them into one solve
            try:
                item = inbox.q.get(timeout=min(linger_s, left_ns * 1e-9))
            except queue.Empty:
                item = None
    return n


def _next_item(core: FusionCore, inbox: _Inbox, next_diag: int) -> tuple | None:
    """The next queued item, waiting at most until the next epoch deadline or diagnostics
    (not at all with a solve backlog, at most 0.1 s)."""
    now = time.time_ns()
    dl = core.book.next_deadline_wall_ns()
    wake = min(next_diag, dl if dl is not None else next_diag)
    timeout = 0.0 if core.backlog else min(max((wake - now) * 1e-9, 0.0), 0.1)
    try:
        return inbox.q.get(timeout=timeout)
    except queue.Empty:
        return None


def freeze_heap() -> None:
    """Collect, then move every object alive to the collector's permanent generation
    (``gc.freeze``): after the warm-up the imports, numba dispatchers and caches are hundreds
    of thousands of objects that a full collection would scan again and again, each time in
    the middle of a solve step (measured with bench_fusion_cost.py --schedule: one step took
    89 ms instead of ~20 ms with the collector on, none did with it off). Objects made
    later are collected as before."""
    gc.collect()
    gc.freeze()


def stamp_published(core: FusionCore, estimates: list, put: Callable[[Any], None]) -> None:
    """Publish ``estimates`` with ``put``, each stamped ``t_pub_wall_ns`` = the wall clock
    just before it is handed to the bus (after its solve), and the core's latency record
    rewritten to match: the published and diagnosed latency (anchor publish -> fusion
    publish) includes the solve and the publishing of the estimates before it.

    The core appends one latency per estimate with an input time, in order, stamped with
    the step's start time; those entries are replaced by the after-solve ones.
    """
    lat = core.latencies_ns
    for _ in range(min(sum(e.t_input_wall_ns > 0 for e in estimates), len(lat))):
        lat.pop()
    replace, now = msgspec.structs.replace, time.time_ns
    for est in estimates:
        est = replace(est, t_pub_wall_ns=now())
        put(est)
        core.published += 1
        if est.t_input_wall_ns > 0:
            lat.append(est.t_pub_wall_ns - est.t_input_wall_ns)


def ingest_rest(core: FusionCore, inbox: _Inbox, unsubscribe: Callable[[], Any],
                log: logging.Logger) -> int:
    """At stop: ingest everything queued and everything Zenoh delivers until ``unsubscribe``
    (run on a helper thread: a Zenoh callback blocked on the full queue must be able to
    finish while the subscribers are undeclared) has returned, so nothing received is lost.
    Returns the number of items ingested."""
    done = threading.Event()

    def run() -> None:
        try:
            unsubscribe()
        finally:
            done.set()

    threading.Thread(target=run, name="fusion-unsubscribe", daemon=True).start()
    n = 0
    while True:
        try:
            item = inbox.q.get(timeout=0.01) if not done.is_set() else inbox.q.get_nowait()
        except queue.Empty:
            if done.is_set():
                return n
            continue
        _ingest(core, inbox, item, log)
        n += 1


class StepCost:
    """Duration of a solve step as ``fixed + per_epoch * n`` [ns], fitted by least squares
    over the recent steps (exponential forgetting ``memory``).

    A step's cost has a part per call (the tracker's vectorised update ~2.6 ms with 8 anchors,
    batch assembly) and a part per epoch (~0.6-1 ms): sizing steps by the mean cost per epoch
    (as before) charged the per-call part to every epoch, so steps stayed at the minimum size
    and the per-call part was paid every few epochs. The fit's per-epoch cost is kept within
    [``MIN_SHARE``, 1] of the mean cost per epoch (noise of a loaded machine; equal step sizes
    leave the split unknown: then the mean, i.e. no fixed part).
    """

    MIN_SHARE = 0.2

    def __init__(self, memory: float = 0.95) -> None:
        self.memory = memory
        self._w = self._n = self._t = self._nn = self._nt = 0.0

    def add(self, n: int, t_ns: float) -> None:
        """One solve step of ``n`` > 0 epochs that took ``t_ns``."""
        k = self.memory
        self._w = k * self._w + 1.0
        self._n = k * self._n + n
        self._t = k * self._t + t_ns
        self._nn = k * self._nn + n * n
        self._nt = k * self._nt + n * t_ns

    @property
    def measured(self) -> bool:
        return self._w > 0

    def model(self) -> tuple[float, float]:
        """``(fixed_ns, per_epoch_ns)``."""
        w, n, t = self._w, self._n, self._t
        mean = t / max(n, 1e-9)  # mean cost per epoch
        var = w * self._nn - n * n
        per = (w * self._nt - n * t) / var if var > 1e-6 * max(w * self._nn, 1.0) else mean
        per = min(max(per, self.MIN_SHARE * mean), mean)
        return max((t - per * n) / w, 0.0), max(per, 1.0)

    def epochs_within(self, budget_ns: float) -> int:
        """Epochs a step of about ``budget_ns`` takes (0 if even the fixed part exceeds it)."""
        fixed, per = self.model()
        return max(int((budget_ns - fixed) / per), 0)


@dataclass
class Turn:
    """What one turn of the service loop did (wall and monotonic times [ns])."""

    ingested: int
    published: int
    ingest_ns: int  # time spent ingesting (monotonic)
    budget_ns: int  # the turn's ingest budget
    solve_start_wall_ns: int
    solve_end_wall_ns: int  # the solve step returned (before publishing)


class ServiceLoop:
    """The fusion's main-thread loop without the bus: wait, ingest (bounded in time), solve
    (a number of epochs that adapts to the measured solve cost), publish, diagnostics.

    Parameters
    ----------
    core : FusionCore
    inbox : _Inbox
        The queue Zenoh's callbacks fill.
    put_estimate, put_diagnostics : callable
        Hand one message to the bus (the service: its publishers).
    ingest_budget_s : float [s]
        Longest ingest between two solve steps.
    solve_budget_s : float [s]
        Target duration of one solve step (:data:`BEHIND_BUDGET_S` while the previous step
        left ready epochs): the step's epoch limit is what fits in it by the measured
        :class:`StepCost` (at least :data:`MIN_MEASURED_STEP_EPOCHS`, at most
        ``max_fixes_per_step``; :data:`MIN_STEP_EPOCHS` before any step was measured).
    declare_nodes : callable, optional
        ``declare_nodes(node_ids, limit) -> done``: called after a turn while accepted nodes
        may lack an estimate publisher (the service declares :data:`DECLARES_PER_TURN` per
        turn, before or soon after their first epoch is ready).
    """

    def __init__(self, core: FusionCore, inbox: _Inbox, put_estimate: Callable[[Any], None],
                 put_diagnostics: Callable[[Any], None], log: logging.Logger, *,
                 ingest_budget_s: float = INGEST_BUDGET_S,
                 solve_budget_s: float = SOLVE_BUDGET_S,
                 declare_nodes: Callable[[Any, int], bool] | None = None) -> None:
        self.core, self.inbox, self.log = core, inbox, log
        self.declare_nodes, self._n_nodes, self._declared = declare_nodes, 0, True
        self.put_estimate, self.put_diagnostics = put_estimate, put_diagnostics
        self.ingest_budget_ns = round(ingest_budget_s * 1e9)
        self.solve_budget_ns = round(solve_budget_s * 1e9)
        self.period_ns = round(core.config.diagnostics_period_s * 1e9)
        self.next_diag = time.time_ns() + self.period_ns
        self.cost = StepCost()  # measured duration of a solve step
        self.last_step_ns = 0  # duration of the previous solve step [ns]
        self.done = 0  # samples ingested + estimates solved (the heartbeat's progress)
        self.last_epoch: int | None = None  # newest epoch solved

    def progress(self) -> Progress:
        """The heartbeat's figures (read from the heartbeat thread)."""
        core = self.core
        return Progress(progress=self.done, pending=self.inbox.q.qsize() + core.backlog,
                        last_epoch=self.last_epoch, published=core.published)

    def step_limit(self) -> int | None:
        """Epochs the next solve step may take (adaptive, see the class docstring); None: all
        of them, without a work bound (``FusionConfig.bounded_steps`` False)."""
        if not self.core.config.bounded_steps:
            return None
        top = self.core.config.max_fixes_per_step
        if not self.cost.measured:
            return min(MIN_STEP_EPOCHS, top)
        budget = (max(self.solve_budget_ns, round(BEHIND_BUDGET_S * 1e9)) if self.core.backlog
                  else self.solve_budget_ns)
        return max(min(self.cost.epochs_within(budget), top),
                   min(MIN_MEASURED_STEP_EPOCHS, top))

    def ingest_budget(self) -> int:
        """This turn's ingest budget [ns]: the configured one, or INGEST_SHARE times the
        previous solve step (at most INGEST_MAX_S) if that is longer."""
        return max(self.ingest_budget_ns,
                   min(int(INGEST_SHARE * self.last_step_ns), round(INGEST_MAX_S * 1e9)))

    def turn(self) -> Turn:
        """Wait for input (at most until the next deadline or diagnostics), ingest for at
        most the ingest budget, solve one step, publish, diagnostics when due."""
        core = self.core
        item = _next_item(core, self.inbox, self.next_diag)
        t_in = time.monotonic_ns()
        budget = self.ingest_budget()
        n_in = _drain(core, self.inbox, item, core.config.linger_s, self.log, t_in + budget)
        ingest_ns = time.monotonic_ns() - t_in
        t_solve = time.time_ns()
        early: list = []  # published during the step (core.step's emit)

        def emit(ests: list) -> None:
            stamp_published(core, ests, self.put_estimate)
            early.extend(ests)

        out = core.step(t_solve, limit=self.step_limit(), emit=emit)
        t_done = time.time_ns()
        self.last_step_ns = t_done - t_solve
        if out or early:
            self.cost.add(len(out) + len(early), t_done - t_solve)
        stamp_published(core, out, self.put_estimate)
        self.done += n_in + len(out) + len(early)
        for est in (*early[-1:], *out[-1:]):
            if self.last_epoch is None or est.epoch > self.last_epoch:
                self.last_epoch = est.epoch
        if self.declare_nodes is not None and (
                not self._declared or len(core.node_ids) != self._n_nodes):
            self._n_nodes = len(core.node_ids)
            self._declared = self.declare_nodes(core.node_ids, DECLARES_PER_TURN)
        if t_done >= self.next_diag or core.changed:
            self.put_diagnostics(core.diagnostics(t_done))
            self.next_diag = t_done + self.period_ns
        return Turn(n_in, len(out) + len(early), ingest_ns, budget, t_solve, t_done)


def _serve(core: FusionCore, inbox: _Inbox, ends: _Endpoints, stop: threading.Event,
           log: logging.Logger) -> None:
    """Turns of :class:`ServiceLoop` until ``stop``; then flush what is pending (nothing
    already received is lost) and undeclare."""
    loop = ServiceLoop(core, inbox, ends.put_estimate,
                       lambda d: ends.put_diagnostics(d, inbox), log,
                       declare_nodes=ends.declare_nodes)
    beat = HeartbeatThread(ends.session, ends.keys.heartbeat("fusion"), "fusion", loop.progress,
                           logger=log).start()
    try:
        while not stop.is_set():
            loop.turn()
    finally:
        beat.stop()
        left = ingest_rest(core, inbox, lambda: [s.undeclare() for s in ends.subs], log)
        stamp_published(core, core.flush(time.time_ns()), ends.put_estimate)
        ends.put_diagnostics(core.diagnostics(time.time_ns()), inbox)
        ends.token.undeclare()
        ends.live_sub.undeclare()
        log_event(log, logging.INFO, "ingested the queue at stop", items=left)
        log_event(log, logging.INFO, "fusion stopped", solved=core.solved,
                  published=core.published, rejected=dict(core.rejected),
                  contested_dropped=inbox.contested_dropped,
                  duplicate_publishers=inbox.guard.detections())


def run_fusion(
    config: FusionConfig,
    zenoh_config: Any,
    stop: threading.Event,
    *,
    logger: logging.Logger | None = None,
    on_ready: Callable[[], None] | None = None,
) -> FusionCore:
    """Run the fusion on a Zenoh session until ``stop`` is set.

    ``zenoh_config`` is a :class:`~diffpos_services.bus.session.ZenohSettings` (opened with
    retries until ``stop``) or a ``zenoh.Config``. Returns the core (its counters).
    """
    log = logger or logging.getLogger("diffpos.fusion")
    keep_heap()  # the tracker's temporaries reuse their pages (diffpos_services.heap)
    # the kernels' row pool: threads only (nothing forks); they start on the first split call
    kernel_pool.set_threads(config.kernel_threads)
    rows = None
    try:
        core = FusionCore(config, logger=log)
        rows = start_workers(core, log)  # spawned (fork + exec) before zenoh.open()
        inbox = _Inbox(config, stop)
        core.warm_up()  # while the workers warm up on their own
        if rows is not None:
            log_event(log, logging.INFO, "fusion workers ready", ready=rows.wait_ready(),
                      pids=rows.pids)
        freeze_heap()
        session = open_session(zenoh_config, stop, logger=log) if isinstance(
            zenoh_config, ZenohSettings) else zenoh.open(zenoh_config)
        if session is None:
            return core
        with session:
            # a shard publishes only its own responders' estimates
            mine = None if config.nodes is None else tuple(filter(config.owns, config.nodes))
            ends = _declare(session, core.keys, inbox, mine)
            ends.shard = (config.shard, config.shards)  # replay runs each shard's record
            log_event(log, logging.INFO, "fusion ready", site=config.site,
                      shard=f"{config.shard}/{config.shards}",
                      subscriptions=[fusion_subscription(core.keys)],
                      kernel_threads=config.kernel_threads, workers=config.workers)
            if on_ready is not None:
                on_ready()
            _serve(core, inbox, ends, stop, log)
        return core
    finally:
        if rows is not None:
            rows.close()
            log_event(log, logging.INFO, "fusion workers stopped",
                      failures=dict(rows.failures), calls=dict(rows.calls),
                      speed=round(rows.speed, 3), latency_ms=round(1e3 * rows.latency_s, 2))
        kernel_pool.shutdown()
