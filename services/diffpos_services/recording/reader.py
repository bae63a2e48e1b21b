"""Reading recordings: :class:`McapScanner` and decoding (pure Python, no Zenoh).

* :class:`McapScanner` - a sequential, damage-tolerant reader: works on complete files and on
  truncated ones (no footer, e.g. after SIGKILL), skips chunks that fail their CRC, resyncs
  past a record whose length field is corrupt (the next chunk that decompresses and passes
  its CRC), and parses chunk contents with ``struct`` directly (several times faster than
  ``mcap``'s record objects, which matters for replay). Every damage it meets is counted in
  :class:`Damage` AND logged as a WARNING of the ``diffpos.recording`` logger naming the file
  and byte, so every reader (replay, to-rerun, inspect, recover, the dashboard) says so.
  Channels whose topic looks like ours but that are not diffpos channels (not ``json`` with a
  ``diffpos.*`` JSON Schema: another tool's protobuf, CDR or schema-less JSON) are skipped and
  counted; a file with no diffpos channel but such look-alikes is refused
  (:class:`ForeignRecordingError`, one line, exit code 1).
* :class:`JsonDecoderFactory` - lets ``mcap.reader.make_reader`` decode our JSON channels.
"""

from __future__ import annotations

import io
import json
import logging
import os
import re
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import lz4.frame
import msgspec
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.decoder import DecoderFactory
from mcap.records import Attachment, Metadata, Schema, Statistics

from diffpos_services.recording.errors import ForeignRecordingError, RecordingError
from diffpos_services.recording.schemas import MESSAGE_ENCODING
from diffpos_services.recording.topics import parse_topic
from diffpos_services.recording.writer import existing_parts

__all__ = [
    "MCAP_MAGIC",
    "ChannelInfo",
    "Damage",
    "JsonDecoderFactory",
    "McapScanner",
    "PartsScanner",
    "RawMessage",
    "SideRecords",
    "is_diffpos_channel",
    "side_records",
]

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

_LOG = logging.getLogger("diffpos.recording")
#: damage notes logged per file (the rest are counted in Damage.notes only)
_MAX_LOGGED_NOTES = 10
#: a chunk record's start as found when resyncing: opcode 0x06, then 36 bytes (length,
#: start/end time, uncompressed size, CRC), then the compression string
_CHUNK_START_RE = re.compile(
    rb"\x06(?=.{36}(?:\x04\x00\x00\x00zstd|\x03\x00\x00\x00lz4|\x00\x00\x00\x00))", re.S)
_RESYNC_WINDOW = 4 << 20

