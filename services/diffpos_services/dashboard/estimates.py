"""Logging of the position estimates: one function per logged stream."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import rerun as rr
from numpy.typing import NDArray

from diffpos_services.dashboard.building import BuildingOutline, FloatArray
from diffpos_services.dashboard.columns import EstimateColumns, EventColumns
from diffpos_services.dashboard.common import (
    _EXCLUDED_COLOR,
    BOOKKEEPING_REASONS,
    CHI2_3DOF_95,
    UNIDENTIFIABLE_STATUSES,
    _group,
    _rgba,
    _sorted_by_time,
    _time_column,
    anchor_color,
    confidence_colors,
    node_color,
    status_color,
)
from diffpos_services.dashboard.events import _status_level, log_events
from diffpos_services.dashboard.floors import _log_floor_table
from diffpos_services.dashboard.geometry import Tracks, ellipsoid_axes, path_strips
from diffpos_services.dashboard.mechanisms import MAX_VERTICES, mechanism_strips
from diffpos_services.dashboard.plans import FLEET_LINES, PlanState, log_plan_markers
from diffpos_services.wire.messages import GOOD_STATUSES


def _scalar_series(
    rec: rr.RecordingStream, path: str, t_ns: np.ndarray, values: np.ndarray
) -> None:
    """Values at their times; a missing value (NaN: no position, no truth) is a gap in the
    plotted line (a ``Clear`` at that time), never a line drawn across it."""
    ok = np.isfinite(values)
    if ok.any():
        rec.send_columns(
            path, indexes=[_time_column(t_ns[ok])], columns=rr.Scalars.columns(scalars=values[ok])
        )
    if not ok.all():
        rec.send_columns(path, indexes=[_time_column(t_ns[~ok])],
                         columns=rr.Clear.columns(is_recursive=np.zeros(int((~ok).sum()), bool)))


@dataclass
class _EstimateState:
    """What log_estimates remembers between batches (live streaming)."""

    last_path_bucket: dict[str, int] = field(default_factory=dict)
    last_links: dict[str, dict[str, str]] = field(default_factory=dict)
    last_status: dict[str, str] = field(default_factory=dict)
    last_floor_bucket: int | None = None
    #: node -> (estimated floor, true floor, probability, time of the fix [ns]) of its
    #: latest fix with a position (the floor table)
    floors: dict[str, tuple[int, int, float, int]] = field(default_factory=dict)
    #: node -> (time [ns], position [m], floor) of its latest fix with a position (markers)
    last_fix: dict[str, tuple[int, FloatArray, int]] = field(default_factory=dict)
    residual_styled: set[str] = field(default_factory=set)
    node_styled: set[str] = field(default_factory=set)
    fleet_styled: bool = False
    plan: PlanState = field(default_factory=PlanState)
    dropped_bad_time: int = 0


def _select_fixes(est: EstimateColumns, keep: NDArray[np.bool_]) -> EstimateColumns:
    """The fixes ``keep`` (bool, shape (K,)) of ``est`` with their links (re-indexed)."""
    new_index = np.cumsum(keep) - 1
    lk = keep[est.link_fix]
    return EstimateColumns(
        t_ns=est.t_ns[keep],
        node_id=est.node_id[keep],
        status=est.status[keep],
        position_m=est.position_m[keep],
        covariance_m2=est.covariance_m2[keep],
        peb_m=est.peb_m[keep],
        floor_index=est.floor_index[keep],
        link_fix=new_index[est.link_fix[lk]],
        link_anchor_id=est.link_anchor_id[lk],
        link_used=est.link_used[lk],
        link_residual_m=est.link_residual_m[lk],
        link_reason=est.link_reason[lk],
        link_mechanism=est.link_mechanism[lk],
        floor_probability=est.floor_probability[keep],
        floor_probabilities=est.floor_probabilities[keep],
    )


@dataclass(frozen=True)
class _Batch:
    """One batch of fixes and what the streams derive from it once (all arrays per fix,
    ``anchor_ids``/``anchor_code`` per link: ``np.unique(est.link_anchor_id, return_inverse)``)."""

    est: EstimateColumns
    has_pos: NDArray[np.bool_]
    est_floor: NDArray[np.int64]
    true_floor: NDArray[np.int64]
    err_3d: FloatArray
    err_z: FloatArray
    colors: NDArray[np.uint8]
    half_m: FloatArray
    quat_xyzw: FloatArray
    cov_ok: NDArray[np.bool_]
    anchor_ids: NDArray[np.str_]
    anchor_code: NDArray[np.int64]

    @property
    def t(self) -> NDArray[np.int64]:
        return self.est.t_ns


@dataclass(frozen=True)
class _Paths:
    """Paths of every link of a batch: ``strips`` (L, MAX_VERTICES, 3) anchor -> interaction
    points -> estimate (the mechanism the fusion used, estimate v2; else anchor -> window-edge
    point of the modelled edge -> estimate), drawable ``ok``, and their colours and radii."""

    strips: FloatArray
    ok: NDArray[np.bool_]
    colors: NDArray[np.uint8]
    radii: NDArray[np.float32]


def log_estimates(
    rec: rr.RecordingStream,
    est: EstimateColumns,
    *,
    anchors: Tracks | None = None,
    truth: Tracks | None = None,
    building: BuildingOutline | None = None,
    confidence_scale: float = math.sqrt(CHI2_3DOF_95),
    path_period_s: float = 0.5,
    floor_period_s: float = 1.0,
    state: _EstimateState | None = None,
) -> _EstimateState:
    """Estimates, uncertainty, diffraction paths, metrics, floor table and events.

    One function per logged stream (:func:`_log_estimate_points`, :func:`_log_paths`,
    :func:`_log_errors`, :func:`_log_residuals`, :func:`_log_gating`,
    :func:`_log_floor_table`, events from :func:`_status_events` and
    :func:`_exclusion_events`), called in this order.

    Parameters
    ----------
    est : EstimateColumns
        The fixes to log (any mix of nodes and times).
    anchors : Tracks, optional
        Anchor positions over time (from AnchorState); needed for the diffraction paths.
    truth : Tracks, optional
        True node positions over time with the true floor as ``extra``; gives the error
        series and the true floor.
    building : BuildingOutline, optional
        Gives the window edge of the estimated floor for the paths (the edge the fusion
        models, :attr:`BuildingOutline.edge`), and true floors from z.
    confidence_scale : float
        Mahalanobis radius of the drawn ellipsoid (default: 95 % in 3D).
    path_period_s : float [s]
        Diffraction paths of a node are drawn at most once per this measurement-time period.
    floor_period_s : float [s]
        The floor table is refreshed at most once per this period.
    state : optional
        Returned by the previous call (streaming); ``None`` for a single bulk call.

    Returns
    -------
    state
        Pass it to the next call when streaming.
    """
    st = state if state is not None else _EstimateState()
    est = _drop_bad_times(rec, est, st)
    if len(est) == 0:
        return st
    b = _batch(est, truth, building, confidence_scale)
    paths = _diffraction_paths(b, anchors, building)
    path_period_ns = max(1, int(path_period_s * 1e9))
    events: list[EventColumns] = []
    for nid, rows in _group(est.node_id):
        rows = _sorted_by_time(b.t, rows)
        _log_estimate_points(rec, nid, rows, b, st)
        if paths is not None:
            _log_paths(rec, nid, rows, b, paths, path_period_ns, st)
        _log_errors(rec, nid, rows, b, st)
        _log_floor_probabilities(rec, nid, rows, b)
        events.append(_status_events(nid, rows, b, st))
        fixed = rows[b.has_pos[rows]]
        if fixed.size:  # the latest fix with a position, for the floor table
            last = fixed[-1]
            st.floors[nid] = (int(b.est_floor[last]), int(b.true_floor[last]),
                              float(est.floor_probability[last]), int(b.t[last]))
    if est.link_fix.size:
        events.append(_exclusion_events(b, st))
        _log_residuals(rec, b, st)
        _log_gating(rec, b)
    _log_fleet_errors(rec, b, st)
    _log_floor_table(rec, b, floor_period_s, st)
    log_plan_markers(rec, b, building, path_period_s, st.plan)
    log_events(rec, EventColumns.concat(events))
    return st


def _drop_bad_times(
    rec: rr.RecordingStream, est: EstimateColumns, st: _EstimateState
) -> EstimateColumns:
    """``est`` without fixes of negative ``t_ns`` (invalid on the wire: times are ns since the
    Unix epoch), counted in ``st`` and reported by one ERROR event."""
    bad_time = est.t_ns < 0
    if not bad_time.any():
        return est
    n_bad = int(bad_time.sum())
    st.dropped_bad_time += n_bad
    est = _select_fixes(est, ~bad_time)
    if len(est):
        log_events(
            rec,
            EventColumns(
                [int(est.t_ns.max())],
                [f"{n_bad} estimates with a negative t_ns dropped (invalid time from the fusion)"],
                ["ERROR"],
            ),
        )
    return est


def _batch(
    est: EstimateColumns,
    truth: Tracks | None,
    building: BuildingOutline | None,
    confidence_scale: float,
) -> _Batch:
    """Truth, errors, floors, status colours and ellipsoids of a batch of fixes."""
    k, t, pos = len(est), est.t_ns, est.position_m
    has_pos = np.all(np.isfinite(pos), axis=1)
    if truth is not None:
        true_pos, true_floor, known = truth.sample(est.node_id, t)
    else:
        true_pos = np.full((k, 3), np.nan)
        true_floor = np.full(k, -1, np.int64)
        known = np.zeros(k, bool)
    if building is not None:  # the floor of the true position at the fix's time (as scored)
        true_floor = np.where(known, building.floor_of(true_pos[:, 2]), true_floor)
    est_floor = est.floor_index
    if building is not None:
        est_floor = np.where((est_floor < 0) & has_pos, building.floor_of(pos[:, 2]), est_floor)
    half, quat, cov_ok = ellipsoid_axes(est.covariance_m2, scale=confidence_scale)
    statuses = np.unique(est.status)
    status_colors = np.array([status_color(s) for s in statuses], np.uint8).reshape(-1, 4)
    anc_u, anc_c = np.unique(est.link_anchor_id, return_inverse=True)
    return _Batch(
        est=est,
        has_pos=has_pos,
        est_floor=est_floor,
        true_floor=true_floor,
        err_3d=np.linalg.norm(pos - true_pos, axis=1),
        err_z=pos[:, 2] - true_pos[:, 2],
        colors=confidence_colors(status_colors[np.searchsorted(statuses, est.status)],
                                 est.floor_probability),
        half_m=half,
        quat_xyzw=quat,
        cov_ok=cov_ok & has_pos,
        anchor_ids=anc_u,
        anchor_code=anc_c,
    )


def _diffraction_paths(
    b: _Batch, anchors: Tracks | None, building: BuildingOutline | None
) -> _Paths | None:
    """The path of every link (vectorised), or None without links or anchor tracks.

    A used link whose estimate names its mechanism (estimate v2: ``est.link_mechanism``) is
    drawn along that mechanism's interaction
    points; the others over the modelled window edge (estimate v1)."""
    est, lf = b.est, b.est.link_fix
    if not lf.size or anchors is None:
        return None
    a_pos, _, a_known = anchors.sample(None, b.t[lf], coded=(b.anchor_ids, b.anchor_code))
    strips = path_strips(a_pos, est.position_m[lf], b.est_floor[lf], building)
    if building is not None:
        labels = np.where(est.link_used, est.link_mechanism, "")
        if np.any(labels != ""):  # (L, MAX_VERTICES, 3): edge paths repeat their last point
            pad = np.repeat(strips[:, -1:], MAX_VERTICES - strips.shape[1], axis=1)
            mech = mechanism_strips(a_pos, est.position_m[lf], b.est_floor[lf], labels, building)
            strips = np.where((labels != "")[:, None, None], mech,
                              np.concatenate([strips, pad], axis=1))
    ok = a_known & b.has_pos[lf] & np.all(np.isfinite(strips), axis=(1, 2))
    # no path for bookkeeping exclusions (nothing was measured); gated ones are drawn red
    ok &= est.link_used | ~np.isin(est.link_reason, list(BOOKKEEPING_REASONS))
    colors = _rgba([anchor_color(str(a)) for a in b.anchor_ids])[b.anchor_code]
    colors[~est.link_used] = _EXCLUDED_COLOR
    radii = np.where(est.link_used, 0.05, 0.03).astype(np.float32)
    return _Paths(strips=strips, ok=ok, colors=colors, radii=radii)


#: marker of a responder [ui points: the same size on screen at any zoom]
MARKER_RADIUS_UI = 7.0
#: outline of the 95 % ellipsoid [ui points]
ELLIPSOID_LINE_UI = 1.5


def _last_fix_rows(
    nid: str, rows: NDArray[np.int64], b: _Batch, st: _EstimateState
) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.int64]]:
    """For each fix of a node (time-sorted ``rows``): the position, time and floor of the
    node's latest fix with a position up to it (this batch or, before it, ``st.last_fix``);
    time -1 where the node never had one. Updates ``st.last_fix``."""
    hp = b.has_pos[rows]
    idx = np.where(hp, np.arange(len(rows)), -1)
    np.maximum.accumulate(idx, out=idx)
    prev = st.last_fix.get(nid)
    pos = np.full((len(rows), 3), np.nan)
    t_fix = np.full(len(rows), -1, np.int64)
    floor = np.full(len(rows), -1, np.int64)
    have = idx >= 0
    pos[have] = b.est.position_m[rows[idx[have]]]
    t_fix[have] = b.t[rows[idx[have]]]
    floor[have] = b.est_floor[rows[idx[have]]]
    if prev is not None:
        pos[~have], t_fix[~have], floor[~have] = prev[1], prev[0], prev[2]
    if t_fix[-1] >= 0:
        st.last_fix[nid] = (int(t_fix[-1]), pos[-1].copy(), int(floor[-1]))
    return pos, t_fix, floor


def _log_estimate_points(
    rec: rr.RecordingStream, nid: str, rows: NDArray[np.int64], b: _Batch, st: _EstimateState
) -> None:
    """``world/nodes/<node>/estimate``: one marker per responder (size in ui points: visible
    at any zoom) in the colour of its newest status dimmed by floor confidence, and the 95 %
    ellipsoid of the fix (outline in ui points). Labels (``<node> F<floor>``, ``<node>?`` on
    the last fix when the newest estimate has no position) are hidden in 3D, where 50 would
    overlap: they show on hover and selection; the floor plans carry readable ones. A fix
    without a position keeps the marker on the node's last fix, without ellipsoid; before
    the node's first fix there is no marker. One entity: one chunk per node and batch."""
    pos, t_fix, floor = _last_fix_rows(nid, rows, b, st)
    hp = b.has_pos[rows]
    shown = t_fix >= 0
    fl = lambda f: "?" if f < 0 else str(f)  # noqa: E731
    label = [
        f"{nid} F{fl(f)}" if fresh else f"{nid}?"
        for f, fresh in zip(floor.tolist(), hp.tolist(), strict=True)
    ]
    colors = b.colors[rows]
    ok = b.cov_ok[rows]
    sel_c = rows[ok]
    n_shown, n_c = int(shown.sum()), int(sel_c.size)
    rec.send_columns(
        f"world/nodes/{nid}/estimate",
        indexes=[_time_column(b.t[rows])],
        columns=[
            *rr.Points3D.columns(
                positions=pos[shown],
                colors=colors[shown],
                radii=np.full(n_shown, -MARKER_RADIUS_UI, np.float32),
                labels=np.asarray(label)[shown],
                show_labels=np.zeros(n_shown, bool),
            ).partition(shown.astype(np.int64)),
            *rr.Ellipsoids3D.columns(
                centers=b.est.position_m[sel_c],
                half_sizes=b.half_m[sel_c],
                quaternions=b.quat_xyzw[sel_c],
                colors=b.colors[sel_c],
                line_radii=np.full(n_c, -ELLIPSOID_LINE_UI, np.float32),
            ).partition(ok.astype(np.int64)),
        ],
    )


