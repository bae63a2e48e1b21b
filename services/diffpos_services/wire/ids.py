"""Identifier checks of decoded messages (the ``Id`` fields of :mod:`~diffpos_services.wire.messages`).

An ``Id`` carries its pattern (:data:`ID_PATTERN`) in the JSON
Schema only, so msgspec does not run the regex on every id of every message; the decoders of
:func:`~diffpos_services.wire.messages.decoder` call :func:`id_checker`'s function after the
decode instead. It compares a message's ids with the set of ids already found valid (a few C
set operations per message: a 200-node RangeBatch no longer pays 200 regex matches) and runs
the regex only on an id it has not seen. The set is bounded (:data:`MAX_KNOWN_IDS`; past it an
unknown id is matched every time), so a flood of distinct ids costs time, never memory.

A message with an invalid id is rejected as before: :class:`ValueError` with msgspec's message
for a pattern mismatch, naming the JSON path of the first invalid id. One difference: msgspec
reported the first error in the order of the JSON text, so a message with a bad id AND another
bad field now names the other field (both are reason ``schema``).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from operator import attrgetter
from typing import Any

import msgspec
from msgspec import inspect as mi

__all__ = ["ID_PATTERN", "MAX_KNOWN_IDS", "id_checker", "valid_id"]

#: What an identifier is on the wire ("(?!\n)": Python's "$", as msgspec's and jsonschema's,
#: also matches before a final newline).
ID_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_\-]{0,63}$(?!\n)"

#: At most this many distinct valid ids are remembered (a fusion sees a few hundred).
MAX_KNOWN_IDS = 1 << 16
_ID_SEARCH = re.compile(ID_PATTERN).search  # msgspec's constraint uses re.search
_known: set[str] = set()
_MISMATCH = f"Expected `str` matching regex {ID_PATTERN!r} - at "  # + the JSON path

# a plan step: ("id", None) | ("each", step) | ("struct", ((name, json_name, step), ...))
_Step = tuple[str, Any]


def valid_id(value: Any) -> bool:
    """Whether ``value`` is an identifier (a ``str`` matching :data:`ID_PATTERN`)."""
    if value in _known:
        return True
    if type(value) is not str or _ID_SEARCH(value) is None:
        return False
    if len(_known) < MAX_KNOWN_IDS:
        _known.add(value)
    return True


def _is_id(t: Any) -> bool:
    return (isinstance(t, mi.Metadata) and isinstance(t.type, mi.StrType)
            and (t.extra_json_schema or {}).get("pattern") == ID_PATTERN)


def _step(t: Any) -> _Step | None:
    """How to reach the ids inside a value of msgspec type ``t`` (None: it holds none)."""
    if _is_id(t):
        return ("id", None)
    if isinstance(t, mi.Metadata):
        return _step(t.type)
    if isinstance(t, mi.UnionType):  # T | None: a None value holds no id
        steps = [s for s in map(_step, t.types) if s is not None]
        if len(steps) > 1:
            raise TypeError(f"ids in a union of several types are not supported: {t}")
        return steps[0] if steps else None
    if isinstance(t, mi.ListType | mi.VarTupleType | mi.SetType | mi.FrozenSetType):
        sub = _step(t.item_type)
        return None if sub is None else ("each", sub)
    if isinstance(t, mi.StructType):
        plan = tuple((f.name, f.encode_name, s) for f in t.fields
                     if (s := _step(f.type)) is not None)
        return ("struct", plan) if plan else None
    if isinstance(t, mi.DictType | mi.TupleType):
        inner = ([t.key_type, t.value_type] if isinstance(t, mi.DictType) else list(t.item_types))
        if any(_step(x) is not None for x in inner):
            raise TypeError(f"ids in a {type(t).__name__} are not supported: {t}")
    return None


def _first_bad(value: Any, step: _Step, path: str) -> str | None:
    """The JSON path of the first invalid id in ``value`` (None: all valid)."""
    kind, sub = step
    if value is None:
        return None
    if kind == "id":
        return None if valid_id(value) else path
    if kind == "each":
        for i, item in enumerate(value):
            bad = _first_bad(item, sub, f"{path}[{i}]")
            if bad is not None:
                return bad
        return None
    for name, json_name, s in sub:
        bad = _first_bad(getattr(value, name), s, f"{path}.{json_name}")
        if bad is not None:
            return bad
    return None


def _all_known(step: _Step, known: set[str]) -> Callable[[Any], bool]:
    """A function ``value -> bool``: True if every id in ``value`` is in ``known`` (ids that
    are None count as known: they hold no id). False sends the message to :func:`_first_bad`,
    which decides; so this is only ever a fast yes, built once per message type from its plan
    (a set comparison per field or per list, no path strings)."""
    kind, sub = step
    if kind == "id":
        return lambda v: v is None or v in known
    if kind == "each" and sub == ("id", None):
        return lambda v: v is None or known.issuperset(v)
    if kind == "each" and sub[0] == "struct" and len(sub[1]) == 1 and sub[1][0][2] == ("id", None):
        get_one = attrgetter(sub[1][0][0])  # a list of structs with one id field (links)
        return lambda v: v is None or known.issuperset(map(get_one, v))
    if kind == "each":
        item = _all_known(sub, known)
        return lambda v: v is None or all(map(item, v))
    fields = tuple((attrgetter(name), _all_known(s, known)) for name, _, s in sub)
    return lambda v: v is None or all(f(get(v)) for get, f in fields)


def id_checker(kind: type[msgspec.Struct]) -> Callable[[Any], None] | None:
    """A function ``message -> None`` raising :class:`ValueError` (msgspec's wording, with the
    JSON path) if a decoded ``kind`` holds an invalid id; None if ``kind`` has no ``Id``.

    The common case costs one set comparison per id field or list of ids (ids inside a list
    of structs included) against the known valid ids; anything else (an unseen id, an
    invalid one) takes the full walk, which also learns the new valid ids.
    """
    step = _step(mi.type_info(kind))
    if step is None:
        return None
    plan = step[1]
    scalars = tuple(name for name, _, s in plan if s == ("id", None))
    lists = tuple(name for name, _, s in plan if s == ("each", ("id", None)))
    nested = len(scalars) + len(lists) < len(plan)
    get_scalars = attrgetter(*scalars) if len(scalars) > 1 else None
    one = scalars[0] if len(scalars) == 1 else None
    known = _known
    all_known = _all_known(step, known) if nested else None

    def check(msg: Any) -> None:
        if all_known is not None:
            if all_known(msg):
                return
        else:
            if one is not None:
                fast = getattr(msg, one) in known
            else:
                fast = get_scalars is None or known.issuperset(get_scalars(msg))
            for name in lists:
                fast = fast and known.issuperset(getattr(msg, name))
            if fast:
                return
        bad = _first_bad(msg, step, "$")
        if bad is not None:
            raise ValueError(f"{_MISMATCH}`{bad}`")

    return check
