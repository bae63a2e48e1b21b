"""The default blueprint (layout) of the dashboard: what the person coordinating a response
sees first."""

from __future__ import annotations

import numpy as np
import rerun.blueprint as rrb
from numpy.typing import ArrayLike

from diffpos_services.dashboard.common import TIMELINE

#: names of the views of :func:`default_blueprint` (tests read them back from the .rrd)
BUILDING_VIEW = "Building: responders now (marker + 95 % ellipsoid), UAV anchors"
FLOOR_VIEW = "Who is on which floor now"
EVENTS_VIEW = "Events (DEBUG hidden: see the view's level filter)"
#: the paths of every responder (``world/paths/<node>``) are hidden in the building view
#: until shown per responder (blueprint panel: the eye of ``world/paths/<node>``)
PATHS_ENTITY = "world/paths"


def camera_for(points_m: ArrayLike) -> rrb.EyeControls3D | None:
    """A camera in front of the facade (``y < 0``, where the UAVs fly), above it, looking at
    the centre of ``points_m`` (shape (N, 3) [m]: building corners and every anchor position)
    from far enough that all of them are in view (a 60 degree field of view, with margin).
    ``None`` without finite points (the viewer then fits the scene itself)."""
    p = np.asarray(points_m, float).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if not p.size:
        return None
    lo, hi = p.min(axis=0), p.max(axis=0)
    center = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 5.0)
    direction = np.array([-0.35, -1.0, 0.55])
    direction /= np.linalg.norm(direction)
    # a sphere of this radius fits a 60 degree cone from 1 / sin(30 deg) = 2 radii away
    eye = center + direction * 2.1 * radius
    return rrb.EyeControls3D(position=tuple(eye), look_target=tuple(center), eye_up=(0, 0, 1))


def default_blueprint(*, view_points_m: ArrayLike | None = None) -> rrb.Blueprint:
    """The diffpos dashboard layout (embedded in every .rrd and sent to live viewers).

    Left: the building with one marker per responder (its 95 % ellipsoid, grey on its last
    fix when the newest estimate has no position) and the anchors; the paths of the
    responders are hidden (``world/paths``: shown per responder on demand). Right: who is on
    which floor now (floor table: probability of the chosen floor, age of the last fix), the
    event log, and tabs with the per-node error, PEB, residual, gating and fusion plots.

    Parameters
    ----------
    view_points_m : array, shape (N, 3) [m], optional
        Points the default camera must show (building corners, every anchor position:
        :func:`camera_for`); default: the viewer fits the scene.

    The time panel follows the newest data: live, and for a file its end, where every
    responder that ever had a fix has a marker (the last fix, with its age).
    """
    eye = camera_for(view_points_m) if view_points_m is not None else None
    building = rrb.Spatial3DView(
        origin="world",
        name=BUILDING_VIEW,
        line_grid=rrb.LineGrid3D(visible=True, spacing=5.0),
        eye_controls=eye,
        overrides={PATHS_ENTITY: rrb.EntityBehavior(visible=False)},
    )
    plots = rrb.Tabs(
        rrb.TimeSeriesView(origin="metrics/error_3d_m", name="3D error per node [m]"),
        rrb.TimeSeriesView(origin="metrics/error_z_m", name="z error per node [m]"),
        rrb.TimeSeriesView(origin="metrics/peb_m", name="PEB per node [m]"),
        rrb.TimeSeriesView(origin="metrics/residual_m", name="Range residuals per anchor [m]"),
        rrb.TimeSeriesView(origin="metrics/gating", name="Measurements used / excluded"),
        rrb.TimeSeriesView(origin="metrics/fusion", name="Fusion counters"),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            building,
            rrb.Vertical(
                rrb.TextDocumentView(origin="floors", name=FLOOR_VIEW),
                rrb.TextLogView(
                    origin="events",
                    name=EVENTS_VIEW,
                    rows=rrb.TextLogRows(
                        filter_by_log_level=["INFO", "WARN", "ERROR", "CRITICAL"]
                    ),
                ),
                plots,
                row_shares=[3, 1, 2],
            ),
            column_shares=[1.5, 1.0],
        ),
        rrb.TimePanel(timeline=TIMELINE, play_state="following", state="collapsed"),
        collapse_panels=True,
    )
