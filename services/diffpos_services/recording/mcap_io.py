"""MCAP input/output for diffpos recordings (pure Python, no Zenoh).

What lives here
---------------
* :class:`SchemaRegistry` - the JSON Schemas of ``schemas/*.json`` and which one belongs to a
  key expression.
* :class:`McapSink` - writes ``(key, payload, receive_ns)`` tuples to an MCAP file: one channel
  per key expression, schema encoding ``jsonschema``, message encoding ``json`` (Foxglove opens
  it), ``log_time`` = receive time, ``publish_time`` = the message's own measurement time,
  sequence numbers kept, zstd chunks. Counts received vs written and gaps in sequence numbers.
  The recorder service is a thin Zenoh wrapper around it.
* :class:`JsonDecoderFactory` - lets ``mcap.reader.make_reader`` decode our JSON channels.
* :class:`McapScanner` - a sequential, damage-tolerant reader: works on complete files and on
  truncated ones (no footer, e.g. after SIGKILL), skips chunks that fail their CRC, and parses
  chunk contents with ``struct`` directly (several times faster than ``mcap``'s record objects,
  which matters for replay).
* :func:`recover` - rewrites a truncated or damaged recording into a valid, indexed one.
* :func:`summarize` - channels, schemas, counts, time span, anchors, nodes (``diffpos inspect``).

All times are integer nanoseconds since the Unix epoch.
"""

from __future__ import annotations

import functools
import json
import os
import re
import struct
import threading
import time
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec
from mcap.decoder import DecoderFactory
from mcap.records import Attachment, Metadata, Schema
from mcap.writer import CompressionType, Writer

from diffpos_services.resources import schema_dir
from diffpos_services.wire.keys import PREFIX, parse_key

__all__ = [
    "LIVELINESS_SCHEMA",
    "MESSAGE_ENCODING",
    "SCHEMA_ENCODING",
    "ChannelSummary",
    "Damage",
    "JsonDecoderFactory",
    "McapScanner",
    "McapSink",
    "RawMessage",
    "RecordingError",
    "RecordingSummary",
    "RecoverReport",
    "SchemaEntry",
    "SchemaRegistry",
    "SeqTracker",
    "SinkStats",
    "liveliness_topic",
    "parse_topic",
    "recover",
    "replay_estimate_topic",
    "summarize",
]

SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"
MCAP_MAGIC = b"\x89MCAP0\r\n"

# MCAP record opcodes (spec: https://mcap.dev/spec)
_OP_HEADER = 0x01
_OP_FOOTER = 0x02
_OP_SCHEMA = 0x03
_OP_CHANNEL = 0x04
_OP_MESSAGE = 0x05
_OP_CHUNK = 0x06
_OP_ATTACHMENT = 0x09
_OP_METADATA = 0x0C
_OP_DATA_END = 0x0F
_OP_STATISTICS = 0x0B

_REC_HEAD = struct.Struct("<BQ")
_MSG_HEAD = struct.Struct("<HIQQ")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")

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


class RecordingError(Exception):
    """A recording cannot be read or written; the message says what to do about it."""


# ----------------------------------------------------------------------------------------
# topics
# ----------------------------------------------------------------------------------------


def parse_topic(topic: str) -> tuple[str, dict[str, str]]:
    """Classify a key expression / MCAP topic.

    Parameters
    ----------
    topic : str
        e.g. ``diffpos/site1/anchor/a3/range/n12``.

    Returns
    -------
    kind : str
        A :func:`diffpos_services.wire.keys.parse_key` kind (``anchor_state``, ``range``,
        ``estimate``, ``diagnostics``, ``truth_node``, ``truth_anchor``, ``run_control``, ...),
        or one of the recording-only kinds ``liveliness`` (the recorder's event channel) and
        ``replay_estimate`` (estimates written by ``diffpos replay``), or ``unknown``.
    fields : dict
        ``site`` and, when present, ``anchor`` and ``node``.
    """
    parts = topic.split("/")
    if len(parts) >= 4 and parts[0] == PREFIX:
        if parts[2:] == ["recorder", "liveliness"]:
            return "liveliness", {"site": parts[1]}
        if (
            len(parts) == 6
            and parts[2] == "replay"
            and parts[3] == "node"
            and parts[5] == "estimate"
        ):
            return "replay_estimate", {"site": parts[1], "node": parts[4]}
    pk = parse_key(topic)
    if pk is None:
        return "unknown", {}
    fields = {"site": pk.site}
    if pk.anchor_id is not None:
        fields["anchor"] = pk.anchor_id
    if pk.node_id is not None:
        fields["node"] = pk.node_id
    return pk.kind, fields


def replay_estimate_topic(site: str, node_id: str) -> str:
    """MCAP topic of a replayed estimate (kept apart from the live ``node/<id>/estimate``)."""
    return f"{PREFIX}/{site}/replay/node/{node_id}/estimate"


