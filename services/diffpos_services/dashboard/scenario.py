"""The building of a scenario as the dashboard draws it (:class:`BuildingOutline`, with the
window edge the fusion models): from a file, a shipped name, the default scenario, a
command-line option, or the scenario attached to a recording.

Files are read by :mod:`diffpos_services.scenario_io` (the one scenario loader); the edge is
the fusion's ``--edge auto`` rule, :func:`diffpos.scenario.first_arrival_edge`.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from diffpos.scenario import Scenario, first_arrival_edge
from diffpos_services.dashboard.building import BuildingOutline
from diffpos_services.errors import ConfigError
from diffpos_services.scenario_io import scenario_or_default

__all__ = [
    "building_for_option",
    "building_from_attachments",
    "building_from_scenario_file",
    "building_of_scenario",
]


def building_of_scenario(scenario: Scenario) -> BuildingOutline:
    """The outline of ``scenario``'s building, drawn with the window edge the fusion models
    for it by default (``--edge auto``: :func:`diffpos.scenario.first_arrival_edge`)."""
    edge, _why = first_arrival_edge(scenario)
    return dataclasses.replace(BuildingOutline.from_object(scenario.building), edge=edge)


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
