"""Typed configuration from plain options: :func:`build_config`, :func:`load_json_option`.

:func:`build_config` turns plain options into a typed, validated ``msgspec.Struct`` and raises
:class:`~diffpos_services.errors.ConfigError` naming the bad field (the CLI prints it, no
traceback).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any, TypeVar

import msgspec

from diffpos_services.errors import ConfigError

__all__ = ["build_config", "load_json_option"]

T = TypeVar("T")


def build_config(kind: type[T], values: Mapping[str, Any]) -> T:
    """Validate ``values`` into the typed config struct ``kind``.

    Raises
    ------
    ConfigError
        With msgspec's path to the offending field, e.g.
        ``invalid fusion config: Expected `float` >= 0.0 - at `$.deadline_s```.
    """
    try:
        cfg = msgspec.convert(dict(values), type=kind, strict=False)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"invalid {kind.__name__}: {exc}") from None
    check = getattr(cfg, "check", None)
    if check is not None:
        try:
            check()
        except ValueError as exc:
            raise ConfigError(f"invalid {kind.__name__}: {exc}") from None
    return cfg


def load_json_option(option: str, path: str) -> Any:
    """The JSON document in the file ``path`` given to the command-line ``option``.

    Raises
    ------
    ConfigError
        Naming the option and the file, e.g. ``--config run.json: cannot read it (No such
        file or directory)`` or ``... not valid JSON (...)``.
    """
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except OSError as exc:
        raise ConfigError(f"{option} {path}: cannot read it ({exc.strerror})") from None
    except ValueError as exc:
        raise ConfigError(f"{option} {path}: not valid JSON ({exc})") from None
