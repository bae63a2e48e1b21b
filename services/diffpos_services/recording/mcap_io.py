"""Transitional re-exports of the former single MCAP module.

The recording package is split by role (like the ``mcap`` package): :mod:`.errors`,
:mod:`.topics`, :mod:`.schemas`, :mod:`.writer` (sink), :mod:`.reader` (scanner, decoding),
:mod:`.repair` (recover) and :mod:`.summary` (inspect). Import from those; this module goes
away once the dashboard and ``to-rerun`` import from them too.
"""

from __future__ import annotations

from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.reader import (
    ChannelInfo,
    Damage,
    JsonDecoderFactory,
    McapScanner,
    RawMessage,
)
from diffpos_services.recording.repair import RecoverReport, recover
from diffpos_services.recording.schemas import (
    LIVELINESS_SCHEMA,
    MESSAGE_ENCODING,
    SCHEMA_ENCODING,
    SchemaEntry,
    SchemaRegistry,
)
from diffpos_services.recording.summary import ChannelSummary, RecordingSummary, summarize
from diffpos_services.recording.topics import SeqTracker, parse_topic
from diffpos_services.recording.writer import McapSink, SinkStats

__all__ = [
    "LIVELINESS_SCHEMA",
    "MESSAGE_ENCODING",
    "SCHEMA_ENCODING",
    "ChannelInfo",
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
    "parse_topic",
    "recover",
    "summarize",
]