_REC_HEAD = struct.Struct("<BQ")
_MSG_HEAD = struct.Struct("<HIQQ")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")


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
    skipped_bytes : int [bytes]
        Bytes passed over to resync after a record with a corrupt length or opcode (the
        records in them are lost; the reading went on at the next readable chunk).
    foreign_messages : int
        Messages on channels whose topic looks like a diffpos key but that are not diffpos
        channels (skipped; see :func:`is_diffpos_channel`).
    notes : list of str
        Human-readable details.
    """

    truncated: bool = False
    bad_chunks: int = 0
    bad_records: int = 0
    unread_bytes: int = 0
    messages_without_channel: int = 0
    skipped_bytes: int = 0
    foreign_messages: int = 0
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not (
            self.truncated or self.bad_chunks or self.bad_records or self.messages_without_channel
            or self.skipped_bytes or self.foreign_messages
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
    accept_foreign : bool
        Read a file whose diffpos-looking channels are all another tool's (``diffpos
        recover`` copies any MCAP); by default :meth:`iter_batches` refuses it at the end.

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
    foreign : dict[int, str]
        Channel id -> why it is not a diffpos channel, for channels whose topic looks like a
        diffpos key (their messages are skipped and counted in :attr:`damage`).

    Raises
    ------
    RecordingError
        The file does not exist, or is not MCAP at all (bad magic).
    """

    def __init__(self, path: str | os.PathLike[str], *, validate_crcs: bool = True,
                 accept_foreign: bool = False) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError(f"recording {self.path} does not exist (or is not a file)")
        with open(self.path, "rb") as f:
            head = f.read(8)
        if not head:
            raise ForeignRecordingError(f"{self.path} is empty (0 bytes): not a recording")
        if head != MCAP_MAGIC:
            raise ForeignRecordingError(
                f"{self.path} is not an MCAP file (it does not start with the MCAP magic bytes)"
            )
        self.validate_crcs = validate_crcs
        self.accept_foreign = accept_foreign
        self.foreign: dict[int, str] = {}
        self.ours_read = False  # a message of a diffpos channel was read
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
            why = _not_ours(self.channels[cid], self.schemas.get(sid))
            if why is not None and not self.accept_foreign:
                self.foreign[cid] = why

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
            data = zstandard.ZstdDecompressor().decompress(comp_data, max_output_size=usize)
        elif comp == "lz4":
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
        n = len(data)
        p = 0
        unpack_head = _REC_HEAD.unpack_from
        unpack_msg = _MSG_HEAD.unpack_from
        topics = self._readable_topics()
        foreign = self.foreign
        while p < n:
            op, ln = unpack_head(data, p)
            b = p + 9
            p = b + ln
            if op == _OP_MESSAGE:
                cid, seq, log_t, pub_t = unpack_msg(data, b)
                topic = topics.get(cid)
                if topic is None:
                    if cid in foreign:
                        self.damage.foreign_messages += 1
                    else:
                        self.damage.messages_without_channel += 1
                    continue
                if topic_filter is not None and topic not in topic_filter:
                    continue
                append(RawMessage(topic, cid, seq, log_t, pub_t, data[b + 22 : p]))
            elif op == _OP_CHANNEL:
                self._add_channel(data, b)
                topics = self._readable_topics()
            elif op == _OP_SCHEMA:
                self._add_schema(data, b)
        if p != n:
            raise ValueError("chunk records overrun the chunk")
        if out:
            self.ours_read = True
        return out

    def _readable_topics(self) -> dict[int, str]:
        return {c.id: c.topic for c in self.channels.values() if c.id not in self.foreign}

    def iter_batches(self, topics: set[str] | None = None) -> Iterator[list[RawMessage]]:
        """Messages in file order, one list per chunk (or per loose message).

        Parameters
        ----------
        topics : set of str, optional
            Only these topics; ``None``: all.

        Yields
        ------
        batch : list of RawMessage

        Raises
        ------
        ForeignRecordingError
            At the end of the file, when it held no diffpos channel but channels that only
            look like ours (unless ``accept_foreign``).
        """
        size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            f.read(8)
            offset = 8
            while True:
                head = f.read(9)
                if len(head) == 0:
                    self.damage.truncated = True
                    self._note(f"file ends at byte {offset} without a footer")
                    break
                op, ln = _REC_HEAD.unpack(head) if len(head) == 9 else (-1, 0)
                if op == _OP_CHUNK and ln > size - offset - 9:  # its contents may say better
                    own = _chunk_own_length(f.read(64))
                    f.seek(offset + 9)
                    if own is not None and own <= size - offset - 9:  # the CRC check decides
                        self.damage.bad_records += 1
                        self._note(f"chunk at byte {offset}: record length field {ln} runs "
                                   f"past the end; read by its contents ({own} bytes)")
                        ln = own
                if len(head) < 9 or ln > size - offset - 9 or not _known_opcode(op):
                    what = ("a record header cut short" if len(head) < 9 else
                            f"opcode 0x{op:02x}" if not _known_opcode(op) else
                            f"a record (opcode 0x{op:02x}) of {ln} bytes, past the end")
                    offset = self._resync(f, offset, size, what)
                    if offset is None:
                        break
                    continue
                body = f.read(ln)
                offset += 9 + ln
                self.offset = offset
                if op == _OP_CHUNK:
                    own = _chunk_own_length(body)
                    if own != ln and own is not None and own <= size - (offset - ln):
                        # the length field disagrees with the chunk's own records length:
                        # read the chunk by its contents (its CRC decides below)
                        self.damage.bad_records += 1
                        self._note(f"chunk at byte {offset - 9 - ln}: record length field "
                                   f"{ln} disagrees with its contents ({own} bytes): read "
                                   "by its contents")
                        f.seek(offset - ln)
                        body = f.read(own)
                        offset, ln = offset - ln + own, own
                        self.offset = offset
                    try:
                        batch = self._chunk_messages(body, topics)
                    except Exception as exc:  # zstd/lz4/struct errors, CRC: skip the chunk
                        self.damage.bad_chunks += 1
                        self._note(f"chunk at byte {offset - 9 - ln} skipped: {exc}")
                        if not self._plausible_next(f, offset, size):  # its length is bad too
                            offset = self._resync(f, offset - 9 - ln + 1, size,
                                                  "the record after a corrupt chunk")
                            if offset is None:
                                break
                        continue
                    if batch:
                        yield batch
                    continue
                if op == _OP_FOOTER:
                    if f.read(8) != MCAP_MAGIC:
                        self.damage.truncated = True
                        self._note("footer not followed by the MCAP magic")
                    else:
                        self.complete = True
                    break
                batch = self._top_record(op, body, offset - 9 - ln, topics)
                if batch:
                    yield batch
        self._check_ours()

    def _top_record(self, op: int, body: bytes, at: int,
                    topics: set[str] | None) -> list[RawMessage] | None:
        """A record outside chunks: a loose message (returned) or a side record (kept)."""
        try:
            if op == _OP_MESSAGE:
                cid, seq, log_t, pub_t = _MSG_HEAD.unpack_from(body, 0)
                ch = self.channels.get(cid)
                if ch is None:
                    self.damage.messages_without_channel += 1
                elif cid in self.foreign:
                    self.damage.foreign_messages += 1
                elif topics is None or ch.topic in topics:
                    self.ours_read = True
                    return [RawMessage(ch.topic, cid, seq, log_t, pub_t, body[22:])]
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
        except (struct.error, UnicodeDecodeError, ValueError) as exc:
            self.damage.bad_records += 1
            self._note(f"record opcode 0x{op:02x} at byte {at} skipped: {exc}")
        return None

    def _plausible_next(self, f, offset: int, size: int) -> bool:
        """The bytes at ``offset`` start a record (or the file ends there)."""
        if offset == size:
            return True
        head = f.read(9)
        f.seek(offset)
        if len(head) < 9:
            return False
        op, ln = _REC_HEAD.unpack(head)
        return _known_opcode(op) and ln <= size - offset - 9

    def _resync(self, f, offset: int, size: int, what: str) -> int | None:
        """Find the next chunk that reads (decompresses, passes its CRC) at or after
        ``offset``; position ``f`` there and return its offset, or None (then the rest of
        the file is unreadable: counted as truncated)."""
        start = offset
        pos = offset
        while pos < size:
            f.seek(pos)
            window = f.read(_RESYNC_WINDOW + 64)
            for m in _CHUNK_START_RE.finditer(window):
                cand = pos + m.start()
                if cand < start or not self._chunk_reads(f, cand, size):
                    continue
                self.damage.bad_records += 1
                self.damage.skipped_bytes += cand - start
                self._note(f"{what} at byte {start}: resynced at the next readable chunk, "
                           f"byte {cand} ({cand - start} bytes skipped)")
                f.seek(cand)
                self.offset = cand
                return cand
            pos += _RESYNC_WINDOW
        self.damage.truncated = True
        self.damage.unread_bytes = size - start
        self._note(f"file unreadable from byte {start} ({what}): last {size - start} bytes "
                   "hold no readable chunk")
        self.offset = size
        return None

    def _chunk_reads(self, f, at: int, size: int) -> bool:
        f.seek(at)
        op, ln = _REC_HEAD.unpack(f.read(9))
        if op != _OP_CHUNK or ln > size - at - 9 or ln < 40:
            return False
        body = f.read(ln)
        seen = self.damage.messages_without_channel
        try:
            self._chunk_messages(body, set())  # registers its channels; no message copied
        except Exception:
            return False
        finally:
            self.damage.messages_without_channel = seen
        return True

    def _note(self, text: str) -> None:
        """Record a damage note and log it (the first :data:`_MAX_LOGGED_NOTES` per file)."""
        self.damage.notes.append(text)
        n = len(self.damage.notes)
        if n <= _MAX_LOGGED_NOTES:
            _LOG.warning("%s: %s", self.path, text)
        elif n == _MAX_LOGGED_NOTES + 1:
            _LOG.warning("%s: further damage only counted (diffpos inspect lists it)", self.path)

    def _check_ours(self) -> None:
        """Refuse a file whose only diffpos-looking channels are not diffpos channels."""
        if not self.foreign:
            return
        ch = self.channels[next(iter(self.foreign))]
        why = self.foreign[ch.id]
        if self.ours_read or self.accept_foreign or any(
                cid not in self.foreign and parse_topic(c.topic)[0] != "unknown"
                for cid, c in self.channels.items()):
            self._note(f"{self.damage.foreign_messages} messages on {len(self.foreign)} "
                       f"channels that are not diffpos channels skipped (e.g. {ch.topic}: {why})")
            return
        raise ForeignRecordingError(
            f"{self.path} is not a diffpos recording: its {len(self.foreign)} channels with "
            f"diffpos-looking topics are another tool's (e.g. {ch.topic}: {why}; diffpos "
            "channels are json with a diffpos.* JSON Schema)")

    def messages(self, topics: set[str] | None = None) -> Iterator[RawMessage]:
        """Messages in file order (receive order for our recorder); see :meth:`iter_batches`."""
        for batch in self.iter_batches(topics):
            yield from batch

    def schema_of(self, channel_id: int) -> Schema | None:
        ch = self.channels.get(channel_id)
        return None if ch is None else self.schemas.get(ch.schema_id)


