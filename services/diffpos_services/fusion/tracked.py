"""The mechanism-aware solve step (``method = "mnls"``) and the per-responder tracker.

Used by :meth:`FusionCore._solve <diffpos_services.fusion.core.FusionCore._solve>` when the
method is ``mnls``: the epochs of a batch (gathered and prepared by
:mod:`diffpos_services.fusion.step`) get

- the snapshot fix :func:`diffpos.estimators.mnls.solver` on the scenario's building (every row
  without tracking; with tracking only the rows whose node never had one, whose node the
  tracker does not place (UNINITIALISED, LOST: the snapshot is then the only fix of it), or
  whose last snapshot is ``snapshot_period_s`` of measurement time old; for a *confident*
  confirmed track, its floor at >= :data:`CONFIDENT_FLOOR_PROBABILITY` and its averaged NIS
  <= :data:`CONFIDENT_NIS`, ``FusionConfig.confident_snapshot_period_s`` old: by default
  never after its first, a confident track's snapshot decides nothing). The snapshot is
  published alongside (``PositionEstimateV2.snapshot``, an independent check of the track) and
  never feeds the tracker, nor anything else of the fusion (no divergence test or
  re-initialisation reads it: the tracker's own initialisation is its grid snapshot,
  :func:`diffpos.tracking.model.snapshot_init`), so this policy changes no tracked estimate,
  only the CPU: an mnls fix costs ~7 ms with 8 anchors, i.e. 0.7 ms per node-epoch at 10 Hz
  with a 1 s period, more than the tracker's update. (Until 2026-11-27 an unconfirmed track
  got one every epoch: 1,654 instead of 661 snapshots in the 30 s soak replay, the tracked
  estimates bit for bit the same, CPU 58.0 / 56.2 -> 49.9 / 46.3 s: docs/measurements.md.)
  Measured (``bench_tracking``'s lockstep emulation, seed 0, 20 s;
  the trkcost branch's report): a confirmed track was confident in 93.0 / 99.6 / 92.2 % of
  the node-epochs of ``default`` / ``large`` / ``other-building``, its floor then right in
  96.6 / 99.9 / 95.3 % of them (44.7 / 64.7 / 8.6 % when not confident): the confident
  tracks get a snapshot every 10 s, the doubtful ones every second;
- with tracking, the update of :mod:`diffpos.tracking.tracker` (per node: floor x {level, vertical}
  hypotheses, one iterated EKF each, mixed between epochs): all the
  batch's nodes in one vectorised call per *round* (a round holds at most one epoch per node,
  oldest first, so a backlog of several epochs of one node is applied in time order). A node
  whose epoch has no usable range is predicted only (COASTING, the covariance grows).

**Bounded work per step** (``heavy``, the live service's steps; issue 16): a track
initialisation (the grid snapshot: ~5 ms per node with 8 anchors; 3.3 ms with 16 since
2026-11-28) and an mnls snapshot fix (~3.5 ms) each cost several epochs' updates (~0.6 ms per
node-epoch + ~2.6 ms per call, ``large``'s batches). Without a bound, the first epoch of 50
new nodes cost ~0.45 s in one step, and the snapshots of 50 unconfirmed tracks ~0.2 s per epoch
after it, so every node's estimate waited (real-time ``large``: end-to-end p99 1.75 s). A
budgeted step (one with a ``limit``) does at most ``heavy`` of them (:func:`heavy_budget`: a
fraction of the work of the epochs it solves): initialisations first, in row order; a node whose initialisation does not fit
is passed to the tracker without ranges this epoch (it stays UNINITIALISED or LOST, published
without a position on time) and is initialised by a later step; then the due snapshots, the
stalest first; one that does not fit stays due. The budget only moves *when* a track starts and
*which* epochs carry a snapshot. The epochs of a budgeted step's initialisations are solved
after its other epochs (:meth:`TrackBank.hold_inits`), and the live service publishes those
first: an initialisation delays only its own node's estimate. Snapshots have a budget of their own besides
(:data:`SNAPSHOT_WORK_EPOCHS`: one per 50 epochs solved on average, a credit the bank carries
from step to step), and a step that leaves ready epochs (the fusion is behind its input)
gives none to a node the tracker places (they were ~18 % of the CPU on the 16 x 200 soak's
input, `bench_fusion_cost.py --schedule`: 36,833 / 39,760 -> 49,564 / 50,509 of 60,000).
``heavy=None`` (replay of steps without a limit, flush, tests) is unbounded.

:class:`TrackBank` holds the tracker state of every node the core has seen (rows of one
:class:`~diffpos.tracking.tracker.TrackerState`); it is part of the network-free core, so a replay
re-runs it. Everything is a function of the inputs: no clock, no randomness. Without a budget a
node's result depends only on its own epochs (rows are independent in every vectorised step),
so any batching gives the same numbers bit for bit; with one, also on the steps' ``limit``
(which the decision record keeps, so a replay by the record re-issues the same steps and gets
the same numbers bit for bit).

:func:`~diffpos_services.fusion.estimates_v2.estimates_v2` turns a solved batch into
:class:`~diffpos_services.wire.messages.PositionEstimateV2` messages (a column batch).
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from diffpos.alignment import PendingEpoch
from diffpos.estimators.mnls import solver as mnls_solver
from diffpos.estimators.mnls.rules import SnrRule
from diffpos.estimators.result import ExclusionReason, FixStatus
from diffpos.paths.mechanisms import MECHANISMS
from diffpos.tracking.state import (
    TrackerConfig,
    TrackerState,
    TrackStatus,
    floor_probabilities,
    has_position,
)
from diffpos.tracking.tracker import init_state, update
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.estimates import Estimates
from diffpos_services.fusion.rows import run_update, slim_state
from diffpos_services.fusion.step import Batch, Prepared, Results
from diffpos_services.fusion.workers import INIT_COST, RowPool

__all__ = ["HEAVY_MIN_OPERATIONS", "HEAVY_WORK_EPOCHS", "SNAPSHOT_WORK_EPOCHS", "Solved",
           "TrackBank", "heavy_budget", "in_publish_order", "solve_mnls"]

_FIX_NAMES = {int(s): s.name for s in FixStatus}
_TRACK_NAMES = {int(s): s.name for s in TrackStatus}
_RAIM = int(ExclusionReason.RAIM)
#: A confirmed track is *confident* when its most probable floor has at least this
#: probability (marginal over the vertical modes) ...
CONFIDENT_FLOOR_PROBABILITY = 0.99
#: ... and its averaged NIS per used range (the tracker's ``nis``) is at most this (the
#: residuals fit their sigmas: rms within 2 sigma).
CONFIDENT_NIS = 4.0
#: Epochs solved per track initialisation or mnls snapshot fix a budgeted step may do. With 8
#: anchors an initialisation costs ~5 ms and a snapshot ~3.5 ms, an epoch ~1-1.2 ms all in
#: (tracker update, batch assembly, messages; the live ``large`` run's steps replayed): the
#: heavy work of a step is then at most about half its regular work, so a burst of new tracks
#: slows the steps by up to a half instead of stalling them (50 new nodes at 10 Hz are
#: initialised within ~1 s, bench_fusion_cost.py --schedule); each step may do at least
#: :data:`HEAVY_MIN_OPERATIONS`.
HEAVY_WORK_EPOCHS = 10
#: Heavy operations any budgeted step may do, however few epochs it solves: ~10 ms with 8
#: anchors, well inside the 50 ms end-to-end goal. With one, a small fleet's tracks started one
#: per step (6 responders: 15 of the first 120 estimates had no position, where the
#: unbudgeted fusion initialised all six in the first step).
HEAVY_MIN_OPERATIONS = 2
#: Epochs solved per mnls snapshot fix budgeted steps may do, on average (a credit carried
#: from step to step in the :class:`TrackBank`, at most :data:`SNAPSHOT_BURST` banked), within
#: the step's ``heavy`` budget. A snapshot never feeds the tracker (it is a check published
#: alongside), so its rate only moves CPU: at ~3.5 ms it costs ~6 epochs' updates, and one per
#: 50 epochs adds ~10 % to the regular work of a step instead of up to ~60 % (5 snapshots in a
#: step of 50 epochs with ``heavy_budget``; measured on the real-time ``large`` input,
#: bench_fusion_cost.py --schedule: steps of 42 epochs with 4 snapshots took 50 ms, 35 epochs
#: without 21-23 ms). With N nodes at 10 Hz the credit gives N/5 snapshots per s: twenty
#: times what confident tracks need (N/100); doubtful and unconfirmed tracks (due every 1 s)
#: and nodes without a tracked position (every epoch) get theirs as the credit allows, the
#: stalest first.
SNAPSHOT_WORK_EPOCHS = 50
#: Snapshot credit a bank may hold [snapshots] (a burst after quiet steps stays small).
SNAPSHOT_BURST = 2


def heavy_budget(n_epochs: int | None, lagging: bool = False) -> int | None:
    """Track initialisations + snapshot fixes a budgeted step that solves ``n_epochs`` epochs
    may do (``None``: an unbudgeted step, unbounded; at least :data:`HEAVY_MIN_OPERATIONS`, so a
    step always makes progress). Proportional to the epochs it solves, not to its limit (a
    fusion behind its input gets no more per epoch); ``lagging``: the minimum (admit_lag_s)."""
    if n_epochs is None:
        return None
    return max(HEAVY_MIN_OPERATIONS, 0 if lagging else int(n_epochs) // HEAVY_WORK_EPOCHS)


class TrackBank:
    """Tracker state of every node, grown as nodes appear (row ``index[node_id]``).

    Parameters
    ----------
    building : diffpos.scenario.Building
    config : TrackerConfig, optional
    radio : diffpos.scenario.Radio, optional
        The scenario's radio: the tracker then scores each mechanism's predicted SNR against
        the measured one (what separates floors that the ranges alone cannot).
    """

    def __init__(self, building: Any, config: TrackerConfig | None = None, radio: Any = None
                 ) -> None:
        self.building = building
        self.radio = radio  # with it, the measured SNR scores every mechanism's strength
        self.config = config or TrackerConfig()
        self.index: dict[str, int] = {}
        self.state: TrackerState = init_state(0, building)
        self.snapshot_ns: dict[str, int] = {}  # measurement time of each node's last snapshot
        self.deferred = 0  # initialisations deferred by a step's work budget (solve_mnls)
        self.snapshot_epochs = 0  # snapshot credit of the budgeted steps [epochs solved]
        #: the row-parallel worker pool (FusionConfig.workers > 1; set by the service or
        #: replay): the update's and the snapshot fixes' rows split over processes, same numbers
        self.pool: RowPool | None = None

    def snapshot_allowance(self, n_epochs: int) -> int:
        """Snapshot fixes a budgeted step solving ``n_epochs`` epochs may do: the credit of
        the epochs solved so far (one snapshot per :data:`SNAPSHOT_WORK_EPOCHS`, at most
        :data:`SNAPSHOT_BURST` banked), this step's epochs included."""
        self.snapshot_epochs = min(self.snapshot_epochs + int(n_epochs),
                                   SNAPSHOT_BURST * SNAPSHOT_WORK_EPOCHS)
        return self.snapshot_epochs // SNAPSHOT_WORK_EPOCHS

    def spend_snapshots(self, n: int) -> None:
        """``n`` snapshot fixes were done by a budgeted step (:meth:`snapshot_allowance`)."""
        self.snapshot_epochs -= n * SNAPSHOT_WORK_EPOCHS

    def rows_of(self, node_ids: list[str]) -> np.ndarray:
        """State rows of ``node_ids`` (new nodes get new, uninitialised rows)."""
        new = [n for n in dict.fromkeys(node_ids) if n not in self.index]
        if new:
            for n in new:
                self.index[n] = len(self.index)
            more = init_state(len(new), self.building)
            self.state = TrackerState(*(np.concatenate([getattr(self.state, f), getattr(more, f)])
                                        for f in TrackerState.__dataclass_fields__))
        return np.array([self.index[n] for n in node_ids], dtype=np.int64)

    def status_of(self, node_ids: list[str]) -> np.ndarray:
        """Current track status of ``node_ids`` (UNINITIALISED for unknown nodes)."""
        return np.array([self.state.status[self.index[n]] if n in self.index
                         else int(TrackStatus.UNINITIALISED) for n in node_ids], dtype=np.int8)

    def needs_init(self, rows: np.ndarray, n_ranges: np.ndarray) -> np.ndarray:
        """Whether the tracker would initialise each of ``rows`` (state rows) given its number
        of usable ranges: UNINITIALISED or LOST with at least ``min_ranges_init`` ranges (a
        re-initialisation after divergence is decided inside the update and not counted)."""
        st = self.state.status[rows]
        return ~has_position(st) & (n_ranges >= self.config.min_ranges_init)

    def hold_inits(self, epochs: list[PendingEpoch], budget: int, newest: bool = False
                   ) -> tuple[list[PendingEpoch], list[PendingEpoch]]:
        """``(now, later)``: the epochs of a budgeted step split so that its initialisations do
        not delay the other estimates (module docstring). ``later`` holds the first ``budget``
        epochs (in the order :func:`solve_mnls` initialises them: rounds, row order) whose node
        the tracker would initialise (UNINITIALISED or LOST, at least ``min_ranges_init``
        ranges) and every later epoch of their nodes; ``now`` the rest, in their order. Nothing
        is held when that would leave ``now`` empty. ``newest`` (a lagging step): only a held
        node's newest epoch is held (its track starts from the freshest ranges, the older ones
        go out without a position). Only the bank's state is read (new nodes get rows)."""
        last = {pe.node_id: i for i, pe in enumerate(epochs)}
        if not self._may_start(last):  # the common step: nothing to hold (and no new row)
            return epochs, []
        held: set[str] = set()
        for rows_l in _rounds(epochs):
            if len(held) >= budget:
                break
            ids = [epochs[i].node_id for i in rows_l]
            n = np.array([len(epochs[last[nid] if newest else i].ranges)  # the one initialised
                          for i, nid in zip(rows_l, ids, strict=True)])
            for i in np.flatnonzero(self.needs_init(self.rows_of(ids), n))[:budget - len(held)]:
                held.add(ids[i])
        hold = [pe.node_id in held and (not newest or last[pe.node_id] == i)
                for i, pe in enumerate(epochs)]
        now = [pe for pe, h in zip(epochs, hold, strict=True) if not h]
        return (epochs, []) if not now else (now, list(itertools.compress(epochs, hold)))

    def _may_start(self, node_ids) -> bool:
        """Whether any of ``node_ids`` is new, UNINITIALISED or LOST (:meth:`needs_init`
        can hold for none of the others, whatever its ranges)."""
        get = self.index.get
        rows = [get(n, -1) for n in node_ids]
        if -1 in rows:
            return True
        return not bool(has_position(self.state.status[rows]).all())

    def confident_of(self, node_ids: list[str]) -> np.ndarray:
        """Whether each node's track is confident (:data:`CONFIDENT_FLOOR_PROBABILITY`,
        :data:`CONFIDENT_NIS`; False for unknown nodes): its snapshot period is then
        ``FusionConfig.confident_snapshot_period_s``."""
        out = np.zeros(len(node_ids), bool)
        known = [(i, self.index[n]) for i, n in enumerate(node_ids) if n in self.index]
        if not known:
            return out
        at, rows = (np.array(v) for v in zip(*known, strict=True))
        floor_p = floor_probabilities(self.state.log_prob[rows]).max(axis=1)
        out[at] = (floor_p >= CONFIDENT_FLOOR_PROBABILITY) & (self.state.nis[rows]
                                                               <= CONFIDENT_NIS)
        return out

    def update(self, node_ids: list[str], anchors: np.ndarray, ranges: np.ndarray,
               sigmas: np.ndarray, mask: np.ndarray, t_ns: np.ndarray,
               snr_db: np.ndarray | None = None, radio: Any = None):
        """One epoch of ranges (and their SNR, NaN: unknown) for distinct ``node_ids``:
        :func:`diffpos.tracking.tracker.update` on their rows (``radio`` overrides the bank's);
        returns the :class:`~diffpos.tracking.tracker.TrackOutput`."""
        rows = self.rows_of(node_ids)
        fields = TrackerState.__dataclass_fields__
        at = _as_slice(rows)  # the rows' views (the update copies what it keeps)
        sub = TrackerState(*(getattr(self.state, f)[at] for f in fields))
        radio = self.radio if radio is None else radio
        if self.pool is None or self.pool.building is not self.building:
            new, out = _update_rows(self.building, sub, anchors, ranges, sigmas, mask, t_ns,
                                    snr_db, self.config, radio)
        else:  # an initialisation costs ~INIT_COST updates: the shares balanced by it
            cost = np.where(self.needs_init(rows, np.count_nonzero(mask, axis=1)), INIT_COST,
                            1.0)
            args = (slim_state(sub, self.config), anchors, ranges, sigmas, mask, t_ns, snr_db)
            new, out = self.pool.map_rows("update", args, cost,
                                          lambda *a: run_update(self.building, *a),
                                          shared=(self.config, radio))
        for f in fields:  # the rows in place (the bank's arrays are its own: rows_of copies)
            if (v := getattr(new, f)) is not None:  # None: a slimmed SNR cache, unchanged
                getattr(self.state, f)[at] = v
        return out


