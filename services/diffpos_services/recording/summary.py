"""What is in a recording: :func:`summarize` (channels, schemas, counts, time span, anchors,
nodes, liveliness events; ``diffpos inspect``) and :func:`validate_file` (every message
against its channel's JSON Schema; ``diffpos inspect --validate``). Works on truncated files
too."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from diffpos_services.recording.reader import Damage, McapScanner
from diffpos_services.recording.topics import SeqTracker, natural_key, parse_topic

__all__ = ["ChannelSummary", "RecordingSummary", "summarize", "validate_file"]


@dataclass(frozen=True)
class ChannelSummary:
    """Per-channel counts of a recording."""

    topic: str
    kind: str
    schema: str
    message_encoding: str
    count: int
    first_log_ns: int
    last_log_ns: int


@dataclass(frozen=True)
class RecordingSummary:
    """What ``diffpos inspect`` prints.

    Attributes
    ----------
    path : str
    size_bytes : int [bytes]
    complete : bool
        Has a footer (else: truncated, see ``damage``).
    messages : int
    start_ns, end_ns : int [ns]
        First / last receive time.
    channels : list of ChannelSummary
    schemas : dict[str, str]
        Schema name -> encoding.
    anchors, nodes : list of str
        Ids seen in topics.
    liveliness : list of dict
        The recorded liveliness events.
    metadata : dict[str, dict[str, str]]
    attachments : list of (name, media_type, size_bytes)
    damage : Damage
    gaps : dict[str, int]
        Sequence stream (see :class:`SeqTracker`) -> messages missing by sequence number.
    out_of_order : dict[str, int]
        Sequence stream -> sequence numbers that went backwards or repeated.
    """

    path: str
    size_bytes: int
    complete: bool
    messages: int
    start_ns: int
    end_ns: int
    channels: list[ChannelSummary]
    schemas: dict[str, str]
    anchors: list[str]
    nodes: list[str]
    liveliness: list[dict[str, Any]]
    metadata: dict[str, dict[str, str]]
    attachments: list[tuple[str, str, int]]
    damage: Damage
    gaps: dict[str, int] = field(default_factory=dict)
    out_of_order: dict[str, int] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        """Span of receive times [s]."""
        return (self.end_ns - self.start_ns) / 1e9 if self.messages else 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "size_bytes": self.size_bytes,
            "complete": self.complete,
            "messages": self.messages,
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "duration_s": self.duration_s,
            "channels": [c.__dict__ for c in self.channels],
            "schemas": self.schemas,
            "anchors": self.anchors,
            "nodes": self.nodes,
            "liveliness": self.liveliness,
            "metadata": self.metadata,
            "attachments": [list(a) for a in self.attachments],
            "damage": {**self.damage.__dict__, "ok": self.damage.ok},
            "gaps": self.gaps,
            "out_of_order": self.out_of_order,
        }


def summarize(path: str | os.PathLike[str]) -> RecordingSummary:
    """Scan a recording (complete or truncated) and summarise it; see :class:`RecordingSummary`."""
    sc = McapScanner(path)
    counts: dict[int, int] = {}
    first: dict[int, int] = {}
    last: dict[int, int] = {}
    seq = SeqTracker()
    live: list[dict[str, Any]] = []
    kinds: dict[int, str] = {}
    for batch in sc.iter_batches():
        for m in batch:
            cid = m.channel_id
            c = counts.get(cid, 0)
            counts[cid] = c + 1
            if c == 0:
                kinds[cid] = parse_topic(m.topic)[0]
                first[cid] = m.log_ns
                last[cid] = m.log_ns
            else:
                first[cid] = min(first[cid], m.log_ns)
                last[cid] = max(last[cid], m.log_ns)
            seq.add(m.topic, m.sequence)
            if kinds.get(cid) == "liveliness" and len(live) < 10000:
                try:
                    live.append(json.loads(m.data))
                except ValueError:
                    pass
    anchors: set[str] = set()
    nodes: set[str] = set()
    chans = []
    for cid, ch in sorted(sc.channels.items()):
        kind, fields = parse_topic(ch.topic)
        if "anchor" in fields:
            anchors.add(fields["anchor"])
        if "node" in fields:
            nodes.add(fields["node"])
        sch = sc.schemas.get(ch.schema_id)
        chans.append(
            ChannelSummary(
                topic=ch.topic,
                kind=kind,
                schema=sch.name if sch else "",
                message_encoding=ch.message_encoding,
                count=counts.get(cid, 0),
                first_log_ns=first.get(cid, 0),
                last_log_ns=last.get(cid, 0),
            )
        )
    for ev in live:
        if ev.get("role") == "anchor" and ev.get("id"):
            anchors.add(str(ev["id"]))
    chans.sort(key=lambda c: natural_key(c.topic))
    total = sum(counts.values())
    return RecordingSummary(
        path=str(path),
        size_bytes=Path(path).stat().st_size,
        complete=sc.complete,
        messages=total,
        start_ns=min(first.values()) if first else 0,
        end_ns=max(last.values()) if last else 0,
        channels=chans,
        schemas={s.name: s.encoding for s in sc.schemas.values()},
        anchors=sorted(anchors, key=natural_key),
        nodes=sorted(nodes, key=natural_key),
        liveliness=live,
        metadata={m.name: dict(m.metadata) for m in sc.metadata},
        attachments=[(a.name, a.media_type, len(a.data)) for a in sc.attachments],
        damage=sc.damage,
        gaps=dict(sorted(seq.gaps.items())),
        out_of_order=dict(sorted(seq.out_of_order.items())),
    )


def validate_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Validate every message of a recording against its channel's embedded JSON Schema.

    Returns
    -------
    dict
        ``checked``, ``invalid`` (count), ``no_schema`` (messages on schema-less channels),
        ``not_json`` and ``examples`` (first 10 problems as strings).

    Raises
    ------
    ImportError
        The ``jsonschema`` package (an optional extra) is not installed.
    """
    import jsonschema  # optional (the test extra): diffpos inspect --validate says so

    sc = McapScanner(path)
    validators: dict[int, object] = {}
    out = {"checked": 0, "invalid": 0, "no_schema": 0, "not_json": 0, "examples": []}
    for m in sc.messages():
        v = validators.get(m.channel_id)
        if v is None:
            sch = sc.schema_of(m.channel_id)
            if sch is None or sch.encoding != "jsonschema":
                v = False
            else:
                doc = json.loads(sch.data)
                v = jsonschema.validators.validator_for(doc)(doc)
            validators[m.channel_id] = v
        try:
            obj = json.loads(m.data)
        except ValueError:
            out["not_json"] += 1
            continue
        if v is False:
            out["no_schema"] += 1
            continue
        out["checked"] += 1
        err = jsonschema.exceptions.best_match(v.iter_errors(obj))
        if err is not None:
            out["invalid"] += 1
            if len(out["examples"]) < 10:
                out["examples"].append(f"{m.topic} seq {m.sequence}: {err.message}")
    return out
