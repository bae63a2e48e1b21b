"""Logging of the text events and the fusion diagnostics; liveliness records -> events."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import rerun as rr
from numpy.typing import ArrayLike

from diffpos_services.dashboard.columns import EventColumns
from diffpos_services.dashboard.common import UNIDENTIFIABLE_STATUSES, _time_column
from diffpos_services.wire.messages import GOOD_STATUSES


def _status_level(before: str | None, status: str) -> str:
    """Text-log level of a status change (ERROR unidentifiable, WARN bad, INFO recovered)."""
    if status in UNIDENTIFIABLE_STATUSES:
        return "ERROR"
    if status in GOOD_STATUSES:
        return "DEBUG" if before is None or before in GOOD_STATUSES else "INFO"
    return "WARN"


def log_events(rec: rr.RecordingStream, events: EventColumns) -> None:
    """Text events on the ``events`` entity (sorted by time)."""
    if not events.t_ns.size:
        return
    order = np.argsort(events.t_ns, kind="stable")
    rec.send_columns(
        "events",
        indexes=[_time_column(events.t_ns[order])],
        columns=rr.TextLog.columns(text=events.text[order], level=events.level[order]),
    )


def log_diagnostics(
    rec: rr.RecordingStream, diags: Sequence[Any], *, state: dict | None = None
) -> dict:
    """Fusion counters and anchor joined/left events from ``FusionDiagnostics`` messages
    (an anchor the fusion no longer sees is DEBUG: whether it was lost or the run ended is
    told by the liveliness events, :func:`liveliness_events` and the live service).

    Rows are placed at ``watermark_ns`` (newest measurement time seen by the fusion); messages
    without a watermark are skipped. Returns the live-anchor set to pass back when streaming.
    """
    st = state if state is not None else {"live": None}
    rows = sorted((d for d in diags if d.watermark_ns is not None), key=lambda d: d.watermark_ns)
    if not rows:
        return st
    t = np.array([d.watermark_ns for d in rows], np.int64)
    for name in ("gated", "solved", "published", "late_ranges", "pending_epochs"):
        vals = np.array([float(getattr(d, name)) for d in rows])
        rec.send_columns(
            f"metrics/fusion/{name}",
            indexes=[_time_column(t)],
            columns=rr.Scalars.columns(scalars=vals),
        )
    ev_t, ev_txt, ev_lvl = [], [], []
    live = st["live"]
    for d, ti in zip(rows, t.tolist(), strict=True):
        now = set(d.live_anchors)
        if live is not None:
            for a in sorted(now - live):
                ev_t.append(ti)
                ev_txt.append(f"anchor {a} joined")
                ev_lvl.append("INFO")
            for a in sorted(live - now):  # the liveliness events say whether it was lost
                ev_t.append(ti)
                ev_txt.append(f"fusion no longer sees anchor {a}")
                ev_lvl.append("DEBUG")
        else:
            ev_t.append(ti)
            ev_txt.append("fusion sees anchors: " + (", ".join(sorted(now)) or "none"))
            ev_lvl.append("INFO")
        live = now
    st["live"] = live
    log_events(rec, EventColumns(np.asarray(ev_t, np.int64), ev_txt, ev_lvl))
    return st


def liveliness_events(
    records: Sequence[Mapping[str, Any]],
    *,
    wall_ns: ArrayLike,
    meas_ns: ArrayLike,
) -> EventColumns:
    """Anchor joined/left events from liveliness records, on the measurement timeline.

    Liveliness is stamped with wall-clock receive times; they are mapped to measurement
    time by interpolating the (``t_pub_wall_ns``, ``t_ns``) pairs of the anchor states.

    Parameters
    ----------
    records : sequence of mapping
        ``{"key", "alive", "t_ns" (wall) [ns], "role", "id"}`` (the recorder's events).
    wall_ns, meas_ns : array_like of int, shape (K,) [ns]
        Publish wall times and measurement times of messages (any publisher).
    """
    w = np.asarray(wall_ns, np.int64)
    mt = np.asarray(meas_ns, np.int64)
    recs = [r for r in records if r.get("role") in ("anchor", "fusion")]
    if not recs or not w.size:
        return EventColumns.concat([])
    order = np.argsort(w, kind="stable")
    w, mt = w[order], mt[order]
    t_wall = np.array([int(r["t_ns"]) for r in recs], np.int64)
    # measurement time = wall time + offset of the nearest earlier message
    k = np.clip(np.searchsorted(w, t_wall, side="right") - 1, 0, w.size - 1)
    t_meas = t_wall + (mt[k] - w[k])
    who = [f"{r.get('role')} {r.get('id') or ''}".strip() for r in recs]
    alive = [bool(r.get("alive")) for r in recs]
    joined = [i for i, a in enumerate(alive) if a]
    left = [i for i, a in enumerate(alive) if not a]
    out = [EventColumns(t_meas[joined], [f"{who[i]} joined" for i in joined], ["INFO"] * len(joined))]
    normal = [i for i in left if is_normal_end(int(t_wall[i]), int(w[-1]))]
    lost = [i for i in left if i not in normal]
    out.append(EventColumns(t_meas[lost], [lost_text(who[i]) for i in lost], ["WARN"] * len(lost)))
    if normal:
        out.append(EventColumns([int(t_meas[normal].max())], [end_text([who[i] for i in normal])],
                                ["INFO"]))
    return EventColumns.concat(out)


#: a service that leaves at most this long before the last message of the run [ns] stopped
#: with the others at the end of the run (a normal end), not during it (a fault)
END_GRACE_NS = 1_000_000_000


def is_normal_end(left_wall_ns: int, last_data_wall_ns: int) -> bool:
    """Whether a service that left at ``left_wall_ns`` stopped at the end of the run: no
    data was published more than :data:`END_GRACE_NS` after it left (else the run went on
    without it: lost)."""
    return last_data_wall_ns <= left_wall_ns + END_GRACE_NS


def end_text(who: Sequence[str]) -> str:
    """The one event of a normal end: who stopped."""
    return f"run ended: {', '.join(who)} stopped with the data (normal end, not a fault)"


def lost_text(who: str) -> str:
    """The event of a service lost while the run went on."""
    return f"{who} left while the others went on publishing (lost: a fault)"
