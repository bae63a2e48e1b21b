"""Logging of the position estimates: one function per logged stream."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import rerun as rr
from numpy.typing import NDArray

from diffpos.geometry import diffraction_point
from diffpos_services.dashboard.building import BuildingOutline
from diffpos_services.dashboard.columns import EstimateColumns, EventColumns
from diffpos_services.dashboard.common import (
    _EXCLUDED_COLOR,
    _OTHER_STATUS_COLOR,
    _STATUS_COLORS,
    BOOKKEEPING_REASONS,
    CHI2_3DOF_95,
    GOOD_STATUSES,
    UNIDENTIFIABLE_STATUSES,
    _group,
    _rgba,
    _sorted_by_time,
    _time_column,
    anchor_color,
)
from diffpos_services.dashboard.events import _status_level, log_events
from diffpos_services.dashboard.geometry import Tracks, ellipsoid_axes


def _scalar_series(
    rec: rr.RecordingStream, path: str, t_ns: np.ndarray, values: np.ndarray
) -> None:
    ok = np.isfinite(values)
    if ok.any():
        rec.send_columns(
            path, indexes=[_time_column(t_ns[ok])], columns=rr.Scalars.columns(scalars=values[ok])
        )


@dataclass
class _EstimateState:
    """What log_estimates remembers between batches (live streaming)."""

    last_path_bucket: dict[str, int] = field(default_factory=dict)
    last_links: dict[str, dict[str, str]] = field(default_factory=dict)
    last_status: dict[str, str] = field(default_factory=dict)
    last_floor_bucket: int | None = None
    floors: dict[str, tuple[int, int]] = field(default_factory=dict)
    residual_styled: set[str] = field(default_factory=set)
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
    )


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
        Gives the window edge of the estimated floor for the paths, and true floors from z.
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
    bad_time = est.t_ns < 0
    if bad_time.any():  # invalid on the wire (times are ns since the Unix epoch): not drawn
        n_bad = int(bad_time.sum())
        st.dropped_bad_time += n_bad
        est = _select_fixes(est, ~bad_time)
        if len(est):
            log_events(
                rec,
                EventColumns(
                    [int(est.t_ns.max())],
                    [
                        f"{n_bad} estimates with a negative t_ns dropped (invalid time from the fusion)"
                    ],
                    ["ERROR"],
                ),
            )
    k = len(est)
    if k == 0:
        return st
    t = est.t_ns
    pos = est.position_m
    has_pos = np.all(np.isfinite(pos), axis=1)

    # ---- truth, errors, floors
    if truth is not None:
        true_pos, true_floor, known = truth.sample(est.node_id, t)
    else:
        true_pos = np.full((k, 3), np.nan)
        true_floor = np.full(k, -1, np.int64)
        known = np.zeros(k, bool)
    if building is not None:
        derived = building.floor_of(true_pos[:, 2])
        true_floor = np.where(known & (true_floor < 0), derived, true_floor)
    err_3d = np.linalg.norm(pos - true_pos, axis=1)
    err_z = pos[:, 2] - true_pos[:, 2]
    est_floor = est.floor_index
    if building is not None:
        est_floor = np.where((est_floor < 0) & has_pos, building.floor_of(pos[:, 2]), est_floor)

    half, quat, cov_ok = ellipsoid_axes(est.covariance_m2, scale=confidence_scale)
    cov_ok &= has_pos

    # ---- links: anchor positions and window-edge points (vectorised over all links)
    n_links = est.link_fix.size
    lf = est.link_fix
    anc_u, anc_c = np.unique(est.link_anchor_id, return_inverse=True)
    link_ok = np.zeros(n_links, bool)
    strips = np.zeros((n_links, 3, 3))
    if n_links and anchors is not None:
        a_pos, _, a_known = anchors.sample(None, t[lf], coded=(anc_u, anc_c))
        node = pos[lf]
        link_ok = a_known & has_pos[lf]
        if building is not None:
            fl = np.where(est_floor[lf] >= 0, est_floor[lf], building.floor_of(node[:, 2]))
            ze = building.upper_edge_z_m(fl)
            start = np.stack([np.full(n_links, building.x_min_m), np.zeros(n_links), ze], axis=1)
            end = start.copy()
            end[:, 0] = building.x_max_m
            with np.errstate(invalid="ignore"):
                q = diffraction_point(a_pos, node, start, end).point_m
        else:
            q = 0.5 * (a_pos + node)
        strips = np.stack([a_pos, q, node], axis=1)
        link_ok &= np.all(np.isfinite(strips), axis=(1, 2))
        # no path for bookkeeping exclusions (nothing was measured); gated ones are drawn red
        link_ok &= est.link_used | ~np.isin(est.link_reason, list(BOOKKEEPING_REASONS))
    link_colors = _rgba([anchor_color(str(a)) for a in anc_u])[anc_c]
    link_colors[~est.link_used] = _EXCLUDED_COLOR
    link_radii = np.where(est.link_used, 0.05, 0.03).astype(np.float32)

    status_colors = np.array(
        [_STATUS_COLORS.get(s, _OTHER_STATUS_COLOR) for s in np.unique(est.status)], np.uint8
    )
    status_idx = np.searchsorted(np.unique(est.status), est.status)
    colors = status_colors[status_idx]

    path_period_ns = max(1, int(path_period_s * 1e9))
    events_t: list[np.ndarray] = []
    events_text: list[list[str]] = []
    events_level: list[list[str]] = []

    for nid, rows in _group(est.node_id):
        rows = _sorted_by_time(t, rows)
        tr = t[rows]
        hp = has_pos[rows]
        n_pos = hp.astype(np.int64)
        label = [
            f"{nid} F{ef if ef >= 0 else '?'}" + (f" (true F{tf})" if 0 <= tf != ef else "")
            for ef, tf in zip(est_floor[rows].tolist(), true_floor[rows].tolist(), strict=True)
        ]
        sel = rows[hp]
        ok = cov_ok[rows]
        sel_c = rows[ok]
        # point and ellipsoid on one entity: one chunk per node and batch instead of two
        rec.send_columns(
            f"world/nodes/{nid}/estimate",
            indexes=[_time_column(tr)],
            columns=[
                *rr.Points3D.columns(
                    positions=pos[sel],
                    colors=colors[sel],
                    radii=np.full(sel.size, 0.25, np.float32),
                    labels=np.asarray(label)[hp],
                ).partition(n_pos),
                *rr.Ellipsoids3D.columns(
                    centers=pos[sel_c],
                    half_sizes=half[sel_c],
                    quaternions=quat[sel_c],
                    colors=colors[sel_c],
                    line_radii=np.full(sel_c.size, 0.02, np.float32),
                ).partition(ok.astype(np.int64)),
            ],
        )
        # diffraction paths, decimated in measurement time
        if n_links and anchors is not None:
            bucket = tr // path_period_ns
            first = np.ones(len(rows), bool)
            first[1:] = bucket[1:] != bucket[:-1]
            prev = st.last_path_bucket.get(nid)
            if prev is not None:
                first &= bucket != prev
            if first.any():
                st.last_path_bucket[nid] = int(bucket[-1])
                prow = rows[first]
                rank = np.full(k, -1, np.int64)
                rank[prow] = np.arange(prow.size)
                lsel = np.flatnonzero((rank[lf] >= 0) & link_ok)
                lsel = lsel[np.argsort(rank[lf[lsel]], kind="stable")]
                per_row = np.bincount(rank[lf[lsel]], minlength=prow.size)
                rec.send_columns(
                    f"world/nodes/{nid}/paths",
                    indexes=[_time_column(tr[first])],
                    columns=rr.LineStrips3D.columns(
                        strips=strips[lsel],
                        colors=link_colors[lsel],
                        radii=link_radii[lsel],
                    ).partition(per_row),
                )
        _scalar_series(rec, f"metrics/error_3d_m/{nid}", tr, err_3d[rows])
        _scalar_series(rec, f"metrics/error_z_m/{nid}", tr, err_z[rows])
        _scalar_series(rec, f"metrics/peb_m/{nid}", tr, est.peb_m[rows])

        # status changes -> events
        prev_status = st.last_status.get(nid)
        stat = est.status[rows]
        change = np.ones(len(rows), bool)
        change[1:] = stat[1:] != stat[:-1]
        if prev_status is not None:
            change[0] = stat[0] != prev_status
        elif stat[0] in GOOD_STATUSES:
            change[0] = False
        st.last_status[nid] = str(stat[-1])
        if change.any():
            ci = np.flatnonzero(change)
            events_t.append(tr[ci])
            txt, lvl = [], []
            for i in ci:
                s = str(stat[i])
                before = str(stat[i - 1]) if i > 0 else prev_status
                txt.append(
                    f"node {nid}: status {s}"
                    + (" (unidentifiable geometry)" if s in UNIDENTIFIABLE_STATUSES else "")
                )
                lvl.append(_status_level(before, s))
            events_text.append(txt)
            events_level.append(lvl)

        # latest floors for the floor table
        last = rows[-1]
        st.floors[nid] = (int(est_floor[last]), int(true_floor[last]))

    # ---- exclusions: an event when an anchor becomes excluded (or changes reason) for a node
    if n_links:
        # integer codes: sorting and comparing ints is much cheaper than strings
        node_u, node_c = np.unique(est.node_id, return_inverse=True)
        cur_str = np.where(est.link_used, "", est.link_reason)
        reason_u, reason_c = np.unique(cur_str, return_inverse=True)
        lorder = np.lexsort((t[lf], anc_c, node_c[lf]))
        ex_t, ex_txt, ex_lvl = [], [], []
        nl, al, cl, tl = node_c[lf][lorder], anc_c[lorder], reason_c[lorder], t[lf][lorder]
        empty = np.flatnonzero(reason_u == "")
        empty_code = int(empty[0]) if empty.size else -1
        first = np.ones(n_links, bool)
        first[1:] = (nl[1:] != nl[:-1]) | (al[1:] != al[:-1])
        changed = np.zeros(n_links, bool)
        changed[1:] = cl[1:] != cl[:-1]
        first_idx = np.flatnonzero(first)
        # the first link of each (node, anchor) pair compares with the previous batch's state
        for i in first_idx:
            before = st.last_links.get(str(node_u[nl[i]]), {}).get(str(anc_u[al[i]]), "")
            changed[i] = str(reason_u[cl[i]]) != before
        is_used = cl == empty_code
        prev_excluded = np.zeros(n_links, bool)
        prev_excluded[1:] = cl[:-1] != empty_code
        for i in first_idx:
            prev_excluded[i] = bool(
                st.last_links.get(str(node_u[nl[i]]), {}).get(str(anc_u[al[i]]), "")
            )
        events_idx = np.flatnonzero(changed & (~is_used | prev_excluded))
        first_set = set(first_idx.tolist())
        for i in events_idx:
            ex_t.append(tl[i])
            node_s, anc_s = node_u[nl[i]], anc_u[al[i]]
            if is_used[i]:
                if i in first_set:
                    before = st.last_links.get(str(node_s), {}).get(str(anc_s), "")
                else:
                    before = str(reason_u[cl[i - 1]])
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
        if ex_t:
            events_t.append(np.asarray(ex_t, np.int64))
            events_text.append(ex_txt)
            events_level.append(ex_lvl)

        # residual scatter per anchor and gating counts per fusion time
        used = est.link_used & np.isfinite(est.link_residual_m)
        used_idx = np.flatnonzero(used)
        used_order = used_idx[np.argsort(anc_c[used_idx], kind="stable")]
        used_bounds = np.searchsorted(anc_c[used_order], np.arange(len(anc_u) + 1))
        for ai, aid in enumerate(anc_u.tolist()):
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
        ut, inv = np.unique(t[lf], return_inverse=True)
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

    # ---- floor table, refreshed at most once per floor period (latest fix per node)
    floor_period_ns = max(1, int(floor_period_s * 1e9))
    fb = t // floor_period_ns
    ub = np.unique(fb)
    if st.last_floor_bucket is not None:
        ub = ub[ub != st.last_floor_bucket]
    if ub.size:
        # snapshot at the end of each bucket: latest fix per node up to that time
        snap_t = np.array([t[fb == b].max() for b in ub], np.int64)
        texts = _floor_tables(est, est_floor, true_floor, snap_t, st)
        st.last_floor_bucket = int(ub[-1])
        rec.send_columns(
            "floors",
            indexes=[_time_column(snap_t)],
            columns=rr.TextDocument.columns(text=texts, media_type=["text/markdown"] * len(texts)),
        )

    if events_t:
        log_events(
            rec,
            EventColumns(
                np.concatenate(events_t),
                [x for part in events_text for x in part],
                [x for part in events_level for x in part],
            ),
        )
    return st


def _floor_tables(
    est: EstimateColumns,
    est_floor: NDArray[np.int64],
    true_floor: NDArray[np.int64],
    snap_t: NDArray[np.int64],
    st: _EstimateState,
) -> list[str]:
    """Markdown tables (one per snapshot time) of the latest estimated/true floor per node."""
    groups = _group(est.node_id)
    nodes = sorted(set(st.floors) | {g for g, _ in groups})
    # latest (est, true) per node at each snapshot: (n_nodes, n_snap)
    est_m = np.full((len(nodes), snap_t.size), -2, np.int64)
    tru_m = np.full((len(nodes), snap_t.size), -2, np.int64)
    pos = {n: i for i, n in enumerate(nodes)}
    prior = dict(st.floors)
    for nid, i in pos.items():
        if nid in prior:
            est_m[i, :], tru_m[i, :] = prior[nid]
    for nid, rows in groups:
        rows = _sorted_by_time(est.t_ns, rows)
        k = np.searchsorted(est.t_ns[rows], snap_t, side="right") - 1
        have = k >= 0
        i = pos[nid]
        est_m[i, have] = est_floor[rows][k[have]]
        tru_m[i, have] = true_floor[rows][k[have]]
    fmt = lambda v: "?" if v < 0 else str(v)  # noqa: E731
    texts = []
    for j in range(snap_t.size):
        hits = [
            (e == tr) for e, tr in zip(est_m[:, j], tru_m[:, j], strict=True) if e >= 0 and tr >= 0
        ]
        if hits:
            head = f"**Floor estimate: {sum(hits)}/{len(hits)} nodes on the true floor**\n\n"
        elif np.any(tru_m[:, j] >= 0):
            head = "**Floor estimate**: no node has a fix\n\n"
        else:
            head = "**Floor estimate** (no ground truth)\n\n"
        rows = ["| node | estimated | true | |", "|---|---|---|---|"]
        for i, nid in enumerate(nodes):
            e, tr = est_m[i, j], tru_m[i, j]
            if e == -2:
                continue
            mark = "" if e < 0 or tr < 0 else ("ok" if e == tr else "**WRONG**")
            rows.append(f"| {nid} | {fmt(e)} | {fmt(tr)} | {mark} |")
        texts.append(head + "\n".join(rows))
    return texts