class PartsScanner:
    """The parts of a split recording (``r.mcap``, ``r_0001.mcap``, ...: the recorder's
    ``--split-size`` / ``--split-duration``, see :func:`..writer.existing_parts`) read as one,
    in order, with :class:`McapScanner`'s interface. Channel ids restart in every part: a
    :class:`RawMessage`'s ``channel_id`` is its part's; use the topic across parts.

    Attributes
    ----------
    parts : list of McapScanner
    """

    def __init__(self, first: str | os.PathLike[str], *, validate_crcs: bool = True,
                 accept_foreign: bool = False) -> None:
        paths = existing_parts(first) or [Path(first)]
        self.parts = [McapScanner(p, validate_crcs=validate_crcs, accept_foreign=accept_foreign)
                      for p in paths]
        self.path = self.parts[0].path
        self.size_bytes = sum(p.size_bytes for p in self.parts)
        self._done_bytes = 0
        self._current = self.parts[0]

    def __getattr__(self, name: str):  # metadata, attachments, header, schemas: part 0's
        if name in ("metadata", "attachments", "header_library", "header_profile",
                    "statistics", "schemas", "validate_crcs"):
            return getattr(self.parts[0], name)
        raise AttributeError(name)

    @property
    def offset(self) -> int:
        return self._done_bytes + self._current.offset

    @property
    def channels(self) -> dict[tuple[int, int], ChannelInfo]:
        """Every part's channels, keyed by (part index, channel id)."""
        return {(i, cid): ch for i, p in enumerate(self.parts) for cid, ch in p.channels.items()}

    @property
    def complete(self) -> bool:
        return all(p.complete for p in self.parts)

    @property
    def damage(self) -> Damage:
        out = Damage()
        for p in self.parts:
            d = p.damage
            out.truncated |= d.truncated
            out.bad_chunks += d.bad_chunks
            out.bad_records += d.bad_records
            out.unread_bytes += d.unread_bytes
            out.messages_without_channel += d.messages_without_channel
            out.skipped_bytes += d.skipped_bytes
            out.foreign_messages += d.foreign_messages
            out.notes += [f"{p.path.name}: {n}" for n in d.notes]
        return out

    def iter_batches(self, topics: set[str] | None = None) -> Iterator[list[RawMessage]]:
        """:meth:`McapScanner.iter_batches` over every part in turn."""
        for p in self.parts:
            self._current = p
            yield from p.iter_batches(topics)
            self._done_bytes += p.size_bytes
        self._current = McapScanner.__new__(McapScanner)
        self._current.offset = 0

    def messages(self, topics: set[str] | None = None) -> Iterator[RawMessage]:
        for batch in self.iter_batches(topics):
            yield from batch