def liveliness_topic(site: str) -> str:
    """MCAP topic of the recorder's liveliness-event channel of ``site``."""
    return f"{PREFIX}/{site}/recorder/liveliness"


#: message kind -> its sequence stream (the key pattern of one publisher's counter): an anchor
#: numbers its state and all its ranges with one counter, the fusion all its estimates
SEQUENCE_STREAMS: dict[str, str] = {
    "anchor_state": "anchor/{anchor}/**",
    "range": "anchor/{anchor}/**",
    "range_batch": "anchor/{anchor}/**",
    "estimate": "node/*/estimate",
    "replay_estimate": "replay/node/*/estimate",
}
#: kinds whose messages carry a ``seq`` field (the others - truth, diagnostics, run control,
#: liveliness events, foreign channels - are not checked for gaps)
SEQUENCED_KINDS = frozenset(SEQUENCE_STREAMS)


class SeqTracker:
    """Gaps and repeats in publisher sequence numbers, per sequence stream.

    A stream is one publisher's counter (:data:`SEQUENCE_STREAMS`: one per anchor, one for
    the fusion's estimates). Only :data:`SEQUENCED_KINDS` are tracked.

    Attributes
    ----------
    gaps : dict[str, int]
        Stream -> messages missing (sum of the holes).
    out_of_order : dict[str, int]
        Stream -> sequence numbers that went backwards or repeated.
    gap_list : list of (stream, first_missing, last_missing)
        The holes, first 1000.
    """

    def __init__(self) -> None:
        self._stream: dict[str, str | None] = {}
        self._last: dict[str, int] = {}
        self.gaps: dict[str, int] = {}
        self.out_of_order: dict[str, int] = {}
        self.gap_list: list[tuple[str, int, int]] = []
        self.total_gaps = 0
        self.total_out_of_order = 0

    def stream_of(self, topic: str) -> str | None:
        """Sequence stream of a topic (``None``: not tracked)."""
        st = self._stream.get(topic, "")
        if st == "":
            kind, fields = parse_topic(topic)
            if kind not in SEQUENCED_KINDS:
                st = None
            else:
                st = f"{PREFIX}/{fields['site']}/" + SEQUENCE_STREAMS[kind].format(**fields)
            self._stream[topic] = st
        return st

    def add(self, topic: str, seq: int) -> int:
        """Account one message; returns the number of messages found missing before it."""
        st = self.stream_of(topic)
        if st is None:
            return 0
        last = self._last.get(st)
        self._last[st] = seq
        if last is None:
            return 0
        if seq > last + 1:
            n = seq - last - 1
            self.gaps[st] = self.gaps.get(st, 0) + n
            self.total_gaps += n
            if len(self.gap_list) < 1000:
                self.gap_list.append((st, last + 1, seq - 1))
            return n
        if seq <= last:
            self.out_of_order[st] = self.out_of_order.get(st, 0) + 1
            self.total_out_of_order += 1
        return 0


# ----------------------------------------------------------------------------------------
# schemas
# ----------------------------------------------------------------------------------------


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
                if base in versions and versions[base] > ver:
                    continue
                versions[base] = ver
                name = str(doc.get("title") or path.name[: -len(".json")])
                data = json.dumps(doc, separators=(",", ":"), sort_keys=True).encode()
                self.by_stem[base] = SchemaEntry(name=name, data=data, source=path.name)
                self.documents[name] = doc
        elif schema_dir is None:
            # installed without the repository's schemas/: the files are generated from the
            # message structs, so generate the same documents
            from diffpos_services.wire import messages

            for kind, stem in messages.MESSAGE_TYPES.items():
                doc = messages.json_schema(kind)
                data = json.dumps(doc, separators=(",", ":"), sort_keys=True).encode()
                name = str(doc["title"])
                self.by_stem[re.sub(r"\.v\d+$", "", stem)] = SchemaEntry(name, data, "generated")
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

    def for_key(self, key: str) -> SchemaEntry | None:
        """The schema of the messages published on ``key``, or ``None`` if unknown."""
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


class _Stamp(msgspec.Struct):
    """The two fields the sink reads from every payload (everything else is ignored)."""

    t_ns: int | None = None
    seq: int | None = None


