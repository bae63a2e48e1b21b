"""The live fusion's overload policy: what a step that cannot take every ready epoch drops.

A fusion slower than its input (``FusionConfig.max_backlog_s`` set: the live service) first
coalesces per node once the ready epochs span more than ``supersede_after_s``
(:func:`supersede`: each node's newest ready epoch, nodes least recently served first; with
admission on, every epoch of a node without a confirmed track), then drops what is still more
than ``max_backlog_s`` behind the newest ready epoch (:func:`shed`). A step that leaves more
than ``admit_lag_s`` of ready epochs is :meth:`OverloadPolicy.lagging` (it starts only the
minimum of new tracks). All are functions of the ready queue, the served record and the tracks
(the released epochs and the steps' limits are in the decision record), so a replay by that
record drops the same.
:class:`~diffpos_services.fusion.core.FusionCore` counts what they drop (``rejected``).
"""

from __future__ import annotations

import collections
import itertools
import math
from collections.abc import Callable, Iterable
from typing import Any

from diffpos.tracking.state import TrackStatus
from diffpos_services.fusion.config import LEGACY_ADMIT_LAG_S

__all__ = ["BEHIND_KEEP_EPOCHS", "OverloadPolicy", "ready_span", "shed", "supersede"]

#: ready epochs kept per node when a live step is behind (:func:`supersede`): its newest
#: one. Measured on the 16 x 200 soak input, the live loop on a virtual clock (benchmarks/
#: bench_fusion_cost.py --schedule, the first 15 s, CPU x1 / x1.5 / x2; a trial version that
#: queued the nodes by place), keeping the newest 1, 2 or 4: about as many estimates either way (x1: 21,920-24,493 vs 22,944-25,598 vs 22,010;
#: x2: 5,812 / 5,941 / 6,037: the tracker's update costs more after a longer gap, so skipped
#: epochs save less than their share), but each further kept epoch adds about a round of
#: latency: mean age of a node's picture x1 167-189 / 236-279 / 459 ms, x2 381 / 488 / 711 ms
BEHIND_KEEP_EPOCHS = 1
# track statuses of a node whose ready epochs are never superseded (admission on): no track
# (its epochs cost no update) or one not confirmed yet (admission bounds how many start)
_UNCONFIRMED = frozenset({int(TrackStatus.UNINITIALISED), int(TrackStatus.LOST),
                          int(TrackStatus.INITIALISING)})


def _epochs(x: float, to_int) -> float:
    """``to_int(x)`` [epochs]; +inf stays +inf (an infinite setting means never: the
    FusionConfig accepts it, and ``math.floor``/``ceil`` of inf would raise)."""
    return to_int(x) if math.isfinite(x) else math.inf


def ready_span(ready: Iterable) -> int:
    """Newest minus oldest ready epoch [epochs] (0 when at most one epoch is ready)."""
    epochs = [pe.epoch for pe in ready]
    return max(epochs) - min(epochs) if epochs else 0


def supersede(ready: collections.deque, served: dict[str, int],
              keep_all: frozenset[str] = frozenset()) -> collections.deque:
    """Per-node coalescing of a backlog (the live fusion is slower than its input): of each
    node's ready epochs only the newest :data:`BEHIND_KEEP_EPOCHS` are kept (the older ones
    are dropped unsolved: the caller counts them as ``superseded``), and the nodes are queued
    least recently served first (``served``: node -> the running count of node-epochs taken by
    budgeted steps when it was last taken; never served: first; ties in queue order). A queue
    with no more than that many epochs of any node is returned as it is. A node in
    ``keep_all`` (one without a confirmed track: no track, its epochs cost no update and are
    published without a position, or a new one, of which admission starts few) keeps every
    ready epoch, oldest first.

    So a behind fusion holds at most that many ready epochs per node and solves them in
    rounds: no node is solved again before every other node with a ready epoch was (no node
    starved, whatever its id or place in a release), each with its newest ranges; the work
    per round is bounded by the number of nodes and the latency is about one round instead of
    the backlog limit. A node's epochs are released in time order, so its last ones in the
    queue are its newest."""
    items = list(ready)
    slots: dict[str, list[int]] = {}
    for i, pe in enumerate(items):
        slots.setdefault(pe.node_id, []).append(i)
    if all(len(v) <= BEHIND_KEEP_EPOCHS or n in keep_all for n, v in slots.items()):
        return ready  # less than a round behind: nothing changes (the order neither)
    order = sorted(slots, key=lambda nid: (served.get(nid, -1), slots[nid][0]))
    return collections.deque(items[i] for nid in order for i in (
        slots[nid] if nid in keep_all else slots[nid][-BEHIND_KEEP_EPOCHS:]))


