"""Identifier checks after the decode (wire/ids.py) against the checked-in JSON Schemas.

The ``Id`` pattern is no longer a msgspec constraint (the regex per id made decoding a
200-node RangeBatch ~3x slower); :func:`M.decoder` checks the ids against the set of ids
already found valid. Reference: ``jsonschema`` with the schema files (the published contract,
with the pattern), on candidate ids in every id position of every message type that has one,
including ids nested in lists of structs; the decoder must accept exactly what the schema
accepts, reject the rest with reason ``schema`` and the JSON path, and stay right once its set
of known ids is full."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import msgspec
import pytest
from diffpos_services.wire import ids as wire_ids
from diffpos_services.wire import messages as M
from diffpos_services.wire.ids import ID_PATTERN
from test_wire_contract import _examples

SCHEMA_DIR = Path(__file__).resolve().parents[2] / "schemas"

CANDIDATES = ["a", "uav_1", "node-7", "_x", "N" * 64, "N" * 65, "-lead", "", "a/b", "a b",
              "a\n", "\na", "é", "a.b", "a*", "x" * 63 + "\n", "0", "a_b-c-9"]


_ID_KEYS = ("anchor_id", "node_id", "id")
_ID_LIST_KEYS = ("node_ids", "used_anchors", "live_anchors")


def _id_positions(doc, path=()) -> list[tuple]:
    """Paths (keys/indices) of every id in a message document, at any depth."""
    out = []
    if isinstance(doc, dict):
        for key, value in doc.items():
            if key in _ID_KEYS and isinstance(value, str):
                out.append((*path, key))
            elif key in _ID_LIST_KEYS:
                out += [(*path, key, i) for i in range(len(value))]
            else:
                out += _id_positions(value, (*path, key))
    elif isinstance(doc, list):
        for i, value in enumerate(doc):
            out += _id_positions(value, (*path, i))
    return out


def _set(doc, path, value):
    for p in path[:-1]:
        doc = doc[p]
    doc[path[-1]] = value


def _schema_path(path) -> str:
    return "$" + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path)


def test_the_decoder_accepts_exactly_what_the_schema_accepts():
    checked = 0
    for kind, examples in _examples().items():
        validator = jsonschema.Draft202012Validator(
            json.loads((SCHEMA_DIR / M.schema_filename(kind)).read_text()))
        dec = M.decoder(kind)
        positions = [p for ex in examples for p in _id_positions(json.loads(M.encode(ex)))]
        if kind in (M.RunControl, M.RunClock):
            assert not positions
            continue
        assert positions, kind
        raws = {p: M.encode(ex) for ex in examples for p in _id_positions(json.loads(M.encode(ex)))}
        for path in positions:
            for cand in CANDIDATES:
                doc = json.loads(raws[path])
                _set(doc, path, cand)
                ok = validator.is_valid(doc)
                try:
                    dec(json.dumps(doc).encode())
                    accepted = True
                except M.DecodeError as exc:
                    accepted = False
                    assert exc.reason == "schema" and exc.field == _schema_path(path), exc
                assert accepted == ok, (kind.__name__, path, cand)
                checked += 1
    assert checked > 150


def _schema_id_fields(obj, name=None) -> set[str]:
    """Property names whose value (or its items, or a member of anyOf) has the id pattern."""
    out = set()
    if isinstance(obj, dict):
        if obj.get("pattern") == ID_PATTERN and name is not None:
            out.add(name)
        for key, value in obj.items():
            if key == "properties":
                for prop, sub in value.items():
                    out |= _schema_id_fields(sub, prop)
            elif key == "$defs":
                for sub in value.values():
                    out |= _schema_id_fields(sub)
            elif key in ("items", "anyOf", "oneOf"):
                out |= _schema_id_fields(value, name)
    elif isinstance(obj, list):
        for value in obj:
            out |= _schema_id_fields(value, name)
    return out


def _plan_id_fields(step) -> set[str]:
    kind, sub = step
    if kind == "each":
        return _plan_id_fields(sub)
    out = set()
    if kind == "struct":
        for _, json_name, s in sub:
            out |= {json_name} if s[0] != "struct" and _leaf_is_id(s) else set()
            out |= _plan_id_fields(s) if s[0] != "id" else set()
    return out


def _leaf_is_id(step) -> bool:
    return step[0] == "id" or (step[0] == "each" and _leaf_is_id(step[1]))


def test_checker_finds_every_id_field_the_schemas_constrain():
    """Each message type: the decoder's plan checks exactly the fields that the schema gives
    the id pattern (so no id field escapes the check and nothing else is checked)."""
    for kind in M.MESSAGE_TYPES:
        schema = json.loads((SCHEMA_DIR / M.schema_filename(kind)).read_text())
        expected = _schema_id_fields(schema)
        step = wire_ids._step(msgspec.inspect.type_info(kind))
        assert (set() if step is None else _plan_id_fields(step)) == expected, kind.__name__


def test_a_full_set_of_known_ids_still_checks(monkeypatch):
    monkeypatch.setattr(wire_ids, "_known", set())
    monkeypatch.setattr(wire_ids, "MAX_KNOWN_IDS", 3)
    dec = M.decoder(M.RangeBatch)  # a new closure; ids.py's set read at call time
    raw = json.loads(M.encode(_examples()[M.RangeBatch][0]))
    for k in range(6):
        doc = dict(raw, node_ids=[f"n{k}_{j}" for j in range(3)])
        assert dec(json.dumps(doc).encode()).node_ids == doc["node_ids"]
        bad = dict(raw, node_ids=[f"n{k}", "a/b", f"m{k}"])
        with pytest.raises(M.DecodeError) as info:
            dec(json.dumps(bad).encode())
        assert info.value.field == "$.node_ids[1]"
    assert len(wire_ids._known) <= 3