@dataclass
class SinkStats:
    """Counters of a :class:`McapSink`.

    Attributes
    ----------
    received : int
        Messages handed to :meth:`McapSink.write`.
    written : int
        Messages added to the MCAP writer (equal to ``received`` unless writing failed).
    flushed : int
        Messages (incl. liveliness events) in chunks already written to the file (they
        survive a SIGKILL).
    flushed_written : int
        Value of ``written`` at the last flush: the first ``flushed_written`` bus messages
        are on disk.
    unknown_schema : int
        Messages on keys with no schema (recorded on a schema-less channel).
    undecodable : int
        Payloads that are not JSON objects with integer ``t_ns``/``seq`` (still recorded,
        with ``publish_time`` = receive time).
    gaps : int
        Messages missing according to sequence numbers (sum of the holes).
    out_of_order : int
        Sequence numbers that went backwards or repeated (publisher restart, duplicate).
    per_key : dict
        key -> number of messages written.
    gap_list : list of (key, first_missing, last_missing)
        The holes, first 1000.
    """

    received: int = 0
    written: int = 0
    flushed: int = 0
    flushed_written: int = 0
    unknown_schema: int = 0
    undecodable: int = 0
    gaps: int = 0
    out_of_order: int = 0
    liveliness_events: int = 0
    per_key: dict[str, int] = field(default_factory=dict)
    gap_list: list[tuple[str, int, int]] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (``gap_list`` truncated to its first 100 entries)."""
        return {
            "received": self.received,
            "written": self.written,
            "flushed": self.flushed,
            "flushed_written": self.flushed_written,
            "unknown_schema": self.unknown_schema,
            "undecodable": self.undecodable,
            "gaps": self.gaps,
            "out_of_order": self.out_of_order,
            "liveliness_events": self.liveliness_events,
            "channels": len(self.per_key),
            "gap_list": [list(g) for g in self.gap_list[:100]],
        }


class McapSink:
    """Write bus messages to an MCAP file; unit-testable without Zenoh.

    Thread-safe: :meth:`write`, :meth:`flush` and the other methods take an internal lock, so
    a drain thread and a flush timer can share one sink.

    Parameters
    ----------
    output : path or binary file
        Destination. A path is opened (parent directories created) and closed by :meth:`close`.
    registry : SchemaRegistry, optional
        Where schemas come from (default: the repository's ``schemas/``).
    compression : {"zstd", "lz4", "none"}
        Chunk compression.
    chunk_size : int [bytes]
        Uncompressed size at which a chunk is closed even without :meth:`flush`.
    time_field, seq_field : str
        Payload fields holding the measurement time [ns] and the publisher's sequence number.
    profile : str
        MCAP header profile (empty: no well-known profile).

    Examples
    --------
    >>> sink = McapSink("x.mcap")                                           # doctest: +SKIP
    >>> sink.write("diffpos/s/anchor/a1/state", b'{"t_ns": 5, "seq": 0}', 7)  # doctest: +SKIP
    >>> sink.close()                                                         # doctest: +SKIP
    """

    def __init__(
        self,
        output: str | os.PathLike[str] | IO[bytes],
        *,
        registry: SchemaRegistry | None = None,
        compression: str = "zstd",
        chunk_size: int = 1024 * 1024,
        time_field: str = "t_ns",
        seq_field: str = "seq",
        profile: str = "",
        library: str = "diffpos-recorder",
    ) -> None:
        comp = {
            "zstd": CompressionType.ZSTD,
            "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE,
        }.get(compression)
        if comp is None:
            raise RecordingError(f"compression must be zstd, lz4 or none, not {compression!r}")
        self.registry = registry if registry is not None else SchemaRegistry()
        if isinstance(output, (str, os.PathLike)):
            path = Path(output)
            path.parent.mkdir(parents=True, exist_ok=True)
            self._file: IO[bytes] = open(path, "wb")
            self._own_file = True
            self.path: Path | None = path
        else:
            self._file = output
            self._own_file = False
            self.path = None
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp)
        self._writer.start(profile=profile, library=library)
        if (time_field, seq_field) == ("t_ns", "seq"):
            stamp_type: type = _Stamp
        else:
            stamp_type = msgspec.defstruct(
                "_CustomStamp",
                [(time_field, int | None, None), (seq_field, int | None, None)],
            )
        self._stamp_decoder = msgspec.json.Decoder(stamp_type)
        self._time_field = time_field
        self._seq_field = seq_field
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.seq = SeqTracker()
        self._unknown_keys: set[str] = set()
        self._alive: dict[str, bool] = {}
        self._pending = 0
        self._lock = threading.Lock()
        self._closed = False
        self.stats = SinkStats()

    # -- channels -------------------------------------------------------------------------

    def _schema_id(self, entry: SchemaEntry | None) -> int:
        if entry is None:
            return 0
        sid = self._schema_ids.get(entry.name)
        if sid is None:
            sid = self._writer.register_schema(entry.name, SCHEMA_ENCODING, entry.data)
            self._schema_ids[entry.name] = sid
        return sid

    def channel(self, key: str) -> int:
        """Channel id of ``key`` (registered on first use with its schema)."""
        cid = self._channels.get(key)
        if cid is None:
            entry = self.registry.for_key(key)
            kind = self.registry.kind(key)
            meta = {"key_expr": key, "kind": kind}
            if entry is not None:
                meta["schema_file"] = entry.source
            cid = self._writer.register_channel(key, MESSAGE_ENCODING, self._schema_id(entry), meta)
            self._channels[key] = cid
        return cid

    # -- messages -------------------------------------------------------------------------

    def write(
        self,
        key: str,
        payload: bytes,
        receive_ns: int,
        *,
        publish_ns: int | None = None,
        sequence: int | None = None,
    ) -> None:
        """Record one message.

        Parameters
        ----------
        key : str
            Key expression it arrived on (becomes the MCAP topic).
        payload : bytes
            The message as published (JSON).
        receive_ns : int [ns]
            Receive time; becomes ``log_time``.
        publish_ns : int [ns], optional
            Measurement time; default: the payload's ``t_ns`` (else ``receive_ns``).
        sequence : int, optional
            Publisher sequence number; default: the payload's ``seq`` (else 0).
        """
        with self._lock:
            self._write_locked(key, payload, receive_ns, publish_ns, sequence)

    def _write_locked(self, key, payload, receive_ns, publish_ns, sequence) -> None:
        stats = self.stats
        stats.received += 1
        if self._closed:
            raise RecordingError("write() after close()")
        if publish_ns is None or sequence is None:
            try:
                stamp = self._stamp_decoder.decode(payload)
                t = getattr(stamp, self._time_field)
                s = getattr(stamp, self._seq_field)
            except (msgspec.DecodeError, msgspec.ValidationError):
                stats.undecodable += 1
                t = s = None
            if publish_ns is None:
                publish_ns = t if t is not None and t >= 0 else receive_ns
            if sequence is None:
                sequence = s
        cid = self._channels.get(key)
        if cid is None:
            cid = self.channel(key)
            if self.registry.for_key(key) is None:
                self._unknown_keys.add(key)
        if key in self._unknown_keys:
            stats.unknown_schema += 1
        if sequence is not None and sequence >= 0:
            if self.seq.add(key, sequence):
                stats.gaps = self.seq.total_gaps
                stats.gap_list = self.seq.gap_list
            stats.out_of_order = self.seq.total_out_of_order
            seq32 = sequence & 0xFFFFFFFF
        else:
            seq32 = 0
        self._writer.add_message(
            cid,
            log_time=int(receive_ns),
            data=payload,
            publish_time=int(publish_ns),
            sequence=seq32,
        )
        stats.written += 1
        stats.per_key[key] = stats.per_key.get(key, 0) + 1
        self._pending += 1

    def write_liveliness(self, site: str, key: str, alive: bool, receive_ns: int) -> bool:
        """Record a liveliness token appearing (``alive``) or disappearing.

        Only changes are recorded: a liveliness subscriber with history may report a token
        twice (from the history query and live), the repeat is dropped.

        Parameters
        ----------
        site : str
            Site name (the event goes to :func:`liveliness_topic` of it).
        key : str
            The token's key expression.
        alive : bool
            ``True`` for PUT (joined), ``False`` for DELETE (left).
        receive_ns : int [ns]
            When the recorder saw it.

        Returns
        -------
        bool
            Whether an event was recorded (False for a repeat).
        """
        role, ident = "unknown", ""
        parts = key.split("/")
        if len(parts) >= 4 and parts[2] == "alive":  # diffpos/<site>/alive/<role>[/<id>]
            role, ident = parts[3], "/".join(parts[4:])
        event = {
            "v": 1,
            "key": key,
            "alive": bool(alive),
            "t_ns": int(receive_ns),
            "role": role,
            "id": ident,
        }
        payload = json.dumps(event, separators=(",", ":")).encode()
        topic = liveliness_topic(site)
        with self._lock:
            if self._alive.get(key) == bool(alive):
                return False
            self._alive[key] = bool(alive)
            self.stats.liveliness_events += 1
            cid = self._channels.get(topic)
            if cid is None:
                entry = self.registry.by_stem["liveliness"]
                cid = self._writer.register_channel(
                    topic,
                    MESSAGE_ENCODING,
                    self._schema_id(entry),
                    {"key_expr": topic, "kind": "liveliness", "schema_file": entry.source},
                )
                self._channels[topic] = cid
            self._writer.add_message(
                cid,
                log_time=int(receive_ns),
                data=payload,
                publish_time=int(receive_ns),
                sequence=self.stats.liveliness_events - 1,
            )
            self._pending += 1
        return True

    def counts_by_kind(self) -> dict[str, int]:
        """Messages written so far per message kind (see :func:`parse_topic`)."""
        with self._lock:
            items = list(self.stats.per_key.items())
        out: dict[str, int] = {}
        for key, n in items:
            kind = self.registry.kind(key)
            out[kind] = out.get(kind, 0) + n
        return out

    # -- self-description ---------------------------------------------------------------------

    def add_metadata(self, name: str, data: dict[str, Any]) -> None:
        """MCAP metadata record; non-string values are JSON-encoded."""
        clean = {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in data.items()}
        with self._lock:
            self._writer.add_metadata(name, clean)

    def add_attachment(
        self,
        name: str,
        data: bytes,
        *,
        media_type: str = "application/octet-stream",
        log_ns: int | None = None,
    ) -> None:
        """MCAP attachment (e.g. the scenario TOML), written immediately."""
        t = time.time_ns() if log_ns is None else int(log_ns)
        with self._lock:
            self._writer.add_attachment(
                create_time=t, log_time=t, name=name, media_type=media_type, data=bytes(data)
            )
            self._file.flush()

    # -- durability -----------------------------------------------------------------------

    def flush(self, *, fsync: bool = False) -> int:
        """Close the chunk in progress and push it to the OS.

        Returns
        -------
        flushed : int
            Total messages (incl. liveliness events) now on disk; after a SIGKILL a recovered
            file holds at least this many.
        """
        with self._lock:
            if self._closed:
                return self.stats.flushed
            if self._pending:
                self._writer.flush()
                self.stats.flushed += self._pending
                self._pending = 0
                self.stats.flushed_written = self.stats.written
            if fsync:
                os.fsync(self._file.fileno())
            return self.stats.flushed

    def close(self, *, final_metadata: dict[str, Any] | None = None) -> SinkStats:
        """Write the summary and footer (the file becomes a valid indexed MCAP).

        Parameters
        ----------
        final_metadata : dict, optional
            Written as metadata ``recorder_stats`` together with the counters.
        """
        with self._lock:
            if self._closed:
                return self.stats
            meta = {"stats": self.stats.as_dict()}
            if final_metadata:
                meta.update(final_metadata)
            clean = {k: v if isinstance(v, str) else json.dumps(v) for k, v in meta.items()}
            self._writer.add_metadata("recorder_stats", clean)
            self._writer.finish()
            self.stats.flushed += self._pending
            self._pending = 0
            self.stats.flushed_written = self.stats.written
            self._closed = True
            self._file.flush()
            if self._own_file:
                self._file.close()
        return self.stats

    def __enter__(self) -> McapSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ----------------------------------------------------------------------------------------
# reading
# ----------------------------------------------------------------------------------------


class JsonDecoderFactory(DecoderFactory):
    """``make_reader(f, decoder_factories=[JsonDecoderFactory()])`` decodes ``json`` channels."""

    def decoder_for(self, message_encoding: str, schema: Schema | None):
        if message_encoding != MESSAGE_ENCODING:
            return None
        return json.loads


class RawMessage(msgspec.Struct, frozen=True, array_like=True):
    """One recorded message as stored (payload not decoded).

    Attributes
    ----------
    topic : str
    channel_id : int
    sequence : int
    log_ns : int [ns]
        Receive time.
    publish_ns : int [ns]
        Measurement time.
    data : bytes
    """

    topic: str
    channel_id: int
    sequence: int
    log_ns: int
    publish_ns: int
    data: bytes


@dataclass
class Damage:
    """What a scan could not read.

    Attributes
    ----------
    truncated : bool
        The file ends before its footer (writer killed, disk full, copy cut short).
    bad_chunks : int
        Chunks skipped because they failed to decompress or their CRC did not match.
    bad_records : int
        Other records skipped (unparseable).
    unread_bytes : int [bytes]
        Bytes at the end of the file that did not form a complete record.
    messages_without_channel : int
        Messages whose channel record was never seen (skipped).
    notes : list of str
        Human-readable details.
    """

    truncated: bool = False
    bad_chunks: int = 0
    bad_records: int = 0
    unread_bytes: int = 0
    messages_without_channel: int = 0
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not (
            self.truncated or self.bad_chunks or self.bad_records or self.messages_without_channel
        )


@dataclass(frozen=True)
class ChannelInfo:
    """A channel as found in the file."""

    id: int
    topic: str
    message_encoding: str
    schema_id: int
    metadata: dict[str, str]


class McapScanner:
    """Sequential, damage-tolerant MCAP reader.

    Parameters
    ----------
    path : path
        The recording.
    validate_crcs : bool
        Check chunk CRCs (a failing chunk is skipped and counted in :attr:`damage`).

    Attributes (filled while iterating)
    -----------------------------------
    schemas : dict[int, mcap.records.Schema]
    channels : dict[int, ChannelInfo]
    metadata : list of mcap.records.Metadata
    attachments : list of mcap.records.Attachment
    statistics : mcap.records.Statistics or None
        From the summary section (only in complete files).
    damage : Damage
    complete : bool
        The footer and trailing magic were read.

    Raises
    ------
    RecordingError
        The file does not exist, or is not MCAP at all (bad magic).
    """

    def __init__(self, path: str | os.PathLike[str], *, validate_crcs: bool = True) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError(f"recording {self.path} does not exist (or is not a file)")
        with open(self.path, "rb") as f:
            head = f.read(8)
        if head != MCAP_MAGIC:
            raise RecordingError(
                f"{self.path} is not an MCAP file (it does not start with the MCAP magic bytes)"
            )
        self.validate_crcs = validate_crcs
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, ChannelInfo] = {}
        self.metadata: list[Metadata] = []
        self.attachments: list[Attachment] = []
        self.statistics = None
        self.damage = Damage()
        self.complete = False
        self.header_library = ""
        self.header_profile = ""
        self.size_bytes = self.path.stat().st_size
        self.offset = 0  # bytes consumed so far (for progress bars)

    # -- record parsing -----------------------------------------------------------------

    def _add_schema(self, body: bytes | memoryview, pos: int = 0) -> None:
        sid = _U16.unpack_from(body, pos)[0]
        pos += 2
        name, pos = _str(body, pos)
        enc, pos = _str(body, pos)
        n = _U32.unpack_from(body, pos)[0]
        pos += 4
        data = bytes(body[pos : pos + n])
        if sid not in self.schemas:
            self.schemas[sid] = Schema(id=sid, name=name, encoding=enc, data=data)

    def _add_channel(self, body: bytes | memoryview, pos: int = 0) -> None:
        cid = _U16.unpack_from(body, pos)[0]
        sid = _U16.unpack_from(body, pos + 2)[0]
        topic, pos = _str(body, pos + 4)
        enc, pos = _str(body, pos)
        meta, pos = _map(body, pos)
        if cid not in self.channels:
            self.channels[cid] = ChannelInfo(cid, topic, enc, sid, meta)

    def _chunk_messages(self, body: bytes, topic_filter) -> list[RawMessage]:
        # Chunk: start u64, end u64, uncompressed_size u64, crc u32, compression str,
        # records_len u64, records
        usize = _U64.unpack_from(body, 16)[0]
        crc = _U32.unpack_from(body, 24)[0]
        comp, pos = _str(body, 28)
        rlen = _U64.unpack_from(body, pos)[0]
        pos += 8
        comp_data = body[pos : pos + rlen]
        if comp == "zstd":
            import zstandard

            data = zstandard.ZstdDecompressor().decompress(comp_data, max_output_size=usize)
        elif comp == "lz4":
            import lz4.frame

            data = lz4.frame.decompress(comp_data)
        elif comp == "":
            data = bytes(comp_data)
        else:
            raise ValueError(f"unsupported chunk compression {comp!r}")
        if len(data) != usize:
            raise ValueError("chunk size mismatch")
        if self.validate_crcs and crc and zlib.crc32(data) != crc:
            raise ValueError("chunk CRC mismatch")
        out: list[RawMessage] = []
        append = out.append
        channels = self.channels
        n = len(data)
        p = 0
        unpack_head = _REC_HEAD.unpack_from
        unpack_msg = _MSG_HEAD.unpack_from
        topics: dict[int, str] = {c.id: c.topic for c in channels.values()}
        while p < n:
            op, ln = unpack_head(data, p)
            b = p + 9
            p = b + ln
            if op == _OP_MESSAGE:
                cid, seq, log_t, pub_t = unpack_msg(data, b)
                topic = topics.get(cid)
                if topic is None:
                    self.damage.messages_without_channel += 1
                    continue
                if topic_filter is not None and topic not in topic_filter:
                    continue
                append(RawMessage(topic, cid, seq, log_t, pub_t, data[b + 22 : p]))
            elif op == _OP_CHANNEL:
                self._add_channel(data, b)
                topics = {c.id: c.topic for c in channels.values()}
            elif op == _OP_SCHEMA:
                self._add_schema(data, b)
        if p != n:
            raise ValueError("chunk records overrun the chunk")
        return out

    def iter_batches(self, topics: set[str] | None = None) -> Iterator[list[RawMessage]]:
        """Messages in file order, one list per chunk (or per loose message).

        Parameters
        ----------
        topics : set of str, optional
            Only these topics; ``None``: all.

        Yields
        ------
        batch : list of RawMessage
        """
        size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            f.read(8)
            offset = 8
            while True:
                head = f.read(9)
                if len(head) == 0:
                    self.damage.truncated = True
                    self.damage.notes.append(f"file ends at byte {offset} without a footer")
                    return
                if len(head) < 9:
                    self._truncated(offset, size, "inside a record header")
                    return
                op, ln = _REC_HEAD.unpack(head)
                if ln > size - offset - 9:
                    self._truncated(offset, size, f"inside a record (opcode 0x{op:02x})")
                    return
                body = f.read(ln)
                offset += 9 + ln
                self.offset = offset
                try:
                    if op == _OP_CHUNK:
                        try:
                            batch = self._chunk_messages(body, topics)
                        except Exception as exc:  # zstd/lz4/struct errors: skip chunk
                            self.damage.bad_chunks += 1
                            self.damage.notes.append(
                                f"chunk at byte {offset - 9 - ln} skipped: {exc}"
                            )
                            continue
                        if batch:
                            yield batch
                    elif op == _OP_MESSAGE:
                        cid, seq, log_t, pub_t = _MSG_HEAD.unpack_from(body, 0)
                        ch = self.channels.get(cid)
                        if ch is None:
                            self.damage.messages_without_channel += 1
                        elif topics is None or ch.topic in topics:
                            yield [RawMessage(ch.topic, cid, seq, log_t, pub_t, body[22:])]
                    elif op == _OP_SCHEMA:
                        self._add_schema(body)
                    elif op == _OP_CHANNEL:
                        self._add_channel(body)
                    elif op == _OP_METADATA:
                        name, p = _str(body, 0)
                        meta, p = _map(body, p)
                        self.metadata.append(Metadata(name=name, metadata=meta))
                    elif op == _OP_ATTACHMENT:
                        self.attachments.append(_attachment(body))
                    elif op == _OP_HEADER:
                        self.header_profile, p = _str(body, 0)
                        self.header_library, _ = _str(body, p)
                    elif op == _OP_STATISTICS:
                        self.statistics = _statistics(body)
                    elif op == _OP_FOOTER:
                        tail = f.read(8)
                        if tail != MCAP_MAGIC:
                            self.damage.truncated = True
                            self.damage.notes.append("footer not followed by the MCAP magic")
                        else:
                            self.complete = True
                        return
                except (struct.error, UnicodeDecodeError, ValueError) as exc:
                    self.damage.bad_records += 1
                    self.damage.notes.append(
                        f"record opcode 0x{op:02x} at byte {offset - 9 - ln} skipped: {exc}"
                    )

    def _truncated(self, offset: int, size: int, where: str) -> None:
        self.damage.truncated = True
        self.damage.unread_bytes = size - offset
        self.damage.notes.append(
            f"file truncated {where} at byte {offset}: last {size - offset} bytes unreadable"
        )

    def messages(self, topics: set[str] | None = None) -> Iterator[RawMessage]:
        """Messages in file order (receive order for our recorder); see :meth:`iter_batches`."""
        for batch in self.iter_batches(topics):
            yield from batch

    def schema_of(self, channel_id: int) -> Schema | None:
        ch = self.channels.get(channel_id)
        return None if ch is None else self.schemas.get(ch.schema_id)


def _str(buf, pos: int) -> tuple[str, int]:
    n = _U32.unpack_from(buf, pos)[0]
    pos += 4
    if pos + n > len(buf):
        raise ValueError("string runs past the record")
    return bytes(buf[pos : pos + n]).decode("utf-8"), pos + n


def _map(buf, pos: int) -> tuple[dict[str, str], int]:
    n = _U32.unpack_from(buf, pos)[0]
    pos += 4
    end = pos + n
    out: dict[str, str] = {}
    while pos < end:
        k, pos = _str(buf, pos)
        v, pos = _str(buf, pos)
        out[k] = v
    return out, pos


def _attachment(body: bytes) -> Attachment:
    log_t, create_t = struct.unpack_from("<QQ", body, 0)
    name, p = _str(body, 16)
    media, p = _str(body, p)
    n = _U64.unpack_from(body, p)[0]
    p += 8
    return Attachment(
        log_time=log_t,
        create_time=create_t,
        name=name,
        media_type=media,
        data=bytes(body[p : p + n]),
    )


def _statistics(body: bytes):
    import io

    from mcap.data_stream import ReadDataStream
    from mcap.records import Statistics

    return Statistics.read(ReadDataStream(io.BytesIO(body)))


# ----------------------------------------------------------------------------------------
# recover
# ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RecoverReport:
    """Outcome of :func:`recover`.

    Attributes
    ----------
    messages : int
        Messages copied to the new file.
    channels, schemas, metadata, attachments : int
    damage : Damage
        What could not be read from the input.
    was_complete : bool
        The input already had a footer (recovery was a plain re-index/copy).
    """

    messages: int
    channels: int
    schemas: int
    metadata: int
    attachments: int
    damage: Damage
    was_complete: bool


def recover(
    src: str | os.PathLike[str],
    dst: str | os.PathLike[str],
    *,
    compression: str = "zstd",
    progress: Callable[[int], None] | None = None,
) -> RecoverReport:
    """Rewrite a truncated or damaged MCAP file into a valid, indexed one.

    Every complete chunk (with its schemas and channels), loose message, metadata and
    attachment record is copied in file order; an incomplete last record and chunks failing
    their CRC are dropped and counted.

    Parameters
    ----------
    src, dst : path
        Input and output (must differ).
    compression : {"zstd", "lz4", "none"}
    progress : callable, optional
        Called with the number of messages copied so far after each chunk.

    Raises
    ------
    RecordingError
        ``src`` missing / not MCAP, or ``src`` and ``dst`` are the same file.
    """
    src, dst = Path(src), Path(dst)
    if dst.exists() and src.exists() and os.path.samefile(src, dst):
        raise RecordingError(
            "recover writes a new file: give an output path different from the input"
        )
    scanner = McapScanner(src)
    comp = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[
        compression
    ]
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_name(dst.name + ".partial")
    n_msgs = 0
    with open(tmp, "wb") as f:
        w = Writer(f, compression=comp)
        started = False
        schema_map: dict[int, int] = {}
        channel_map: dict[int, int] = {}
        n_meta = n_att = 0

        def ensure_started() -> None:
            nonlocal started
            if not started:
                w.start(
                    profile=scanner.header_profile,
                    library=scanner.header_library or "diffpos-recover",
                )
                started = True

        def map_channel(cid: int) -> int:
            new = channel_map.get(cid)
            if new is None:
                ch = scanner.channels[cid]
                sid = 0
                if ch.schema_id:
                    sid = schema_map.get(ch.schema_id, 0)
                    sch = scanner.schemas.get(ch.schema_id)
                    if sid == 0 and sch is not None:
                        sid = w.register_schema(sch.name, sch.encoding, sch.data)
                        schema_map[ch.schema_id] = sid
                new = w.register_channel(ch.topic, ch.message_encoding, sid, ch.metadata)
                channel_map[cid] = new
            return new

        for batch in scanner.iter_batches():
            ensure_started()
            for m in batch:
                w.add_message(
                    map_channel(m.channel_id),
                    log_time=m.log_ns,
                    data=m.data,
                    publish_time=m.publish_ns,
                    sequence=m.sequence,
                )
            n_msgs += len(batch)
            # metadata / attachments seen so far are written as they come
            while n_meta < len(scanner.metadata):
                md = scanner.metadata[n_meta]
                w.add_metadata(md.name, md.metadata)
                n_meta += 1
            while n_att < len(scanner.attachments):
                a = scanner.attachments[n_att]
                w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
                n_att += 1
            if progress is not None:
                progress(n_msgs)
        ensure_started()
        for md in scanner.metadata[n_meta:]:
            w.add_metadata(md.name, md.metadata)
        for a in scanner.attachments[n_att:]:
            w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        if not scanner.complete and not any(m.name == "recovery" for m in scanner.metadata):
            w.add_metadata(
                "recovery",
                {
                    "source": src.name,
                    "truncated": json.dumps(scanner.damage.truncated),
                    "bad_chunks": str(scanner.damage.bad_chunks),
                    "unread_bytes": str(scanner.damage.unread_bytes),
                    "messages": str(n_msgs),
                },
            )
        w.finish()
    os.replace(tmp, dst)
    return RecoverReport(
        messages=n_msgs,
        channels=len(channel_map),
        schemas=len(schema_map),
        metadata=len(scanner.metadata),
        attachments=len(scanner.attachments),
        damage=scanner.damage,
        was_complete=scanner.complete,
    )


# ----------------------------------------------------------------------------------------
# summary (diffpos inspect)
# ----------------------------------------------------------------------------------------


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


@functools.lru_cache(maxsize=1 << 16)
def _natural(s: str) -> tuple:
    """Natural sort key (``n2`` < ``n10``); cached: replay sorts by node id per estimate."""
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s))


def summarize(path: str | os.PathLike[str]) -> RecordingSummary:
    """Scan a recording (complete or truncated) and summarise it; see :class:`RecordingSummary`."""
    sc = McapScanner(path)
    counts: dict[int, int] = {}
    first: dict[int, int] = {}
    last: dict[int, int] = {}
    seq = SeqTracker()
    live: list[dict[str, Any]] = []
    for batch in sc.iter_batches():
        for m in batch:
            cid = m.channel_id
            c = counts.get(cid, 0)
            counts[cid] = c + 1
            if c == 0:
                first[cid] = m.log_ns
                last[cid] = m.log_ns
            else:
                first[cid] = min(first[cid], m.log_ns)
                last[cid] = max(last[cid], m.log_ns)
            seq.add(m.topic, m.sequence)
            if m.topic.endswith("/recorder/liveliness") and len(live) < 10000:
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
    chans.sort(key=lambda c: _natural(c.topic))
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
        anchors=sorted(anchors, key=_natural),
        nodes=sorted(nodes, key=_natural),
        liveliness=live,
        metadata={m.name: dict(m.metadata) for m in sc.metadata},
        attachments=[(a.name, a.media_type, len(a.data)) for a in sc.attachments],
        damage=sc.damage,
        gaps=dict(sorted(seq.gaps.items())),
        out_of_order=dict(sorted(seq.out_of_order.items())),
    )
