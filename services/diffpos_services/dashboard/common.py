"""Constants, colours and small column helpers shared by the dashboard's logging functions."""

from __future__ import annotations

import zlib
from collections.abc import Iterable, Sequence

import numpy as np
import rerun as rr
from numpy.typing import ArrayLike, NDArray

#: Rerun application id of every diffpos recording (live and offline share it).
APP_ID = "diffpos"
#: Name of the measurement-time timeline (timestamps = message ``t_ns``).
TIMELINE = "meas_time"

#: chi-square 95 % quantile for 3 degrees of freedom: scale of the 95 % confidence ellipsoid.
CHI2_3DOF_95 = 7.814727903251178


#: colour of every status the fusion publishes (``diffpos.estimators.result.FixStatus``
#: names without tracking, ``diffpos.tracking.state.TrackStatus`` names with it), distinct
#: within and across both families, and a short meaning for the legend. Greens and blues:
#: a position to trust (confirmed, or new / untested); yellow: predicted only; orange to red:
#: a position not to trust; violet, magenta, brown: no position (the marker stays on the
#: last fix). Legacy names of older recordings share the colour of their successor.
STATUS_STYLE: dict[str, tuple[tuple[int, int, int, int], str]] = {
    "TRACKING": ((40, 200, 90, 255), "confirmed track"),
    "INITIALISING": ((60, 200, 235, 255), "new track"),
    "COASTING": ((240, 215, 60, 255), "predicted, no ranges"),
    "LOST": ((215, 70, 215, 255), "last fix, no ranges"),
    "UNINITIALISED": ((205, 205, 205, 255), "no fix yet"),
    "OK": ((140, 225, 60, 255), "fix passed the test"),
    "OK_UNVERIFIED": ((70, 130, 245, 255), "fix, untested"),
    "NOT_CONVERGED": ((250, 165, 40, 255), "did not converge"),
    "GATING_FAILED": ((240, 100, 40, 255), "failed the test"),
    "NOT_IDENTIFIABLE": ((230, 35, 60, 255), "bad geometry"),
    "TOO_FEW_ANCHORS": ((150, 110, 235, 255), "< 3 ranges, last fix"),
    "INVALID_INPUT": ((165, 100, 60, 255), "bad input, last fix"),
}
_LEGACY_STATUS = {"DEGRADED": "NOT_CONVERGED", "UNIDENTIFIABLE": "NOT_IDENTIFIABLE",
                  "INSUFFICIENT": "TOO_FEW_ANCHORS"}
#: colour of a status no table above names (never one of the fusion's)
OTHER_STATUS_COLOR = (110, 110, 110, 255)
#: a floor probability below this dims the marker (the floor is not sure)
SURE_FLOOR_P = 0.9


def status_color(status: str) -> tuple[int, int, int, int]:
    """RGBA of a published status (:data:`STATUS_STYLE`; unknown: :data:`OTHER_STATUS_COLOR`)."""
    style = STATUS_STYLE.get(_LEGACY_STATUS.get(status, status))
    return style[0] if style is not None else OTHER_STATUS_COLOR


def confidence_colors(colors: ArrayLike, floor_p: ArrayLike) -> NDArray[np.uint8]:
    """Status colours (N, 4) dimmed by floor confidence: full colour at a floor probability
    of :data:`SURE_FLOOR_P` or more or unknown (NaN), mixed towards dark grey below it (half
    way at p = 0.5, 70 % at p <= 0.3)."""
    c = np.asarray(colors, np.float64).reshape(-1, 4)
    p = np.asarray(floor_p, np.float64).reshape(-1)
    mix = np.where(np.isfinite(p), np.clip((SURE_FLOOR_P - p) / 0.8, 0.0, 0.7), 0.0)
    rgb = c[:, :3] * (1 - mix[:, None]) + 45.0 * mix[:, None]
    return np.concatenate([rgb, c[:, 3:]], axis=1).round().astype(np.uint8)


def short_id(node_id: str) -> str:
    """The label of a responder on the plans: its id without a leading letter prefix
    (``n07`` -> ``07``, ``r01`` -> ``01``); the whole id when nothing would be left."""
    s = node_id.lstrip("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ_-")
    return s or node_id


#: statuses reported as "unidentifiable geometry"
UNIDENTIFIABLE_STATUSES = frozenset({"NOT_IDENTIFIABLE", "UNIDENTIFIABLE"})
#: exclusion reasons that are bookkeeping of the fusion (no range, no anchor state, ...), not
#: outlier gating; their events are logged at DEBUG level (hidden by default in the viewer)
BOOKKEEPING_REASONS = frozenset(
    {
        "NOT_REPORTED",
        "NOT_DETECTED",
        "NO_ANCHOR_STATE",
        "STALE",
        "ANCHOR_LOST",
        "MISSING",
        "NOT_USED",
    }
)
_TRUTH_COLOR = (240, 240, 240, 255)
_EXCLUDED_COLOR = (235, 40, 40, 220)
_PALETTE = np.array(
    [
        (31, 119, 180),
        (255, 127, 14),
        (44, 160, 44),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
        (23, 190, 207),
        (188, 189, 34),
        (127, 127, 127),
        (57, 106, 177),
    ],
    dtype=np.uint8,
)


def anchor_color(anchor_id: str) -> tuple[int, int, int, int]:
    """Stable RGBA colour of an anchor (same in every run, live or offline)."""
    r, g, b = _PALETTE[zlib.crc32(anchor_id.encode()) % len(_PALETTE)]
    return int(r), int(g), int(b), 255


def node_color(node_id: str) -> tuple[int, int, int, int]:
    """Stable RGBA of a responder's plot lines (a palette colour by a hash of its id)."""
    r, g, b = _PALETTE[zlib.crc32(b"node:" + node_id.encode()) % len(_PALETTE)]
    return int(r), int(g), int(b), 255


def _time_column(t_ns: ArrayLike) -> rr.TimeColumn:
    return rr.TimeColumn(
        TIMELINE, timestamp=np.asarray(t_ns, dtype=np.int64).astype("datetime64[ns]")
    )


def _str_array(values: Iterable[str] | ArrayLike) -> NDArray[np.str_]:
    arr = np.asarray(list(values) if not isinstance(values, np.ndarray) else values)
    if arr.size == 0:
        return np.zeros(0, dtype="<U1")
    return arr if arr.dtype.kind == "U" else arr.astype(str)


def _check_len(name: str, arr: np.ndarray, n: int, tail: tuple[int, ...] = ()) -> None:
    if arr.shape != (n, *tail):
        raise ValueError(f"{name} must have shape {(n, *tail)}, got {arr.shape}")


def _group(ids: NDArray[np.str_]) -> list[tuple[str, NDArray[np.int64]]]:
    """(id, row indices in original order) for each distinct id."""
    if ids.size == 0:
        return []
    order = np.argsort(ids, kind="stable")
    uniq, start = np.unique(ids[order], return_index=True)
    stops = [*start[1:], len(order)]
    return [(str(u), order[a:b]) for u, a, b in zip(uniq, start, stops, strict=True)]


def _sorted_by_time(t_ns: NDArray[np.int64], rows: NDArray[np.int64]) -> NDArray[np.int64]:
    return rows[np.argsort(t_ns[rows], kind="stable")]


def _rgba(rows: Sequence[tuple[int, int, int, int]]) -> NDArray[np.uint8]:
    return np.asarray(rows, dtype=np.uint8).reshape(-1, 4)
