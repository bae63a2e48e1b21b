"""Repairing recordings: :func:`recover` rewrites a truncated or damaged file into a valid,
indexed one (``diffpos recover``)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import Writer

from diffpos_services.recording.outputs import atomic_path, check_output
from diffpos_services.recording.reader import Damage, McapScanner, RawMessage
from diffpos_services.recording.writer import COMPRESSION

__all__ = ["RecoverReport", "recover"]


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
    their CRC are dropped and counted; after a record whose length or opcode is corrupt the
    copy resyncs at the next chunk that reads (only the bytes in between are lost: one
    corrupted chunk length used to drop the rest of the file). Any MCAP is copied, also one
    whose channels are not diffpos channels.

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
        ``src`` missing / not MCAP.
    ConfigError
        ``dst`` is ``src`` (same inode), a directory, or not writable.
    """
    src, dst = Path(src), Path(dst)
    check_output(dst, option="--out", inputs=[src])
    scanner = McapScanner(src, accept_foreign=True)
    comp = COMPRESSION[compression]
    with atomic_path(dst) as tmp, open(tmp, "wb") as f:  # renamed to dst once complete
        copy = _Copy(scanner, Writer(f, compression=comp))
        for batch in scanner.iter_batches():
            copy.messages(batch)
            copy.side_records()  # metadata / attachments seen so far are written as they come
            if progress is not None:
                progress(copy.n_msgs)
        copy.finish(src.name)
    return RecoverReport(
        messages=copy.n_msgs,
        channels=len(copy.channel_map),
        schemas=len(copy.schema_map),
        metadata=len(scanner.metadata),
        attachments=len(scanner.attachments),
        damage=scanner.damage,
        was_complete=scanner.complete,
    )


class _Copy:
    """The state of one :func:`recover` copy: the writer, started on first use with the
    input's header, and the input -> output schema and channel ids."""

    def __init__(self, scanner: McapScanner, writer: Writer) -> None:
        self.scanner = scanner
        self.w = writer
        self.started = False
        self.schema_map: dict[int, int] = {}
        self.channel_map: dict[int, int] = {}
        self.n_msgs = self.n_meta = self.n_att = 0

    def start(self) -> None:
        if not self.started:
            sc = self.scanner
            self.w.start(profile=sc.header_profile, library=sc.header_library or "diffpos-recover")
            self.started = True

    def channel(self, cid: int) -> int:
        """Output channel id of input channel ``cid`` (registered with its schema on first use)."""
        new = self.channel_map.get(cid)
        if new is None:
            ch = self.scanner.channels[cid]
            sid = 0
            if ch.schema_id:
                sid = self.schema_map.get(ch.schema_id, 0)
                sch = self.scanner.schemas.get(ch.schema_id)
                if sid == 0 and sch is not None:
                    sid = self.w.register_schema(sch.name, sch.encoding, sch.data)
                    self.schema_map[ch.schema_id] = sid
            new = self.w.register_channel(ch.topic, ch.message_encoding, sid, ch.metadata)
            self.channel_map[cid] = new
        return new

    def messages(self, batch: list[RawMessage]) -> None:
        self.start()
        for m in batch:
            self.w.add_message(
                self.channel(m.channel_id),
                log_time=m.log_ns,
                data=m.data,
                publish_time=m.publish_ns,
                sequence=m.sequence,
            )
        self.n_msgs += len(batch)

    def side_records(self) -> None:
        """Metadata and attachments read since the last call."""
        sc = self.scanner
        while self.n_meta < len(sc.metadata):
            md = sc.metadata[self.n_meta]
            self.w.add_metadata(md.name, md.metadata)
            self.n_meta += 1
        while self.n_att < len(sc.attachments):
            a = sc.attachments[self.n_att]
            self.w.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
            self.n_att += 1

    def finish(self, source_name: str) -> None:
        """The rest of the side records, a ``recovery`` note for a damaged input, the footer."""
        self.start()
        self.side_records()
        sc = self.scanner
        if not sc.damage.ok and not any(m.name == "recovery" for m in sc.metadata):
            self.w.add_metadata(
                "recovery",
                {
                    "source": source_name,
                    "truncated": json.dumps(sc.damage.truncated),
                    "bad_chunks": str(sc.damage.bad_chunks),
                    "unread_bytes": str(sc.damage.unread_bytes),
                    "skipped_bytes": str(sc.damage.skipped_bytes),
                    "bad_records": str(sc.damage.bad_records),
                    "messages": str(self.n_msgs),
                },
            )
        self.w.finish()
