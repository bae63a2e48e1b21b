"""Every status the fusion publishes has its own marker colour, and the legend names it.

References, independent of the dashboard: the fusion's status enums themselves
(``diffpos.estimators.result.FixStatus`` without tracking, ``diffpos.tracking.state.TrackStatus``
with it; ``fusion/estimates_v1.py`` and ``fusion/tracked.py`` publish their ``.name``); the
colours are read back from a written .rrd with Rerun's own reader, not from the colour table.
Before this test the dashboard had no colour for ``TRACKING`` and ``INITIALISING``: both fell
back to the grey of a stale marker, and so did ``COASTING``, ``LOST``, ``UNINITIALISED``,
``TOO_FEW_ANCHORS`` and ``INVALID_INPUT``."""

from __future__ import annotations

import numpy as np
from diffpos_services.dashboard.columns import EstimateColumns
from diffpos_services.dashboard.convert import rrd_rows
from diffpos_services.dashboard.stream import write_rrd

from diffpos.estimators.result import FixStatus
from diffpos.tracking.state import TrackStatus

PUBLISHED = [s.name for s in TrackStatus] + [s.name for s in FixStatus]
T0 = 1_800_000_000_000_000_000
#: the marker colour of a fix whose status the dashboard does not know (the old fallback)
GREY = (150, 150, 150, 255)


def _rgba(packed: int) -> tuple[int, int, int, int]:
    return tuple(int(packed).to_bytes(4, "big"))  # Rerun packs 0xRRGGBBAA


def _one_fix_per_status(path):
    """One responder per published status, each with one sure fix (floor probability 1)."""
    n = len(PUBLISHED)
    est = EstimateColumns(
        t_ns=np.full(n, T0), node_id=[f"n{i:02d}" for i in range(n)], status=PUBLISHED,
        position_m=np.column_stack([np.arange(n, dtype=float), np.full(n, 3.0),
                                    np.full(n, 5.5)]),
        covariance_m2=np.tile(np.eye(3) * 0.01, (n, 1, 1)), peb_m=np.full(n, 0.2),
        floor_index=np.zeros(n, np.int64), floor_probability=np.ones(n))
    write_rrd(path, estimates=est)
    return rrd_rows(path)


def test_every_published_status_has_a_distinct_marker_colour(tmp_path):
    rows = _one_fix_per_status(tmp_path / "s.rrd")
    color = {}
    for i, status in enumerate(PUBLISHED):
        marker = [r for _, r in rows[f"/world/nodes/n{i:02d}/estimate"]
                  if r.get("Points3D:colors")]
        color[status] = _rgba(marker[-1]["Points3D:colors"][0])
    assert len(set(color.values())) == len(PUBLISHED), color
    assert GREY not in color.values()
    # the ones the default fusion (mnls + tracking) publishes, by name
    assert color["TRACKING"] != color["INITIALISING"]


def test_the_legend_names_every_published_status_in_its_marker_colour(tmp_path):
    rows = _one_fix_per_status(tmp_path / "s.rrd")
    (_, text), = rows["/legend/text"]
    (_, swatch), = rows["/legend/swatches"]
    legend = {t.split()[0]: _rgba(c) for t, c in zip(text["Points2D:labels"],
                                                     swatch["Points2D:colors"], strict=False)}
    for i, status in enumerate(PUBLISHED):
        marker = [r for _, r in rows[f"/world/nodes/n{i:02d}/estimate"]
                  if r.get("Points3D:colors")][-1]
        assert legend[status] == _rgba(marker["Points3D:colors"][0]), status
