"""The default blueprint (layout) of the dashboard: what the person coordinating a response
sees first."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import rerun.blueprint as rrb
from numpy.typing import ArrayLike

from diffpos_services.dashboard.building import BuildingOutline
from diffpos_services.dashboard.common import TIMELINE
from diffpos_services.dashboard.plans import LEGEND_BOUNDS, floor_view_name

#: names of the views of :func:`default_blueprint` (tests read them back from the .rrd)
BUILDING_VIEW = "Building: responders now (marker + 95 % ellipsoid), UAV anchors"
FLOOR_VIEW = "Who is on which floor now"
EVENTS_VIEW = "Events (DEBUG hidden: see the view's level filter)"
LEGEND_VIEW = "Legend: marker colour = status, dimmed = floor unsure; plot lines"
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


def default_blueprint(
    *,
    view_points_m: ArrayLike | None = None,
    building: BuildingOutline | None = None,
    plot_nodes: Sequence[str] = (),
) -> rrb.Blueprint:
    """The diffpos dashboard layout (embedded in every .rrd and sent to live viewers).

    Left (with a building): the floor plans, top floor first, two per row, and the legend
    (every status the fusion publishes, dimming for an unsure floor, the plot lines). Right:
    the building in 3D with one marker per responder (its 95 % ellipsoid; the paths hidden,
    ``world/paths``: shown per responder on demand) and the anchors; who is on which floor
    now (floor table: probability of the chosen floor, age of the last fix); the events
    (normal end INFO, faults WARN/ERROR); tabs with the plots: the 3D error of all
    responders as three lines (median, 95th percentile, worst), the floor probability of
    each responder of ``plot_nodes`` and their 3D error, z error and PEB, the residuals,
    gating and fusion counters. Plot legends are off: the legend view names every line.

    Parameters
    ----------
    view_points_m : array, shape (N, 3) [m], optional
        Points the default camera must show (building corners, every anchor position:
        :func:`camera_for`); default: the viewer fits the scene.
    building : BuildingOutline, optional
        Gives the floor plans (none without it).
    plot_nodes : sequence of str
        The responders whose plots are shown (the others are logged and can be added).

    The time panel follows the newest data: live, and for a file its end, where every
    responder that ever had a fix has a marker (the last fix, with its age).
    """
    eye = camera_for(view_points_m) if view_points_m is not None else None
    building_3d = rrb.Spatial3DView(
        origin="world",
        name=BUILDING_VIEW,
        line_grid=rrb.LineGrid3D(visible=False),
        eye_controls=eye,
        overrides={PATHS_ENTITY: rrb.EntityBehavior(visible=False)},
    )
    right = rrb.Vertical(
        building_3d,
        rrb.TextDocumentView(origin="floors", name=FLOOR_VIEW),
        rrb.TextLogView(
            origin="events",
            name=EVENTS_VIEW,
            rows=rrb.TextLogRows(filter_by_log_level=["INFO", "WARN", "ERROR", "CRITICAL"]),
        ),
        _plots(list(plot_nodes)),
        row_shares=[2.2, 1.6, 1.0, 1.8],
    )
    if building is None:
        body: rrb.Container = right
    else:
        body = rrb.Horizontal(_plans(building), right, column_shares=[1.25, 1.0])
    return rrb.Blueprint(
        body,
        rrb.TimePanel(timeline=TIMELINE, play_state="following", state="collapsed"),
        collapse_panels=True,
    )


def _plans(building: BuildingOutline) -> rrb.Grid:
    """The floor plans, top floor first, two per row, then the legend."""
    x0, x1, d = building.x_min_m, building.x_max_m, building.depth_m
    m = 0.06 * max(x1 - x0, d)
    bounds = rrb.VisualBounds2D(x_range=(x0 - m, x1 + m), y_range=(-d - m, 2 * m))
    views: list[rrb.View] = [
        rrb.Spatial2DView(origin=f"plan/F{k}", name=floor_view_name(building, k),
                          visual_bounds=bounds, background=(25, 27, 32, 255))
        for k in reversed(range(building.n_floors))
    ]
    views.append(rrb.Spatial2DView(
        origin="legend", name=LEGEND_VIEW, background=(25, 27, 32, 255),
        visual_bounds=rrb.VisualBounds2D(x_range=LEGEND_BOUNDS[0], y_range=LEGEND_BOUNDS[1])))
    return rrb.Grid(*views, grid_columns=2)


def _plots(plot_nodes: list[str]) -> rrb.Tabs:
    """The plot tabs (legends off: the legend view names the lines)."""
    off = rrb.PlotLegend(visible=False)
    sel = " ".join(plot_nodes)

    def of(what: str) -> list[str]:
        return [f"+ /metrics/{what}/{n}" for n in plot_nodes]

    tabs = [rrb.TimeSeriesView(origin="metrics/fleet/error_3d_m", plot_legend=off,
                               name="3D error, all responders: median, p95, worst [m]")]
    tabs += [rrb.TimeSeriesView(
        origin=f"metrics/floor_probability/{n}", name=f"floor probability of {n}",
        axis_y=rrb.ScalarAxis(range=(0.0, 1.45)), plot_legend=rrb.PlotLegend(
            corner=rrb.Corner2D.LeftTop, visible=True)) for n in plot_nodes]
    if plot_nodes:
        tabs += [rrb.TimeSeriesView(origin="metrics", contents=of(what), plot_legend=off,
                                    name=f"{title} of {sel} [m]")
                 for what, title in (("error_3d_m", "3D error"), ("error_z_m", "z error"),
                                     ("peb_m", "PEB"))]
    tabs += [
        rrb.TimeSeriesView(origin="metrics/residual_m", name="Range residuals per anchor [m]"),
        rrb.TimeSeriesView(origin="metrics/gating", name="Measurements used / excluded"),
        rrb.TimeSeriesView(origin="metrics/fusion", name="Fusion counters"),
    ]
    return rrb.Tabs(*tabs)