def _as_slice(rows: np.ndarray) -> slice | np.ndarray:
    """``rows`` as a slice when they are consecutive and ascending (a step's nodes in the
    order they came: most calls), else themselves."""
    if rows.size and rows[-1] - rows[0] == rows.size - 1 and (
            rows.size == 1 or bool((np.diff(rows) == 1).all())):
        return slice(int(rows[0]), int(rows[-1]) + 1)
    return rows


def _update_rows(building, sub, anchors, ranges, sigmas, mask, t_ns, snr_db, config, radio):
    """:func:`diffpos.tracking.tracker.update` of ``sub``'s rows (what a worker runs for its share)."""
    return update(sub, anchors, ranges, sigmas, mask, t_ns, building, config, snr_db=snr_db,
                  radio=radio)


@dataclass
class Solved:
    """A batch solved by :func:`solve_mnls` (rows = epochs, columns = the batch's anchors)."""

    res: Results  # the published fix per row (used / exclusion reasons / residuals)
    status: list[str]  # status name per row
    floor_prob: np.ndarray  # (B, F), NaN rows: none
    mechanism: np.ndarray  # (B, M) slot or -1
    snap: Results | None  # the mnls snapshot of the rows that got one (tracking only)
    snap_rows: np.ndarray  # (B,) bool: row has a snapshot
    snap_floor: np.ndarray  # (B,) floor of the snapshot, -1
    snap_prob: np.ndarray  # (B, F)
    tracking: bool
    #: snapshot fixes started and not collected yet (``solve_mnls(defer=True)``): their rows'
    #: estimates wait for :func:`finish_snapshots`, the others need not
    pending: list = field(default_factory=list)


