"""Reading scenario files (TOML) into :class:`diffpos.scenario.Scenario`.

The core (:mod:`diffpos.scenario`) validates plain dicts and never touches files; this module
does the I/O and turns every failure (missing file, TOML syntax error, invalid field) into a
:class:`diffpos.scenario.ScenarioError` whose message starts with the file name, so a CLI can
print it as one line.
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

from diffpos.scenario import Scenario, ScenarioError, default_scenario
from diffpos_services.resources import scenario_dir

__all__ = ["SCENARIO_DIR", "load_scenario", "resolve_scenario"]

#: The shipped ``scenarios/`` (packaged copy in a wheel, the repository's in a checkout).
SCENARIO_DIR = scenario_dir()


def load_scenario(path: str | os.PathLike[str]) -> Scenario:
    """Read and validate a scenario TOML file.

    Parameters
    ----------
    path : path-like
        A ``.toml`` file; a bare name such as ``"paper"`` or ``"large"`` is looked up in
        :data:`SCENARIO_DIR` if no such file exists.

    Returns
    -------
    Scenario

    Raises
    ------
    ScenarioError
        ``"<file>: ..."`` for a missing/unreadable file, a TOML syntax error (with line and
        column) or an invalid field (with its path, e.g. ``anchors[1].position_m``).
    """
    p = resolve_scenario(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise ScenarioError(f"{p}: no such scenario file (shipped: "
                            f"{', '.join(sorted(x.stem for x in SCENARIO_DIR.glob('*.toml')))})"
                            ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"{p}: cannot read the file ({exc})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{p}: TOML syntax error: {exc}") from None
    try:
        return Scenario.from_dict(data)
    except ScenarioError as exc:
        raise ScenarioError(f"{p}: {exc}") from None


def resolve_scenario(path: str | os.PathLike[str]) -> Path:
    """The file a scenario argument refers to (a path, or a shipped scenario's name)."""
    p = Path(path)
    if not p.exists() and p.suffix == "" and (SCENARIO_DIR / f"{p.name}.toml").exists():
        return SCENARIO_DIR / f"{p.name}.toml"
    return p


def scenario_or_default(path: str | os.PathLike[str] | None) -> Scenario:
    """:func:`load_scenario` of ``path``, or the paper's scenario when ``path`` is None."""
    return default_scenario() if path is None else load_scenario(path)
