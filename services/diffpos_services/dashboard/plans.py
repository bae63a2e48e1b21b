"""The coordinator's floor plans: one top-down 2D view per floor (``plan/F<k>``) with the
floor's walls, windows and stairs, every responder whose latest fix is on that floor as a
marker coloured by status and floor confidence, its horizontal 95 % ellipse, and labels that
never overlap (short ids; responders whose labels would overlap share one label); and the
legend (``legend``): every status the fusion publishes with its colour, and the plot lines.

Plan coordinates: ``(x, -y)`` of the building frame, so on screen (2D views point ``y``
down) the facade with the windows is at the bottom, the inside above it and the street with
the UAVs below: the plan seen from above with the facade towards the viewer, as in the 3D
view. One function per logged stream, as in :mod:`.estimates`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import rerun as rr
from numpy.typing import NDArray

from diffpos_services.dashboard.building import BuildingOutline, FloatArray
from diffpos_services.dashboard.common import (
    STATUS_STYLE,
    SURE_FLOOR_P,
    _group,
    _rgba,
    _sorted_by_time,
    _time_column,
    confidence_colors,
    short_id,
    status_color,
)

#: chi-square 95 % quantile for 2 degrees of freedom: the horizontal ellipse of the plans
CHI2_2DOF_95 = 5.991464547107979
#: responder marker on the plans [ui points]
PLAN_MARKER_UI = 7.0
#: a fix older than this is marked stale on the plans (``07?``) [s]
STALE_S = 2.0
#: labels of the plans are laid out for this many label heights across the plan's long side
#: (the label box height, text and padding, at the default zoom of a plan view about 380
#: points wide: measured on the web viewer's screenshots)
LABEL_ROWS = 24.0
#: the plot lines of the legend: (entity name, colour, meaning)
FLEET_LINES = (
    ("median", (31, 119, 180, 255), "median error"),
    ("p95", (250, 165, 40, 255), "p95 error"),
    ("worst", (230, 35, 60, 255), "worst error"),
)


def plan_xy(p_m: FloatArray) -> FloatArray:
    """Plan coordinates ``(x, -y)`` of building-frame points ``(..., >= 2)`` [m]."""
    p = np.asarray(p_m, np.float64)
    return np.stack([p[..., 0], -p[..., 1]], axis=-1)


def floor_view_name(building: BuildingOutline, k: int) -> str:
    """The name of floor ``k``'s plan view (the floor, its heights)."""
    z0 = building.first_floor_z_m + k * building.floor_height_m
    return f"F{k} plan (z {z0:g}-{z0 + building.floor_height_m:g} m), facade at the bottom"


# ============================================================================ static
def log_plans_building(rec: rr.RecordingStream, building: BuildingOutline) -> None:
    """Static plan of every floor: ``plan/F<k>/walls`` (outer and interior walls),
    ``plan/F<k>/windows`` (the window band on the facade ``y = 0``), ``plan/F<k>/stairs``
    (every flight of stairs that reaches the floor, hatched with its treads; which floors
    it joins shows on hover: no label on the plan, where it would meet responders')."""
    b = building
    x0, x1, d = b.x_min_m, b.x_max_m, b.depth_m
    outer = [plan_xy(np.array([[x0, 0], [x0, d], [x1, d], [x1, 0]], float))]
    inner = [plan_xy(np.array([[pos, lo], [pos, hi]] if axis == "x" else [[lo, pos], [hi, pos]],
                              float)) for axis, pos, (lo, hi) in b.walls]
    for k in range(b.n_floors):
        base = f"plan/F{k}"
        rec.log(f"{base}/walls", rr.LineStrips2D(
            outer + inner, colors=[(175, 175, 185, 255)] * 1 + [(120, 120, 130, 255)] * len(inner),
            radii=[-2.0] + [-1.0] * len(inner), draw_order=1.0), static=True)
        rec.log(f"{base}/windows", rr.LineStrips2D(
            [plan_xy(np.array([[x0, 0], [x1, 0]], float))], colors=[(90, 170, 255, 255)],
            radii=[-3.0], labels=["windows (facade)"], show_labels=False, draw_order=2.0),
            static=True)
        flights = [s for s in b.stairs if s[4] <= k <= s[5]]
        if not flights:
            continue
        boxes, treads, labels = [], [], []
        for sx0, sx1, sy0, sy1, lo, hi in flights:
            boxes.append((sx0, -sy1, sx1 - sx0, sy1 - sy0))
            labels.append(f"stairs F{lo}-F{hi}")
            along_x = (sx1 - sx0) >= (sy1 - sy0)
            for u in np.arange(sx0 if along_x else sy0, (sx1 if along_x else sy1), 0.3):
                seg = [[u, sy0], [u, sy1]] if along_x else [[sx0, u], [sx1, u]]
                treads.append(plan_xy(np.array(seg, float)))
        rec.log(f"{base}/stairs", rr.Boxes2D(
            mins=[bx[:2] for bx in boxes], sizes=[bx[2:] for bx in boxes],
            colors=[(150, 140, 110, 255)], radii=[-1.0], labels=labels, show_labels=False,
            draw_order=1.5), static=True)
        rec.log(f"{base}/stairs/treads", rr.LineStrips2D(
            treads, colors=[(110, 105, 85, 255)], radii=[-0.5], draw_order=1.4), static=True)


