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

__all__ = ["COMPRESSION", "McapSink", "SinkStats"]

#: ``compression`` option -> MCAP chunk compression
COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}


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
        comp = COMPRESSION.get(compression)
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
        create_ns: int | None = None,
    ) -> None:
        """MCAP attachment (e.g. the scenario TOML), written immediately."""
        t = time.time_ns() if log_ns is None else int(log_ns)
        c = t if create_ns is None else int(create_ns)
        with self._lock:
            self._writer.add_attachment(
                create_time=c, log_time=t, name=name, media_type=media_type, data=bytes(data)
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
