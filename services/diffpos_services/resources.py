"""Where the shipped schemas/ and scenarios/ are, installed or in a checkout.

A wheel carries copies under ``diffpos_services/_data`` (setup.py's build hook); an editable
install or a plain checkout reads the repository's top-level folders.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["data_dir", "scenario_dir", "schema_dir"]

_PACKAGE = Path(__file__).resolve().parent


def data_dir(name: str) -> Path:
    """The folder ``name`` (``schemas`` or ``scenarios``): packaged copy first, else the checkout's."""
    packaged = _PACKAGE / "_data" / name
    if packaged.is_dir():
        return packaged
    return _PACKAGE.parents[1] / name


def schema_dir() -> Path:
    """The JSON Schemas of the wire messages (one file per message and version)."""
    return data_dir("schemas")


def scenario_dir() -> Path:
    """The shipped TOML scenarios (``paper``, ``large``, ...)."""
    return data_dir("scenarios")