def _chunk_own_length(body: bytes) -> int | None:
    """A chunk record's length by its contents (start, end, size, CRC, compression string,
    records length, records), or None when the body is too short to say."""
    try:
        n = _U32.unpack_from(body, 28)[0]
        return 40 + n + _U64.unpack_from(body, 32 + n)[0]
    except struct.error:
        return None


def _known_opcode(op: int) -> bool:
    """An MCAP opcode (0x01-0x0F) or a user one (0x80-0xFF); 0x00 and 0x10-0x7F are reserved:
    met where a record should start, they mean the bytes are not a record boundary."""
    return 0x01 <= op <= 0x0F or op >= 0x80


def is_diffpos_channel(channel: ChannelInfo, schema: Schema | None) -> bool:
    """A channel diffpos wrote: ``json`` messages with a ``diffpos.*`` JSON Schema (every
    channel of the recorder and of ``diffpos replay``), or a topic that is not a diffpos key
    at all (then it is simply not ours to read, nothing to refuse)."""
    return _not_ours(channel, schema) is None


def _not_ours(channel: ChannelInfo, schema: Schema | None) -> str | None:
    if parse_topic(channel.topic)[0] == "unknown":
        return None
    if channel.message_encoding != MESSAGE_ENCODING:
        return f"message encoding {channel.message_encoding!r}"
    if schema is None or not schema.name.startswith("diffpos."):
        return "no JSON Schema" if schema is None else f"schema {schema.name!r}"
    return None


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


def _statistics(body: bytes) -> Statistics:
    return Statistics.read(ReadDataStream(io.BytesIO(body)))


# -- metadata and attachments anywhere in the file ---------------------------------------

