"""Replay by the live fusion's decision record (issue 15 item 3): the same calls, same order.

The live fusion hands out its decision record with every diagnostics message
(``FusionDiagnostics.decisions``, see ``diffpos_services.fusion.decisions``): the samples in
the order it ingested them (key + CRC-32 of the payload, and the receive wall time it was
given), the anchors' liveliness events it saw, and the wall times of the steps that solved
something. :class:`DecisionReplayer` re-issues exactly these calls on a fresh fusion core
with the recorded payloads: the recorder's receive order (which differs from the fusion's
under load) no longer matters, so the replayed fixes are those of the live run, bit for bit.

Matching: each recorded fusion input waits in a pool keyed by (topic, CRC-32) until the
record names it (the record is published up to a diagnostics period after the samples; under
load later). A sample the record names but the recording lacks (the recorder dropped it) is
waited for ``window_ns`` of recording time, then skipped and counted (``samples_missing``:
the replay can then differ from the live run). Inputs the live fusion never ingested leave
the pool after ``window_ns`` (``inputs_not_ingested``). Memory is bounded by the window.
"""

from __future__ import annotations

import collections
import zlib
from collections.abc import Callable
from typing import Any

from diffpos_services.wire import messages as M

__all__ = ["DecisionReplayer"]

OP_SAMPLE, OP_OVERSIZED, OP_ALIVE, OP_LOST, OP_STEP, OP_FLUSH = M.DECISION_OPS
_FOREVER = 2**62


class DecisionReplayer:
    """Feeds a fusion core the live fusion's recorded calls.

    Parameters
    ----------
    core : FusionCore
        A fresh core with the live settings (``record_decisions=False``).
    emit : callable
        ``emit(estimates, now_wall_ns)`` for the estimates of every step and the flush.
    window_ns : int [ns]
        How long (recording time) a named sample is waited for and an unnamed input kept.
    """

    def __init__(self, core: Any, emit: Callable[[list, int], None], *,
                 window_ns: int = 30_000_000_000) -> None:
        self.core = core
        self.emit = emit
        self.window_ns = int(window_ns)
        self._pool: dict[tuple[str, int], collections.deque[bytes]] = {}
        self._arrivals: collections.deque[tuple[int, tuple[str, int]]] = collections.deque()
        # events: (op, key, value, wall_ns, log_ns of the chunk that named it)
        self._events: collections.deque[tuple[int, str, int, int, int]] = collections.deque()
        self._next_chunk = 0
        self.counts: collections.Counter[str] = collections.Counter()
        # the sample the record waits for (key, named at log_ns): inputs of other keys only
        # join the pool until it comes (nothing else can be issued before it)
        self._blocked: tuple[str, int] | None = None
        self._blocked_named_ns = 0

    # ------------------------------------------------------------------ input
    def add_input(self, topic: str, data: bytes, log_ns: int) -> None:
        """A recorded fusion input (anchor state, range, range batch)."""
        k = (topic, zlib.crc32(data))
        q = self._pool.get(k)
        if q is None:
            q = self._pool[k] = collections.deque()
        q.append(data)
        arrivals = self._arrivals
        arrivals.append((log_ns, k))
        horizon = log_ns - self.window_ns
        if arrivals[0][0] >= horizon and (not self._events or (
                self._blocked is not None and k != self._blocked
                and self._blocked_named_ns >= horizon)):
            return  # nothing to issue (or still waiting for another sample), nothing expires
        self._run(log_ns)

    def add_chunk(self, chunk: M.DecisionChunk, log_ns: int) -> None:
        """A recorded decision chunk (in recording order; a gap in the numbering is counted
        in ``chunks_missing``)."""
        c = self.counts
        if chunk.chunk > self._next_chunk:
            c["chunks_missing"] += chunk.chunk - self._next_chunk
        if chunk.chunk < self._next_chunk and chunk.ops:
            c["chunks_repeated"] += 1
            return
        if chunk.ops or chunk.dropped:
            self._next_chunk = chunk.chunk + 1
        c["chunks"] += 1
        c["events_not_recorded"] += chunk.dropped
        wall = 0
        keys, ev = chunk.keys, self._events
        for op, ref, val, dw in zip(chunk.ops, chunk.refs, chunk.values, chunk.wall_delta_ns,
                                    strict=True):
            wall += dw
            ev.append((op, keys[ref], val, wall, log_ns))
        self._run(log_ns)

    def restart(self, core: Any, now_log_ns: int) -> None:
        """The live fusion restarted (a new instance, whose record begins at chunk 0): the old
        instance's remaining calls are issued now (a sample it names that is not here by now
        was never recorded before it died: skipped, counted in ``samples_missing``), then
        ``core`` (a fresh one, as the restarted fusion starts afresh) takes the new record.
        Inputs not ingested yet stay in the pool: the new instance may name them."""
        self._run(now_log_ns, wait=False)
        self.core = core
        self._next_chunk = 0
        self._blocked = None
        self.counts["restarts"] += 1

    def finish(self) -> None:
        """End of the recording: what the record names and never came is skipped."""
        self._run(_FOREVER)
        self.counts["inputs_not_ingested"] += sum(len(q) for q in self._pool.values())
        self._pool.clear()
        self._arrivals.clear()

    # ------------------------------------------------------------------ the calls
    def _run(self, now_log_ns: int, *, wait: bool = True) -> None:
        """Issue the recorded calls whose samples are here (in order: a missing one blocks
        the rest until it comes or its wait expires; ``wait=False``: skipped at once), then
        forget stale inputs."""
        ev, pool, core, c = self._events, self._pool, self.core, self.counts
        self._blocked = None
        while ev:
            op, key, val, wall, named_ns = ev[0]
            if op == OP_SAMPLE:
                q = pool.get((key, val))
                if not q:
                    if wait and now_log_ns - named_ns <= self.window_ns:
                        self._blocked, self._blocked_named_ns = (key, val), named_ns
                        break
                    c["samples_missing"] += 1
                    ev.popleft()
                    continue
                data = q.popleft()
                if not q:
                    del pool[(key, val)]
                core.on_sample(key, data, wall)
                c["samples"] += 1
            elif op == OP_STEP:
                self.emit(core.step(wall, limit=None if val < 0 else val), wall)
                c["steps"] += 1
            elif op == OP_FLUSH:
                self.emit(core.flush(wall), wall)
            elif op in (OP_ALIVE, OP_LOST):
                core.on_liveliness(key, op == OP_ALIVE, wall)
            else:
                core.on_oversized(key, val)
            ev.popleft()
        arrivals, horizon = self._arrivals, now_log_ns - self.window_ns
        while arrivals and arrivals[0][0] < horizon:
            _, k = arrivals.popleft()
            q = pool.get(k)
            if q:
                q.popleft()
                c["inputs_not_ingested"] += 1
                if not q:
                    del pool[k]

    @property
    def report(self) -> dict[str, int]:
        """Counts: chunks, samples, steps, chunks_missing, samples_missing,
        inputs_not_ingested, events_not_recorded (all 0 but the first three: bit-identical
        to the live run), restarts (live fusion instances after the first, each replayed
        on a fresh core)."""
        keys = ("chunks", "samples", "steps", "chunks_missing", "chunks_repeated",
                "samples_missing", "inputs_not_ingested", "events_not_recorded", "restarts")
        return {k: int(self.counts.get(k, 0)) for k in keys}
