"""Reading scenario files (TOML) into :class:`diffpos.scenario.Scenario`: the ONE loader.

The core (:mod:`diffpos.scenario`) validates plain dicts and never touches files; this module
does the I/O and turns every failure (missing file, TOML syntax error, invalid field) into a
:class:`diffpos.scenario.ScenarioError` whose message starts with the file name, so a CLI can
print it as one line.

- :func:`load_scenario`: a file, or a shipped scenario's name (``paper``, ``large``);
- :func:`resolve_scenario`: the file such an argument refers to;
- :func:`scenario_or_default`: :func:`load_scenario`, or the built-in paper scenario for None;
- :func:`load_scenario_option`: the same for a command-line option, failures as
  :class:`~diffpos_services.errors.ConfigError` (exit code 2) saying what to fix;
- :func:`scenario_from_toml`: TOML text from elsewhere (a recording's attachment).
"""

from __future__ import annotations

import logging
import os
import tomllib
from pathlib import Path

from diffpos.scenario import Scenario, ScenarioError, default_scenario
from diffpos_services.errors import ConfigError
from diffpos_services.resources import scenario_dir

__all__ = [
    "SCENARIO_DIR",
    "load_scenario",
    "load_scenario_option",
    "resolve_scenario",
    "scenario_from_toml",
    "scenario_or_default",
]

#: The shipped ``scenarios/`` (packaged copy in a wheel, the repository's in a checkout).
SCENARIO_DIR = scenario_dir()


_LOG = logging.getLogger("diffpos.scenario")


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
    return scenario_from_toml(text, source=str(p))


def scenario_from_toml(data: str | bytes, *, source: str) -> Scenario:
    """The scenario of TOML text, e.g. a scenario file attached to a recording.

    Raises
    ------
    ScenarioError
        ``"<source>: ..."`` for bytes that are not UTF-8, a TOML syntax error or an invalid
        field.

    Every validation warning of the scenario (e.g. fewer than 3 anchors: no fix is ever
    possible) is logged as a WARNING of the ``diffpos.scenario`` logger, naming ``source``.
    """
    if isinstance(data, bytes | bytearray | memoryview):
        try:
            data = bytes(data).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ScenarioError(f"{source}: not UTF-8 text ({exc})") from None
    try:
        doc = tomllib.loads(data)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{source}: TOML syntax error: {exc}") from None
    try:
        scenario = Scenario.from_dict(doc)
    except ScenarioError as exc:
        raise ScenarioError(f"{source}: {exc}") from None
    for warning in scenario.warnings:  # valid, but useless for fixing (the core prints nothing)
        _LOG.warning("%s: %s", source, warning)
    return scenario


def resolve_scenario(path: str | os.PathLike[str]) -> Path:
    """The file a scenario argument refers to (a path, or a shipped scenario's name)."""
    p = Path(path)
    if not p.exists() and p.suffix == "" and (SCENARIO_DIR / f"{p.name}.toml").exists():
        return SCENARIO_DIR / f"{p.name}.toml"
    return p


def scenario_or_default(path: str | os.PathLike[str] | None) -> Scenario:
    """:func:`load_scenario` of ``path``, or the paper's scenario when ``path`` is None."""
    return default_scenario() if path is None else load_scenario(path)


def load_scenario_option(path: str | os.PathLike[str] | None, *,
                         option: str = "--scenario") -> Scenario:
    """The scenario a command-line option names (``None``: the built-in paper scenario):
    the one loader of every service's ``--scenario`` (anchor, fusion, emulate).

    Raises
    ------
    ConfigError
        One line: the option, the file, what is wrong (missing file with the shipped names,
        TOML syntax with line and column, the invalid field) and what to do about it.
    """
    try:
        return scenario_or_default(path)
    except ScenarioError as exc:
        msg = str(exc)
        where = f"{option} {path}: " if str(path) not in msg else f"{option}: "
        raise ConfigError(f"{where}{msg} (fix the file, or give another scenario file or a "
                          "shipped name)") from None