_OP_ATTACHMENT_INDEX = 0x0A
_OP_METADATA_INDEX = 0x0D
_FOOTER = struct.Struct("<BQQQI")  # opcode, length (20), summary_start, summary_offset_start, crc


@dataclass
class SideRecords:
    """The metadata and attachment records of a file, wherever they are.

    Attributes
    ----------
    metadata : list of mcap.records.Metadata
    attachments : list of mcap.records.Attachment
    source : str
        ``"summary index"`` (read through the summary section's metadata / attachment
        indexes) or ``"scan"`` (every top-level record visited, chunks skipped unread).
    """

    metadata: list[Metadata] = field(default_factory=list)
    attachments: list[Attachment] = field(default_factory=list)
    source: str = "scan"


def side_records(path: str | os.PathLike[str]) -> SideRecords:
    """Every metadata and attachment record of an MCAP file, before reading any message.

    Writers put metadata anywhere in the data section: our recorder before the first chunk,
    the standard ``mcap`` writer and ``diffpos replay --write-mcap`` wherever it was added
    (often after the chunks). A complete file is read through its summary section's
    metadata and attachment indexes (a few seeks); a file without them, or a truncated one,
    is scanned record by record, seeking over chunks without decompressing them.

    Raises
    ------
    RecordingError
        Missing or not MCAP (see :class:`McapScanner`).
    """
    McapScanner(path)  # existence and magic checks with their messages
    with open(path, "rb") as f:
        out = _side_records_from_summary(f)
        if out is None:
            out = _side_records_by_scan(f)
    return out


def _read_record(f, offset: int) -> tuple[int, bytes]:
    f.seek(offset)
    head = f.read(9)
    if len(head) < 9:
        raise ValueError("record header past the end of the file")
    op, ln = _REC_HEAD.unpack(head)
    body = f.read(ln)
    if len(body) < ln:
        raise ValueError("record past the end of the file")
    return op, body


def _side_records_from_summary(f) -> SideRecords | None:
    size = f.seek(0, os.SEEK_END)
    if size < 8 + _FOOTER.size + 8:
        return None
    f.seek(size - 8 - _FOOTER.size)
    tail = f.read(_FOOTER.size + 8)
    if tail[-8:] != MCAP_MAGIC:
        return None
    op, ln, summary_start, _offsets, _crc = _FOOTER.unpack(tail[:-8])
    if op != _OP_FOOTER or ln != 20 or not 8 <= summary_start < size:
        return None
    f.seek(summary_start)
    summary = f.read(size - 8 - _FOOTER.size - summary_start)
    meta_at: list[tuple[int, int]] = []
    att_at: list[tuple[int, int]] = []
    stats = None
    try:
        p = 0
        while p + 9 <= len(summary):
            op, ln = _REC_HEAD.unpack_from(summary, p)
            body = summary[p + 9 : p + 9 + ln]
            p += 9 + ln
            if op == _OP_METADATA_INDEX:
                meta_at.append(struct.unpack_from("<QQ", body, 0))
            elif op == _OP_ATTACHMENT_INDEX:
                att_at.append(struct.unpack_from("<QQ", body, 0))
            elif op == _OP_STATISTICS:
                stats = _statistics(body)
        if stats is None or (stats.metadata_count, stats.attachment_count) != (
            len(meta_at), len(att_at)
        ):
            return None  # indexes missing or incomplete: scan instead
        out = SideRecords(source="summary index")
        for offset, _length in meta_at:
            op, body = _read_record(f, offset)
            if op != _OP_METADATA:
                return None
            name, q = _str(body, 0)
            out.metadata.append(Metadata(name=name, metadata=_map(body, q)[0]))
        for offset, _length in att_at:
            op, body = _read_record(f, offset)
            if op != _OP_ATTACHMENT:
                return None
            out.attachments.append(_attachment(body))
    except (struct.error, UnicodeDecodeError, ValueError):
        return None
    return out


def _side_records_by_scan(f) -> SideRecords:
    out = SideRecords(source="scan")
    size = f.seek(0, os.SEEK_END)
    offset = 8
    while offset + 9 <= size:
        f.seek(offset)
        op, ln = _REC_HEAD.unpack(f.read(9))
        if ln > size - offset - 9 or op == _OP_FOOTER:
            break
        try:
            if op == _OP_METADATA:
                body = f.read(ln)
                name, q = _str(body, 0)
                out.metadata.append(Metadata(name=name, metadata=_map(body, q)[0]))
            elif op == _OP_ATTACHMENT:
                out.attachments.append(_attachment(f.read(ln)))
        except (struct.error, UnicodeDecodeError, ValueError):
            pass  # a damaged side record: the message scan reports damage
        offset += 9 + ln
    return out