def finish_snapshots(s: Solved) -> None:  # the fixes solve_mnls(defer=True) left pending
    while s.pending:
        s.pending.pop(0)()


def in_publish_order(s: Solved, epochs: list[PendingEpoch],
                     emit: Callable[[Estimates], Any] | None,
                     build: Callable[[np.ndarray], Sequence]) -> Estimates:
    """The estimates ``build(rows)`` of a batch solved with ``defer``: first the rows without
    a pending snapshot fix, handed to ``emit`` (when given) before the fixes are collected,
    then those with one (an mnls fix costs ~6 ms with 8 anchors, a third of a 50-node step of
    ``large``) and a node's later rows (its estimates keep their order: backlog, start-up),
    each part in row order. Returns what was not emitted. The order (so the sequence
    numbers) is the same with or without ``emit``: a replay numbers them as live did."""
    late = s.snap_rows & bool(s.pending)
    if late.any():  # and every later row of the same nodes
        waiting: set[str] = set()
        for i, pe in enumerate(epochs):
            if late[i] or pe.node_id in waiting:
                late[i] = True
                waiting.add(pe.node_id)
    out = Estimates([build(np.flatnonzero(~late))])
    if late.any():
        if emit is not None and out:
            emit(out)
            out = Estimates()
        finish_snapshots(s)
        out += build(np.flatnonzero(late))
    return out


