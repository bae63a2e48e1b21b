"""The fusion's decision record: every call that changed the core's state, in order.

Why: the live fusion's release decisions (which ranges make an epoch, which arrive late and
are dropped, when an epoch times out) depend on the order and the wall times at which the
samples reached it. The recorder sees the same samples in ITS order, which under CPU load
differs (issue 15 item 3: 96.9 % of statuses equal, positions up to 6.7 m apart). So the
core writes down its ingest order - each sample by key and CRC-32 of its payload, with the
receive wall time it was given - its liveliness events and the wall times of the steps that
solved something; :meth:`FusionCore.diagnostics` hands the record out in chunks
(``FusionDiagnostics.decisions``, published and recorded with the diagnostics), and
``diffpos replay`` re-issues exactly these calls (:class:`DecisionReplayer` in
:mod:`diffpos_services.replay.decided`). Same calls, same arguments, same core: the same
fixes, bit for bit. Steps that released nothing are not written (they change nothing).

The record costs one tuple append per call (measured in benchmarks/bench_replay.py) and a
few bytes per sample on the bus (columns, times as deltas).
"""

from __future__ import annotations

import zlib

from diffpos_services.wire import messages as M

__all__ = ["DecisionLog"]

OP_SAMPLE, OP_OVERSIZED, OP_ALIVE, OP_LOST, OP_STEP, OP_FLUSH = M.DECISION_OPS


class DecisionLog:
    """Collects the core's state-changing calls until :meth:`take`.

    Parameters
    ----------
    max_events : int
        Events kept at most between two :meth:`take` calls (the oldest are dropped and
        counted in ``dropped``: the record is then incomplete, replay says so).
    """

    def __init__(self, max_events: int = 1_000_000) -> None:
        self.max_events = int(max_events)
        self.chunk = 0
        self.dropped = 0
        self._keys: dict[str, int] = {}
        self._ops: list[int] = []
        self._refs: list[int] = []
        self._vals: list[int] = []
        self._walls: list[int] = []

    def _add(self, op: int, ref: str, val: int, wall_ns: int) -> None:
        if len(self._ops) >= self.max_events:
            self.dropped += 1
            return
        i = self._keys.get(ref)
        if i is None:
            i = self._keys[ref] = len(self._keys)
        self._ops.append(op)
        self._refs.append(i)
        self._vals.append(val)
        self._walls.append(int(wall_ns))

    def sample(self, key: str, payload: bytes, rx_wall_ns: int) -> None:
        self._add(OP_SAMPLE, key, zlib.crc32(payload), rx_wall_ns)

    def oversized(self, key: str, size: int) -> None:
        self._add(OP_OVERSIZED, key, int(size), 0)

    def liveliness(self, anchor_id: str, alive: bool, wall_ns: int) -> None:
        self._add(OP_ALIVE if alive else OP_LOST, anchor_id, 0, wall_ns)

    def step(self, now_wall_ns: int, limit: int | None, n_ready: int) -> None:
        """A step that released or solved something (``n_ready`` > 0)."""
        self._add(OP_STEP, "", -1 if limit is None else int(limit), now_wall_ns)

    def flush(self, now_wall_ns: int) -> None:
        self._add(OP_FLUSH, "", 0, now_wall_ns)

    def __len__(self) -> int:
        return len(self._ops)

    def take(self) -> M.DecisionChunk:
        """The events since the last call as one chunk, and a fresh start. Chunks with events
        are numbered 0, 1, ...; an empty one carries the number of the next (a reader that
        missed it missed nothing). Wall times are deltas from the previous event (the first
        one absolute)."""
        walls, prev = [], 0
        for w in self._walls:
            walls.append(w - prev)
            prev = w
        out = M.DecisionChunk(chunk=self.chunk, keys=list(self._keys), ops=self._ops,
                              refs=self._refs, values=self._vals, wall_delta_ns=walls,
                              dropped=self.dropped)
        if self._ops or self.dropped:
            self.chunk += 1  # empty chunks share the next one's number: losing them loses nothing
        self.dropped = 0
        self._keys, self._ops, self._refs, self._vals, self._walls = {}, [], [], [], []
        return out
