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

Bounded input: a scenario file is at most :data:`MAX_SCENARIO_BYTES` (512 KiB; the shipped ones
are a few kB) and nests arrays, inline tables and dotted keys at most :data:`MAX_NESTING`
(32) deep. Both are checked before the TOML parser runs (a TOML nested 100,000 deep used to
end in a ``RecursionError`` traceback, a dotted key 100,000 parts long took 75 s), so a
hostile file is refused in well under a second with a message that names the limit; the
counts (anchors, nodes, ...) are :mod:`diffpos.scenario`'s limits.
"""

from __future__ import annotations

import logging
import os
import re
import tomllib
from pathlib import Path

from diffpos.scenario import Scenario, ScenarioError, default_scenario
from diffpos_services.errors import ConfigError
from diffpos_services.resources import scenario_dir

__all__ = [
    "MAX_NESTING",
    "MAX_SCENARIO_BYTES",
    "SCENARIO_DIR",
    "check_toml_shape",
    "load_scenario",
    "load_scenario_option",
    "resolve_scenario",
    "scenario_from_toml",
    "scenario_or_default",
]

#: The shipped ``scenarios/`` (packaged copy in a wheel, the repository's in a checkout).
SCENARIO_DIR = scenario_dir()


_LOG = logging.getLogger("diffpos.scenario")

#: Largest accepted scenario file [bytes] (tomllib reads ~1 MB/s on a loaded 2-core machine).
MAX_SCENARIO_BYTES = 512 * 1024
#: Deepest accepted nesting of arrays and inline tables, and most parts of a dotted key.
MAX_NESTING = 32

# strings and comments, whose brackets and dots are text (multi-line forms first)
_TEXT_RE = re.compile(
    r'"""(?:[^"\\]|\\.|"(?!""))*"""'
    r"|'{3}[\s\S]*?'{3}"
    r'|"(?:[^"\\\n]|\\.)*"'
    r"|'[^'\n]*'"
    r"|#[^\n]*"
)
_BRACKET_RE = re.compile(r"[\[\]{}]")
_SEGMENT_RE = re.compile(r"[^\[\]{}=,\n]+")


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
        with open(p, "rb") as f:
            text = f.read(MAX_SCENARIO_BYTES + 1).decode("utf-8")
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
    check_toml_shape(data, source=source)
    try:
        doc = tomllib.loads(data)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{source}: TOML syntax error: {exc}") from None
    except RecursionError:  # not reached after the shape check; never a traceback
        raise ScenarioError(f"{source}: nested too deeply for the TOML parser") from None
    try:
        scenario = Scenario.from_dict(doc)
    except ScenarioError as exc:
        raise ScenarioError(f"{source}: {exc}") from None
    for warning in scenario.warnings:  # valid, but useless for fixing (the core prints nothing)
        _LOG.warning("%s: %s", source, warning)
    return scenario


def check_toml_shape(text: str, *, source: str) -> None:
    """Refuse TOML text larger than :data:`MAX_SCENARIO_BYTES` or nested deeper than
    :data:`MAX_NESTING` (brackets and braces outside strings and comments; parts of a dotted
    key) before it is parsed: linear passes over the text.

    Raises
    ------
    ScenarioError
        ``"<source>: ..."`` naming the limit and, for nesting, the line.
    """
    if len(text) > MAX_SCENARIO_BYTES or len(text.encode("utf-8")) > MAX_SCENARIO_BYTES:
        raise ScenarioError(f"{source}: larger than {MAX_SCENARIO_BYTES:,} bytes "
                            "(scenario_io.MAX_SCENARIO_BYTES): not a scenario file")
    code = _TEXT_RE.sub(lambda m: "\n" * m.group().count("\n") + '""', text)
    depth = 0
    for m in _BRACKET_RE.finditer(code):
        depth += 1 if m.group() in "[{" else -1
        if depth > MAX_NESTING:
            raise ScenarioError(f"{source}: line {code.count(chr(10), 0, m.start()) + 1}: "
                                f"arrays or inline tables nested more than {MAX_NESTING} deep "
                                "(scenario_io.MAX_NESTING)")
    for m in _SEGMENT_RE.finditer(code):
        if m.group().count(".") >= MAX_NESTING:
            raise ScenarioError(f"{source}: line {code.count(chr(10), 0, m.start()) + 1}: a "
                                f"dotted key of more than {MAX_NESTING} parts "
                                "(scenario_io.MAX_NESTING)")


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