def _mnls_rows(res: Results, rows: np.ndarray, prep: Prepared, batch: Batch, model,
               floor: np.ndarray, prob: np.ndarray, mech: np.ndarray,
               pool: RowPool | None = None) -> None:
    """The mnls fixes of ``rows`` into ``res`` and the floor/mechanism arrays (``model``:
    (building, radio or None); ``pool``: computed by a worker, same numbers)."""
    _mnls_finish(_mnls_start(rows, prep, batch, model, pool), res, floor, prob, mech)


def _mnls_start(rows: np.ndarray, prep: Prepared, batch: Batch, model,
                pool: RowPool | None = None) -> tuple | None:
    """Start the mnls fixes of ``rows``: with ``pool``, sent whole to its least loaded
    worker and not waited for (the snapshot never feeds the tracker: the tracker update of
    the round runs meanwhile, its shares counting the worker's snapshot work; a snapshot fix
    with 16 anchors costs ~15 updates, and one or two per step kept in the fusion's process
    were ~40 % of its serial work in the soak); :func:`_mnls_finish` collects them."""
    if rows.size == 0:
        return None
    building, radio, rule, order = model
    args = (prep.safe_apos[rows], prep.rng_in[rows], prep.sig_eff[rows], batch.use[rows],
            None if radio is None else batch.snr[rows])

    def here(apos, rng, sig, mask, snr, radio_, rule_, order_):
        return mnls_solver.mnls(apos, rng, sig, building=building, mask=mask, snr_db=snr,
                                radio=radio_, snr_rule=SnrRule(*rule_), max_order=order_)

    if pool is None or pool.building is not building:  # computed when collected
        return rows, None, lambda _: here(*args, radio, rule, order)
    return rows, pool.submit("mnls", args, rows.size, here, shared=(radio, rule, order)), \
        lambda p: pool.result(p, here, shared=(radio, rule, order))