#: the legend's layout: rows one unit apart, the second column at this x, text characters
#: about this wide (the legend view's bounds fit a plan cell: 20 x 14 units)
LEGEND_COLUMN_X = 11.0
LEGEND_CHAR_W = 0.34
LEGEND_BOUNDS = ((-0.5, 20.0), (-0.7, 13.3))


def log_legend(rec: rr.RecordingStream, plot_nodes: dict[str, tuple[int, int, int, int]]
               | None = None) -> None:
    """Static ``legend``: a swatch and its text per status the fusion publishes
    (:data:`~diffpos_services.dashboard.common.STATUS_STYLE`, tracking and snapshot
    statuses) and how a marker shows an unsure floor (first column), the plot lines (fleet
    statistics and the responders the plots show, ``plot_nodes``: id -> colour; second
    column). Rerun centres a label on its point: each text's point is placed so the text
    starts right of its swatch."""
    left = [(c, f"{name} {what}") for name, (c, what) in STATUS_STYLE.items()]
    dim = tuple(int(v) for v in confidence_colors([STATUS_STYLE["TRACKING"][0]], [0.5])[0])
    left.append((dim, f"dimmed: floor p < {100 * SURE_FLOOR_P:.0f} %"))
    right = [((150, 140, 110, 255), "hatched box: stairs"), ((90, 170, 255, 255),
                                                             "blue: windows (facade)")]
    right += [(c, f"plot: {what}") for _, c, what in FLEET_LINES]
    right += [(c, f"plot: {nid}") for nid, c in (plot_nodes or {}).items()]
    xs = [0.0] * len(left) + [LEGEND_COLUMN_X] * len(right)
    ys = [float(i) for i in range(len(left))] + [float(i) for i in range(len(right))]
    rows = left + right
    sw = np.array([xs, ys], float).T
    text_x = [x + 0.7 + 0.5 * LEGEND_CHAR_W * len(t) for x, (_, t) in zip(xs, rows, strict=True)]
    rec.log("legend/swatches", rr.Points2D(sw, colors=_rgba([c for c, _ in rows]),
                                           radii=[-6.0]), static=True)
    rec.log("legend/text", rr.Points2D(
        np.array([text_x, ys], float).T, radii=[0.0], labels=[t for _, t in rows],
        show_labels=True, colors=[(230, 230, 230, 255)]), static=True)


# ============================================================================ responders
@dataclass
class PlanState:
    """What :func:`log_plan_markers` remembers between batches (live)."""

    last_bucket: int | None = None
    #: node -> (status, time [ns]) of its newest estimate
    status: dict[str, tuple[str, int]] | None = None
    #: node -> (time [ns], plan xy (2,), floor, floor probability, 2x2 covariance) of its
    #: newest fix with a position
    fix: dict[str, tuple[int, FloatArray, int, float, FloatArray]] | None = None

    def __post_init__(self) -> None:
        self.status = self.status or {}
        self.fix = self.fix or {}


def _snapshot_times(t: NDArray[np.int64], period_ns: int, st: PlanState) -> NDArray[np.int64]:
    """The newest time of every ``period_ns`` bucket of ``t`` not drawn yet."""
    fb = t // period_ns
    ub = np.unique(fb)
    if st.last_bucket is not None:
        ub = ub[ub > st.last_bucket]
    if not ub.size:
        return np.zeros(0, np.int64)
    st.last_bucket = int(ub[-1])
    order = np.argsort(fb, kind="stable")  # older buckets (already drawn) sort first
    return np.maximum.reduceat(t[order], np.searchsorted(fb[order], ub)).astype(np.int64)


