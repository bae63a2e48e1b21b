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


_STATUS_COLORS = {
    "OK": (40, 200, 90, 255),
    "OK_UNVERIFIED": (170, 210, 60, 255),
    "DEGRADED": (250, 170, 30, 255),
    "NOT_CONVERGED": (250, 170, 30, 255),
    "GATING_FAILED": (250, 120, 30, 255),
    "NOT_IDENTIFIABLE": (230, 50, 50, 255),
    "UNIDENTIFIABLE": (230, 50, 50, 255),
}
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
_OTHER_STATUS_COLOR = (150, 150, 150, 255)
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
