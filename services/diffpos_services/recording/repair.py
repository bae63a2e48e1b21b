"""Repairing recordings: :func:`recover` rewrites a truncated or damaged file into a valid,
indexed one (``diffpos recover``)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import Writer

from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.reader import Damage, McapScanner
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
    comp = COMPRESSION[compression]
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
