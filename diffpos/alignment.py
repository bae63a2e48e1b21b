"""Time alignment of asynchronous anchor measurements for the fusion (pure: numpy + stdlib).

Model and assumptions
---------------------
* Every anchor stamps its own state reports and ranges with **its own clock** (``t_ns``).
  The anchor position used with a range is its reported state **interpolated at the range's
  own t_ns** (:class:`StateHistory`), so an anchor's clock offset cancels between its own
  state and ranges.
* Different anchors are not synchronised: the fusion assumes their clocks agree within
  ``clock_tolerance_ns`` (a few ms: GNSS-disciplined clocks do far better; the paper assumes
  synchronised or round-trip ranging). Ranges are grouped per node into **epochs** of
  ``epoch_period_ns`` (epoch ``e`` holds ``e T <= t_ns < (e + 1) T``).
* Within an epoch the ranges were taken at different times while the node may move. The
  fix is referred to ``t_ref`` = the mean time of its ranges; each range is either
  compensated for the node's motion with a velocity estimate (``r' = r - J v (t - t_ref)``,
  :func:`compensate_node_motion`) or only de-weighted: its sigma is inflated by
  ``speed_sigma |t - t_ref|`` (:func:`effective_sigma_m`), together with the anchor's
  reported position uncertainty projected on the line of sight.
* An epoch of a node is **ready** (:class:`EpochBook`) when every live anchor has either
  reported for it or moved past its end (``latest t_ns >= end + clock_tolerance``), or when
  the **watermark** passed its end by the **allowance** (``release="measurement"``, the
  default). Both are measurement times, so the decision depends on what arrived and in which
  order, never on how fast the fusion's machine is (CPU load, replay speed):

  - watermark: the ``min_reports``-th newest latest time of the anchors (one or two stalled
    or hung anchors do not hold it back; a single future-stamped anchor does not push it;
    none with fewer anchors);
  - an epoch is *closed* the moment the watermark passes it (later ranges for it are late),
    so which ranges a fix uses depends on the arrival order only, not on when the fusion's
    loop happens to run (live and replay decide alike);
  - allowance: how far behind the watermark the anchors' data arrives, measured per anchor
    (the largest of its last 256 lags, plus a quarter), the largest over anchors that keep
    up, bounded to ``[deadline_ns, max_lag_ns]``; an anchor lagging beyond ``max_lag_ns`` (stalled,
    replaying a backlog) is not waited for: its ranges are late until it caught up.

  Wall-clock fallbacks only when measurement time stops: the bus was quiet for
  ``max_lag_ns`` (no range ingested: end of a run, every anchor gone) or an epoch waited
  ``max_lag_ns`` of wall time (fewer anchors than ``min_reports`` advance, a hung anchor
  among too few).
  ``release="wall"`` is the former rule (a wall deadline after the first range).
"""

from __future__ import annotations

import collections
import math
import operator
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from itertools import repeat
from typing import Any, Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "AlignmentConfig",
    "EpochBook",
    "EpochColumns",
    "PendingEpoch",
    "RangeEntry",
    "compensate_node_motion",
    "effective_sigma_m",
    "epoch_columns",
    "epoch_of",
    "epoch_reports",
    "reported_anchors",
]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class AlignmentConfig:
    """Time-alignment settings of the fusion.

    Attributes
    ----------
    epoch_period_ns : int [ns]
        Fusion epoch length (typically the anchors' ranging period).
    clock_tolerance_ns : int [ns]
        Assumed bound on the clock offset between anchors.
    deadline_ns : int [ns]
        The smallest allowance (measurement time past the watermark) an epoch waits for
        missing anchors. With ``release="wall"``: the wall time after the first range
        of an epoch at which it is solved (the former fixed deadline).
    max_state_extrapolation_ns : int [ns]
        How far beyond the newest (or before the oldest) anchor state a position may be
        extrapolated; beyond it the range is rejected as ``NO_ANCHOR_STATE``.
    node_speed_sigma_m_s : float [m/s]
        One-sigma node speed used to inflate sigmas when no velocity estimate is used.
    velocity_sigma_m_s : float [m/s]
        One-sigma error of a node velocity estimate used for motion compensation.
    min_reports : int
        An epoch is released before its deadline only with at least this many anchor reports
        (3: fewer cannot give a 3D fix anyway): at start-up, before every anchor has been
        seen, the first anchors alone must not complete an epoch.
    max_future_ns : int [ns]
        An epoch starting more than this after the consensus time (lower median of the live
        anchors' latest times, with >= 3 of them) is a *stray*: it is solved like any other
        but does not move the node's "already solved" mark, so one range with a wrong
        (future) time stamp cannot make the node's good ranges late.
    max_lag_ns : int or None [ns]
        The largest allowance (``None``: ``10 * deadline_ns``); an anchor whose data lags
        the watermark by more is not waited for. Also the wall-time bound of an epoch's wait.
    release : "measurement" or "wall"
        Epoch release rule (see the module docstring).
    """

    epoch_period_ns: int = 100_000_000
    clock_tolerance_ns: int = 5_000_000
    deadline_ns: int = 300_000_000
    max_state_extrapolation_ns: int = 500_000_000
    node_speed_sigma_m_s: float = 1.0
    velocity_sigma_m_s: float = 0.3
    min_reports: int = 3
    max_future_ns: int = 1_000_000_000
    max_lag_ns: int | None = None
    release: Literal["measurement", "wall"] = "measurement"

    def __post_init__(self) -> None:
        if self.release not in ("measurement", "wall"):
            raise ValueError("release must be 'measurement' or 'wall'")
        if self.max_lag_ns is not None and int(self.max_lag_ns) < int(self.deadline_ns):
            raise ValueError("max_lag_ns must be >= deadline_ns [ns]")
        for name in ("epoch_period_ns", "deadline_ns"):
            if int(getattr(self, name)) <= 0:
                raise ValueError(f"{name} must be > 0 [ns]")
        for name in ("clock_tolerance_ns", "max_state_extrapolation_ns", "max_future_ns"):
            if int(getattr(self, name)) < 0:
                raise ValueError(f"{name} must be >= 0 [ns]")
        for name in ("node_speed_sigma_m_s", "velocity_sigma_m_s"):
            if not float(getattr(self, name)) >= 0:
                raise ValueError(f"{name} must be >= 0 [m/s]")