def _node_at(nid: str, rows: NDArray[np.int64], b: Any, snaps: NDArray[np.int64],
             st: PlanState) -> list[tuple | None]:
    """Per snapshot: (status, fix time, xy, floor, p, cov 2x2) of node ``nid`` (None before
    its first fix); updates ``st`` with the node's newest estimate and fix of the batch."""
    est, t = b.est, b.t
    rows = _sorted_by_time(t, rows)
    fixed = rows[b.has_pos[rows]]
    ks = np.searchsorted(t[rows], snaps, side="right") - 1
    kf = np.searchsorted(t[fixed], snaps, side="right") - 1
    out: list[tuple | None] = []
    for j in range(snaps.size):
        status = (str(est.status[rows[ks[j]]]), int(t[rows[ks[j]]])) if ks[j] >= 0 \
            else st.status.get(nid)
        if kf[j] >= 0:
            r = fixed[kf[j]]
            fix = (int(t[r]), plan_xy(est.position_m[r]), int(b.est_floor[r]),
                   float(est.floor_probability[r]), est.covariance_m2[r, :2, :2])
        else:
            fix = st.fix.get(nid)
        out.append(None if fix is None or status is None else (status[0], *fix))
    st.status[nid] = (str(est.status[rows[-1]]), int(t[rows[-1]]))
    if fixed.size:
        r = fixed[-1]
        st.fix[nid] = (int(t[r]), plan_xy(est.position_m[r]), int(b.est_floor[r]),
                       float(est.floor_probability[r]), est.covariance_m2[r, :2, :2])
    return out


def _ellipse(center: FloatArray, cov_xy: FloatArray, n: int = 24) -> FloatArray | None:
    """The 95 % horizontal ellipse of a fix in plan coordinates (None: no covariance)."""
    if not np.all(np.isfinite(cov_xy)):
        return None
    c = np.array([[cov_xy[0, 0], -cov_xy[0, 1]], [-cov_xy[1, 0], cov_xy[1, 1]]])  # y -> -y
    w, v = np.linalg.eigh(0.5 * (c + c.T))
    if w.min() < 0:
        return None
    a = np.linspace(0, 2 * np.pi, n + 1)
    circle = np.stack([np.cos(a), np.sin(a)], axis=1) * np.sqrt(w * CHI2_2DOF_95)
    return center + circle @ v.T


def declutter(xy: FloatArray, names: list[str], height_m: float) -> list[tuple[FloatArray, str]]:
    """Labels that do not overlap: each label is a box ``height_m`` high and 0.62 of that
    per character wide, centred 1.4 ``height_m`` above its first responder's marker; a
    responder whose label box would overlap an existing one joins that label (``07 12``;
    beyond three names ``07 12 31 +2``). Returns ``(anchor xy, text)`` per label."""
    order = np.lexsort((xy[:, 0], xy[:, 1])) if len(xy) else np.zeros(0, int)
    labels: list[list[Any]] = []  # [anchor (2,), names]

    def box(anchor: FloatArray, text: str) -> tuple[float, float, float, float]:
        half = 0.5 * 0.62 * height_m * max(len(text), 2) + 0.15 * height_m
        return (anchor[0] - half, anchor[0] + half, anchor[1] - 0.6 * height_m,
                anchor[1] + 0.6 * height_m)

    def text_of(ns: list[str]) -> str:
        return " ".join(ns[:3]) + (f" +{len(ns) - 3}" if len(ns) > 3 else "")

    def hit(a: tuple, c: tuple) -> bool:
        return a[0] < c[1] and c[0] < a[1] and a[2] < c[3] and c[2] < a[3]

    for i in order:
        anchor = xy[i] + np.array([0.0, -1.4 * height_m])
        mine = box(anchor, names[i])
        for lab in labels:
            if hit(mine, box(lab[0], text_of(lab[1]))):
                lab[1].append(names[i])
                break
        else:
            labels.append([anchor, [names[i]]])
    # a grown label may now reach a neighbour: merge until no two overlap
    merged = True
    while merged:
        merged = False
        for a in range(len(labels)):
            for c in range(a + 1, len(labels)):
                if hit(box(labels[a][0], text_of(labels[a][1])),
                       box(labels[c][0], text_of(labels[c][1]))):
                    labels[a][1] += labels.pop(c)[1]
                    merged = True
                    break
            if merged:
                break
    return [(lab[0], text_of(lab[1])) for lab in labels]