def _mnls_finish(started: tuple | None, res: Results, floor: np.ndarray, prob: np.ndarray,
                 mech: np.ndarray) -> None:
    """The fixes of :func:`_mnls_start` into ``res`` and the floor/mechanism arrays."""
    if started is None:
        return
    rows, fix, collect = started
    if collect is not None:
        fix = collect(fix)
    res.put(rows, fix)
    floor[rows] = fix.floor
    prob[rows] = fix.floor_probability
    # the published labels are the 18 mechanisms': a higher-order family (mnls_max_order > 2,
    # slot >= 18) is published without one
    mech[rows] = np.where(fix.used & (fix.mechanism < len(MECHANISMS)), fix.mechanism, -1)


def _rounds(epochs: list[PendingEpoch]) -> list[list[int]]:
    """Row indices in rounds of distinct nodes, each node's epochs oldest first."""
    order = sorted(range(len(epochs)), key=lambda i: (epochs[i].epoch, epochs[i].node_id))
    rounds: list[list[int]] = []
    depth: dict[str, int] = {}
    for i in order:
        k = depth.get(epochs[i].node_id, 0)
        depth[epochs[i].node_id] = k + 1
        if k == len(rounds):
            rounds.append([])
        rounds[k].append(i)
    return rounds


def _snapshot_due(bank: TrackBank, epochs: list[PendingEpoch], t_ref: np.ndarray,
                  cfg: FusionConfig, limit: float = math.inf, behind: bool = False,
                  starting: np.ndarray | None = None) -> np.ndarray:
    """Rows that get an mnls snapshot while tracking (module docstring): at most ``limit``
    of the due ones, those with the oldest snapshot first (never: first of all), the rest
    stay due. ``starting``: the rows whose track the tracker initialises now; without
    ``cfg.snapshot_at_start`` they get none, their track's start counting as their last
    check."""
    ids = [pe.node_id for pe in epochs]
    status = bank.status_of(ids)
    placed = has_position(status)  # the tracker publishes a position
    sure = (status == int(TrackStatus.TRACKING)) & bank.confident_of(ids)
    period = round(cfg.snapshot_period_s * 1e9)
    long_period = (math.inf if cfg.confident_snapshot_period_s is None
                   else max(period, round(cfg.confident_snapshot_period_s * 1e9)))
    lasts = [bank.snapshot_ns.get(nid) for nid in ids]
    seen = np.array([x is not None for x in lasts], bool)
    age = np.asarray(t_ref) - np.array([0 if x is None else x for x in lasts], np.int64)
    # not due: placed, with a snapshot younger than its period (int64 ns; an infinite
    # confident period: never due again)
    young = np.where(sure, (age < long_period) if long_period != math.inf else True,
                     age < period)
    due = ~(placed & seen & (age >= 0) & young)
    if behind:  # the tracked estimates first: a snapshot only where it is the only fix
        due &= ~placed
    start = (np.zeros(len(epochs), bool) if starting is None or cfg.snapshot_at_start
             else starting)
    due &= ~start
    todo = np.flatnonzero(due)
    if todo.size > limit:
        never = -(2**63)
        order = sorted(todo.tolist(), key=lambda i: never if lasts[i] is None else lasts[i])
        due[order[int(limit):]] = False
        todo = np.flatnonzero(due)
    for i in itertools.chain(todo, np.flatnonzero(start)):
        bank.snapshot_ns[ids[i]] = int(t_ref[i])
    return due