def epoch_of(t_ns: ArrayLike, period_ns: int) -> NDArray[np.int64]:
    """Epoch index ``floor(t_ns / period_ns)`` (works for negative times)."""
    return np.floor_divide(np.asarray(t_ns, dtype=np.int64), np.int64(period_ns))


def effective_sigma_m(
    sigma_range_m: ArrayLike,
    anchor_sigma_m: ArrayLike,
    line_of_sight: ArrayLike,
    dt_s: ArrayLike,
    speed_sigma_m_s: ArrayLike,
) -> FloatArray:
    """Range sigma including anchor position uncertainty and node-motion misalignment.

    ``sigma_eff^2 = sigma_r^2 + sum_i (u_i sigma_a,i)^2 + (speed_sigma dt)^2`` with ``u`` the
    unit line of sight anchor -> node (the gradient of the path length with respect to the
    anchor position is a unit vector close to it).

    Parameters
    ----------
    sigma_range_m : array_like, shape (...) [m]
    anchor_sigma_m : array_like, shape (..., 3) [m]
    line_of_sight : array_like, shape (..., 3) [-]
        Any vector along anchor -> node (normalised here).
    dt_s : array_like, shape (...) [s]
        Measurement time minus fix reference time.
    speed_sigma_m_s : array_like [m/s]
    """
    u = np.asarray(line_of_sight, float)
    u = u / np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-12)
    a = np.sum(np.square(u * np.asarray(anchor_sigma_m, float)), axis=-1)
    motion = np.square(np.asarray(speed_sigma_m_s, float) * np.asarray(dt_s, float))
    return np.sqrt(np.square(np.asarray(sigma_range_m, float)) + a + motion)


def compensate_node_motion(
    range_m: ArrayLike,
    jacobian: ArrayLike,
    node_velocity_m_s: ArrayLike,
    dt_s: ArrayLike,
) -> FloatArray:
    """Refer ranges to the fix time: ``r' = r - (J . v) dt``.

    Parameters
    ----------
    range_m : array_like, shape (...) [m]
        Range measured at ``t`` (with the anchor at its position at ``t``).
    jacobian : array_like, shape (..., 3) [m/m]
        Gradient of the path length with respect to the node position.
    node_velocity_m_s : array_like, shape (..., 3) [m/s]
    dt_s : array_like, shape (...) [s]
        ``t - t_ref``.
    """
    rate = np.sum(np.asarray(jacobian, float) * np.asarray(node_velocity_m_s, float), axis=-1)
    return np.asarray(range_m, float) - rate * np.asarray(dt_s, float)


# ----------------------------------------------------------------------------- epochs
class RangeEntry(NamedTuple):
    """One range in an epoch (what the fusion keeps of a RangeMeasurement).

    A named tuple (immutable, created ~4x faster than a frozen dataclass: the fusion makes
    one per range, 4,000 per second at 8 anchors x 50 nodes x 10 Hz).
    """

    t_ns: int
    range_m: float | None
    sigma_m: float
    snr_db: float
    t_pub_wall_ns: int
    rx_wall_ns: int


