"""Writing recordings: :class:`McapSink` (pure Python, no Zenoh).

:class:`McapSink` writes ``(key, payload, receive_ns)`` tuples to an MCAP file: one channel
per key expression, schema encoding ``jsonschema``, message encoding ``json`` (Foxglove opens
it), ``log_time`` = receive time, ``publish_time`` = the message's own measurement time,
sequence numbers kept, zstd chunks. Counts received vs written and gaps in sequence numbers.
The recorder service is a thin Zenoh wrapper around it. All times are integer nanoseconds
since the Unix epoch.
"""

from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec
from mcap.writer import CompressionType, Writer

from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.schemas import (
    MESSAGE_ENCODING,
    SCHEMA_ENCODING,
    SchemaEntry,
    SchemaRegistry,
)
from diffpos_services.recording.topics import SeqTracker
from diffpos_services.wire.keys import Keys

__all__ = ["COMPRESSION", "McapSink", "SinkStats", "SplitPolicy", "existing_parts", "part_path",
           "recording_set", "restart_path"]

#: ``compression`` option -> MCAP chunk compression
COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}


@dataclass(frozen=True)
class SplitPolicy:
    """When :class:`McapSink` starts a new file (checked at each :meth:`McapSink.flush`).

    The mcap writer keeps an index entry per chunk and channel in memory until the file is
    finished (~35 kB per chunk with ~500 channels: +10 MB per minute at 5 flushes/s);
    finishing the file every ``max_bytes`` / ``max_duration_s`` bounds that memory, like
    rosbag2's ``--max-bag-size`` / ``--max-bag-duration``. Every part is a complete,
    indexed MCAP file with the recording's metadata and attachments.

    Attributes
    ----------
    max_bytes : int or None [bytes]
        Start a new part once the current one is this large (``None``: no size limit).
    max_duration_s : float or None [s]
        Start a new part once the current one spans this much receive time.
    """

    max_bytes: int | None = None
    max_duration_s: float | None = None

    def __post_init__(self) -> None:
        if self.max_bytes is not None and self.max_bytes <= 0:
            raise ValueError(f"split size {self.max_bytes} must be > 0 [bytes]")
        if self.max_duration_s is not None and not self.max_duration_s > 0:
            raise ValueError(f"split duration {self.max_duration_s} must be > 0 [s]")

    @property
    def active(self) -> bool:
        return self.max_bytes is not None or self.max_duration_s is not None


def part_path(first: str | os.PathLike[str], index: int) -> Path:
    """Path of part ``index`` of a split recording: part 0 is ``first`` itself (what the
    recorder was told to write, so whoever waits for that file finds it), part k > 0 is
    ``<stem>_<k:04d>.mcap`` next to it."""
    first = Path(first)
    return first if index == 0 else first.with_name(f"{first.stem}_{index:04d}{first.suffix}")


def existing_parts(first: str | os.PathLike[str]) -> list[Path]:
    """The parts of a split recording that exist on disk, in order (:func:`part_path` 0, 1,
    ... up to the first missing one); empty if not even ``first`` was written."""
    parts = []
    while (p := part_path(first, len(parts))).exists():
        parts.append(p)
    return parts


def restart_path(first: str | os.PathLike[str], k: int) -> Path:
    """The file of a recording's ``k``-th restart (``diffpos emulate`` restarts a dead
    recorder onto ``<stem>-restart<k>.mcap`` next to the first file)."""
    first = Path(first)
    return first.with_name(f"{first.stem}-restart{k}{first.suffix}")


def recording_set(first: str | os.PathLike[str]) -> list[Path]:
    """Every file of one run's recording, in order: the first file's split parts, then each
    restart's (:func:`restart_path` 1, 2, ... up to the first missing one) with its parts.
    Sequence numbers run on across them, so a loss is counted across the set."""
    out = list(existing_parts(first))
    k = 1
    while (parts := existing_parts(restart_path(first, k))):
        out += parts
        k += 1
    return out


class _Stamp(msgspec.Struct):
    """The two fields the sink reads from every payload (everything else is ignored)."""

    t_ns: int | None = None
    seq: int | None = None


class _Tag(msgspec.Struct):
    """The ``schema`` tag of a payload (read once per channel, at registration)."""

    schema: Any = None