def shed(ready: collections.deque, max_backlog_epochs: int) -> collections.deque:
    """The ready epochs without those more than ``max_backlog_epochs`` older than the newest
    ready one (the caller counts them as ``overloaded``). After :func:`supersede` each node
    has at most :data:`BEHIND_KEEP_EPOCHS` ready epochs, its newest: this drops only when one
    round of all nodes takes longer than ``max_backlog_s``, or a node's newest ready epoch is
    that old (its ranges stopped)."""
    if not ready:
        return ready
    keep_from = max(pe.epoch for pe in ready) - max_backlog_epochs
    if min(pe.epoch for pe in ready) >= keep_from:
        return ready
    return collections.deque(pe for pe in ready if pe.epoch >= keep_from)


class OverloadPolicy:
    """The policy of one fusion core (``config``: its FusionConfig): the spans in epochs and
    the served record (:func:`supersede`'s ``served``)."""

    def __init__(self, config: Any) -> None:
        period = config.epoch_period_s
        self.max_backlog_epochs = (None if config.max_backlog_s is None else
                                   _epochs(config.max_backlog_s / period, math.ceil))
        # the ready span (epochs) beyond which a behind step coalesces per node
        self.supersede_span = _epochs(config.supersede_after_s / period + 1e-9, math.floor)
        # the span (epochs) of what a step leaves beyond which it admits no new-track work
        self.admit_span = _epochs(config.admit_lag_s / period + 1e-9, math.floor)
        self.served: dict[str, int] = {}
        self._count = 0  # node-epochs taken by budgeted steps so far
        #: the tracker's status of node ids (``TrackBank.status_of``; set by a core that
        #: tracks): with admission on (``admit_lag_s`` below the legacy setting of a replay of
        #: an older recording), a node without a confirmed track keeps every ready epoch
        self.status_of: Callable[[list[str]], Any] | None = None
        self._keep_unconfirmed = config.admit_lag_s < LEGACY_ADMIT_LAG_S

    def apply(self, ready: collections.deque, limit: int | None,
              rejected: collections.Counter) -> collections.deque:
        """The ready queue a step with ``limit`` solves from (the same object when nothing
        is dropped); what it drops is added to ``rejected["superseded"]`` /
        ``["overloaded"]``. Only a budgeted step (``limit``) with more ready epochs than its
        limit, with ``max_backlog_s`` set, drops anything."""
        if limit is None or len(ready) <= limit or not self.max_backlog_epochs:
            return ready
        for reason, drop in (("superseded", self._supersede), ("overloaded", self._shed)):
            n = len(ready)
            ready = drop(ready)
            if len(ready) < n:  # a reason is counted once something was dropped for it
                rejected[reason] += n - len(ready)
        return ready

    def lagging(self, ready: collections.deque, todo: int) -> bool:
        """Whether a step that takes the first ``todo`` of ``ready`` leaves epochs spanning
        more than ``admit_lag_s`` (newest - oldest left): the fusion is that far behind its
        input and admits no more new-track work than the minimum (``tracked.heavy_budget``).
        A function of the queue alone (the decision record replays it); False without a
        tracker (:attr:`status_of` unset: nothing reads it, the backlog is not scanned)."""
        if self.status_of is None or todo >= len(ready):
            return False
        return ready_span(itertools.islice(ready, todo, None)) > self.admit_span

    def _supersede(self, ready: collections.deque) -> collections.deque:
        if ready_span(ready) <= self.supersede_span:
            return ready
        keep = self._unconfirmed(ready)  # their epochs never make a confirmed track stale
        if keep and ready_span(pe for pe in ready if pe.node_id not in keep
                               ) <= self.supersede_span:
            return ready
        return supersede(ready, self.served, keep)

    def _unconfirmed(self, ready: collections.deque) -> frozenset[str]:
        """The ready nodes without a confirmed track (UNINITIALISED, LOST, INITIALISING;
        none without a tracker or with admission off)."""
        if self.status_of is None or not self._keep_unconfirmed:
            return frozenset()
        ids = list(dict.fromkeys(pe.node_id for pe in ready))
        return frozenset(n for n, s in zip(ids, self.status_of(ids).tolist(), strict=True)
                         if s in _UNCONFIRMED)

    def _shed(self, ready: collections.deque) -> collections.deque:
        return shed(ready, self.max_backlog_epochs)

    def taken(self, epochs: list) -> None:
        """A budgeted step took ``epochs`` (in its order) from the queue: the served record."""
        self.served.update(zip([pe.node_id for pe in epochs],
                               range(self._count, self._count + len(epochs)), strict=True))
        self._count += len(epochs)
