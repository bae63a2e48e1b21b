"""Row shares of the fusion's worker pool (:mod:`diffpos_services.fusion.workers`): slicing
a call's arguments by rows and joining the results, the contiguous shares balanced by
cost, speed and the work a worker already has, and the tracker state a share carries."""

from __future__ import annotations

import dataclasses
import itertools
from typing import Any

import numpy as np

from diffpos.tracking.model import snr_reuse_on
from diffpos.tracking.state import SNR_CACHE_LINKS, SNR_CACHE_SLOTS, TrackerState
from diffpos.tracking.tracker import update

__all__ = ["concat_rows", "preloaded_bounds", "run_update", "share_bounds", "slim_state",
           "take_rows"]


def take_rows(x: Any, sl: slice) -> Any:
    """Rows ``sl`` of ``x``: an array (axis 0), a dataclass of arrays (every array field),
    a tuple of those, or None/scalars (unchanged)."""
    if isinstance(x, np.ndarray):
        return x[sl] if x.ndim else x
    if isinstance(x, tuple):
        return tuple(take_rows(v, sl) for v in x)
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return dataclasses.replace(x, **{f.name: take_rows(getattr(x, f.name), sl)
                                         for f in dataclasses.fields(x) if f.init})
    return x


def concat_rows(parts: list[Any]) -> Any:
    """The inverse of :func:`take_rows` over consecutive shares: arrays concatenated on axis
    0, dataclasses and tuples field by field, anything else taken from the first part."""
    first = parts[0]
    if len(parts) == 1:
        return first
    if isinstance(first, np.ndarray):
        return np.concatenate(parts) if first.ndim else first
    if isinstance(first, tuple):
        return tuple(concat_rows([p[i] for p in parts]) for i in range(len(first)))
    if dataclasses.is_dataclass(first) and not isinstance(first, type):
        return dataclasses.replace(first, **{
            f.name: concat_rows([getattr(p, f.name) for p in parts])
            for f in dataclasses.fields(first) if f.init})
    return first


def share_bounds(cost: np.ndarray, n: int, weights: Any = None) -> list[slice]:
    """At most ``n`` non-empty contiguous slices of ``range(len(cost))``, in row order, whose
    total costs (each row's ``cost`` > 0) are about proportional to ``weights`` (n values > 0,
    the sharers' speeds; default equal)."""
    c = np.cumsum(np.asarray(cost, dtype=np.float64))
    if c.size == 0:
        return []
    w = np.cumsum(np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64))
    # the k-th cut after the first row whose cumulative cost reaches the k-th weight fraction
    cuts = np.searchsorted(c, c[-1] * w[:-1] / w[-1], side="left") + 1
    edges = np.unique(np.concatenate([[0], np.minimum(cuts, c.size), [c.size]]))
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(edges.tolist()) if b > a]


def preloaded_bounds(cost: np.ndarray, weights: list[float], preload: list[float]
                     ) -> list[slice]:
    """Exactly ``len(weights)`` contiguous slices of ``range(len(cost))`` in row order (some
    possibly empty) such that each sharer's ``preload`` (work it already has) plus its
    rows' cost is about proportional to its weight: a sharer whose preload exceeds its
    part gets no rows."""
    cost = np.asarray(cost, dtype=np.float64)
    c = np.cumsum(cost)
    n = len(weights)
    if c.size == 0:
        return [slice(0, 0)] * n
    w = np.asarray(weights, dtype=np.float64)
    total = c[-1] + float(np.sum(preload))
    target = np.maximum(total * w / w.sum() - np.asarray(preload, dtype=np.float64), 0.0)
    target *= c[-1] / max(float(target.sum()), 1e-300)
    # the k-th cut after the first row whose cumulative cost reaches the k-th target sum
    ends = np.cumsum(target)[:-1]
    cuts = np.where(ends > 0, np.searchsorted(c, ends - 1e-9 * c[-1], side="left") + 1, 0)
    edges = np.concatenate([[0], np.minimum(np.maximum.accumulate(cuts), c.size), [c.size]])
    return [slice(int(a), int(b)) for a, b in itertools.pairwise(edges.tolist())]


_SNR_CACHE = ("snr_node", "snr_anchor", "snr_pred")


def slim_state(sub: TrackerState, config: Any) -> TrackerState:
    """``sub`` without its SNR cache fields (None) when the tracker neither reads nor carries
    them (:func:`diffpos.tracking.model.snr_reuse_on` false: both reuse margins 0): they are
    7.2 of the ~11 KB per row that would cross the pipe both ways for nothing. With the
    default margins (0.05 / 0.1 m) reuse is on and the whole state crosses (1.4 MB each way
    for a 128-row share: ~2 ms of the caller's CPU, bench_workers.py)."""
    if snr_reuse_on(config):
        return sub
    return dataclasses.replace(sub, **dict.fromkeys(_SNR_CACHE))


def run_update(building: Any, sub: TrackerState, anchors, ranges, sigmas, mask, t_ns, snr_db,
               config, radio) -> tuple[TrackerState, Any]:
    """:func:`diffpos.tracking.tracker.update` of a share of rows, ``sub`` possibly slimmed by
    :func:`slim_state`: the missing cache fields are given as read-only NaN views (never read
    nor written with reuse off: a write would raise, and the share be redone by the caller)
    and returned as None (the caller keeps its own, unchanged rows)."""
    slim = sub.snr_node is None
    if slim:
        n, h = sub.mean.shape[:2]
        shapes = {"snr_node": ((n, h, 3), np.float64),
                  "snr_anchor": ((n, h, SNR_CACHE_LINKS, 3), np.float32),
                  "snr_pred": ((n, h, SNR_CACHE_LINKS, len(SNR_CACHE_SLOTS)), np.float32)}
        sub = dataclasses.replace(sub, **{k: np.broadcast_to(np.array(np.nan, dt), shape)
                                          for k, (shape, dt) in shapes.items()})
    new, out = update(sub, anchors, ranges, sigmas, mask, t_ns, building, config,
                      snr_db=snr_db, radio=radio)
    return (slim_state(new, config) if slim else new), out
