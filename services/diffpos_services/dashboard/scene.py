"""Logging of the scene: the building wireframe, the anchors with their trails, node truth."""

from __future__ import annotations

import numpy as np
import rerun as rr

from diffpos_services.dashboard.building import BuildingOutline
from diffpos_services.dashboard.columns import AnchorColumns, TruthColumns
from diffpos_services.dashboard.common import (
    _TRUTH_COLOR,
    _group,
    _rgba,
    _sorted_by_time,
    _time_column,
    anchor_color,
)


# ============================================================================ logging functions
def log_building(rec: rr.RecordingStream, building: BuildingOutline) -> None:
    """Static wireframe: floor outlines, the window band of each floor on the facade and
    one label per floor (``F<k>``, beside the west wall).

    Also sets ``world`` to a right-handed z-up frame (the building frame).
    """
    b = building
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    x0, x1, d = b.x_min_m, b.x_max_m, b.depth_m
    floors = []
    z0 = b.first_floor_z_m
    for k in range(b.n_floors + 1):
        z = z0 + k * b.floor_height_m
        floors.append([[x0, 0, z], [x1, 0, z], [x1, d, z], [x0, d, z], [x0, 0, z]])
    top = z0 + b.n_floors * b.floor_height_m
    for x, y in ((x0, 0), (x1, 0), (x1, d), (x0, d)):
        floors.append([[x, y, 0.0], [x, y, top]])
    rec.log(
        "world/building/floors",
        rr.LineStrips3D(floors, colors=[(160, 160, 170, 255)], radii=0.03),
        static=True,
    )
    windows = []
    for k in range(b.n_floors):
        z_lo = z0 + k * b.floor_height_m + b.sill_height_m
        z_hi = z_lo + b.window_height_m
        windows.append([[x0, 0, z_lo], [x1, 0, z_lo], [x1, 0, z_hi], [x0, 0, z_hi], [x0, 0, z_lo]])
    rec.log(
        "world/building/windows",
        rr.LineStrips3D(windows, colors=[(90, 170, 255, 255)], radii=0.05),
        static=True,
    )
    # one label per floor, outside the west wall at mid-floor height: never level with a
    # responder of another floor in perspective, never on top of the markers
    mid = z0 + (np.arange(b.n_floors) + 0.5) * b.floor_height_m
    rec.log(
        "world/building/floor_labels",
        rr.Points3D(np.stack([np.full(b.n_floors, x0 - 0.04 * (x1 - x0)),
                              np.zeros(b.n_floors), mid], axis=1),
                    radii=[0.0], labels=[f"F{k}" for k in range(b.n_floors)],
                    show_labels=True, colors=[(200, 200, 210, 255)]),
        static=True,
    )


def log_anchors(
    rec: rr.RecordingStream,
    anchors: AnchorColumns,
    *,
    history: AnchorColumns | None = None,
    trail_s: float = 30.0,
    trail_period_s: float = 0.5,
    trail_max_points: int = 60,
) -> None:
    """Anchor positions and their trails.

    Parameters
    ----------
    anchors : AnchorColumns
        The new rows to log.
    history : AnchorColumns, optional
        Earlier rows (already logged) used only to draw the beginning of the trails.
    trail_s : float [s]
        Trail length in measurement time.
    trail_period_s : float [s]
        A trail is re-drawn at most once per this period of measurement time (per anchor).
    trail_max_points : int
        Trails are subsampled to at most this many points.
    """
    if not len(anchors):
        return
    period_ns = max(1, int(trail_period_s * 1e9))
    trail_ns = int(trail_s * 1e9)
    for aid, rows in _group(anchors.anchor_id):
        rows = _sorted_by_time(anchors.t_ns, rows)
        t = anchors.t_ns[rows]
        pos = anchors.position_m[rows]
        color = anchor_color(aid)
        rec.send_columns(
            f"world/anchors/{aid}",
            indexes=[_time_column(t)],
            columns=rr.Points3D.columns(
                positions=pos,
                colors=_rgba([color] * len(rows)),
                radii=np.full(len(rows), -9.0, np.float32),  # ui points: any zoom
                labels=np.full(len(rows), aid),
            ),
        )
        # trails: full track = history + new rows; one strip per new trail bucket
        if history is not None and len(history):
            hsel = history.anchor_id == aid
            t_all = np.concatenate([history.t_ns[hsel], t])
            p_all = np.concatenate([history.position_m[hsel], pos])
            order = np.argsort(t_all, kind="stable")
            t_all, p_all = t_all[order], p_all[order]
            prev_bucket = history.t_ns[hsel].max() // period_ns if hsel.any() else None
        else:
            t_all, p_all, prev_bucket = t, pos, None
        bucket = t // period_ns
        first = np.ones(len(t), bool)
        first[1:] = bucket[1:] != bucket[:-1]
        if prev_bucket is not None:
            first &= bucket != prev_bucket
        emit_t = t[first]
        if not emit_t.size:
            continue
        lo = np.searchsorted(t_all, emit_t - trail_ns, side="left")
        hi = np.searchsorted(t_all, emit_t, side="right")
        strips = []
        for a, b in zip(lo, hi, strict=True):
            step = max(1, (b - a) // trail_max_points)
            idx = np.arange(b - 1, a - 1, -step)[::-1]
            strips.append(p_all[idx])
        rec.send_columns(
            f"world/anchors/{aid}/trail",
            indexes=[_time_column(emit_t)],
            columns=rr.LineStrips3D.columns(
                strips=strips,
                colors=_rgba([(*color[:3], 160)] * len(strips)),
                radii=np.full(len(strips), 0.08, np.float32),
            ),
        )


def log_truth(rec: rr.RecordingStream, truth: TruthColumns) -> None:
    """True node positions (emulation) as small white points ``world/nodes/<node>/truth``."""
    for nid, rows in _group(truth.node_id):
        rows = _sorted_by_time(truth.t_ns, rows)
        n = len(rows)
        rec.send_columns(
            f"world/nodes/{nid}/truth",
            indexes=[_time_column(truth.t_ns[rows])],
            columns=rr.Points3D.columns(
                positions=truth.position_m[rows],
                colors=_rgba([_TRUTH_COLOR] * n),
                radii=np.full(n, -3.0, np.float32),  # ui points
            ),
        )
