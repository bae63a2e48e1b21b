"""What is in a recording: :func:`summarize` (channels, schemas, counts, time span, anchors,
nodes, liveliness events, heartbeats; ``diffpos inspect``) and :func:`validate_file` (every message
against diffpos' own JSON Schema of its kind; ``diffpos inspect --validate``). Works on
truncated files too. Also the run settings a recording stores (:func:`live_fusion_settings`,
:func:`attached_scenario`, :func:`recorded_building`)."""

from __future__ import annotations

import json
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from diffpos.scenario import Building, Scenario, ScenarioError, default_scenario
from diffpos_services.fusion.config import building_of
from diffpos_services.recording.heartbeats import HeartbeatLog
from diffpos_services.recording.reader import Damage, McapScanner, SideRecords
from diffpos_services.recording.schemas import SchemaRegistry
from diffpos_services.recording.topics import SEQUENCED_KINDS, SeqTracker, natural_key, parse_topic
from diffpos_services.recording.writer import recording_set

__all__ = [
    "ChannelSummary",
    "RecordingSummary",
    "SetLosses",
    "attached_scenario",
    "live_fusion_settings",
    "recorded_building",
    "set_losses",
    "summarize",
    "validate_file",
]


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
    heartbeats : list of dict
        Per publisher and process start, its heartbeats
        (:class:`~diffpos_services.recording.heartbeats.ProcessBeats` as a dict): beats,
        progress, the longest silence and stall and when they began.
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
    heartbeats: list[dict[str, Any]] = field(default_factory=list)

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
            "heartbeats": self.heartbeats,
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
    beats = HeartbeatLog()
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
            if kinds.get(cid) == "heartbeat":
                beats.add(m.data, m.log_ns)
            elif kinds.get(cid) == "liveliness" and len(live) < 10000:
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
        heartbeats=[p.as_dict() for p in beats.processes()],
    )


@dataclass(frozen=True)
class SetLosses:
    """Messages missing by sequence number across every file of a recording (split parts and
    restarts, :func:`~diffpos_services.recording.writer.recording_set`): a part that starts
    after a hole (the recorder was dead, hung or restarting) counts it, where each file alone
    says ``gaps: 0``.

    Attributes
    ----------
    files : list of str
    missing : int
        Messages missing in all.
    by_stream : dict[str, int]
        Sequence stream (one publisher's counter) -> messages missing.
    holes : list of (stream, first, last)
        The missing sequence numbers (first 1000 holes).
    restarted_streams : dict[str, int]
        Streams whose numbers went backwards (a publisher restarted): the messages it sent
        before it restarted and after the last recorded one cannot be counted.
    damage : list of str
        Every file's damage notes.
    """

    files: list[str]
    missing: int
    by_stream: dict[str, int]
    holes: list[tuple[str, int, int]]
    restarted_streams: dict[str, int]
    damage: list[str]

    def line(self) -> str:
        """One line for a summary."""
        if not self.missing:
            return (f"recording: 0 messages missing by sequence number across its "
                    f"{len(self.files)} file(s)")
        top = sorted(self.by_stream.items(), key=lambda kv: -kv[1])[:4]
        detail = ", ".join(f"{st.split('/', 2)[-1]}: {n}" for st, n in top)
        return (f"recording: {self.missing} messages missing by sequence number across its "
                f"{len(self.files)} file(s) ({detail}{', ...' if len(self.by_stream) > 4 else ''})")