def log_plan_markers(rec: rr.RecordingStream, b: Any, building: BuildingOutline | None,
                     period_s: float, st: PlanState) -> None:
    """``plan/F<k>/responders`` (markers: status colour dimmed by floor confidence, the full
    detail of each in its label, shown on selection or hover), ``plan/F<k>/labels`` (the
    decluttered short ids) and ``plan/F<k>/ellipses`` (95 % horizontal ellipses of fresh
    fixes): a snapshot of every responder on the floor of its latest fix, at most once per
    ``period_s`` of measurement time."""
    if building is None or len(b.est) == 0:
        return
    snaps = _snapshot_times(b.t, max(1, int(period_s * 1e9)), st)
    if not snaps.size:
        return
    groups = dict(_group(b.est.node_id))
    nodes = sorted(set(st.fix) | set(groups))
    per_node = {n: (_node_at(n, groups[n], b, snaps, st) if n in groups
                    else [(st.status[n][0], *st.fix[n]) if n in st.status else None] * snaps.size)
                for n in nodes}
    height = max(building.x_max_m - building.x_min_m, building.depth_m) / LABEL_ROWS
    for k in range(building.n_floors):
        _log_floor_snapshots(rec, k, nodes, per_node, snaps, height)


def _log_floor_snapshots(rec: rr.RecordingStream, k: int, nodes: list[str],
                         per_node: dict[str, list[tuple | None]], snaps: NDArray[np.int64],
                         height_m: float) -> None:
    """The responders of floor ``k`` at every snapshot time, as three partitioned columns."""
    pos, col, full, n_m = [], [], [], []
    lab_xy, lab_txt, n_l = [], [], []
    ell, ell_col, n_e = [], [], []
    for j, t_snap in enumerate(snaps.tolist()):
        here = [(n, per_node[n][j]) for n in nodes
                if per_node[n][j] is not None and per_node[n][j][3] == k]
        n_m.append(len(here))
        xy = np.array([s[2] for _, s in here], float).reshape(-1, 2)
        names = []
        for n, (status, t_fix, p_xy, _f, p, cov) in here:
            age = (t_snap - t_fix) * 1e-9
            c = confidence_colors([status_color(status)], [p])[0]
            pos.append(p_xy)
            col.append(c)
            prob = f", floor p {100 * p:.0f} %" if np.isfinite(p) else ""
            full.append(f"{n} {status} F{k}{prob}, fix {age:.1f} s ago")
            names.append(short_id(n) + ("?" if age >= STALE_S else ""))
            e = _ellipse(p_xy, cov) if age < STALE_S else None
            if e is not None:
                ell.append(e)
                ell_col.append(c)
        labels = declutter(xy, names, height_m)
        n_l.append(len(labels))
        lab_xy += [a for a, _ in labels]
        lab_txt += [t for _, t in labels]
        n_e.append(len(ell) - sum(n_e))
    idx = [_time_column(snaps)]
    base = f"plan/F{k}"
    rec.send_columns(f"{base}/responders", indexes=idx, columns=rr.Points2D.columns(
        positions=np.array(pos, float).reshape(-1, 2), colors=_rgba(col),
        radii=np.full(len(pos), -PLAN_MARKER_UI, np.float32), labels=full,
        show_labels=np.zeros(len(pos), bool), draw_order=np.full(len(pos), 10.0, np.float32),
    ).partition(n_m))
    rec.send_columns(f"{base}/labels", indexes=idx, columns=rr.Points2D.columns(
        positions=np.array(lab_xy, float).reshape(-1, 2),
        radii=np.zeros(len(lab_xy), np.float32), labels=lab_txt,
        show_labels=np.ones(len(lab_xy), bool), colors=_rgba([(235, 235, 235, 255)] * len(lab_xy)),
        draw_order=np.full(len(lab_xy), 11.0, np.float32),
    ).partition(n_l))
    rec.send_columns(f"{base}/ellipses", indexes=idx, columns=rr.LineStrips2D.columns(
        strips=ell, colors=_rgba(ell_col), radii=np.full(len(ell), -1.0, np.float32),
        draw_order=np.full(len(ell), 9.0, np.float32),
    ).partition(n_e))


__all__ = ["CHI2_2DOF_95", "FLEET_LINES", "PlanState", "declutter",
           "floor_view_name", "log_legend", "log_plan_markers", "log_plans_building", "plan_xy"]
