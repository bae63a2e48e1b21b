"""Reading recordings: :class:`McapScanner` and decoding (pure Python, no Zenoh).

* :class:`McapScanner` - a sequential, damage-tolerant reader: works on complete files and on
  truncated ones (no footer, e.g. after SIGKILL), skips chunks that fail their CRC, and parses
  chunk contents with ``struct`` directly (several times faster than ``mcap``'s record
  objects, which matters for replay).
* :class:`JsonDecoderFactory` - lets ``mcap.reader.make_reader`` decode our JSON channels.
"""

from __future__ import annotations

import io
import json
import os
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
        if not head:
            raise ForeignRecordingError(f"{self.path} is empty (0 bytes): not a recording")
        if head != MCAP_MAGIC:
            raise ForeignRecordingError(
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


class PartsScanner:
    """The parts of a split recording (``r.mcap``, ``r_0001.mcap``, ...: the recorder's
    ``--split-size`` / ``--split-duration``, see :func:`..writer.existing_parts`) read as one,
    in order, with :class:`McapScanner`'s interface. Channel ids restart in every part: a
    :class:`RawMessage`'s ``channel_id`` is its part's; use the topic across parts.

    Attributes
    ----------
    parts : list of McapScanner
    """

    def __init__(self, first: str | os.PathLike[str], *, validate_crcs: bool = True) -> None:
        paths = existing_parts(first) or [Path(first)]
        self.parts = [McapScanner(p, validate_crcs=validate_crcs) for p in paths]
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