_TAG_DECODER = msgspec.json.Decoder(_Tag)


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
    split : SplitPolicy, optional
        Start a new file (see :func:`part_path`) when the current one is too large or too
        long (needs a path ``output``). Metadata and attachments added before are repeated in
        every part; sequence gaps and counters span the parts.

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
        split: SplitPolicy | None = None,
    ) -> None:
        comp = COMPRESSION.get(compression)
        if comp is None:
            raise RecordingError(f"compression must be zstd, lz4 or none, not {compression!r}")
        self.registry = registry if registry is not None else SchemaRegistry()
        self._writer_args = {"chunk_size": chunk_size, "compression": comp}
        self._header = {"profile": profile, "library": library}
        self.split = split if split is not None and split.active else None
        self.path: Path | None = None
        self.parts: list[Path] = []
        self._side: list[tuple[str, tuple]] = []  # metadata / attachments, for every part
        self._part_first_ns: int | None = None
        self._part_last_ns = 0
        self._part_written = 0
        self._part_done = False  # the current part is full: next message opens a new one
        if isinstance(output, (str, os.PathLike)):
            self.path = Path(output)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._own_file = True
            self._open_part(self.path)
        else:
            if self.split is not None:
                raise RecordingError("splitting a recording needs a file path, not a stream")
            self._file: IO[bytes] = output
            self._own_file = False
            self._start_writer()
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
        self.seq = SeqTracker()
        self._unknown_keys: set[str] = set()
        self._alive: dict[str, bool] = {}
        self._pending = 0
        self._lock = threading.Lock()
        self._closed = False
        self.stats = SinkStats()

    # -- parts ----------------------------------------------------------------------------

    def _start_writer(self) -> None:
        self._writer = Writer(self._file, **self._writer_args)
        self._writer.start(**self._header)
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[str, int] = {}

    def _open_part(self, path: Path) -> None:
        self._file = open(path, "wb")
        self.parts.append(path)
        self._start_writer()
        for what, args in self._side:  # the recording's metadata and attachments, again
            if what == "metadata":
                self._writer.add_metadata(*args)
            else:
                self._writer.add_attachment(*args)
        self._part_first_ns, self._part_written = None, 0

    def _part_full(self) -> bool:
        sp = self.split
        if sp is None or self._part_written == 0:
            return False
        if sp.max_bytes is not None and self._file.tell() >= sp.max_bytes:
            return True
        return (sp.max_duration_s is not None and self._part_first_ns is not None
                and self._part_last_ns - self._part_first_ns >= sp.max_duration_s * 1e9)

    def _next_part(self) -> None:
        """Finish the current (full) part, complete and indexed, and open the next one; called
        before the first message after the part filled up (so no part is empty)."""
        self._part_done = False
        index = len(self.parts)
        self._writer.add_metadata("part", {
            "index": str(index - 1), "messages": str(self._part_written),
            "next": part_path(self.parts[0], index).name,
        })
        self._writer.finish()
        self._file.close()
        self._open_part(part_path(self.parts[0], index))

    # -- channels -------------------------------------------------------------------------

    def _schema_id(self, entry: SchemaEntry | None) -> int:
        if entry is None:
            return 0
        sid = self._schema_ids.get(entry.name)
        if sid is None:
            sid = self._writer.register_schema(entry.name, SCHEMA_ENCODING, entry.data)
            self._schema_ids[entry.name] = sid
        return sid

    def channel(self, key: str, tag: str | None = None) -> int:
        """Channel id of ``key`` (registered on first use with its schema: the version the
        first message's ``schema`` tag names, else the newest)."""
        cid = self._channels.get(key)
        if cid is None:
            entry = self.registry.for_key(key, tag)
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
        if self._part_done:
            self._next_part()
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
            cid = self.channel(key, self._tag(payload))
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
        self._part_written += 1
        if self._part_first_ns is None:
            self._part_first_ns = int(receive_ns)
        self._part_last_ns = int(receive_ns)

    @staticmethod
    def _tag(payload: bytes) -> str | None:
        try:
            tag = _TAG_DECODER.decode(payload).schema
        except (msgspec.DecodeError, msgspec.ValidationError):
            return None
        return tag if isinstance(tag, str) else None

    def write_liveliness(self, site: str, key: str, alive: bool, receive_ns: int) -> bool:
        """Record a liveliness token appearing (``alive``) or disappearing.

        Only changes are recorded: a liveliness subscriber with history may report a token
        twice (from the history query and live), the repeat is dropped.

        Parameters
        ----------
        site : str
            Site name (the event goes to :meth:`Keys.recorder_liveliness` of it).
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
        topic = Keys(site).recorder_liveliness()
        with self._lock:
            if self._alive.get(key) == bool(alive):
                return False
            self._alive[key] = bool(alive)
            self.stats.liveliness_events += 1
            if self._part_done:
                self._next_part()
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
            self._side.append(("metadata", (name, clean)))

    def add_attachment(
        self,
        name: str,
        data: bytes,
        *,
        media_type: str = "application/octet-stream",
        log_ns: int | None = None,
        create_ns: int | None = None,
    ) -> None:
        """MCAP attachment (e.g. the scenario TOML), written immediately."""
        t = time.time_ns() if log_ns is None else int(log_ns)
        c = t if create_ns is None else int(create_ns)
        with self._lock:
            args = (c, t, name, media_type, bytes(data))
            self._writer.add_attachment(*args)
            self._side.append(("attachment", args))
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
            if self._part_full():
                self._part_done = True
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
            if self.split is not None:
                self._writer.add_metadata("part", {"index": str(len(self.parts) - 1),
                                                   "messages": str(self._part_written), "next": ""})
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