def _silent_inputs(batch: Batch, prep: Prepared, rows: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The tracker's anchors and SNRs of ``rows``: the used anchors' positions and SNRs, and
    with ``batch.silent`` (``TrackerConfig.silent_anchor_nats``) every silent anchor's
    position with SNR -inf (:func:`diffpos.tracking.silent.silent_links`)."""
    if batch.silent is None:
        return prep.safe_apos[rows], batch.snr[rows]
    s = batch.silent[rows]
    return (np.where(s[..., None], batch.apos[rows], prep.safe_apos[rows]),
            np.where(s, -np.inf, batch.snr[rows]))


def solve_mnls(batch: Batch, prep: Prepared, epochs: list[PendingEpoch], cfg: FusionConfig,
               model: tuple, bank: TrackBank | None, heavy: int | None = None,
               defer: bool = False, behind: bool = False) -> Solved:
    """The mnls snapshot fixes and, with ``bank``, the tracked estimates of ``batch``
    (``model``: the building, the radio or None and M-NLS's ``SnrRule`` fields, see
    ``FusionCore.model``; ``heavy``: at most this many track
    initialisations + snapshot fixes, see the module docstring; None: unbounded; ``defer``:
    the tracking snapshot fixes are left in ``Solved.pending``, see :func:`in_publish_order`;
    ``behind``: the step leaves ready epochs, no snapshot fix of a node the tracker places)."""
    b, m = len(epochs), len(batch.names)
    nf = model[0].n_floors
    use = batch.use
    snap = Results(b, m)
    s_floor, s_prob = np.full(b, -1), np.full((b, nf), np.nan)
    s_mech = np.full((b, m), -1)
    if bank is None:
        _mnls_rows(snap, np.arange(b), prep, batch, model, s_floor, s_prob, s_mech)
        return Solved(snap, [_FIX_NAMES[int(s)] for s in snap.status], s_prob, s_mech, None,
                      np.zeros(b, bool), s_floor, s_prob, False)
    due = np.zeros(b, bool)
    res = Results(b, m)
    status = [""] * b
    prob = np.full((b, nf), np.nan)
    mech = np.full((b, m), -1)
    left = math.inf if heavy is None else int(heavy)
    snaps = math.inf if heavy is None else bank.snapshot_allowance(b)
    pending: list = []
    for rows_l in _rounds(epochs):
        rows = np.array(rows_l)
        ids = [epochs[i].node_id for i in rows_l]
        use_r = use[rows]
        node_rows = bank.rows_of(ids)
        if heavy is not None:  # initialisations first: they give positions
            new = np.flatnonzero(bank.needs_init(node_rows, use_r.sum(axis=1)))
            later = new[int(min(left, new.size)):]
            left -= new.size - later.size
            if later.size:  # no ranges this epoch: no initialisation, published on time
                use_r = use_r.copy()
                use_r[later] = False
                bank.deferred += int(later.size)
        # the snapshot decision of a round sees the tracks as the previous round left them
        # (a node's epochs in one batch are decided as if they came one call at a time)
        starting = (None if cfg.snapshot_at_start
                    else bank.needs_init(node_rows, use_r.sum(axis=1)))
        due[rows] = _snapshot_due(bank, [epochs[i] for i in rows_l], batch.t_ref[rows], cfg,
                                  min(left, snaps), behind, starting)
        left -= int(due[rows].sum())
        snaps -= int(due[rows].sum())
        # the snapshots (a worker's, with a pool) while the tracker updates the round
        started = _mnls_start(rows[due[rows]], prep, batch, model, bank.pool)
        anc_r, snr_r = _silent_inputs(batch, prep, rows)
        out = bank.update(ids, anc_r, prep.rng_in[rows], prep.sig_eff[rows], use_r,
                          batch.t_ref[rows], snr_db=snr_r, radio=model[1])
        if started is not None:
            finish = functools.partial(_mnls_finish, started, snap, s_floor, s_prob, s_mech)
            if defer:
                pending.append(finish)
            else:
                finish()
        res.pos[rows], res.cov[rows] = out.position_m, out.covariance_m2
        mech[rows] = np.where(use[rows], out.mechanism, -1)
        res.resid[rows] = np.where(mech[rows] >= 0, out.residual_m, np.nan)
        has = has_position(out.status)
        prob[rows] = np.where(has[:, None], out.floor_probabilities, np.nan)
        for r, st in zip(rows_l, out.status.tolist(), strict=True):
            status[r] = _TRACK_NAMES[st]
    res.used = mech >= 0
    res.reason = np.where(use & ~res.used, _RAIM, 0)
    with np.errstate(invalid="ignore"):
        res.peb = np.sqrt(np.trace(res.cov, axis1=1, axis2=2))
        res.zb = np.sqrt(res.cov[:, 2, 2])
    if heavy is not None:
        bank.spend_snapshots(int(due.sum()))
    return Solved(res, status, prob, mech, snap, due, s_floor, s_prob, True, pending)