def _log_paths(
    rec: rr.RecordingStream,
    nid: str,
    rows: NDArray[np.int64],
    b: _Batch,
    paths: _Paths,
    period_ns: int,
    st: _EstimateState,
) -> None:
    """``world/paths/<node>``: the paths of the node's fixes (detail on demand: hidden by the
    default blueprint, shown per responder), at most one fix per ``period_ns`` of measurement
    time (the first fix of each period)."""
    tr = b.t[rows]
    bucket = tr // period_ns
    first = np.ones(len(rows), bool)
    first[1:] = bucket[1:] != bucket[:-1]
    prev = st.last_path_bucket.get(nid)
    if prev is not None:
        first &= bucket != prev
    if not first.any():
        return
    st.last_path_bucket[nid] = int(bucket[-1])
    lf = b.est.link_fix
    prow = rows[first]
    rank = np.full(len(b.est), -1, np.int64)
    rank[prow] = np.arange(prow.size)
    lsel = np.flatnonzero((rank[lf] >= 0) & paths.ok)
    lsel = lsel[np.argsort(rank[lf[lsel]], kind="stable")]
    per_row = np.bincount(rank[lf[lsel]], minlength=prow.size)
    rec.send_columns(
        f"world/paths/{nid}",
        indexes=[_time_column(tr[first])],
        columns=rr.LineStrips3D.columns(
            strips=paths.strips[lsel],
            colors=paths.colors[lsel],
            radii=paths.radii[lsel],
        ).partition(per_row),
    )