class _SequencedTopics(set):
    """A topic filter for :meth:`McapScanner.iter_batches` holding every sequenced topic
    (decided once per topic)."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: dict[object, bool] = {}

    def __contains__(self, topic: object) -> bool:
        ok = self.seen.get(topic)
        if ok is None:
            ok = self.seen[topic] = parse_topic(str(topic))[0] in SEQUENCED_KINDS
        return ok


def set_losses(first: str | os.PathLike[str]) -> SetLosses:
    """Count the messages missing by sequence number across a recording's files, in order
    (see :class:`SetLosses`); only the sequenced topics are read."""
    files = recording_set(first)
    seq = SeqTracker()
    damage: list[str] = []
    for path in files:
        sc = McapScanner(path)
        for batch in sc.iter_batches(_SequencedTopics()):
            for m in batch:
                seq.add(m.topic, m.sequence)
        damage += [f"{path.name}: {n}" for n in sc.damage.notes]
    return SetLosses(files=[str(p) for p in files], missing=seq.total_gaps,
                     by_stream=dict(sorted(seq.gaps.items())), holes=list(seq.gap_list),
                     restarted_streams=dict(sorted(seq.out_of_order.items())), damage=damage)


def validate_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Validate every message of a recording against diffpos' OWN JSON Schemas (``schemas/``,
    :class:`SchemaRegistry`), not the schema embedded in the file (a file may embed
    ``{"type": "object"}`` and carry anything).

    A message is checked against the schema its ``schema`` tag names (e.g.
    ``diffpos.range.v1``); an untagged message (liveliness events) against the schema of its
    topic. A tag that is not one of ours, or not the one of the topic's kind, is invalid.
    Channels whose embedded schema differs from ours are reported in ``schema_mismatch``.

    Returns
    -------
    dict
        ``checked``, ``invalid`` (count), ``no_schema`` (messages on channels that are not
        diffpos keys, untagged), ``not_json``, ``schema_mismatch`` (one ``{"ours", "embedded",
        "channels", "example"}`` per differing pair) and ``examples`` (first 10 problems as strings).

    Raises
    ------
    ImportError
        The ``jsonschema`` package (an optional extra) is not installed.
    """
    import jsonschema  # optional (the test extra): diffpos inspect --validate says so

    sc = McapScanner(path)
    reg = SchemaRegistry()
    validators: dict[str, Any] = {}
    expected: dict[int, str | None] = {}  # channel id -> our schema name for its topic
    out: dict[str, Any] = {"checked": 0, "invalid": 0, "no_schema": 0, "not_json": 0,
                           "schema_mismatch": [], "examples": []}

    def problem(text: str) -> None:
        out["invalid"] += 1
        if len(out["examples"]) < 10:
            out["examples"].append(text)

    for m in sc.messages():
        if m.channel_id not in expected:
            expected[m.channel_id] = _expected_schema(sc, m.channel_id, reg, out)
        try:
            obj = json.loads(m.data)
        except ValueError:
            out["not_json"] += 1
            continue
        tag = obj.get("schema") if isinstance(obj, dict) else None
        name = tag if isinstance(tag, str) else expected[m.channel_id]
        where = f"{m.topic} seq {m.sequence}"
        if name is None:
            out["no_schema"] += 1
            continue
        out["checked"] += 1
        doc = reg.documents.get(name)
        if doc is None:
            problem(f"{where}: schema tag {name!r} is not a diffpos schema")
            continue
        want = expected[m.channel_id]
        if want is not None and _unversioned(want) != _unversioned(name):  # any version of ours
            problem(f"{where}: schema tag {name!r} on a {want} channel")
            continue
        v = validators.get(name)
        if v is None:
            v = validators[name] = jsonschema.validators.validator_for(doc)(doc)
        err = jsonschema.exceptions.best_match(v.iter_errors(obj))
        if err is not None:
            problem(f"{where}: {err.message}")
    return out


def _unversioned(name: str) -> str:
    """``diffpos.estimate.v2`` -> ``diffpos.estimate``."""
    return re.sub(r"\.v\d+$", "", name)