class PendingEpoch:
    """Ranges of one node in one epoch, per anchor (the last one wins).

    Made by an :class:`EpochBook`: its ranges are a row of the epoch's columns (an
    ``_EpochBlock``); ``ranges`` is a read-only mapping view of that row (anchor ->
    :class:`RangeEntry`, each made when read; ``len`` and ``in`` without making any; the
    fusion reads the columns with :func:`epoch_columns`). Made directly (tests, tools):
    ``ranges`` is the dict given (or an empty one), kept and modifiable.
    """

    __slots__ = ("_block", "_dict", "_row", "epoch", "first_rx_wall_ns", "node_id")

    def __init__(self, node_id: str, epoch: int, first_rx_wall_ns: int,
                 ranges: dict[str, RangeEntry] | None = None,
                 _block: _EpochBlock | None = None, _row: int = -1) -> None:
        self.node_id = node_id
        self.epoch = epoch
        self.first_rx_wall_ns = first_rx_wall_ns
        self._dict = {} if ranges is None and _block is None else ranges
        self._block = _block  # (made by the book: its row there)
        self._row = _row

    @property
    def ranges(self) -> Mapping[str, RangeEntry]:
        blk = self._block
        return self._dict if blk is None else _RowRanges(blk, self._row)

    def __repr__(self) -> str:
        return (f"PendingEpoch(node_id={self.node_id!r}, epoch={self.epoch}, "
                f"first_rx_wall_ns={self.first_rx_wall_ns}, ranges={self.ranges!r})")


class _RowRanges(Mapping):
    """A read-only view of one row of an epoch block: anchor -> :class:`RangeEntry`."""

    __slots__ = ("_blk", "_row")

    def __init__(self, blk: _EpochBlock, row: int) -> None:
        self._blk, self._row = blk, row

    def _cols(self) -> list[int]:
        blk = self._blk
        return np.flatnonzero(blk.has[self._row, :len(blk.anchors)]).tolist()

    def __len__(self) -> int:
        blk = self._blk
        return int(np.count_nonzero(blk.has[self._row, :len(blk.anchors)]))

    def __iter__(self) -> Iterator[str]:
        anchors = self._blk.anchors
        return iter([anchors[c] for c in self._cols()])

    def __contains__(self, anchor_id: object) -> bool:
        c = self._blk.cols.get(anchor_id)  # type: ignore[call-overload]
        return c is not None and bool(self._blk.has[self._row, c])

    def __getitem__(self, anchor_id: str) -> RangeEntry:
        if anchor_id not in self:
            raise KeyError(anchor_id)
        return self._blk.entry(self._row, self._blk.cols[anchor_id])

    def __repr__(self) -> str:
        return repr(dict(self))


class _EpochBlock:
    """The ranges of one epoch as columns: a row per node-epoch (pending or released), a
    column per anchor; per cell the range ``r`` [m] (NaN: not detected), ``sig`` [m], ``snr``
    [dB], times ``t``, ``pub``, ``rx`` [ns] and ``has`` (the anchor reported); per row its
    node's book index ``gid``, first receive time, ``open`` (still pending) and its
    :class:`PendingEpoch`. Rows are made in the order nodes first report, so the batches of
    a lockstep run fill contiguous rows (slices, no index arrays)."""

    __slots__ = ("anchors", "cols", "epoch", "first_rx", "gid", "has", "n", "names", "open",
                 "pes", "pub", "r", "rows", "rx", "sig", "snr", "t")

    def __init__(self, epoch: int, rows: int = 64, cols: int = 8) -> None:
        self.epoch = epoch
        self.rows: dict[str, int] = {}  # node -> its pending row
        self.cols: dict[str, int] = {}  # anchor -> column
        self.names: list[str] = []
        self.anchors: list[str] = []
        self.pes: list[PendingEpoch] = []
        self.n = 0
        self.r, self.sig, self.snr = (np.empty((rows, cols)) for _ in range(3))
        self.t, self.pub, self.rx = (np.empty((rows, cols), np.int64) for _ in range(3))
        self.has = np.zeros((rows, cols), bool)
        self.first_rx = np.zeros(rows, np.int64)
        self.gid = np.zeros(rows, np.int64)
        self.open = np.zeros(rows, bool)

    def col(self, anchor_id: str) -> int:
        c = self.cols.get(anchor_id)
        if c is None:
            c = self.cols[anchor_id] = len(self.anchors)
            self.anchors.append(anchor_id)
            if c >= self.has.shape[1]:
                self._grow(self.has.shape[0], 2 * c)
        return c

    def new_rows(self, node_ids: list[str], gids: list[int], rx_wall_ns: Sequence[int]
                 ) -> list[PendingEpoch]:
        """Rows for ``node_ids`` (none of them pending here), first received at
        ``rx_wall_ns``; their :class:`PendingEpoch` objects."""
        r0, k = self.n, len(node_ids)
        if r0 + k > self.has.shape[0]:
            self._grow(max(2 * self.has.shape[0], r0 + k), self.has.shape[1])
        self.n = r0 + k
        self.rows.update(zip(node_ids, range(r0, r0 + k), strict=True))
        self.names += node_ids
        self.gid[r0:r0 + k], self.first_rx[r0:r0 + k] = gids, rx_wall_ns
        self.open[r0:r0 + k] = True
        pes = list(map(PendingEpoch, node_ids, repeat(self.epoch), rx_wall_ns, repeat(None),
                       repeat(self), range(r0, r0 + k)))
        self.pes += pes
        return pes

    def _grow(self, rows: int, cols: int) -> None:
        def grown(a: np.ndarray, fill) -> np.ndarray:
            out = np.full((rows, cols) if a.ndim > 1 else (rows,), fill, a.dtype)
            out[tuple(slice(0, k) for k in a.shape)] = a
            return out
        self.r, self.sig, self.snr = (grown(a, np.nan) for a in (self.r, self.sig, self.snr))
        self.t, self.pub, self.rx = (grown(a, 0) for a in (self.t, self.pub, self.rx))
        self.has = grown(self.has, False)
        self.first_rx, self.gid = grown(self.first_rx, 0), grown(self.gid, 0)
        self.open = grown(self.open, False)

    def count(self, rows: Any) -> NDArray[np.int64]:
        """Reports of ``rows`` (any anchor)."""
        return np.count_nonzero(self.has[rows, :len(self.anchors)], axis=-1)

    def entry(self, row: int, c: int) -> RangeEntry:
        """Cell (row, c) as a :class:`RangeEntry` (range ``None``: not detected)."""
        r = float(self.r[row, c])
        return RangeEntry(int(self.t[row, c]), None if r != r else r, float(self.sig[row, c]),
                          float(self.snr[row, c]), int(self.pub[row, c]), int(self.rx[row, c]))

    def put(self, row: int, c: int, entry: RangeEntry) -> bool:
        """One range into cell (row, c); True if it replaced one."""
        was = bool(self.has[row, c])
        self.has[row, c] = True
        r = entry.range_m
        self.r[row, c] = math.nan if r is None else r
        self.sig[row, c], self.snr[row, c] = entry.sigma_m, entry.snr_db
        self.t[row, c], self.pub[row, c] = entry.t_ns, entry.t_pub_wall_ns
        self.rx[row, c] = entry.rx_wall_ns
        return was

    def put_columns(self, rows: Any, c: int, cols: tuple) -> int:
        """Ranges into column ``c`` of ``rows`` (a slice or an index array): ``cols`` =
        (range, sigma, snr, t, pub, rx), arrays or one value each; how many replaced one."""
        was = int(np.count_nonzero(self.has[rows, c]))
        self.has[rows, c] = True
        self.r[rows, c], self.sig[rows, c], self.snr[rows, c] = cols[:3]
        self.t[rows, c], self.pub[rows, c], self.rx[rows, c] = cols[3:]
        return was