def _log_errors(rec: rr.RecordingStream, nid: str, rows: NDArray[np.int64], b: _Batch,
                st: _EstimateState) -> None:
    """``metrics/error_3d_m/<node>``, ``metrics/error_z_m/<node>``, ``metrics/peb_m/<node>``
    (each node's line in its own colour and named by its id, styled once)."""
    tr = b.t[rows]
    if nid not in st.node_styled:
        st.node_styled.add(nid)
        for what in ("error_3d_m", "error_z_m", "peb_m"):
            rec.log(f"metrics/{what}/{nid}", rr.SeriesLines(colors=[node_color(nid)],
                                                             names=[nid]), static=True)
    _scalar_series(rec, f"metrics/error_3d_m/{nid}", tr, b.err_3d[rows])
    _scalar_series(rec, f"metrics/error_z_m/{nid}", tr, b.err_z[rows])
    _scalar_series(rec, f"metrics/peb_m/{nid}", tr, b.est.peb_m[rows])


#: the fleet lines are computed over the fixes of each fusion epoch of this length [ns]
FLEET_EPOCH_NS = 100_000_000


def _log_fleet_errors(rec: rr.RecordingStream, b: _Batch, st: _EstimateState) -> None:
    """``metrics/fleet/error_3d_m/{median,p95,worst}``: over the responders with a fix and
    truth in each fusion epoch (:data:`FLEET_EPOCH_NS`), at the epoch's newest fix time:
    three lines instead of one per responder."""
    ok = np.isfinite(b.err_3d)
    if not ok.any():
        return
    if not st.fleet_styled:
        st.fleet_styled = True
        for name, color, what in FLEET_LINES:
            rec.log(f"metrics/fleet/error_3d_m/{name}",
                    rr.SeriesLines(colors=[color], names=[what]), static=True)
    t, err = b.t[ok], b.err_3d[ok]
    ep, inv = np.unique(t // FLEET_EPOCH_NS, return_inverse=True)
    order = np.argsort(inv, kind="stable")
    starts = np.searchsorted(inv[order], np.arange(ep.size))
    groups = np.split(err[order], starts[1:])
    t_ep = np.maximum.reduceat(t[order], starts)
    stats = {"median": [np.median(g) for g in groups],
             "p95": [np.percentile(g, 95) for g in groups],
             "worst": [g.max() for g in groups]}
    for name, vals in stats.items():
        rec.send_columns(f"metrics/fleet/error_3d_m/{name}", indexes=[_time_column(t_ep)],
                         columns=rr.Scalars.columns(scalars=np.asarray(vals, float)))


#: colour of each floor's line in the floor-probability plots (F0, F1, ...; cycled)
FLOOR_LINE_COLORS = ((31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40),
                     (148, 103, 189), (140, 86, 75), (227, 119, 194), (188, 189, 34))


def _log_floor_probabilities(rec: rr.RecordingStream, nid: str, rows: NDArray[np.int64],
                             b: _Batch) -> None:
    """``metrics/floor_probability/<node>``: the probability of every floor at each fix
    that has them (estimate v2), one line per floor (``F0``, ``F1``, ...)."""
    probs = b.est.floor_probabilities[rows]
    if not probs.shape[1]:
        return
    have = np.isfinite(probs).any(axis=1)
    if not have.any():
        return
    n_f = probs.shape[1]
    rec.log(f"metrics/floor_probability/{nid}", rr.SeriesLines(
        colors=[(*FLOOR_LINE_COLORS[f % len(FLOOR_LINE_COLORS)], 255) for f in range(n_f)],
        names=[f"F{f}" for f in range(n_f)]), static=True)
    rec.send_columns(f"metrics/floor_probability/{nid}", indexes=[_time_column(b.t[rows][have])],
                     columns=rr.Scalars.columns(scalars=probs[have]))


def _status_events(
    nid: str, rows: NDArray[np.int64], b: _Batch, st: _EstimateState
) -> EventColumns:
    """Status changes of a node (the first fix compares with the previous batch's status;
    a node starting good is no event)."""
    tr = b.t[rows]
    prev_status = st.last_status.get(nid)
    stat = b.est.status[rows]
    change = np.ones(len(rows), bool)
    change[1:] = stat[1:] != stat[:-1]
    if prev_status is not None:
        change[0] = stat[0] != prev_status
    elif stat[0] in GOOD_STATUSES:
        change[0] = False
    st.last_status[nid] = str(stat[-1])
    ci = np.flatnonzero(change)
    txt, lvl = [], []
    for i in ci:
        s = str(stat[i])
        before = str(stat[i - 1]) if i > 0 else prev_status
        txt.append(
            f"node {nid}: status {s}"
            + (" (unidentifiable geometry)" if s in UNIDENTIFIABLE_STATUSES else "")
        )
        lvl.append(_status_level(before, s))
    return EventColumns(tr[ci], txt, lvl)


def _exclusion_events(b: _Batch, st: _EstimateState) -> EventColumns:
    """An event when an anchor becomes excluded for a node (or changes reason), and when it
    is used again; ``st.last_links`` carries the last reason per (node, anchor) over batches."""
    est, t, lf = b.est, b.t, b.est.link_fix
    anc_u, anc_c = b.anchor_ids, b.anchor_code
    n_links = lf.size
    # integer codes: sorting and comparing ints is much cheaper than strings
    node_u, node_c = np.unique(est.node_id, return_inverse=True)
    cur_str = np.where(est.link_used, "", est.link_reason)
    reason_u, reason_c = np.unique(cur_str, return_inverse=True)
    lorder = np.lexsort((t[lf], anc_c, node_c[lf]))
    ex_t, ex_txt, ex_lvl = [], [], []
    nl, al, cl, tl = node_c[lf][lorder], anc_c[lorder], reason_c[lorder], t[lf][lorder]
    empty = np.flatnonzero(reason_u == "")
    empty_code = int(empty[0]) if empty.size else -1

    def before_batch(i: int) -> str:  # last reason of link i's (node, anchor) before the batch
        return st.last_links.get(str(node_u[nl[i]]), {}).get(str(anc_u[al[i]]), "")

    first = np.ones(n_links, bool)
    first[1:] = (nl[1:] != nl[:-1]) | (al[1:] != al[:-1])
    changed = np.zeros(n_links, bool)
    changed[1:] = cl[1:] != cl[:-1]
    first_idx = np.flatnonzero(first)
    # the first link of each (node, anchor) pair compares with the previous batch's state
    for i in first_idx:
        changed[i] = str(reason_u[cl[i]]) != before_batch(i)
    is_used = cl == empty_code
    prev_excluded = np.zeros(n_links, bool)
    prev_excluded[1:] = cl[:-1] != empty_code
    for i in first_idx:
        prev_excluded[i] = bool(before_batch(i))
    events_idx = np.flatnonzero(changed & (~is_used | prev_excluded))
    first_set = set(first_idx.tolist())
    for i in events_idx:
        ex_t.append(tl[i])
        node_s, anc_s = node_u[nl[i]], anc_u[al[i]]
        if is_used[i]:
            before = before_batch(i) if i in first_set else str(reason_u[cl[i - 1]])
            ex_txt.append(f"node {node_s}: anchor {anc_s} used again")
            ex_lvl.append("DEBUG" if before in BOOKKEEPING_REASONS else "INFO")
        else:
            reason = str(reason_u[cl[i]])
            ex_txt.append(f"node {node_s}: anchor {anc_s} excluded ({reason})")
            ex_lvl.append("DEBUG" if reason in BOOKKEEPING_REASONS else "WARN")
    last_idx = np.r_[first_idx[1:] - 1, n_links - 1]
    for i in last_idx:
        st.last_links.setdefault(str(node_u[nl[i]]), {})[str(anc_u[al[i]])] = str(
            reason_u[cl[i]]
        )
    return EventColumns(np.asarray(ex_t, np.int64), ex_txt, ex_lvl)


def _log_residuals(rec: rr.RecordingStream, b: _Batch, st: _EstimateState) -> None:
    """``metrics/residual_m/<anchor>``: post-fit residuals of the used links (points, styled
    once per anchor)."""
    est, t, lf = b.est, b.t, b.est.link_fix
    used = est.link_used & np.isfinite(est.link_residual_m)
    used_idx = np.flatnonzero(used)
    used_order = used_idx[np.argsort(b.anchor_code[used_idx], kind="stable")]
    used_bounds = np.searchsorted(b.anchor_code[used_order], np.arange(len(b.anchor_ids) + 1))
    for ai, aid in enumerate(b.anchor_ids.tolist()):
        li = used_order[used_bounds[ai] : used_bounds[ai + 1]]
        if not li.size:
            continue
        if aid not in st.residual_styled:
            st.residual_styled.add(aid)
            rec.log(
                f"metrics/residual_m/{aid}",
                rr.SeriesPoints(colors=[anchor_color(aid)], marker_sizes=[1.5], names=[aid]),
                static=True,
            )
        li = li[np.argsort(t[lf[li]], kind="stable")]
        rec.send_columns(
            f"metrics/residual_m/{aid}",
            indexes=[_time_column(t[lf[li]])],
            columns=rr.Scalars.columns(scalars=est.link_residual_m[li]),
        )


def _log_gating(rec: rr.RecordingStream, b: _Batch) -> None:
    """``metrics/gating/excluded`` and ``metrics/gating/used``: counts per fusion time."""
    est = b.est
    ut, inv = np.unique(b.t[est.link_fix], return_inverse=True)
    n_ex = np.bincount(inv, weights=(~est.link_used).astype(float), minlength=ut.size)
    n_used = np.bincount(inv, weights=est.link_used.astype(float), minlength=ut.size)
    rec.send_columns(
        "metrics/gating/excluded",
        indexes=[_time_column(ut)],
        columns=rr.Scalars.columns(scalars=n_ex),
    )
    rec.send_columns(
        "metrics/gating/used",
        indexes=[_time_column(ut)],
        columns=rr.Scalars.columns(scalars=n_used),
    )
