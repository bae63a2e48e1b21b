"""The path of the mechanism the fusion used for a link, as a drawable line strip.

Estimate v2 names, per anchor, the first-arrival mechanism its range was explained by (a
label of :data:`diffpos.paths.mechanisms.MECHANISMS`, e.g. ``Tx-D(lower)-R(ceiling)-Rx``). The
interaction points come from the same geometry functions the fusion's path model uses
(:func:`diffpos.paths.model.specular_path`, :func:`diffpos.paths.model.diffracted_path`) for the
estimated position on the estimated floor, so the drawn path is the one the fusion fitted.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from diffpos.paths.mechanisms import MECHANISMS
from diffpos.paths.model import FloorFrame, diffracted_path, specular_path
from diffpos.scenario import Building
from diffpos_services.dashboard.building import BuildingOutline, FloatArray

__all__ = ["MAX_VERTICES", "building_of_outline", "mechanism_strips", "recipe"]

#: vertices of the longest mechanism path (anchor, entry, two reflections, node; or anchor,
#: ground point, entry, one reflection, node)
MAX_VERTICES = 5


def recipe(label: str) -> tuple:
    """``("direct",)``, ``("spec", planes, ground)`` or ``("diff", edge, plane or None)`` of a
    mechanism label (``Tx-R(ground)-R(ceiling)-Rx`` -> ``("spec", ("ceiling",), True)``).

    Raises
    ------
    ValueError
        Not a label of :data:`diffpos.paths.mechanisms.MECHANISMS`.
    """
    if label not in MECHANISMS:
        raise ValueError(f"unknown mechanism {label!r}")
    steps = [(p[0], p[2:-1]) for p in label.split("-")[1:-1]]
    if not steps:
        return ("direct",)
    if steps[0][0] == "D":
        return ("diff", steps[0][1], steps[1][1] if len(steps) > 1 else None)
    return ("spec", tuple(n for _, n in steps if n != "ground"), steps[0][1] == "ground")


def building_of_outline(b: BuildingOutline) -> Building:
    """The path model's :class:`~diffpos.scenario.Building` of the dashboard's outline."""
    return Building(width_m=b.x_max_m - b.x_min_m, center_x_m=0.5 * (b.x_min_m + b.x_max_m),
                    depth_m=b.depth_m, n_floors=b.n_floors, floor_height_m=b.floor_height_m,
                    first_floor_z_m=b.first_floor_z_m, sill_height_m=b.sill_height_m,
                    window_height_m=b.window_height_m)


def _vertices(label: str, a: FloatArray, n: FloatArray, frame: FloorFrame) -> list[FloatArray]:
    rec = recipe(label)
    if rec[0] == "direct":
        return [a, n]
    if rec[0] == "spec":
        g = specular_path(a, n, frame, rec[1], ground=rec[2])
        return [a, *([g.ground_point] if rec[2] else []), *g.points]
    g = diffracted_path(a, n, frame, rec[1], rec[2])
    return [a, *g.points]


def mechanism_strips(anchor_m: FloatArray, node_m: FloatArray, floor_index: NDArray[np.int64],
                     labels: NDArray[np.str_], building: BuildingOutline) -> FloatArray:
    """Line strips anchor -> interaction points -> node of each link's mechanism.

    Parameters
    ----------
    anchor_m, node_m : ndarray, shape (L, 3) [m]
    floor_index : ndarray of int, shape (L,)
        The estimated floor (its window band, floor and ceiling).
    labels : ndarray of str, shape (L,)
        Mechanism labels; ``""`` (unknown) rows stay NaN.
    building : BuildingOutline

    Returns
    -------
    ndarray, shape (L, MAX_VERTICES, 3) [m]
        Shorter paths repeat their last vertex (the node); NaN rows: no path.
    """
    out = np.full((len(labels), MAX_VERTICES, 3), np.nan)
    b = building_of_outline(building)
    fl = np.where(floor_index >= 0, floor_index, building.floor_of(node_m[:, 2]))
    for label in np.unique(labels):
        if label not in MECHANISMS:
            continue
        rows = np.flatnonzero(labels == label)
        frame = FloorFrame.from_building(b, fl[rows])
        with np.errstate(invalid="ignore", divide="ignore"):
            verts = _vertices(str(label), anchor_m[rows], node_m[rows], frame)
        pts = np.stack(verts, axis=1)  # (R, V, 3)
        out[rows, : pts.shape[1]] = pts
        out[rows, pts.shape[1]:] = pts[:, -1:, :]
    return out