def _expected_schema(sc: McapScanner, cid: int, reg: SchemaRegistry,
                     out: dict[str, Any]) -> str | None:
    """Our schema name for channel ``cid`` (``None``: not a diffpos key); notes a channel
    whose embedded schema differs from ours in ``out["schema_mismatch"]``."""
    ch = sc.channels[cid]
    entry = reg.for_key(ch.topic)
    if entry is None:
        return None
    sch = sc.schema_of(cid)
    try:
        embedded = None if sch is None else json.loads(sch.data)
    except ValueError:
        embedded = None
    ours = reg.documents.get(sch.name) if sch is not None else None  # same version of ours
    if embedded != (ours if ours is not None else reg.documents.get(entry.name)):
        label = "none" if sch is None else f"{sch.name} ({len(sch.data)} bytes)"
        for row in out["schema_mismatch"]:
            if (row["ours"], row["embedded"]) == (entry.name, label):
                row["channels"] += 1
                break
        else:
            out["schema_mismatch"].append(
                {"ours": entry.name, "embedded": label, "channels": 1, "example": ch.topic})
    return entry.name


# -- the run settings a recording stores ---------------------------------------------------


def live_fusion_settings(scanner: SideRecords | McapScanner) -> tuple[dict[str, Any], str]:
    """The fusion settings the live run used, as far as the recording says.

    Looks for a metadata record ``fusion_config`` (key -> JSON value), then a ``fusion``
    entry in the ``run_config`` metadata / ``run_config.json`` attachment, in the records of
    :func:`~diffpos_services.recording.reader.side_records` (found anywhere in the file).

    Returns
    -------
    values : dict
        FusionConfig fields (possibly empty).
    source : str
        Where they came from (``"defaults"`` when the recording has none).
    """

    def decode(v: str) -> Any:
        try:
            return json.loads(v)
        except ValueError:
            return v

    for md in scanner.metadata:
        if md.name == "fusion_config":
            return {k: decode(v) for k, v in md.metadata.items()}, "metadata fusion_config"
    for md in scanner.metadata:
        if md.name == "run_config" and "fusion" in md.metadata:
            val = decode(md.metadata["fusion"])
            if isinstance(val, dict):
                return val, "metadata run_config.fusion"
    for att in scanner.attachments:
        if att.name == "run_config.json":
            try:
                doc = json.loads(att.data)
            except ValueError:
                continue
            if isinstance(doc, dict) and isinstance(doc.get("fusion"), dict):
                return doc["fusion"], "attachment run_config.json"
    return {}, "defaults"


def attached_scenario(scanner: SideRecords | McapScanner) -> tuple[Scenario, str]:
    """The scenario of the first valid TOML attachment, else the built-in paper scenario;
    and where it came from."""
    found = _toml_scenario(scanner)
    return found if found is not None else (default_scenario(), "paper scenario (built in)")


def _toml_scenario(scanner: SideRecords | McapScanner) -> tuple[Scenario, str] | None:
    """The scenario of the first valid TOML attachment and its name, or None."""
    for att in scanner.attachments:
        if att.name.endswith(".toml"):
            try:
                scenario = Scenario.from_dict(tomllib.loads(att.data.decode("utf-8")))
            except (UnicodeDecodeError, tomllib.TOMLDecodeError, ScenarioError):
                continue
            return scenario, f"scenario {att.name} (attached)"
    return None


def recorded_building(scanner: SideRecords | McapScanner) -> tuple[Building | None, str]:
    """The building the recorded run's truth is in, and where it came from: the attached
    scenario's (first valid TOML attachment), else the ``building`` table of the recorded
    live fusion settings (:func:`live_fusion_settings`; ``diffpos emulate`` records the
    scenario's, the built-in paper scenario's included); ``None`` when the recording says
    neither (not the built-in paper building: a recording of another building must not be
    scored against it)."""
    found = _toml_scenario(scanner)
    if found is not None:
        return found[0].building, found[1]
    values, source = live_fusion_settings(scanner)
    if isinstance(values.get("building"), dict):
        try:
            return building_of(values["building"]), f"fusion building ({source})"
        except ValueError:
            pass
    return None, "none recorded"