#: "Before any time" for the latest-time and solved-epoch maps [ns or epoch index].
_NEVER = -(2**62)
_NEVER_EPOCH = -(2**63)  # below every epoch index (no epoch is closed)
_EPOCH = operator.attrgetter("epoch")
_FIRST_RX = operator.attrgetter("first_rx_wall_ns")
#: Lag samples kept per anchor, and how many new ones trigger a new allowance.
_LAG_SAMPLES = 256
_LAG_REFRESH = 32


class EpochBook:
    """Groups ranges per (node, epoch) and decides when an epoch is ready to solve.

    Anchors are expected to publish their measurements in time order (they do); a range for
    an epoch that was already solved is counted as *late* (per anchor in ``late_by_anchor``)
    and dropped. ``watermark_ns`` and ``allowance_ns`` are the release rule in force (module
    docstring); ``lag_ns(anchor)`` is an anchor's observed lag behind the watermark.
    """

    def __init__(self, config: AlignmentConfig) -> None:
        self.config = config
        self.pending: dict[tuple[str, int], PendingEpoch] = {}
        self.latest_t_ns: dict[str, int] = {}
        self.solved_upto: dict[str, int] = {}  # node -> last solved epoch
        self.late = 0
        self.late_by_anchor: collections.Counter[str] = collections.Counter()
        self.replaced = 0
        self.strays = 0
        self.max_lag_ns = (10 * int(config.deadline_ns) if config.max_lag_ns is None
                           else int(config.max_lag_ns))
        self.allowance_ns = int(config.deadline_ns)
        self.watermark_ns: int | None = None
        self.last_rx_wall_ns: int | None = None  # newest ingestion wall time of a range
        # epochs up to this one are closed by the watermark (measurement release): decided
        # when the watermark moves, i.e. by arrival order, not by when step() runs
        self.closed_upto = _NEVER
        self._lags: dict[str, collections.deque[int]] = {}
        self._lag_new = 0
        # the ranges by epoch as columns (their PendingEpoch objects are in ``pending``), and
        # a number per node (the release rule's arrays)
        self._blocks: dict[int, _EpochBlock] = {}
        self._gids: dict[str, int] = {}
        self._adds = 0  # ranges added (a change of the pending epochs' contents)
        # (state, live anchors, wall time before which nothing can time out) of the last
        # ready() call that released nothing: the same state releases nothing until then
        self._idle: tuple | None = None

    def add(self, anchor_id: str, node_id: str, entry: RangeEntry) -> bool:
        """Add a range; False (and ``late`` += 1) if its epoch was already solved."""
        t, rx = entry.t_ns, entry.rx_wall_ns
        e = int(t // self.config.epoch_period_ns)
        prev = self.latest_t_ns.get(anchor_id)
        if prev is None or t > prev:  # (note_anchor_time does nothing otherwise)
            self.note_anchor_time(anchor_id, t)
        last_rx = self.last_rx_wall_ns
        if last_rx is None or rx > last_rx:
            self.last_rx_wall_ns = int(rx)
        if e <= self.solved_upto.get(node_id, _NEVER) or e <= self.closed_upto:
            self.late += 1
            self.late_by_anchor[anchor_id] += 1
            return False
        blk = self._block(e)
        row = blk.rows.get(node_id)
        if row is None:
            pe = self.pending[(node_id, e)] = blk.new_rows([node_id], [self._gid(node_id)],
                                                         [rx])[0]
            row = pe._row
        if blk.put(row, blk.col(anchor_id), entry):
            self.replaced += 1
        self._adds += 1
        return True

    def _block(self, epoch: int) -> _EpochBlock:
        blk = self._blocks.get(epoch)
        if blk is None:
            blk = self._blocks[epoch] = _EpochBlock(epoch)
        return blk

    def _gid(self, node_id: str) -> int:
        g = self._gids.get(node_id)
        if g is None:
            g = self._gids[node_id] = len(self._gids)
        return g

    def add_many(self, anchor_id: str, t_ns: int, entries: list[tuple[str, RangeEntry]]) -> int:
        """Add ranges of one anchor taken at the same time ``t_ns`` (one epoch); returns how
        many were late (their node's epoch already solved). A node twice: the last one wins."""
        if entries and len({n for n, _ in entries}) == len(entries):
            t, r, sg, snr, pub, rx = zip(*(x for _, x in entries), strict=True)
            return self.add_columns(anchor_id, t_ns, [n for n, _ in entries],
                                    np.array(r, np.float64), sg, snr, t, pub, rx)
        e = int(t_ns // self.config.epoch_period_ns)
        self.note_anchor_time(anchor_id, t_ns)
        late = 0
        if e <= self.closed_upto:
            late = len(entries)
        else:
            blk = self._block(e)
            c = blk.col(anchor_id)
            for node_id, entry in entries:
                row = blk.rows.get(node_id)
                if row is None:
                    if e <= self.solved_upto.get(node_id, _NEVER):
                        late += 1
                        continue
                    pe = self.pending[(node_id, e)] = blk.new_rows(
                        [node_id], [self._gid(node_id)], [entry.rx_wall_ns])[0]
                    row = pe._row
                self.replaced += blk.put(row, c, entry)
        if entries:
            self._adds += 1
            self._note_rx(entries[-1][1].rx_wall_ns)
        if late:
            self.late += late
            self.late_by_anchor[anchor_id] += late
        return late

    def add_columns(self, anchor_id: str, t_ns: int, node_ids: Sequence[str],
                    range_m: ArrayLike, sigma_m: ArrayLike, snr_db: ArrayLike,
                    meas_t_ns: ArrayLike, t_pub_wall_ns: ArrayLike,
                    rx_wall_ns: ArrayLike) -> int:
        """:meth:`add_many` of one anchor's ranges at ``t_ns`` given as columns (each node
        once): ``range_m`` NaN where not detected; the other columns per range or one value
        for all. Returns how many were late. No Python object per range: the columns go
        into the epoch's block with a few array operations (slices in a lockstep run)."""
        e = int(t_ns // self.config.epoch_period_ns)
        self.note_anchor_time(anchor_id, t_ns)
        n = len(node_ids)
        if not n:
            return 0
        late = 0
        one_rx = isinstance(rx_wall_ns, int | np.integer)
        rx_last = int(rx_wall_ns if one_rx else rx_wall_ns[-1])
        if e <= self.closed_upto:
            late = n
        else:
            blk = self._block(e)
            c = blk.col(anchor_id)
            rows = list(map(blk.rows.get, node_ids))
            cols = (range_m, sigma_m, snr_db, meas_t_ns, t_pub_wall_ns, rx_wall_ns)
            if None in rows:
                rx = [int(rx_wall_ns)] * n if one_rx else rx_wall_ns
                rows, keep = self._new_rows(blk, e, node_ids, rows, rx)
                late = n - len(keep)
                if late:
                    cols = tuple(v if np.ndim(v) == 0 else np.asarray(v)[keep] for v in cols)
            if rows:
                r0 = rows[0]
                at = (slice(r0, r0 + len(rows)) if rows[-1] - r0 == len(rows) - 1
                      and rows == list(range(r0, r0 + len(rows))) else np.array(rows, np.intp))
                self.replaced += blk.put_columns(at, c, cols)
        self._adds += 1
        self._note_rx(rx_last)
        if late:
            self.late += late
            self.late_by_anchor[anchor_id] += late
        return late

    def _new_rows(self, blk: _EpochBlock, e: int, node_ids: Sequence[str],
                  rows: list[int | None], rx_wall_ns: Sequence[int]
                  ) -> tuple[list[int], list[int]]:
        """Rows for the nodes of ``node_ids`` without one (``rows[k]`` None) in epoch ``e``,
        but those whose epoch ``e`` is solved already (late), first received at
        ``rx_wall_ns[k]``; the rows of the kept entries and their indices."""
        solved = self.solved_upto
        new = [k for k, row in enumerate(rows) if row is None]
        fresh = [k for k in new if e > solved.get(node_ids[k], _NEVER)]
        if fresh:
            ids = [node_ids[k] for k in fresh]
            pes = blk.new_rows(ids, [self._gid(x) for x in ids],
                               [int(rx_wall_ns[k]) for k in fresh])
            self.pending.update(zip(zip(ids, repeat(e)), pes, strict=True))
            for k, pe in zip(fresh, pes, strict=True):
                rows[k] = pe._row
        if len(fresh) == len(new):
            return rows, list(range(len(rows)))
        keep = [k for k, row in enumerate(rows) if row is not None]
        return [rows[k] for k in keep], keep

    def _note_rx(self, rx_wall_ns: int) -> None:
        if self.last_rx_wall_ns is None or rx_wall_ns > self.last_rx_wall_ns:
            self.last_rx_wall_ns = int(rx_wall_ns)

    def note_anchor_time(self, anchor_id: str, t_ns: int) -> None:
        """Advance an anchor's latest time (e.g. from its state reports); a new time is also
        a lag sample: how far the watermark was ahead of it when it arrived."""
        prev = self.latest_t_ns.get(anchor_id)
        if prev is None or t_ns > prev:
            t = int(t_ns)
            wm = self.watermark_ns
            if wm is not None:
                lags = self._lags.get(anchor_id)
                if lags is None:
                    lags = self._lags[anchor_id] = collections.deque(maxlen=_LAG_SAMPLES)
                lags.append(max(wm - t, 0))
                self._lag_new += 1
            self.latest_t_ns[anchor_id] = t
            if wm is None or t > wm:
                self._update_watermark()
                self._close()

    def _close(self) -> None:
        """Advance ``closed_upto``: epochs whose end + tolerance + allowance the watermark
        passed (measurement release only; never moves back)."""
        cfg = self.config
        wm = self.watermark_ns
        if cfg.release == "measurement" and wm is not None:
            last = (wm - cfg.clock_tolerance_ns - self._allowance()) // cfg.epoch_period_ns - 1
            if last > self.closed_upto:
                self.closed_upto = int(last)

    def _update_watermark(self) -> None:
        """The ``min_reports``-th newest anchor time (None with fewer anchors: then only the
        wall fallbacks release epochs)."""
        ts = sorted(self.latest_t_ns.values(), reverse=True)
        k = max(self.config.min_reports, 1)
        self.watermark_ns = ts[k - 1] if len(ts) >= k else None

    def lag_ns(self, anchor_id: str) -> int | None:
        """The largest of an anchor's recent lags behind the watermark [ns] (None: no
        samples yet)."""
        lags = self._lags.get(anchor_id)
        return max(lags) if lags else None

    def _allowance(self) -> int:
        """The allowance in force: the largest recent lag of the anchors that keep up (+25 %),
        bounded to ``[deadline_ns, max_lag_ns]`` (recomputed every few lag samples)."""
        if self._lag_new >= _LAG_REFRESH:
            self._lag_new = 0
            keep = [q for a in self._lags if (q := self.lag_ns(a)) is not None
                    and q <= self.max_lag_ns]
            # a quarter more than seen: the next delay is often a little longer
            self.allowance_ns = min(max([int(self.config.deadline_ns), *keep]) * 5 // 4,
                                    self.max_lag_ns)
        return self.allowance_ns

    def forget_anchor(self, anchor_id: str) -> None:
        self.latest_t_ns.pop(anchor_id, None)
        self._lags.pop(anchor_id, None)
        self._update_watermark()

    def set_anchor_time(self, anchor_id: str, t_ns: int) -> None:
        """Overwrite an anchor's latest time (its previous one was found implausible)."""
        self.latest_t_ns[anchor_id] = int(t_ns)
        self._update_watermark()

    def consensus_t_ns(self, live_anchors: set[str] | frozenset[str]) -> int | None:
        """Lower median of the live anchors' latest times (None with fewer than 3)."""
        ts = sorted(self.latest_t_ns[a] for a in live_anchors if a in self.latest_t_ns)
        return ts[(len(ts) - 1) // 2] if len(ts) >= 3 else None

    def _timeout_rule(self, now_wall_ns: int) -> tuple[bool, int, int]:
        """When an epoch is released without waiting for missing anchors (measurement
        watermark past its end + allowance, or a wall-clock fallback), as numbers
        ``(everything, last, cutoff)``: ``pe`` is timed out when ``everything`` (the bus was
        quiet for ``max_lag_ns``: every epoch), ``pe.epoch <= last`` (closed by the watermark)
        or ``pe.first_rx_wall_ns <= cutoff`` (waited ``max_lag_ns`` of wall time; with
        ``release="wall"``: ``deadline_ns``, and nothing is closed)."""
        cfg = self.config
        if cfg.release == "wall":
            # now - first >= deadline <=> first <= now - ceil(deadline) (integer times)
            return False, _NEVER_EPOCH, now_wall_ns - math.ceil(cfg.deadline_ns)
        quiet = (self.last_rx_wall_ns is not None
                 and now_wall_ns - self.last_rx_wall_ns >= self.max_lag_ns)
        return quiet, self.closed_upto, now_wall_ns - self.max_lag_ns

    def ready(self, live_anchors: set[str] | frozenset[str], now_wall_ns: int) -> list[PendingEpoch]:
        """Remove and return the epochs that are ready, oldest first.

        Ready: every live anchor reported for it or its latest time passed the epoch end by
        the clock tolerance (and at least ``min_reports`` reports); or it timed out (module
        docstring: watermark + allowance, or a wall fallback). Epochs of a node are released
        in order (a later epoch never overtakes an earlier pending one).
        """
        out: list[PendingEpoch] = []
        if not self.pending:
            return out
        state = self._state()
        idle = self._idle
        if idle is not None and idle[0] == state and now_wall_ns < idle[2] and (
                idle[1] is live_anchors or idle[1] == live_anchors):
            return out  # nothing changed and nothing can have timed out since (cheap no-op)
        rule = self._timeout_rule(now_wall_ns)
        t_c = self.consensus_t_ns(live_anchors)
        cfg = self.config
        horizon = None if t_c is None else (t_c + cfg.max_future_ns) // cfg.epoch_period_ns
        blocked = np.zeros(len(self._gids), bool)  # per node: an earlier epoch not released
        epochs = sorted(e for e, b in self._blocks.items() if b.open[:b.n].any())
        for e in epochs:  # a node not done in the newest epoch blocks nothing later
            self._release(self._blocks[e], rule, live_anchors, blocked, e != epochs[-1],
                          horizon, out)
        self._idle = None if out else (state, live_anchors, self._wake_wall_ns())
        return out

    def _release(self, blk: _EpochBlock, rule: tuple[bool, int, int],
                 live_anchors: set[str] | frozenset[str], blocked: np.ndarray, block: bool,
                 horizon: int | None, out: list[PendingEpoch]) -> None:
        """:meth:`ready` for one epoch's block: its ready rows into ``out`` (by node id), the
        nodes of the others into ``blocked`` when ``block``."""
        everything, last, cutoff = rule
        cfg = self.config
        e, n = blk.epoch, blk.n
        gid = blk.gid[:n]
        cand = blk.open[:n] & ~blocked[gid]
        if not cand.any():
            return
        if everything or e <= last:
            done = cand
        else:
            done = cand & (blk.first_rx[:n] <= cutoff)  # waited max_lag_ns (wall)
            full = cand & ~done & (blk.count(slice(0, n)) >= cfg.min_reports)
            if full.any():  # complete: each live anchor not past its end reported
                end_ns = (e + 1) * cfg.epoch_period_ns + cfg.clock_tolerance_ns
                latest, cols = self.latest_t_ns, blk.cols
                waiting = [cols.get(a, -1) for a in live_anchors
                           if latest.get(a, _NEVER) < end_ns]
                if -1 not in waiting:
                    done = done | (full & blk.has[:n, waiting].all(axis=1) if waiting else full)
        if block:
            blocked[gid[cand & ~done]] = True
        rel = np.flatnonzero(done)
        if not rel.size:
            return
        blk.open[rel] = False
        names, pes, rows = blk.names, blk.pes, blk.rows
        pending, solved = self.pending, self.solved_upto
        stray = horizon is not None and e > horizon
        for r in sorted(rel.tolist(), key=names.__getitem__):
            node_id = names[r]
            out.append(pes[r])
            del pending[(node_id, e)], rows[node_id]
            if stray:
                self.strays += 1
            else:
                solved[node_id] = max(e, solved.get(node_id, _NEVER))
        if not blk.open[:n].any():
            del self._blocks[e]

    def take_all(self) -> list[PendingEpoch]:
        """Remove and return every pending epoch, oldest epoch first (at shutdown)."""
        out = sorted(self.pending.values(), key=_EPOCH)
        self.pending.clear()
        self._blocks.clear()
        return out

    def _state(self) -> tuple:
        """What ready() depends on besides the live anchors and the wall clock."""
        return (self._adds, len(self.pending), self.closed_upto, self.watermark_ns,
                self.max_lag_ns, self.last_rx_wall_ns, self.config,
                tuple(self.latest_t_ns.items()))

    def _first_rx_wall_ns(self) -> int:
        """The earliest first receive time of a pending epoch (some must be pending)."""
        blocks = [b for b in self._blocks.values() if b.open[:b.n].any()]
        if not blocks:  # (epochs put into ``pending`` directly)
            return min(map(_FIRST_RX, self.pending.values()))
        return min(int(b.first_rx[:b.n][b.open[:b.n]].min()) for b in blocks)

    def _wake_wall_ns(self) -> int:
        """The earliest wall time at which a pending epoch can time out (see _timeout_rule)."""
        first = self._first_rx_wall_ns()
        if self.config.release == "wall":
            return first + self.config.deadline_ns
        wake = first + self.max_lag_ns
        if self.last_rx_wall_ns is not None:
            wake = min(wake, self.last_rx_wall_ns + self.max_lag_ns)
        return wake

    def next_deadline_wall_ns(self) -> int | None:
        """Earliest wall time at which a pending epoch times out by a wall-clock rule (for
        the main loop wait)."""
        if not self.pending:
            return None
        first = self._first_rx_wall_ns()
        if self.config.release == "wall":
            return first + self.config.deadline_ns
        return first + self.max_lag_ns


# ------------------------------------------------------------------- epochs as columns
class EpochColumns(NamedTuple):
    """Epochs' ranges as ``(B, M)`` arrays over anchor columns (:func:`epoch_columns`)."""

    t: NDArray[np.int64]  # [ns] measurement time of each reported range, 0 elsewhere
    range_m: FloatArray  # [m], NaN where not detected
    sigma_m: FloatArray  # [m], 1 where not detected
    snr_db: FloatArray  # [dB], NaN where not detected
    reported: NDArray[np.bool_]  # the anchor reported for the epoch
    detected: NDArray[np.bool_]  # ... with a range
    t_pub_wall: NDArray[np.int64]  # [ns] publish wall time of each reported range, 0 elsewhere
    count: NDArray[np.int64]  # (B,) reports of each epoch (every anchor, named or not)


def _by_block(epochs: Sequence[PendingEpoch]) -> tuple[dict, list[int]]:
    """``{id(block): (block, epoch rows, block rows)}`` of the book-made epochs, and the
    indices of the others (their ranges a dict)."""
    groups: dict[int, tuple[_EpochBlock, list[int], list[int]]] = {}
    loose = []
    for k, pe in enumerate(epochs):
        blk = pe._block
        if blk is None:
            loose.append(k)
            continue
        g = groups.get(id(blk))
        if g is None:
            g = groups[id(blk)] = (blk, [], [])
        g[1].append(k)
        g[2].append(pe._row)
    return groups, loose


def epoch_columns(epochs: Sequence[PendingEpoch], ids: Sequence[str]) -> EpochColumns:
    """The ranges of ``epochs`` (rows) as arrays over the anchor columns ``ids`` (every
    anchor that reported for one of them must be named): gathered from the book's blocks
    with a few array operations per epoch block, no Python object per range."""
    col = {a: j for j, a in enumerate(ids)}
    b, m = len(epochs), len(ids)
    t = np.zeros((b, m), np.int64)
    rng = np.full((b, m), np.nan)
    sig = np.ones((b, m))
    snr = np.full((b, m), np.nan)
    reported = np.zeros((b, m), bool)
    pub = np.zeros((b, m), np.int64)
    count = np.zeros(b, np.int64)
    groups, loose = _by_block(epochs)
    for blk, ri, br in groups.values():
        bc = [c for c, a in enumerate(blk.anchors) if a in col]
        if not bc:
            count[ri] = blk.count(br)
            continue
        jc = [col[blk.anchors[c]] for c in bc]
        sel = np.ix_(br, bc)
        out = np.ix_(ri, jc)
        h = blk.has[sel]
        reported[out] = h
        t[out] = np.where(h, blk.t[sel], 0)
        pub[out] = np.where(h, blk.pub[sel], 0)
        r = blk.r[sel]
        det = h & ~np.isnan(r)
        rng[out] = np.where(det, r, np.nan)
        sig[out] = np.where(det, blk.sig[sel], 1.0)
        snr[out] = np.where(det, blk.snr[sel], np.nan)
        count[ri] = blk.count(br)
    for k in loose:
        ranges = epochs[k].ranges
        count[k] = len(ranges)
        for a, x in ranges.items():
            j = col[a]
            reported[k, j], t[k, j], pub[k, j] = True, x.t_ns, x.t_pub_wall_ns
            if x.range_m is not None:
                rng[k, j], sig[k, j], snr[k, j] = x.range_m, x.sigma_m, x.snr_db
    return EpochColumns(t, rng, sig, snr, reported, ~np.isnan(rng), pub, count)


def epoch_reports(epochs: Sequence[PendingEpoch], ids: Sequence[str]
                  ) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """Which of the anchors ``ids`` reported for each epoch (B, M), and each epoch's number
    of reports from any anchor (B,)."""
    col = {a: j for j, a in enumerate(ids)}
    reported = np.zeros((len(epochs), len(ids)), bool)
    count = np.zeros(len(epochs), np.int64)
    groups, loose = _by_block(epochs)
    for blk, ri, br in groups.values():
        count[ri] = blk.count(br)
        bc = [c for c, a in enumerate(blk.anchors) if a in col]
        if bc:
            reported[np.ix_(ri, [col[blk.anchors[c]] for c in bc])] = blk.has[np.ix_(br, bc)]
    for k in loose:
        ranges = epochs[k].ranges
        count[k] = len(ranges)
        for a in ranges:
            if a in col:
                reported[k, col[a]] = True
    return reported, count


def reported_anchors(epochs: Sequence[PendingEpoch]) -> set[str]:
    """The anchors that reported for at least one of ``epochs``."""
    out: set[str] = set()
    groups, loose = _by_block(epochs)
    for blk, _, br in groups.values():
        m = len(blk.anchors)
        out.update(blk.anchors[c] for c in np.flatnonzero(blk.has[br, :m].any(axis=0)).tolist())
    for k in loose:
        out.update(epochs[k].ranges)
    return out
