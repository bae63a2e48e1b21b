"""The building of a scenario as the dashboard draws it (:class:`BuildingOutline`, with the
window edge the fusion models): from a file, a shipped name, the default scenario, a
command-line option, or the scenario attached to a recording.

Files are read by :mod:`diffpos_services.scenario_io` (the one scenario loader); the edge is
the fusion's ``--edge auto`` rule, :func:`diffpos.scenario.first_arrival_edge`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from diffpos.emulation import emulation_nodes
from diffpos.scenario import Scenario, first_arrival_edge
from diffpos_services.dashboard.building import BuildingOutline
from diffpos_services.errors import ConfigError
from diffpos_services.scenario_io import scenario_or_default

__all__ = [
    "building_for_option",
    "building_from_attachments",
    "building_from_scenario_file",
    "building_of_scenario",
    "stairs_of_scenario",
]


def building_of_scenario(scenario: Scenario) -> BuildingOutline:
    """The outline of ``scenario``'s building, drawn with the window edge the fusion models
    for it by default (``--edge auto``: :func:`diffpos.scenario.first_arrival_edge`)."""
    edge, _why = first_arrival_edge(scenario)
    return dataclasses.replace(BuildingOutline.from_object(scenario.building), edge=edge,
                               stairs=stairs_of_scenario(scenario))


#: a leg of a trajectory that changes floor is a flight of stairs when it rises at least this
#: much per metre walked (stairs rise 0.5-0.8 m/m; a loop closing across a floor far less)
STAIR_MIN_SLOPE = 0.3
#: a flight of stairs is drawn at least this wide [m]
STAIR_WIDTH_M = 1.2
#: stairs are looked for over this much of every responder's trajectory [s] (sampled at 4 Hz)
STAIRS_HORIZON_S = 600.0


def stairs_of_scenario(scenario: Scenario) -> tuple[tuple[float, float, float, float, int, int],
                                                    ...]:
    """Stair footprints ``(x0, x1, y0, y1, floor_lo, floor_hi)`` [m] of a scenario: the
    scenario has no stairs of its own, so they are where its responders (``diffpos emulate``'s
    nodes, :func:`diffpos.emulation.emulation_nodes`) change floor within the first
    :data:`STAIRS_HORIZON_S` (of waypoints, the legs between the points given, not the
    closing leg of a loop): every stretch of a trajectory more than 5 cm off the walking
    height of its floor that rises at least :data:`STAIR_MIN_SLOPE` per metre, as a box at
    least :data:`STAIR_WIDTH_M` wide; boxes of the same floors that overlap are merged."""
    b = scenario.building
    t = np.arange(0.0, STAIRS_HORIZON_S, 0.25)
    level0 = b.first_floor_z_m + b.nominal_node_height_m
    boxes: list[list[float]] = []
    for _nid, traj in emulation_nodes(scenario):
        knots = getattr(traj, "times", None)  # waypoints: the legs drawn, not the loop's return
        p = np.asarray(traj.position_m(t if knots is None else t[t <= knots[-1]]), float)
        off = np.abs((p[:, 2] - level0) / b.floor_height_m
                     - np.round((p[:, 2] - level0) / b.floor_height_m)) * b.floor_height_m
        on = off > 0.05
        edges = np.flatnonzero(np.diff(np.r_[0, on.astype(np.int8), 0]))
        for a, e in zip(edges[::2], edges[1::2], strict=True):
            seg = p[max(a - 1, 0):min(e + 1, len(p))]  # with the level samples either side
            f = b.floor_index(seg[:, 2])
            run = float(np.sum(np.linalg.norm(np.diff(seg[:, :2], axis=0), axis=1)))
            rise = float(np.ptp(seg[:, 2]))
            if f.min() == f.max() or rise < STAIR_MIN_SLOPE * run:
                continue  # not a flight of stairs (a loop closing across the building)
            lo, hi = seg[:, :2].min(axis=0), seg[:, :2].max(axis=0)
            pad = np.maximum(STAIR_WIDTH_M - (hi - lo), 0.0) / 2
            boxes.append([lo[0] - pad[0], hi[0] + pad[0], lo[1] - pad[1], hi[1] + pad[1],
                          int(f.min()), int(f.max())])
    return tuple((round(float(x0), 2), round(float(x1), 2), round(float(y0), 2),
                  round(float(y1), 2), int(lo), int(hi))
                 for x0, x1, y0, y1, lo, hi in _merge_boxes(boxes))


def _merge_boxes(boxes: list[list[float]]) -> list[list[float]]:
    """Boxes of the same floors that overlap (or touch within 0.5 m) merged into one."""
    out: list[list[float]] = []
    for bx in sorted(boxes):
        for o in out:
            if o[4:] == bx[4:] and bx[0] <= o[1] + 0.5 and o[0] <= bx[1] + 0.5 \
                    and bx[2] <= o[3] + 0.5 and o[2] <= bx[3] + 0.5:
                o[:4] = [min(o[0], bx[0]), max(o[1], bx[1]), min(o[2], bx[2]), max(o[3], bx[3])]
                break
        else:
            out.append(list(bx))
    return [o for o in out if math.isfinite(sum(o[:4]))]


def building_from_scenario_file(path: str | Path) -> BuildingOutline:
    """The building of a scenario: a TOML file, a shipped name (``paper``, ``large``) or
    ``default`` (the built-in scenario ``diffpos emulate`` runs without a file).

    Raises
    ------
    ValueError
        (``ScenarioError``) naming the file and the problem.
    """
    return building_of_scenario(scenario_or_default(None if str(path) == "default" else path))


def building_for_option(value: str | None, *, option: str = "--scenario") -> BuildingOutline | None:
    """:func:`building_from_scenario_file` for a command-line option (``None`` if not given).

    Raises
    ------
    ConfigError
        Worded for the option: ``--scenario X: cannot read it (...)`` or the scenario error.
    """
    if not value:
        return None
    try:
        return building_from_scenario_file(value)
    except OSError as exc:
        raise ConfigError(f"{option} {value}: cannot read it ({exc.strerror})") from None
    except ValueError as exc:
        raise ConfigError(f"{option} {value}: {exc}") from None


def building_from_attachments(attachments: Sequence[Any]) -> BuildingOutline | None:
    """The building of a recording: the first scenario TOML attached to it, else the
    building of the fusion settings of its run configuration (``run_config.json``, which
    ``diffpos emulate`` attaches to every recording, the default scenario included:
    ``fusion.building`` with the edge the run modelled, ``emulate.edge``); ``None`` if
    neither."""
    for att in attachments:
        if str(att.name).endswith(".toml") or "toml" in str(att.media_type):
            try:
                scen = Scenario.from_dict(tomllib.loads(bytes(att.data).decode()))
            except Exception:  # not a scenario: ignore
                continue
            return building_of_scenario(scen)
    for att in attachments:
        if str(att.name).endswith(".json") or "json" in str(att.media_type):
            outline = _building_of_run_config(bytes(att.data))
            if outline is not None:
                return outline
    return None


def _building_of_run_config(data: bytes) -> BuildingOutline | None:
    """The building of a run configuration's fusion settings (``None``: not one)."""
    try:
        doc = json.loads(data)
        table = doc["fusion"]["building"]
        outline = BuildingOutline.from_object(table)
    except (ValueError, KeyError, TypeError):
        return None
    edge = (doc.get("emulate") or {}).get("edge")
    return dataclasses.replace(outline, edge=edge) if edge in ("upper", "lower") else outline
