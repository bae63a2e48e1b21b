"""MCAP recording -> dashboard .rrd (``diffpos to-rerun``, ``diffpos replay --rrd``), and
reading an .rrd back (tests, quick checks)."""

from __future__ import annotations

import functools
import gc
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import msgspec
import rerun.chunk as rc

from diffpos_services.dashboard.building import BuildingOutline
from diffpos_services.dashboard.columns import EventColumns
from diffpos_services.dashboard.common import TIMELINE
from diffpos_services.dashboard.decode import _LIST_DECODERS, VIEW_DECODERS
from diffpos_services.dashboard.events import liveliness_events
from diffpos_services.dashboard.scenario import building_from_attachments
from diffpos_services.dashboard.stream import _KIND_BY_CLASS, write_rrd_from_messages

# the MCAP reader of the recording package: the one cross-service import of the dashboard
# (converting a recording needs its damage-tolerant scanner)
from diffpos_services.recording.errors import ForeignRecordingError
from diffpos_services.recording.reader import McapScanner
from diffpos_services.wire.keys import parse_recording_topic

__all__ = ["mcap_to_rrd", "rrd_rows"]


# ============================================================================ MCAP -> .rrd
def _topic_kind(topic: str) -> str:
    """The message kind of an MCAP topic (``unknown`` for foreign channels)."""
    pk = parse_recording_topic(topic)
    return "unknown" if pk is None else pk.kind


def _kind_scanner(path: str | Path, kinds: set[str]):
    """A damage-tolerant MCAP scanner plus the live set of topics of the wanted ``kinds``.

    ``McapScanner.iter_batches(topics)`` filters with ``topic in topics`` (a C-level set
    lookup); the set is filled as the scanner registers channels, so topics of other kinds
    (the many range messages) are skipped without being copied or decoded.
    """
    wanted: set[str] = set()

    classified: set[int] = set()

    class _Scanner(McapScanner):
        def _add_channel(self, body, pos=0):  # type: ignore[override]
            super()._add_channel(body, pos)
            # channel records repeat in every chunk: classify each channel id once
            for cid in self.channels.keys() - classified:
                classified.add(cid)
                topic = self.channels[cid].topic
                if _topic_kind(topic) in kinds:
                    wanted.add(topic)

    return _Scanner(path), wanted


_MCAP_KINDS = {
    "anchor_state": "AnchorState",
    "truth_node": "GroundTruth",
    "estimate": "PositionEstimate",
    "replay_estimate": "PositionEstimate",
    "diagnostics": "FusionDiagnostics",
    "liveliness": None,
}


def _refuse_foreign(sc: McapScanner) -> None:
    """A valid MCAP without any diffpos channel: nothing to draw (exit code 1, no file)."""
    if not any(_topic_kind(c.topic) != "unknown" for c in sc.channels.values()):
        found = ", ".join(sorted({c.topic for c in sc.channels.values()})[:5]) or "no channels"
        raise ForeignRecordingError(
            f"no diffpos channels (diffpos/<site>/...) in it ({found}): not a diffpos "
            "recording, nothing to draw; no .rrd written"
        )


def _msg_time_ns(x: Any) -> int | None:
    t = getattr(x, "t_ns", None)
    return t if t is not None else getattr(x, "watermark_ns", None)


def _time_window(
    msgs: list[Any], window_s: tuple[float | None, float | None]
) -> tuple[list[Any], tuple[float, float]]:
    """Messages within ``window_s`` seconds after the first anchor state (or first message),
    and the window in measurement time [ns]."""
    starts = [x.t_ns for x in msgs if _KIND_BY_CLASS.get(type(x).__name__) == "anchor_state"]
    times = [t for t in map(_msg_time_ns, msgs) if t is not None and t >= 0]
    if not times:
        return msgs, (-math.inf, math.inf)
    t0 = min(starts) if starts else min(times)
    lo = -math.inf if window_s[0] is None else t0 + window_s[0] * 1e9
    hi = math.inf if window_s[1] is None else t0 + window_s[1] * 1e9
    out = []
    for x in msgs:
        t = _msg_time_ns(x)
        if t is None or lo <= t <= hi:
            out.append(x)
    return out, (lo, hi)


def _gc_paused(fn):
    """Pause the cyclic garbage collector while ``fn`` runs (bulk conversions).

    Bulk decoding creates hundreds of thousands of small lists; the repeated full
    collections this triggers made decoding ~3x slower. Reference counting still frees
    everything; the previous collector state is restored afterwards.
    """
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        was_enabled = gc.isenabled()
        gc.disable()
        try:
            return fn(*args, **kwargs)
        finally:
            if was_enabled:
                gc.enable()

    return wrapper


