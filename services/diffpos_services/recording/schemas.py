"""The JSON Schemas of recorded channels, by message kind.

* :class:`SchemaRegistry` - the JSON Schemas of ``schemas/*.json`` and which one belongs to a
  key expression (MCAP schema encoding ``jsonschema``, message encoding ``json``: Foxglove
  opens the files).
* :data:`LIVELINESS_SCHEMA` - the recorder's own liveliness-event channel.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.topics import parse_topic
from diffpos_services.resources import schema_dir
from diffpos_services.wire import messages

__all__ = [
    "DEFAULT_KIND_TO_STEMS",
    "LIVELINESS_SCHEMA",
    "MESSAGE_ENCODING",
    "SCHEMA_ENCODING",
    "SchemaEntry",
    "SchemaRegistry",
    "default_schema_dir",
]

SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"

#: JSON Schema of the recorder's own liveliness-event channel (anchors / nodes / services
#: joining and leaving). Kept here because the recorder is the only producer.
LIVELINESS_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "$id": "https://diffpos.invalid/schemas/liveliness_event.v1.json",
    "title": "diffpos.liveliness_event.v1",
    "description": "A liveliness token appeared (alive=true) or disappeared (alive=false), "
    "as seen by the recorder.",
    "type": "object",
    "properties": {
        "v": {"type": "integer", "const": 1, "description": "message version"},
        "key": {"type": "string", "description": "liveliness token key expression"},
        "alive": {"type": "boolean", "description": "true when the token appeared"},
        "t_ns": {"type": "integer", "description": "receive time [ns since Unix epoch]"},
        "role": {"type": "string", "description": "anchor, node, fusion, ... or unknown"},
        "id": {"type": "string", "description": "the entity id parsed from the key"},
    },
    "required": ["v", "key", "alive", "t_ns"],
    "additionalProperties": False,
}


@dataclass(frozen=True)
class SchemaEntry:
    """One JSON Schema as registered in MCAP.

    Attributes
    ----------
    name : str
        MCAP schema name (the schema's ``title``, else the file stem), e.g. ``diffpos.Range``.
    data : bytes
        The schema document (UTF-8 JSON).
    source : str
        File name it came from (``"builtin"`` for the recorder's own schemas).
    """

    name: str
    data: bytes
    source: str


#: message kind (see :func:`parse_topic`) -> candidate schema file stems (first found wins)
DEFAULT_KIND_TO_STEMS: dict[str, tuple[str, ...]] = {
    "anchor_state": ("anchor_state",),
    "range": ("range",),
    "estimate": ("estimate",),
    "diagnostics": ("fusion_diagnostics",),
    "truth_node": ("truth",),
    "truth_anchor": ("truth",),
    "run_control": ("run_control",),
    "run_clock": ("run_clock",),
    "range_batch": ("range_batch",),
    "replay_estimate": ("estimate",),
    "heartbeat": ("heartbeat",),
}


def _stem_base(path: Path) -> str:
    """``range.v1.json`` -> ``range``; ``AnchorState.v2.json`` -> ``anchorstate``."""
    stem = path.name[: -len(".json")] if path.name.endswith(".json") else path.name
    stem = re.sub(r"\.v\d+$", "", stem)
    return stem.lower().replace("-", "_")


def _stem_version(path: Path) -> int:
    m = re.search(r"\.v(\d+)\.json$", path.name)
    return int(m.group(1)) if m else 0


class SchemaRegistry:
    """JSON Schemas by message kind, loaded from a ``schemas/`` directory.

    Parameters
    ----------
    schema_dir : path or None
        Directory of ``*.json`` schema files (``<name>.v<N>.json``; the highest version of a
        name wins). ``None``: the repository's ``schemas/`` next to ``services/`` (or, when
        that does not exist, the same documents generated from the message structs).
    kind_to_stems : dict, optional
        Message kind -> candidate file stems; defaults to :data:`DEFAULT_KIND_TO_STEMS`.
    resolver : callable, optional
        ``resolver(key) -> kind | None`` overriding :func:`parse_topic` (e.g. the runtime's
        key module).
    """

    def __init__(
        self,
        schema_dir: str | os.PathLike[str] | None = None,
        *,
        kind_to_stems: dict[str, tuple[str, ...]] | None = None,
        resolver: Callable[[str], str | None] | None = None,
    ) -> None:
        self.schema_dir = Path(schema_dir) if schema_dir is not None else default_schema_dir()
        self._kind_to_stems = dict(kind_to_stems or DEFAULT_KIND_TO_STEMS)
        self._resolver = resolver
        self.by_stem: dict[str, SchemaEntry] = {}
        self.by_name: dict[str, SchemaEntry] = {}  # every version, by schema name
        self.documents: dict[str, dict[str, Any]] = {}
        versions: dict[str, int] = {}
        if self.schema_dir.is_dir():
            for path in sorted(self.schema_dir.glob("*.json")):
                try:
                    doc = json.loads(path.read_text(encoding="utf-8"))
                except (OSError, ValueError) as exc:
                    raise RecordingError(
                        f"schema file {path} is not valid JSON ({exc}); fix or remove it"
                    ) from exc
                base, ver = _stem_base(path), _stem_version(path)
                name = str(doc.get("title") or path.name[: -len(".json")])
                data = json.dumps(doc, separators=(",", ":"), sort_keys=True).encode()
                self.by_name[name] = SchemaEntry(name=name, data=data, source=path.name)
                self.documents[name] = doc
                if base in versions and versions[base] > ver:
                    continue
                versions[base] = ver
                self.by_stem[base] = self.by_name[name]
        elif schema_dir is None:
            # installed without the repository's schemas/: the files are generated from the
            # message structs, so generate the same documents
            for kind, stem in messages.MESSAGE_TYPES.items():
                doc = messages.json_schema(kind)
                data = json.dumps(doc, separators=(",", ":"), sort_keys=True).encode()
                name = str(doc["title"])
                self.by_name[name] = SchemaEntry(name, data, "generated")
                self.by_stem[re.sub(r"\.v\d+$", "", stem)] = self.by_name[name]
                self.documents[name] = doc
        live = json.dumps(LIVELINESS_SCHEMA, separators=(",", ":"), sort_keys=True).encode()
        self.by_stem.setdefault(
            "liveliness", SchemaEntry(str(LIVELINESS_SCHEMA["title"]), live, "builtin")
        )
        self.documents.setdefault(str(LIVELINESS_SCHEMA["title"]), LIVELINESS_SCHEMA)
        self._kind_to_stems.setdefault("liveliness", ("liveliness",))

    def kind(self, key: str) -> str:
        """Message kind of a key expression (see :func:`parse_topic`)."""
        if self._resolver is not None:
            kind = self._resolver(key)
            if kind:
                return kind
        return parse_topic(key)[0]

    def for_key(self, key: str, tag: str | None = None) -> SchemaEntry | None:
        """The schema of the messages published on ``key``, or ``None`` if unknown.

        ``tag``: the ``schema`` field of a message on it; when it names another version of
        the key's schema (``diffpos.estimate.v1`` where v2 is the newest), that version."""
        entry = self._for_key(key)
        if tag and entry is not None and tag != entry.name and tag in self.by_name:
            if re.sub(r"\.v\d+$", "", tag) == re.sub(r"\.v\d+$", "", entry.name):
                return self.by_name[tag]
        return entry

    def _for_key(self, key: str) -> SchemaEntry | None:
        for stem in self._kind_to_stems.get(self.kind(key), ()):
            entry = self.by_stem.get(stem)
            if entry is not None:
                return entry
        return None


def default_schema_dir() -> Path:
    """The shipped ``schemas/`` directory (:func:`diffpos_services.resources.schema_dir`)."""
    return schema_dir()


# ----------------------------------------------------------------------------------------
# writing
# ----------------------------------------------------------------------------------------
