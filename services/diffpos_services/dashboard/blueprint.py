"""The default blueprint (layout) of the dashboard."""

from __future__ import annotations

import rerun.blueprint as rrb

from diffpos_services.dashboard.common import TIMELINE


# ============================================================================ blueprint
def default_blueprint() -> rrb.Blueprint:
    """The diffpos dashboard layout (embedded in every .rrd and sent to live viewers).

    Left: the 3D building view over the floor table and the event log. Right: time series
    of 3D error, z error and PEB per node, and tabs with residuals per anchor, gating counts
    and fusion counters.
    """
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(
                    origin="world",
                    name="Building (3D): anchors, estimates, 95% ellipsoids, diffraction paths",
                    line_grid=rrb.LineGrid3D(visible=True, spacing=5.0),
                    eye_controls=rrb.EyeControls3D(
                        position=(-20.0, -42.0, 30.0),
                        look_target=(6.0, 6.0, 12.0),
                        eye_up=(0, 0, 1),
                    ),
                ),
                rrb.Horizontal(
                    rrb.TextDocumentView(origin="floors", name="Floor: estimated vs true"),
                    rrb.TextLogView(
                        origin="events",
                        name="Events (DEBUG hidden: see the view's level filter)",
                        rows=rrb.TextLogRows(
                            filter_by_log_level=["INFO", "WARN", "ERROR", "CRITICAL"]
                        ),
                    ),
                    column_shares=[1, 2],
                ),
                row_shares=[3, 1],
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="metrics/error_3d_m", name="3D error per node [m]"),
                rrb.TimeSeriesView(origin="metrics/error_z_m", name="z error per node [m]"),
                rrb.TimeSeriesView(origin="metrics/peb_m", name="PEB per node [m]"),
                rrb.Tabs(
                    rrb.TimeSeriesView(
                        origin="metrics/residual_m", name="Range residuals per anchor [m]"
                    ),
                    rrb.TimeSeriesView(
                        origin="metrics/gating", name="Measurements used / excluded"
                    ),
                    rrb.TimeSeriesView(origin="metrics/fusion", name="Fusion counters"),
                ),
            ),
            column_shares=[0.96, 1.04],
        ),
        rrb.TimePanel(timeline=TIMELINE, play_state="following", state="collapsed"),
        collapse_panels=True,
    )
