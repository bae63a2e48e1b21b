"""Replay's report as a stream: what each fix contributes is reduced as it comes.

Before, ``diffpos replay`` kept every live and replayed estimate (~5 KB per fix: 511 MB for 3
minutes of 8 x 50 nodes at 10 Hz) until the report. Here a fix is matched to the truth and to
its live/replayed twin while the recording is read (both are local in recording time), and
goes in batches into the bounded-memory summaries of :mod:`diffpos.metrics` (the one scorer:
:class:`~diffpos.metrics.StreamingErrorStats` per node and overall,
:class:`~diffpos.metrics.StreamingScore` over the node-epochs): the memory does not grow with
the recording's length (benchmarks/bench_replay.py measures it). The figures are exact (those
of :func:`~diffpos.metrics.error_stats` / :func:`~diffpos.metrics.score` on every value) while
a distribution has at most 4,096 values, then within 0.5 % (percentiles; counts, shares and
max stay exact).

Recorded estimates and truth are decoded into slim structs (only the fields the report reads,
no per-message id regex: the ids are checked against the topic's).
"""

from __future__ import annotations

import array
import bisect
import copy
import dataclasses
import heapq
import itertools
import math
from collections import Counter, defaultdict
from collections.abc import Callable, Mapping
from typing import Any

import msgspec
import numpy as np

from diffpos.floor_calibration import probability_rows
from diffpos.metrics import QuantileSketch, StreamingErrorStats, StreamingScore, ellipsoid_coverage
from diffpos_services.recording.reader import RawMessage
from diffpos_services.recording.topics import SeqTracker, natural_key
from diffpos_services.wire import messages as M

__all__ = ["NO_TRACK_STATUSES", "Comparison", "FixStream", "Recorded", "SlimEstimate",
           "SlimTruth", "TruthBook", "TruthSegments", "slim_decoders"]

_NAN3 = (math.nan, math.nan, math.nan)
#: Statuses of a fix without a track (the tracker's): its anchors were measured but no track
#: existed to use them (before the first initialisation, or after the track was lost), so the
#: "RAIM" the fusion lists for them is not an exclusion (counted as "no track" instead).
NO_TRACK_STATUSES = frozenset({"UNINITIALISED", "LOST"})
_COV_BATCH = 4096
#: scored fixes / node-epochs buffered before they go into the summaries
_BATCH = 8192


class SlimExclusion(msgspec.Struct, frozen=True, gc=False):
    anchor_id: str
    reason: str


class SlimEstimate(msgspec.Struct, frozen=True, gc=False):
    """The fields of an estimate (v1 or v2) the report reads."""

    schema: str
    node_id: str
    t_ns: int
    epoch: int
    status: str
    position_m: tuple[float, float, float] | None = None
    covariance_m2: tuple[tuple[float, float, float], tuple[float, float, float],
                         tuple[float, float, float]] | None = None
    peb_m: float | None = None
    floor_index: int | None = None
    floor_probabilities: list[float] = []  # v1: none
    used_anchors: list[str] = []
    excluded: list[SlimExclusion] = []


class SlimTruth(msgspec.Struct, frozen=True, gc=False):
    schema: str
    entity: str
    id: str
    t_ns: int
    position_m: tuple[float, float, float]
    floor_index: int | None = None


_EST_TAGS = frozenset(t.__struct_config__.tag for t in M.ESTIMATE_TYPES)


def slim_decoders():
    """``(estimate, truth)`` decoders: bytes -> slim struct, ``ValueError`` on bad input
    (malformed JSON, a wrong type, another message's schema tag)."""
    de, dt = msgspec.json.Decoder(SlimEstimate), msgspec.json.Decoder(SlimTruth)

    def estimate(data: bytes) -> SlimEstimate:
        e = de.decode(data)
        if e.schema not in _EST_TAGS:
            raise ValueError(f"not an estimate: {e.schema!r}")
        return e

    def truth(data: bytes) -> SlimTruth:
        g = dt.decode(data)
        if g.schema != "diffpos.truth.v1":
            raise ValueError(f"not ground truth: {g.schema!r}")
        return g

    return estimate, truth