@_gc_paused
def mcap_to_rrd(
    mcap_path: str | Path,
    rrd_path: str | Path,
    *,
    building: Any = None,
    estimates: Sequence[Any] | None = None,
    use_replayed: bool = False,
    recording_id: str | None = None,
    path_period_s: float = 0.5,
    window_s: tuple[float | None, float | None] = (None, None),
) -> dict[str, Any]:
    """Convert a diffpos MCAP recording into the dashboard .rrd (blueprint embedded).

    Reads anchor states, node truth, estimates, fusion diagnostics and liveliness events
    (range messages are skipped without decoding) and writes everything with
    ``send_columns``. Works on truncated recordings too (what was complete is used).

    Parameters
    ----------
    mcap_path : path
        The recording (``diffpos recorder`` / ``diffpos emulate``).
    rrd_path : path
        Output .rrd.
    building : BuildingOutline, scenario building or mapping, optional
        Default: the scenario TOML attached to the recording, if any.
    estimates : sequence of PositionEstimate, optional
        Use these estimates instead of the recorded ones (``diffpos replay --rrd`` passes the
        re-computed fixes here).
    use_replayed : bool
        Use the recorded ``replay/node/<id>/estimate`` channels instead of the live ones.
    recording_id : str, optional
        Rerun recording id; default: the MCAP file stem.
    window_s : (start, end) [s], optional
        Keep only messages whose measurement time lies in this window, in seconds after the
        first anchor state of the recording (``None``: open end).

    Returns
    -------
    dict
        Counts per kind, ``building`` (bool) and ``damage`` notes of the MCAP scan.
    """
    kinds = set(_MCAP_KINDS)
    if estimates is not None:
        kinds -= {"estimate", "replay_estimate"}
    else:
        kinds.discard("estimate" if use_replayed else "replay_estimate")
    sc, wanted = _kind_scanner(mcap_path, kinds)
    kind_of: dict[str, str] = {}
    msgs: list[Any] = []
    live: list[dict[str, Any]] = []
    bad = 0
    payloads: dict[str, list[bytes]] = {}
    for batch in sc.iter_batches(wanted):
        for raw in batch:
            kind = kind_of.get(raw.topic)
            if kind is None:
                kind = kind_of[raw.topic] = _topic_kind(raw.topic)
            payloads.setdefault(kind, []).append(raw.data)
    _refuse_foreign(sc)
    for kind, datas in payloads.items():
        if kind not in VIEW_DECODERS:  # liveliness events (plain JSON objects)
            for data in datas:
                try:
                    live.append(msgspec.json.decode(data))
                except msgspec.DecodeError:
                    bad += 1
            continue
        try:  # one JSON array per kind: far cheaper than one decode call per message
            msgs.extend(_LIST_DECODERS[kind].decode(b"[" + b",".join(datas) + b"]"))
        except msgspec.DecodeError:  # some payload is bad: decode one by one, count them
            for data in datas:
                try:
                    msgs.append(VIEW_DECODERS[kind].decode(data))
                except msgspec.DecodeError:
                    bad += 1
    if estimates is not None:
        msgs.extend(estimates)
    window_ns = (-math.inf, math.inf)
    if window_s != (None, None):
        msgs, window_ns = _time_window(msgs, window_s)
    outline = BuildingOutline.from_object(building) if building is not None else None
    if outline is None:
        outline = building_from_attachments(sc.attachments)
    timed = [x for x in msgs if getattr(x, "t_pub_wall_ns", 0) and hasattr(x, "t_ns")]
    wall = [x.t_pub_wall_ns for x in timed]
    meas = [x.t_ns for x in timed]
    events = liveliness_events(live, wall_ns=wall, meas_ns=meas)
    inside = (events.t_ns >= window_ns[0]) & (events.t_ns <= window_ns[1])
    events = EventColumns(events.t_ns[inside], events.text[inside], events.level[inside])
    counts = write_rrd_from_messages(
        msgs,
        rrd_path,
        building=outline,
        recording_id=recording_id or Path(mcap_path).stem,
        events=events,
        path_period_s=path_period_s,
    )
    return counts | {
        "window_s": list(window_s),
        "liveliness": len(live),
        "undecodable": bad,
        "building": outline is not None,
        "complete": sc.complete,
        "damage": list(sc.damage.notes),
    }


def rrd_rows(path: str | Path) -> dict[str, list[tuple[int | None, dict[str, Any]]]]:
    """Read an .rrd back with Rerun's own reader (``rerun.chunk.RrdReader``).

    Returns
    -------
    dict
        Entity path -> rows sorted by measurement time, each ``(t_ns, {column: value})``
        (``t_ns`` is ``None`` for static rows). Columns are named like ``Points3D:positions``.
        Meant for tests and quick checks of small files.
    """
    rows: dict[str, list[tuple[int | None, dict[str, Any]]]] = {}
    for chunk in rc.RrdReader(path).stream():
        rb = chunk.to_record_batch()
        names = [n for n in rb.schema.names if n not in ("rerun.controls.RowId", TIMELINE)]
        cols = {n: rb.column(n).to_pylist() for n in names}
        if TIMELINE in rb.schema.names:
            times = rb.column(TIMELINE).cast("int64").to_pylist()
        else:
            times = [None] * rb.num_rows
        out = rows.setdefault(str(chunk.entity_path), [])
        for i in range(rb.num_rows):
            out.append((times[i], {n: cols[n][i] for n in names}))
    for v in rows.values():
        v.sort(key=lambda r: (r[0] is not None, r[0] or 0))
    return rows