class TruthBook:
    """Recorded truth per node, the last ``window_ns`` of it (plus the sampling period).

    Columnar: per node the times (``t``, int64), positions (``p``, x y z flattened) and floors
    (``f``) in typed arrays, so a batch of fixes is matched to the truth with a few numpy
    operations (:meth:`segments`, every node at once) instead of a Python call per fix.

    ``floor_of``: the building's ``floor_index`` (heights -> floors): the true floor at a
    time is that of the interpolated true height, as ``emulate``'s live summary has it
    (:func:`diffpos.metrics.truth_at`); ``None`` (no building known): the recorded floor of
    the nearest sample."""

    def __init__(self, window_ns: int,
                 floor_of: Callable[[np.ndarray], Any] | None = None) -> None:
        self.window_ns = window_ns
        self.floor_of = floor_of
        self.t: dict[str, array.array] = defaultdict(lambda: array.array("q"))
        self.p: dict[str, array.array] = defaultdict(lambda: array.array("d"))
        self.f: dict[str, array.array] = defaultdict(lambda: array.array("q"))
        self.first_t: int | None = None
        self.last_t: int | None = None
        self.period: int | None = None
        self._times: set[int] = set()
        self.samples = 0

    def add(self, node: str, t: int, pos, floor: int) -> None:
        self.samples += 1
        if self.first_t is None or t < self.first_t:
            self.first_t = t
        if self.last_t is None or t > self.last_t:
            self.last_t = t
        if self.period is None:  # the spacing of the first samples (as the scorer had it)
            self._times.add(t)
            if len(self._times) >= 64:
                ts = sorted(self._times)
                self.period = min((b - a for a, b in itertools.pairwise(ts) if b > a),
                                  default=None)
                self._times = set()
        ts, ps, fs = self.t[node], self.p[node], self.f[node]
        if ts and t < ts[-1]:  # rare: out of order
            i = bisect.bisect_right(ts, t)
            ts.insert(i, t)
            ps[3 * i:3 * i] = array.array("d", pos)
            fs.insert(i, floor)
        else:
            ts.append(t)
            ps.extend(pos)
            fs.append(floor)
        if ts[-1] - ts[0] > 2 * self.window_ns:  # keep the last window
            cut = bisect.bisect_left(ts, ts[-1] - self.window_ns)
            del ts[:cut], ps[:3 * cut], fs[:cut]

    def finish_period(self) -> None:
        if self.period is None and len(self._times) > 1:
            ts = sorted(self._times)
            self.period = min((b - a for a, b in itertools.pairwise(ts) if b > a),
                              default=None)

    def newest(self, node: str) -> int | None:
        ts = self.t.get(node)
        return ts[-1] if ts else None

    def columns(self, node: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The node's truth as arrays (copies): times (n,) [ns], positions (n, 3) [m],
        floors (n,)."""
        ts = self.t.get(node)
        if not ts:
            return np.empty(0, np.int64), np.empty((0, 3)), np.empty(0, np.int64)
        return (np.frombuffer(ts, np.int64).copy(),
                np.frombuffer(self.p[node], np.float64).reshape(-1, 3).copy(),
                np.frombuffer(self.f[node], np.int64).copy())

    def segments(self, nodes: list[str]) -> TruthSegments:
        """The truth of ``nodes`` as one set of columns, a segment per node (in order)."""
        cols = [self.columns(n) for n in nodes]
        return TruthSegments(*(np.concatenate([c[i] for c in cols]) for i in range(3)),
                             np.array([c[0].size for c in cols], np.int64), self.floor_of)

    def at(self, node: str, t: int, max_gap_ns: int):
        """(position interpolated at t, its floor: :meth:`TruthSegments.at`) or None (no
        sample within ``max_gap_ns``): what :func:`..evaluate.evaluate` did over the whole
        track."""
        pos, floor, ok = self.segments([node]).at(np.zeros(1, np.int64),
                                                  np.array([t], np.int64), max_gap_ns)
        return (tuple(pos[0].tolist()), int(floor[0])) if ok[0] else None


@dataclasses.dataclass
class TruthSegments:
    """Several nodes' truth as one set of columns (:meth:`TruthBook.segments`): times
    ``t`` [ns], positions ``p`` (n, 3) [m] and floors ``f`` of segment ``k`` (its node) at
    ``start[k] .. start[k] + size[k] - 1``, each segment sorted by time; ``floor_of``: as
    :class:`TruthBook`'s."""

    t: np.ndarray
    p: np.ndarray
    f: np.ndarray
    size: np.ndarray
    floor_of: Callable[[np.ndarray], Any] | None = None

    def __post_init__(self) -> None:
        self.start = np.concatenate([[0], np.cumsum(self.size)[:-1]]).astype(np.int64)

    def search(self, seg: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``bisect_left`` of each time ``t[i]`` within its segment ``seg[i]`` (local index)."""
        if self.t.size == 0:
            return np.zeros(t.size, np.int64)
        base = int(min(self.t.min(), t.min()))
        span = int(max(self.t.max(), t.max())) - base + 1
        s0 = self.start[seg]
        if span * max(self.size.size, 1) < 2**62:  # one search over (segment, time) keys
            own = np.repeat(np.arange(self.size.size, dtype=np.int64), self.size)
            keys = (self.t - base) + own * span
            return np.searchsorted(keys, (t - base) + seg * span, side="left") - s0
        j = np.empty(t.size, np.int64)  # (times too far apart for one key: per segment)
        for k in np.unique(seg).tolist():
            sel = seg == k
            lo = int(self.start[k])
            j[sel] = np.searchsorted(self.t[lo:lo + int(self.size[k])], t[sel], side="left")
        return j

    def at(self, seg: np.ndarray, t: np.ndarray, max_gap_ns: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`TruthBook.at` of each time ``t[i]`` (int64 [ns]) in its segment ``seg[i]``
        at once: positions (k, 3), floors (k,) and whether a sample is within ``max_gap_ns``
        (k,) (where not, position and floor are meaningless). The same arithmetic as the
        scalar interpolation, element by element: bit-identical values. The floor is
        ``floor_of`` of the interpolated height, or without it the nearest sample's."""
        k, top = t.size, self.t.size - 1
        if top < 0:
            return np.zeros((k, 3)), np.zeros(k, np.int64), np.zeros(k, bool)
        n, s0 = self.size[seg], self.start[seg]
        j = self.search(seg, t)

        def g(i: np.ndarray) -> np.ndarray:  # a local index -> a global one, kept in range
            return np.clip(s0 + i, 0, top)

        left, right = np.maximum(j - 1, 0), np.minimum(j, n - 1)
        dl, dr = np.abs(t - self.t[g(left)]), np.abs(t - self.t[g(right)])
        near = np.where(dl <= dr, left, right)
        ok = (n > 0) & (np.minimum(dl, dr) <= max_gap_ns)
        jc = np.clip(j, 1, np.maximum(n - 1, 1))
        i0, i1 = g(jc - 1), g(jc)
        t0, t1 = self.t[i0], self.t[i1]
        span = t1 - t0
        w = np.where(span > 0, (t - t0) / np.where(span > 0, span, 1), 0.0)
        a, b = self.p[i0], self.p[i1]
        pos = a + w[:, None] * (b - a)
        first, last = g(np.zeros_like(n)), g(n - 1)
        pos = np.where((t <= self.t[first])[:, None], self.p[first],
                       np.where((t >= self.t[last])[:, None], self.p[last], pos))
        floor = (self.f[g(near)] if self.floor_of is None
                 else np.asarray(self.floor_of(pos[:, 2]), np.int64))
        return pos, floor, ok


@dataclasses.dataclass
class _Errors:
    """The scored fixes of one batch (flushed into the per-node summaries)."""

    node: array.array = dataclasses.field(default_factory=lambda: array.array("H"))
    e3: array.array = dataclasses.field(default_factory=lambda: array.array("d"))
    ez: array.array = dataclasses.field(default_factory=lambda: array.array("d"))
    eh: array.array = dataclasses.field(default_factory=lambda: array.array("d"))
    peb: array.array = dataclasses.field(default_factory=lambda: array.array("d"))
    fok: array.array = dataclasses.field(default_factory=lambda: array.array("b"))


class ErrorArrays(Mapping):
    """The overall error arrays of a stream (``e3``, ``ez``, ``eh``, ``peb`` [m]) for plots,
    made when read: the recorded values while the summary is exact, else its histogram's
    bucket centres (within 0.5 %, see :class:`diffpos.metrics.QuantileSketch`); O(fixes)
    memory only then."""

    def __init__(self, stats: StreamingErrorStats) -> None:
        self._src = {"e3": stats.e3, "ez": stats.ez, "eh": stats.eh, "peb": stats.peb}

    def __getitem__(self, key: str) -> np.ndarray:
        return self._src[key].values()

    def __iter__(self):
        return iter(self._src)

    def __len__(self) -> int:
        return len(self._src)


#: a fix without a floor index, in the store's floor column
_NO_FLOOR = -(2**62)
#: a node without truth, in the newest-truth column (no fix time is at or below it)
_NO_TRUTH = np.iinfo(np.int64).min


class _FixStore:
    """A stream's positioned fixes as columns in arrival order (typed arrays: no object per
    fix), until each is scored against the truth (``scored``) and its node-epoch is scored
    or dropped (referenced by the stream's node-epoch map): node (the stream's index of the
    node), time, position, PEB (NaN: none), floor (:data:`_NO_FLOOR`: none), covariance
    (zeros where ``has_cov`` is 0) and floor probabilities (the estimate's own list, or
    ``()``). Each fix has a number ``id`` (increasing, never reused); :meth:`compact` drops
    what nothing needs any more."""

    def __init__(self) -> None:
        self.next_id = 0
        self._new()

    def _new(self) -> None:
        self.id, self.node, self.t, self.floor = (array.array("q") for _ in range(4))
        self.pos, self.peb, self.cov = array.array("d"), array.array("d"), array.array("d")
        self.has_cov, self.scored = array.array("b"), array.array("b")
        self.probs: list = []

    def __len__(self) -> int:
        return len(self.t)

    def add_columns(self, node: np.ndarray, t: np.ndarray, pos: np.ndarray, peb: np.ndarray,
                    floor: np.ndarray, cov: np.ndarray, has_cov: np.ndarray,
                    probs: list) -> range:
        """Fixes as columns (k,), pos (k, 3), cov (k, 3, 3); their ids."""
        k = t.size
        ids = range(self.next_id, self.next_id + k)
        self.next_id += k
        self.id.frombytes(np.arange(ids.start, ids.stop, dtype=np.int64).tobytes())
        self.node.frombytes(node.astype(np.int64).tobytes())
        self.t.frombytes(t.astype(np.int64).tobytes())
        self.pos.frombytes(np.ascontiguousarray(pos, np.float64).tobytes())
        self.peb.frombytes(peb.astype(np.float64).tobytes())
        self.floor.frombytes(floor.astype(np.int64).tobytes())
        self.cov.frombytes(np.where(has_cov[:, None, None], cov, 0.0).astype(np.float64)
                           .tobytes())
        self.has_cov.frombytes(has_cov.astype(np.int8).tobytes())
        self.scored.frombytes(bytes(k))
        self.probs += probs
        return ids

    def col(self, name: str) -> np.ndarray:
        """A column as a numpy view (pos: (n, 3), cov: (n, 3, 3)); do not keep it across
        :meth:`add` (the array may move)."""
        a = getattr(self, name)
        dt = {"q": np.int64, "d": np.float64, "b": np.int8}[a.typecode]
        v = np.frombuffer(a, dt) if len(a) else np.empty(0, dt)
        return v.reshape(-1, 3) if name == "pos" else v.reshape(-1, 3, 3) if name == "cov" else v

    def rows(self, ids) -> np.ndarray:
        """The rows of fix ids (each must be stored)."""
        return np.searchsorted(self.col("id"), np.asarray(ids, np.int64))

    def compact(self, keep_ids) -> None:
        """Keep the unscored fixes and those of ``keep_ids`` (the node-epoch map's)."""
        if not len(self.t):
            return
        keep = (self.col("scored") == 0) | np.isin(self.col("id"), np.fromiter(
            keep_ids, np.int64))
        if keep.all():
            return
        cols = {k: self.col(k)[keep] for k in ("id", "node", "t", "floor", "pos", "peb",
                                               "cov", "has_cov", "scored")}
        probs = [p for p, k in zip(self.probs, keep.tolist(), strict=True) if k]
        self._new()
        for k, v in cols.items():
            getattr(self, k).frombytes(np.ascontiguousarray(v).tobytes())
        self.probs = probs


_NO_COV = ((0.0, 0.0, 0.0),) * 3  # (a placeholder where a fix has no covariance)


class FixStream:
    """One stream of fixes (the live or the replayed one) reduced for the report.

    ``add`` a fix (any object with the estimate fields), ``advance`` with the recording time,
    ``finish`` at the end, then :meth:`accuracy`, :meth:`node_epochs`, :meth:`gating`.
    """

    def __init__(self, truth: TruthBook, *, max_truth_gap_ns: int, window_ns: int,
                 skip_s: float = 2.0) -> None:
        self.truth = truth
        self.gap = max_truth_gap_ns
        self.window_ns = window_ns
        self.skip_ns = round(skip_s * 1e9)
        self.skip_s = skip_s
        self.total = 0
        self.by_status: Counter[str] = Counter()
        self.fixes_by_node: Counter[str] = Counter()
        self._used: Counter[str] = Counter()
        self._used_lists: list[list[str]] = []  # each fix's used anchors, not counted yet
        self.excluded: dict[str, Counter[str]] = defaultdict(Counter)
        self.no_track: Counter[str] = Counter()  # per anchor: measured, no track to use it
        self.positioned: Counter[str] = Counter()  # per node: fixes with a usable position
        self.no_truth = 0
        self._nodes: dict[str, int] = {}
        self._err = _Errors()
        # the positioned fixes until scored (columns), their nodes in order of first fix
        self._store = _FixStore()
        self._buf: list = []  # positioned fixes given to add(), not in the store yet
        self._node_i: dict[str, int] = {}
        self._node_names: list[str] = []
        self._kept = 0  # fixes kept after the last compaction
        # node-epochs: good fixes' ids by (node, slot) until their truth sample is scored
        self._ne_fix: dict[tuple[str, int], int] = {}
        self._unkeyed = False
        self._ne_next: dict[str, int] = {}  # per node: next truth time to score
        self._ne_d = array.array("d")
        self._ne_ef = array.array("h")
        self._ne_tf = array.array("h")
        self._ne_p: list = []  # the node-epochs' floor probabilities (() where none)
        self._stats: dict[int, StreamingErrorStats] = {}  # per node index
        self._overall = StreamingErrorStats()
        self._ne_stats = StreamingScore()
        self._cov_d: list[np.ndarray] = []  # blocks of (k, 3) differences [m]
        self._cov_c: list[np.ndarray] = []  # their covariances, (k, 3, 3) blocks
        self._cov_n = 0  # rows in _cov_d
        self._cov_in = 0
        self._cov_ok = 0

    def add(self, e: Any) -> None:
        self.total += 1
        self.by_status[e.status] += 1
        self.fixes_by_node[e.node_id] += 1
        self._used_lists.append(e.used_anchors)  # (counted in bulk: :attr:`used`)
        no_track = e.status in NO_TRACK_STATUSES
        for x in e.excluded:
            if no_track and x.reason == "RAIM":
                self.no_track[x.anchor_id] += 1
            else:
                self.excluded[x.anchor_id][x.reason] += 1
        if e.position_m is not None and e.status in M.GOOD_STATUSES:
            self.positioned[e.node_id] += 1
            self._buf.append(e)  # into the store by columns (_take_buffer)

    def _take_buffer(self) -> None:
        """The positioned fixes :meth:`add` buffered into the store, as columns, in order
        (before anything reads the store or adds to it otherwise)."""
        buf = self._buf
        if not buf:
            return
        self._buf = []
        nodes = [e.node_id for e in buf]
        t = [e.t_ns for e in buf]
        covs = [e.covariance_m2 for e in buf]
        has_cov = np.array([c is not None for c in covs], bool)
        ids = self._store.add_columns(
            np.array(list(map(self._index, nodes)), np.int64), np.array(t, np.int64),
            np.array([e.position_m for e in buf], np.float64).reshape(-1, 3),
            np.array([e.peb_m for e in buf], np.float64),  # (None -> NaN)
            np.array([_NO_FLOOR if e.floor_index is None else e.floor_index for e in buf],
                     np.int64),
            np.array([_NO_COV if c is None else c for c in covs], np.float64).reshape(-1, 3, 3),
            has_cov, [getattr(e, "floor_probabilities", ()) for e in buf])
        self._ne_add(nodes, t, ids)

    def _index(self, node: str) -> int:
        """The node's number in the stream (order of first positioned fix)."""
        i = self._node_i.get(node)
        if i is None:
            i = self._node_i[node] = len(self._node_names)
            self._node_names.append(node)
        return i

    @property
    def pending_fixes(self) -> int:
        """Positioned fixes not scored against the truth yet."""
        return len(self._buf) + int(np.count_nonzero(self._store.col("scored") == 0))

    def add_rows(self, r: Any) -> None:
        """:meth:`add` of every row of a batch's columns
        (:class:`~diffpos_services.fusion.estimates.EstimateRows`), in order, without its
        structs: the counts by anchor-list group, the positioned rows' fixes into the
        store as columns."""
        self._take_buffer()
        status, node, group, shared = r.status, r.node_id, r.group, r.shared
        self.total += len(status)
        self.by_status.update(status)
        self.fixes_by_node.update(node)
        used = self._used
        for (g, no_track), k in Counter(zip(group, map(NO_TRACK_STATUSES.__contains__,
                                                        status), strict=True)).items():
            for a in shared[g][1]:
                used[a] += k
            for x in shared[g][2]:
                if no_track and x.reason == "RAIM":
                    self.no_track[x.anchor_id] += k
                else:
                    self.excluded[x.anchor_id][x.reason] += k
        good = M.GOOD_STATUSES
        rows = [i for i in itertools.compress(range(len(status)), r.has_pos)
                if status[i] in good]
        if not rows:
            return
        nodes = [node[i] for i in rows]
        self.positioned.update(nodes)
        sel = np.array(rows, np.intp)
        t = np.array(r.t_ns, np.int64)[sel]
        peb = np.where(np.array(r.ok, bool)[sel],
                       np.array(r.peb, np.float64)[sel], np.nan)  # (None -> NaN)
        probs = [()] * len(rows) if r.probs is None else [r.probs[i] for i in rows]
        floor = np.array([_NO_FLOOR if v is None else v for v in map(r.floor.__getitem__, rows)],
                         np.int64)
        ids = self._store.add_columns(
            np.array(list(map(self._index, nodes)), np.int64), t,
            np.array(list(map(r.pos.__getitem__, rows)), np.float64).reshape(-1, 3), peb,
            floor, np.asarray(r.cov, np.float64)[sel], np.array(r.has_cov, bool)[sel], probs)
        self._ne_add(nodes, t.tolist(), ids)

    @property
    def used(self) -> Counter[str]:
        """Per anchor: the fixes that used it."""
        if self._used_lists:
            self._used.update(itertools.chain.from_iterable(self._used_lists))
            self._used_lists = []
        return self._used

    # -- per fix against the truth (evaluate) ----------------------------------------------
    def _score_fixes(self, rows: np.ndarray) -> None:
        """Score the fixes of store ``rows`` (nodes in stream order, each node's fixes in
        order) against the truth at their times, every node at once."""
        st = self._store
        node_i = st.col("node")[rows]
        order, seg = np.unique(node_i, return_inverse=True)
        nodes = [self._node_names[k] for k in order.tolist()]
        pos, tf, ok = self.truth.segments(nodes).at(seg, st.col("t")[rows], self.gap)
        n_ok = int(np.count_nonzero(ok))
        self.no_truth += rows.size - n_ok
        if not n_ok:
            return
        scored = np.bincount(seg[ok], minlength=len(nodes)).tolist()
        index = np.zeros(len(nodes), np.int64)
        for k, node in enumerate(nodes):  # each node's index at its first scored fix
            if scored[k]:
                index[k] = self._nodes.setdefault(node, len(self._nodes))
        d = st.col("pos")[rows][ok] - pos[ok]
        dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
        peb = st.col("peb")[rows][ok]
        floor = st.col("floor")[rows][ok]
        floor = np.where(floor == _NO_FLOOR, -999, floor)
        self._push_errors(index[seg[ok]], np.sqrt(dx * dx + dy * dy + dz * dz), np.abs(dz),
                          np.sqrt(dx * dx + dy * dy), peb, (floor == tf[ok]).astype(np.int8))

    def _push_errors(self, node_i: np.ndarray, e3: np.ndarray, ez: np.ndarray, eh: np.ndarray,
                     peb: np.ndarray, fok: np.ndarray) -> None:
        """Scored fixes into the batch, flushed into the summaries every :data:`_BATCH`
        values exactly (the summaries see the same batches as fix by fix)."""
        done, n = 0, e3.size
        while done < n:
            err = self._err
            take = min(_BATCH - len(err.e3), n - done)
            sl = slice(done, done + take)
            for col, vals in ((err.node, node_i.astype(np.uint16)), (err.e3, e3), (err.ez, ez),
                              (err.eh, eh), (err.peb, peb), (err.fok, fok)):
                col.frombytes(vals[sl].tobytes())
            done += take
            if len(err.e3) >= _BATCH:
                self._flush_errors()

    def _flush_errors(self) -> None:
        """The batch of scored fixes into the per-node and overall summaries."""
        err = self._err
        if not len(err.e3):
            return
        node = np.frombuffer(err.node, np.uint16)
        cols = [np.frombuffer(getattr(err, k), np.float64) for k in ("e3", "ez", "eh")]
        fok = np.frombuffer(err.fok, np.int8).astype(bool)
        peb = np.frombuffer(err.peb, np.float64)
        self._overall.add(*cols, fok, peb)
        for i in np.unique(node):
            sel = node == i
            st = self._stats.get(int(i))
            if st is None:
                st = self._stats[int(i)] = StreamingErrorStats()
            st.add(*(c[sel] for c in cols), fok[sel], peb[sel])
        self._err = _Errors()

    # -- per node-epoch (node_epoch_accuracy) ----------------------------------------------
    def _ne_add(self, nodes: list[str], times: list[int], ids) -> None:
        """The fixes ``ids`` of ``nodes`` at ``times`` into the node-epoch map (the last
        one of a node-epoch wins)."""
        period = self.truth.period
        if period is None:  # not known yet: keyed by -t until it is (_ne_rekey)
            self._ne_fix.update(zip(zip(nodes, [-t for t in times], strict=True), ids,
                                    strict=True))
            self._unkeyed = True
            return
        self._ne_fix.update(zip(zip(nodes, [t // period for t in times], strict=True), ids,
                                strict=True))

    def _ne_rekey(self) -> None:
        period = self.truth.period
        old = self._ne_fix
        self._ne_fix = {}
        if not old:
            return
        t = self._store.col("t")[self._store.rows(list(old.values()))].tolist()
        for ((node, k), i), ti in zip(old.items(), t, strict=True):
            self._ne_fix[(node, ti // period if k < 0 else k)] = i

    def _ne_score(self, final: bool) -> None:
        """Score every node's truth samples up to its newest (``final``) or half a window
        before it: each sample's fix (same node and epoch) against the truth at the fix's
        own time (:func:`diffpos.metrics.truth_at`), a miss where none; as columns, nodes
        in order, the samples of a node in time order. The buffers are flushed after the
        node where they fill up, as one node at a time would."""
        tb, pop = self.truth, self._ne_fix.pop
        period, start = tb.period, tb.first_t + self.skip_ns
        has_cov = self._store.col("has_cov")
        group: list[tuple[str, int, int, list]] = []
        n_tf, n_cov = len(self._ne_tf), self._cov_n
        for node in list(tb.t):
            ts = tb.t[node]
            if not ts:
                continue
            upto = ts[-1] if final else ts[-1] - self.window_ns // 2
            i0 = bisect.bisect_left(ts, max(self._ne_next.get(node, start), start))
            i1 = max(i0, bisect.bisect_right(ts, upto))
            if i1 == i0:
                continue
            fixes = [pop((node, t // period), None) for t in ts[i0:i1].tolist()]
            group.append((node, i0, i1, fixes))
            self._ne_next[node] = ts[i1 - 1] + 1
            n_tf += i1 - i0
            got = [x for x in fixes if x is not None]
            if got:
                n_cov += int(np.count_nonzero(has_cov[self._store.rows(got)]))
            if n_cov >= _COV_BATCH or n_tf >= _BATCH:
                self._ne_columns(group)
                group = []
                if self._cov_n >= _COV_BATCH:
                    self._coverage()
                if len(self._ne_tf) >= _BATCH:
                    self._flush_node_epochs()
                n_tf, n_cov = len(self._ne_tf), self._cov_n
        if group:
            self._ne_columns(group)

    def _ne_columns(self, group: list[tuple[str, int, int, list]]) -> None:
        """The node-epochs of ``(node, i0, i1, fixes)``: the node's truth samples ``i0 ..
        i1 - 1`` and their fixes (``None``: a miss), into the buffers."""
        tb = self.truth
        segs = tb.segments([g[0] for g in group])
        rows = np.concatenate([np.arange(s0 + i0, s0 + i1) for (_, i0, i1, _), s0
                               in zip(group, segs.start.tolist(), strict=True)])
        p, f = segs.p[rows], segs.f[rows]  # a miss: the sample's own truth
        if tb.floor_of is not None:
            f = np.asarray(tb.floor_of(p[:, 2]), np.int64)
        fixes = list(itertools.chain.from_iterable(g[3] for g in group))
        n = len(fixes)
        d = np.full((n, 3), np.nan)
        ef = np.full(n, -1, np.int64)
        found = [k for k, fix in enumerate(fixes) if fix is not None]
        probs: list = [()] * n
        if found:
            st = self._store
            rows = st.rows([fixes[k] for k in found])
            seg = np.repeat(np.arange(len(group), dtype=np.int64),
                            [g[2] - g[1] for g in group])[found]
            tp, tf, ok = segs.at(seg, st.col("t")[rows], tb.period)
            tp = np.where(ok[:, None], tp, p[found])
            f[found] = np.where(ok, tf, f[found])
            d[found] = st.col("pos")[rows] - tp
            fl = st.col("floor")[rows]
            ef[found] = np.where(fl == _NO_FLOOR, -1, fl)
            for k, row in zip(found, rows.tolist(), strict=True):
                probs[k] = st.probs[row]
            hc = st.col("has_cov")[rows] != 0
            if hc.any():
                self._cov_d.append(d[np.asarray(found)[hc]])
                self._cov_c.append(st.col("cov")[rows[hc]].copy())
                self._cov_n += int(np.count_nonzero(hc))
        self._ne_d.frombytes(d.tobytes())
        self._ne_ef.extend(ef.tolist())
        self._ne_tf.extend(f.tolist())
        self._ne_p.extend(probs)

    def _flush_node_epochs(self) -> None:
        if not len(self._ne_tf):
            return
        self._ne_stats.add(np.frombuffer(self._ne_d, np.float64).reshape(-1, 3),
                           estimate_floor=np.frombuffer(self._ne_ef, np.int16),
                           truth_floor=np.frombuffer(self._ne_tf, np.int16),
                           floor_probabilities=probability_rows(self._ne_p))
        self._ne_d, self._ne_ef, self._ne_tf = array.array("d"), array.array("h"), array.array("h")
        self._ne_p = []

    def _coverage(self) -> None:
        if not self._cov_n:
            return
        d, c = np.concatenate(self._cov_d), np.concatenate(self._cov_c)
        ok = int((np.isfinite(d).all(axis=1) & np.isfinite(c).all(axis=(1, 2))).sum())
        cov = ellipsoid_coverage(d, c)
        if cov is not None:
            self._cov_in += round(cov * ok)
            self._cov_ok += ok
        self._cov_d, self._cov_c, self._cov_n = [], [], 0

    # -- time ------------------------------------------------------------------------------
    def advance(self, now_ns: int, *, final: bool = False) -> None:
        """Score what the truth now covers: fixes the node's truth has passed (or all, when
        ``final``); node-epochs a window older than the node's newest truth."""
        tb = self.truth
        _ = self.used  # (the anchors' counts: bounded memory)
        self._take_buffer()
        rows = self._ready_rows(now_ns, final)
        if rows.size:
            self._store.col("scored")[rows] = 1
            self._score_fixes(rows)
        if tb.period is None:
            if not final:
                return
            tb.finish_period()
            if tb.period is None:
                return
        if self._unkeyed:
            self._ne_rekey()
            self._unkeyed = False
        self._ne_score(final)
        if final:
            self._ne_fix.clear()
            self._coverage()
            self._flush_errors()
            self._flush_node_epochs()
        elif len(self._ne_fix) > 64 * 1024:  # fixes whose node-epoch has no truth
            horizon = (now_ns - 2 * self.window_ns) // tb.period
            self._ne_fix = {k: v for k, v in self._ne_fix.items() if k[1] >= horizon}
        self._compact()

    def _compact(self) -> None:
        """Drop the stored fixes nothing needs any more, once the store doubled."""
        st = self._store
        if len(st) >= 2 * self._kept + 4096 or (not self._ne_fix and len(st)):
            st.compact(self._ne_fix.values())
            self._kept = len(st)

    def _ready_rows(self, now_ns: int, final: bool) -> np.ndarray:
        """The store rows to score now, nodes in stream order, each node's in order: each
        node's unscored fixes up to its first one the node's truth has not passed yet (and
        not older than the window); all when ``final``."""
        st = self._store
        uns = np.flatnonzero(st.col("scored") == 0)
        if not uns.size:
            return uns
        node, t = st.col("node")[uns], st.col("t")[uns]
        if final:
            return uns[np.argsort(node, kind="stable")]
        newest = np.array([_NO_TRUTH if (x := self.truth.newest(n)) is None else x
                           for n in self._node_names], np.int64)
        wait = ~((newest[node] >= t) | (t < now_ns - self.window_ns))
        first = np.full(len(self._node_names), uns.size, np.int64)  # per node: first waiting
        np.minimum.at(first, node[wait], np.flatnonzero(wait))
        take = np.flatnonzero(np.arange(uns.size) < first[node])
        return uns[take[np.argsort(node[take], kind="stable")]]

    # -- results ---------------------------------------------------------------------------
    def accuracy(self) -> tuple[dict[str, Any], ErrorArrays]:
        """``evaluate``'s result: per node and overall error stats, and the overall error
        arrays (made on access, see :class:`ErrorArrays`). Call after ``advance(final=True)``."""
        self._flush_errors()
        per_node: dict[str, Any] = {}
        empty = StreamingErrorStats()
        for name in sorted(self.fixes_by_node, key=natural_key):
            i = self._nodes.get(name)
            st = self._stats.get(i, empty) if i is not None else empty
            per_node[name] = st.result(fixes=self.fixes_by_node[name])
        for name, st in per_node.items():
            st["without_position"] = self.fixes_by_node[name] - self.positioned[name]
        overall = self._overall.result(fixes=self.total)
        overall["without_truth"] = self.no_truth
        overall["without_position"] = self.total - sum(self.positioned.values())
        return {"overall": overall, "per_node": per_node}, ErrorArrays(self._overall)

    def node_epochs(self) -> dict[str, Any]:
        """``node_epoch_accuracy``'s result (every node-epoch of the truth; a miss counts)."""
        self._flush_node_epochs()
        if not self._ne_stats.node_epochs:
            return {}
        cover = self._cov_in / self._cov_ok if self._cov_ok else None
        s = self._ne_stats.result(ellipsoid_coverage=cover)
        return s.as_dict() | {"skip_s": self.skip_s}

    def gating(self) -> dict[str, Any]:
        """Per anchor: fixes that ``used`` it, fixes that measured it while the node had
        ``no_track`` (:data:`NO_TRACK_STATUSES`: not exclusions) and ``excluded`` by reason."""
        anchors = sorted(set(self.used) | set(self.excluded) | set(self.no_track),
                         key=natural_key)
        return {a: {"used": self.used.get(a, 0), "no_track": self.no_track.get(a, 0),
                    "excluded": dict(sorted(self.excluded[a].items()))} for a in anchors}


class Comparison:
    """Recorded-live vs replayed fixes matched on (node, epoch) as they come
    (``compare_estimates``' result; unmatched ones older than the window are counted)."""

    def __init__(self, window_ns: int) -> None:
        self.window_ns = window_ns
        self.sides: tuple[dict, dict] = ({}, {})
        self.counts = Counter()
        self.diffs = array.array("d")  # the latest differing positions' distances [m]
        self._diff_sketch = QuantileSketch()  # ... and the older ones (bounded memory)
        self.identical = 0
        self.peb_max: float | None = None
        self.top: list[tuple[float, int, tuple]] = []
        self._n = 0

    def add(self, side: int, e: Any, now_ns: int) -> None:
        """``side`` 0: live, 1: replayed."""
        self.counts["live" if side == 0 else "replayed"] += 1
        # now_ns: recorded receive time
        self._match(side, (e.node_id, e.epoch), (e.status, e.position_m, e.peb_m, now_ns))

    def add_rows(self, side: int, r: Any, now_ns: int) -> None:
        """:meth:`add` of every row of a batch's columns
        (:class:`~diffpos_services.fusion.estimates.EstimateRows`), in order."""
        self.counts["live" if side == 0 else "replayed"] += len(r.status)
        match, pos, has, peb, ok = self._match, r.pos, r.has_pos, r.peb, r.ok
        for i, key in enumerate(zip(r.node_id, r.epoch, strict=True)):
            match(side, key, (r.status[i], tuple(pos[i]) if has[i] else None,
                              peb[i] if ok[i] else None, now_ns))

    def _match(self, side: int, key: tuple[str, int], item: tuple) -> None:
        other = self.sides[1 - side].pop(key, None)
        if other is None:
            if self.sides[side].pop(key, None) is not None:  # a repeat: the last one counts
                self.counts["only_live" if side == 0 else "only_replayed"] += 1
            self.sides[side][key] = item
            return
        a, b = (item, other) if side == 0 else (other, item)
        c = self.counts
        c["matched"] += 1
        c["status_same"] += a[0] == b[0]
        if a[1] is not None and b[1] is not None:
            pa, pb = a[1], b[1]
            c["with_positions"] += 1
            if tuple(pa) == tuple(pb):
                self.identical += 1
            else:
                dist = math.dist(pa, pb)
                self.diffs.append(dist)
                if len(self.diffs) >= _BATCH:
                    self._diff_sketch.add(np.frombuffer(self.diffs, np.float64))
                    self.diffs = array.array("d")
                self._n += 1
                top = self.top
                # (the heap keeps the 5 largest (dist, -n): a pair no larger than its
                # smallest would be pushed and popped at once, so it is not built)
                if len(top) < 5:
                    heapq.heappush(top, (dist, -self._n, (key[0], key[1], a[0], b[0], a[3])))
                elif dist > top[0][0]:
                    heapq.heappushpop(top, (dist, -self._n, (key[0], key[1], a[0], b[0], a[3])))
            if a[2] is not None and b[2] is not None:
                dp = abs(a[2] - b[2])
                self.peb_max = dp if self.peb_max is None else max(self.peb_max, dp)

    def expire(self, now_ns: int, *, final: bool = False) -> None:
        for side, name in ((0, "only_live"), (1, "only_replayed")):
            d = self.sides[side]
            old = [k for k, v in d.items() if final or now_ns - v[3] > self.window_ns]
            for k in old:
                del d[k]
            self.counts[name] += len(old)

    def result(self) -> dict[str, Any]:
        c = self.counts
        n = c["matched"]
        diffs = copy.deepcopy(self._diff_sketch)  # bounded memory: see diffpos.metrics
        for i in range(0, self.identical, _BATCH):
            diffs.add(np.zeros(min(_BATCH, self.identical - i)))
        diffs.add(np.frombuffer(self.diffs, np.float64))
        return {
            "live": c["live"], "replayed": c["replayed"], "matched": n,
            "only_live": c["only_live"], "only_replayed": c["only_replayed"],
            "status_agree": (c["status_same"] / n) if n else None,
            "with_positions": c["with_positions"],
            "identical_positions": self.identical,
            "position_diff_m": diffs.summary(),
            "peb_diff_m": self.peb_max,
            "examples": [{"node": k[0], "epoch": k[1], "diff_m": dist, "live_status": k[2],
                          "replayed_status": k[3], "received_ns": k[4]}
                         for dist, _, k in sorted(self.top, reverse=True)],
        }


class Recorded:
    """What replay's feed collects besides the fusion's input (``input_kinds``), its
    diagnostics and the anchors' liveliness: truth, live and replayed fixes (reduced as they
    come), their comparison, counts; with ``keep_estimates`` also the estimates.
    ``estimate_shards``: the fusion shards the run configuration records (the estimates'
    sequence streams, :class:`~diffpos_services.recording.topics.SeqTracker`). ``floor_of``:
    the recorded building's ``floor_index``, the true floor of a fix (:class:`TruthBook`);
    ``truth_floor``: where that building came from, for the report."""

    def __init__(self, input_kinds: tuple[str, ...], *, max_truth_gap_ns: int,
                 keep_estimates: bool, window_ns: int,
                 estimate_shards: int | None = None,
                 floor_of: Callable[[np.ndarray], Any] | None = None,
                 truth_floor: str = "the nearest truth sample's") -> None:
        self.input_kinds = input_kinds
        self.truth = TruthBook(window_ns, floor_of)
        self.truth_floor = truth_floor
        kw = {"max_truth_gap_ns": max_truth_gap_ns, "window_ns": window_ns}
        self.live, self.replayed = FixStream(self.truth, **kw), FixStream(self.truth, **kw)
        self.compare = Comparison(window_ns)
        self.keep: tuple[list, list] | None = ([], []) if keep_estimates else None
        self.counts: Counter[str] = Counter()
        self.bad_payloads: Counter[str] = Counter()
        self.seq = SeqTracker(estimate_shards)  # (None: the shard count inferred)
        self.t_origin: int | None = None  # the recording's first message (receive time)
        self.t_first: int | None = None
        self.t_last: int | None = None
        self._dec_est, self._dec_truth = slim_decoders()
        self._dec_full = M.estimate_decoder()

    @property
    def fusion_inputs(self) -> int:
        return sum(self.counts[k] for k in self.input_kinds)

    def advance(self, now_ns: int, *, final: bool = False) -> None:
        self.live.advance(now_ns, final=final)
        self.replayed.advance(now_ns, final=final)
        self.compare.expire(now_ns, final=final)

    def take(self, kind: str, m: RawMessage, node: str | None) -> None:
        """A recorded message that is not a fusion input, diagnostics or liveliness: node
        truth and live estimates (other kinds are only counted)."""
        try:
            if kind == "truth_node":
                g = self._dec_truth(m.data)
                if g.id != node:
                    raise ValueError("id differs from the topic's")
                self.truth.add(g.id, g.t_ns, g.position_m,
                               -999 if g.floor_index is None else g.floor_index)
            elif kind == "estimate":
                e = self._dec_est(m.data)
                if e.node_id != node:
                    raise ValueError("node_id differs from the topic's")
                if self.keep is not None:
                    self.keep[0].append(self._dec_full(m.data))
                self.live.add(e)
                self.compare.add(0, e, m.log_ns)
        except (ValueError, KeyError, TypeError, AttributeError, msgspec.DecodeError):
            self.bad_payloads[kind] += 1
