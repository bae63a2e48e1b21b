"""Rerun dashboard of a diffpos run: pure logging functions and the default blueprint.

Everything here writes to an explicit :class:`rerun.RecordingStream` passed in by the caller
(never the global one), in columns (``send_columns``), so the same code serves

* the live dashboard service (``diffpos dashboard``), which feeds one small batch of bus
  messages at a time into a :class:`Dashboard`, and
* the offline converters (``diffpos to-rerun``, ``diffpos replay --rrd``), which feed a whole
  recording as one batch (:func:`write_rrd`, :func:`write_rrd_from_messages`).

All rows are stamped on the **measurement timeline** :data:`TIMELINE` (the ``t_ns`` of the
messages, integer nanoseconds), never on wall-clock time, so a live recording and a replay
of the same run line up sample for sample.

Entity layout (see :func:`default_blueprint` for how it is shown)::

    world                              view coordinates (right-handed, z up), building frame
    world/building/floors              floor outlines (static wireframe)
    world/building/windows             window band (sill and lintel) on the facade y = 0 (static)
    world/anchors/<anchor>             anchor position (Points3D, self-reported AnchorState)
    world/anchors/<anchor>/trail       recent track of the anchor (LineStrips3D)
    world/nodes/<node>/truth           true node position (emulation only)
    world/nodes/<node>/estimate        estimated position (Points3D, label "<node> F<est>", plus
                                       "(true F<true>)" when the floor is wrong) and its 95 %
                                       confidence ellipsoid from the covariance (Ellipsoids3D)
    world/nodes/<node>/paths           anchor -> window-edge point -> estimate, one strip per
                                       anchor; used anchors in their colour, gated (excluded by
                                       RAIM / pre-gate) in red; no strip for anchors without a
                                       measurement (not reported, not detected, lost, ...)
    metrics/error_3d_m/<node>          |estimate - truth| [m]
    metrics/error_z_m/<node>           estimate z - true z [m]
    metrics/peb_m/<node>               position error bound [m]
    metrics/residual_m/<anchor>        post-fit range residuals of every node (points) [m]
    metrics/gating/excluded            excluded measurements per fusion time (all nodes)
    metrics/gating/used                used measurements per fusion time (all nodes)
    metrics/fusion/<counter>           cumulative fusion counters (FusionDiagnostics)
    floors                             markdown table: estimated vs true floor per node
    events                             text log: anchors joined/left, exclusions with reasons,
                                       status changes (unidentifiable geometry, ...)
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from numpy.typing import ArrayLike, NDArray

from diffpos.geometry import diffraction_point
from diffpos_services.dashboard.building import BuildingOutline, FloatArray

__all__ = [
    "APP_ID",
    "TIMELINE",
    "AnchorColumns",
    "BuildingOutline",
    "Dashboard",
    "EstimateColumns",
    "EventColumns",
    "Tracks",
    "TruthColumns",
    "anchor_columns_from_messages",
    "building_from_scenario_file",
    "default_blueprint",
    "ellipsoid_axes",
    "estimate_columns_from_messages",
    "key_of",
    "liveliness_events",
    "log_anchors",
    "log_building",
    "log_diagnostics",
    "log_estimates",
    "log_events",
    "log_truth",
    "mcap_to_rrd",
    "rrd_rows",
    "truth_columns_from_messages",
    "write_rrd",
    "write_rrd_from_messages",
]

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
#: fix statuses (diffpos.estimators.FixStatus names) that mean a usable fix
GOOD_STATUSES = frozenset({"OK", "OK_UNVERIFIED"})
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


# ============================================================================ input columns
@dataclass(frozen=True)
class AnchorColumns:
    """Anchor states as columns (one row per AnchorState message).

    Attributes
    ----------
    t_ns : ndarray of int64, shape (K,) [ns]
    anchor_id : ndarray of str, shape (K,)
    position_m : ndarray, shape (K, 3) [m]
    """

    t_ns: NDArray[np.int64]
    anchor_id: NDArray[np.str_]
    position_m: FloatArray

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_ns", np.asarray(self.t_ns, dtype=np.int64).reshape(-1))
        object.__setattr__(self, "anchor_id", _str_array(self.anchor_id))
        object.__setattr__(
            self, "position_m", np.asarray(self.position_m, dtype=np.float64).reshape(-1, 3)
        )
        n = self.t_ns.shape[0]
        _check_len("AnchorColumns.anchor_id", self.anchor_id, n)
        _check_len("AnchorColumns.position_m", self.position_m, n, (3,))

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass(frozen=True)
class TruthColumns:
    """Ground truth of nodes as columns (one row per GroundTruth message of a node).

    Attributes
    ----------
    t_ns : ndarray of int64, shape (K,) [ns]
    node_id : ndarray of str, shape (K,)
    position_m : ndarray, shape (K, 3) [m]
    floor_index : ndarray of int64, shape (K,)
        True floor, -1 where unknown (then derived from z if a building is given).
    """

    t_ns: NDArray[np.int64]
    node_id: NDArray[np.str_]
    position_m: FloatArray
    floor_index: NDArray[np.int64] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_ns", np.asarray(self.t_ns, dtype=np.int64).reshape(-1))
        object.__setattr__(self, "node_id", _str_array(self.node_id))
        object.__setattr__(
            self, "position_m", np.asarray(self.position_m, dtype=np.float64).reshape(-1, 3)
        )
        n = self.t_ns.shape[0]
        fl = (
            np.full(n, -1, np.int64)
            if self.floor_index is None
            else np.asarray(self.floor_index, np.int64)
        )
        object.__setattr__(self, "floor_index", fl.reshape(-1))
        _check_len("TruthColumns.node_id", self.node_id, n)
        _check_len("TruthColumns.position_m", self.position_m, n, (3,))
        _check_len("TruthColumns.floor_index", self.floor_index, n)

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass(frozen=True)
class EstimateColumns:
    """Position estimates as columns, with their per-anchor links flattened.

    Attributes
    ----------
    t_ns : ndarray of int64, shape (K,) [ns]
        Fix reference time.
    node_id : ndarray of str, shape (K,)
    status : ndarray of str, shape (K,)
        Fix status name (OK, DEGRADED, UNIDENTIFIABLE, ...).
    position_m : ndarray, shape (K, 3) [m]
        NaN where the fix has no position.
    covariance_m2 : ndarray, shape (K, 3, 3) [m^2]
        NaN where unknown.
    peb_m : ndarray, shape (K,) [m]
        Position error bound, NaN where undefined.
    floor_index : ndarray of int64, shape (K,)
        Estimated floor, -1 where unknown.
    link_fix : ndarray of int64, shape (L,)
        Row (fix) index of each anchor link.
    link_anchor_id : ndarray of str, shape (L,)
    link_used : ndarray of bool, shape (L,)
        True for anchors used in the fix, False for excluded ones.
    link_residual_m : ndarray, shape (L,) [m]
        Post-fit residual of used links, NaN for excluded ones.
    link_reason : ndarray of str, shape (L,)
        Exclusion reason, ``""`` for used links.
    """

    t_ns: NDArray[np.int64]
    node_id: NDArray[np.str_]
    status: NDArray[np.str_]
    position_m: FloatArray
    covariance_m2: FloatArray
    peb_m: FloatArray
    floor_index: NDArray[np.int64]
    link_fix: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    link_anchor_id: NDArray[np.str_] = field(default_factory=lambda: np.zeros(0, "<U1"))
    link_used: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, bool))
    link_residual_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    link_reason: NDArray[np.str_] = field(default_factory=lambda: np.zeros(0, "<U1"))

    def __post_init__(self) -> None:
        s = object.__setattr__
        s(self, "t_ns", np.asarray(self.t_ns, dtype=np.int64).reshape(-1))
        n = self.t_ns.shape[0]
        s(self, "node_id", _str_array(self.node_id))
        s(self, "status", _str_array(self.status))
        s(self, "position_m", np.asarray(self.position_m, dtype=np.float64).reshape(n, 3))
        s(self, "covariance_m2", np.asarray(self.covariance_m2, dtype=np.float64).reshape(n, 3, 3))
        s(self, "peb_m", np.asarray(self.peb_m, dtype=np.float64).reshape(-1))
        s(self, "floor_index", np.asarray(self.floor_index, dtype=np.int64).reshape(-1))
        s(self, "link_fix", np.asarray(self.link_fix, dtype=np.int64).reshape(-1))
        s(self, "link_anchor_id", _str_array(self.link_anchor_id))
        s(self, "link_used", np.asarray(self.link_used, dtype=bool).reshape(-1))
        s(self, "link_residual_m", np.asarray(self.link_residual_m, dtype=np.float64).reshape(-1))
        s(self, "link_reason", _str_array(self.link_reason))
        for name in ("node_id", "status", "peb_m", "floor_index"):
            _check_len(f"EstimateColumns.{name}", getattr(self, name), n)
        n_links = self.link_fix.shape[0]
        for name in ("link_anchor_id", "link_used", "link_residual_m", "link_reason"):
            _check_len(f"EstimateColumns.{name}", getattr(self, name), n_links)
        if n_links and (self.link_fix.min() < 0 or self.link_fix.max() >= n):
            raise ValueError("EstimateColumns.link_fix must index rows 0..K-1")

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass(frozen=True)
class EventColumns:
    """Text events (anchor joined/left, ...) as columns.

    Attributes
    ----------
    t_ns : ndarray of int64, shape (E,) [ns]
    text : ndarray of str, shape (E,)
    level : ndarray of str, shape (E,)
        Rerun text-log level: INFO, WARN, ERROR, ...
    """

    t_ns: NDArray[np.int64]
    text: NDArray[np.str_]
    level: NDArray[np.str_]

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_ns", np.asarray(self.t_ns, dtype=np.int64).reshape(-1))
        object.__setattr__(self, "text", _str_array(self.text))
        object.__setattr__(self, "level", _str_array(self.level))
        _check_len("EventColumns.text", self.text, self.t_ns.shape[0])
        _check_len("EventColumns.level", self.level, self.t_ns.shape[0])

    @classmethod
    def concat(cls, parts: Sequence[EventColumns]) -> EventColumns:
        parts = [p for p in parts if p.t_ns.size]
        if not parts:
            return cls(np.zeros(0, np.int64), np.zeros(0, "<U1"), np.zeros(0, "<U1"))
        return cls(
            np.concatenate([p.t_ns for p in parts]),
            np.concatenate([p.text for p in parts]),
            np.concatenate([p.level for p in parts]),
        )


# ============================================================================ message views
class ExclusionView(msgspec.Struct, frozen=True, gc=False):
    """The part of ``messages.Exclusion`` the dashboard reads."""

    anchor_id: str
    reason: str


class AnchorStateView(msgspec.Struct, frozen=True, gc=False):
    """The part of ``diffpos.anchor_state.v1`` the dashboard reads (other fields skipped)."""

    anchor_id: str
    t_ns: int
    position_m: tuple[float, float, float]
    t_pub_wall_ns: int = 0


class TruthView(msgspec.Struct, frozen=True, gc=False):
    """The part of ``diffpos.truth.v1`` the dashboard reads."""

    entity: str
    id: str
    t_ns: int
    position_m: tuple[float, float, float]
    floor_index: int | None = None


class EstimateView(msgspec.Struct, frozen=True, gc=False):
    """The part of ``diffpos.estimate.v1`` the dashboard reads."""

    node_id: str
    t_ns: int
    status: str
    position_m: tuple[float, float, float] | None
    covariance_m2: (
        tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]
        | None
    )
    peb_m: float | None
    floor_index: int | None
    used_anchors: list[str]
    residuals_m: list[float]
    excluded: list[ExclusionView]
    t_pub_wall_ns: int = 0


class DiagnosticsView(msgspec.Struct, frozen=True, gc=False):
    """The part of ``diffpos.fusion_diagnostics.v1`` the dashboard reads."""

    watermark_ns: int | None
    gated: int
    solved: int
    published: int
    late_ranges: int
    pending_epochs: int
    live_anchors: list[str]


#: bus kind (``keys.parse_key``) -> fast JSON decoder of the dashboard's view of it. The
#: dashboard is a viewer: it type-checks what it draws but leaves the value constraints of
#: the full schemas (id patterns, bounds) to the fusion and the wire-contract tests.
VIEW_DECODERS: dict[str, msgspec.json.Decoder] = {
    "anchor_state": msgspec.json.Decoder(AnchorStateView),
    "truth_node": msgspec.json.Decoder(TruthView),
    "estimate": msgspec.json.Decoder(EstimateView),
    "replay_estimate": msgspec.json.Decoder(EstimateView),
    "diagnostics": msgspec.json.Decoder(DiagnosticsView),
}


# ============================================================================ messages -> columns
def _nan3() -> tuple[float, float, float]:
    return (math.nan, math.nan, math.nan)


def anchor_columns_from_messages(msgs: Sequence[Any]) -> AnchorColumns:
    """Columns from ``AnchorState`` messages (anything with anchor_id, t_ns, position_m)."""
    return AnchorColumns(
        t_ns=np.fromiter((m.t_ns for m in msgs), np.int64, len(msgs)),
        anchor_id=[m.anchor_id for m in msgs],
        position_m=np.array([m.position_m for m in msgs], dtype=np.float64).reshape(-1, 3),
    )


def truth_columns_from_messages(msgs: Sequence[Any]) -> TruthColumns:
    """Columns from node ``GroundTruth`` messages (``entity == "node"``; others skipped)."""
    nodes = [m for m in msgs if getattr(m, "entity", "node") == "node"]
    return TruthColumns(
        t_ns=np.fromiter((m.t_ns for m in nodes), np.int64, len(nodes)),
        node_id=[m.id for m in nodes],
        position_m=np.array([m.position_m for m in nodes], dtype=np.float64).reshape(-1, 3),
        floor_index=np.fromiter(
            (-1 if m.floor_index is None else m.floor_index for m in nodes), np.int64, len(nodes)
        ),
    )


def estimate_columns_from_messages(msgs: Sequence[Any]) -> EstimateColumns:
    """Columns from ``PositionEstimate`` messages (diffpos.estimate.v1)."""
    n = len(msgs)
    nan_cov = (_nan3(), _nan3(), _nan3())
    # links flattened with comprehensions (no per-link Python calls): used ones first, then
    # the excluded ones; residual lists of the wrong length are padded/cut (NaN)
    n_used = np.fromiter((len(m.used_anchors) for m in msgs), np.int64, n)
    n_res = np.fromiter((len(m.residuals_m) for m in msgs), np.int64, n)
    if np.array_equal(n_used, n_res):
        res_flat = [r for m in msgs for r in m.residuals_m]
    else:
        res_flat = [
            r
            for m in msgs
            for r in (list(m.residuals_m) + [math.nan] * len(m.used_anchors))[: len(m.used_anchors)]
        ]
    n_ex = np.fromiter((len(m.excluded) for m in msgs), np.int64, n)
    fix_index = np.arange(n, dtype=np.int64)
    n_u, n_x = int(n_used.sum()), int(n_ex.sum())
    link_fix = np.concatenate([np.repeat(fix_index, n_used), np.repeat(fix_index, n_ex)])
    link_anchor = [a for m in msgs for a in m.used_anchors] + [
        x.anchor_id for m in msgs for x in m.excluded
    ]
    link_used = np.concatenate([np.ones(n_u, bool), np.zeros(n_x, bool)])
    link_res = np.concatenate([np.asarray(res_flat, np.float64), np.full(n_x, math.nan)])
    link_reason = [""] * n_u + [x.reason for m in msgs for x in m.excluded]
    return EstimateColumns(
        t_ns=np.fromiter((m.t_ns for m in msgs), np.int64, n),
        node_id=[m.node_id for m in msgs],
        status=[m.status for m in msgs],
        position_m=np.array(
            [m.position_m if m.position_m is not None else _nan3() for m in msgs], np.float64
        ).reshape(n, 3),
        covariance_m2=np.array(
            [m.covariance_m2 if m.covariance_m2 is not None else nan_cov for m in msgs], np.float64
        ).reshape(n, 3, 3),
        peb_m=np.array([math.nan if m.peb_m is None else m.peb_m for m in msgs], np.float64),
        floor_index=np.fromiter(
            (-1 if m.floor_index is None else m.floor_index for m in msgs), np.int64, n
        ),
        link_fix=link_fix,
        link_anchor_id=link_anchor,
        link_used=link_used,
        link_residual_m=link_res,
        link_reason=link_reason,
    )


# ============================================================================ track lookup
class Tracks:
    """Time-sorted positions per id with vectorised lookup at arbitrary times.

    Parameters
    ----------
    t_ns : array_like of int, shape (K,) [ns]
    ids : array_like of str, shape (K,)
    position_m : array_like, shape (K, 3) [m]
    extra : array_like of int, shape (K,), optional
        An integer attribute (e.g. floor index) looked up as the latest value at or before
        the query time.
    """

    def __init__(
        self,
        t_ns: ArrayLike,
        ids: ArrayLike,
        position_m: ArrayLike,
        extra: ArrayLike | None = None,
    ) -> None:
        t = np.asarray(t_ns, np.int64).reshape(-1)
        ids_a = _str_array(ids)
        pos = np.asarray(position_m, np.float64).reshape(-1, 3)
        ex = np.full(t.shape, -1, np.int64) if extra is None else np.asarray(extra, np.int64)
        order = np.lexsort((t, ids_a)) if t.size else np.zeros(0, np.int64)
        ids_s, t_s, pos_s, ex_s = ids_a[order], t[order], pos[order], ex[order]
        self._data: dict[str, tuple[NDArray[np.int64], FloatArray, NDArray[np.int64]]] = {}
        if t.size:
            uniq, start = np.unique(ids_s, return_index=True)
            stops = [*start[1:], len(ids_s)]
            for name, a, b in zip(uniq, start, stops, strict=True):
                self._data[str(name)] = (t_s[a:b], pos_s[a:b], ex_s[a:b])

    @property
    def ids(self) -> list[str]:
        return sorted(self._data)

    def sample(
        self, ids: ArrayLike, t_ns: ArrayLike, *, coded: tuple[ArrayLike, ArrayLike] | None = None
    ) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.bool_]]:
        """Positions interpolated linearly in time (held constant beyond the ends).

        Parameters
        ----------
        ids : array_like of str, shape (L,)
        t_ns : array_like of int, shape (L,) [ns]
        coded : (names, codes), optional
            ``np.unique(ids, return_inverse=True)`` if the caller has it already (saves a
            string sort); ``ids`` is then ignored.

        Returns
        -------
        position_m : ndarray, shape (L, 3) [m]
            NaN where the id is unknown.
        extra : ndarray of int64, shape (L,)
            Latest ``extra`` value at or before each time (-1 where unknown).
        known : ndarray of bool, shape (L,)
        """
        if coded is None:
            names, codes = np.unique(_str_array(ids), return_inverse=True)
        else:
            names, codes = np.asarray(coded[0]), np.asarray(coded[1])
        t_q = np.asarray(t_ns, np.int64).reshape(-1)
        out = np.full((t_q.size, 3), np.nan)
        extra = np.full(t_q.size, -1, np.int64)
        known = np.zeros(t_q.size, bool)
        if not t_q.size:
            return out, extra, known
        order = np.argsort(codes, kind="stable")
        bounds = np.searchsorted(codes[order], np.arange(len(names) + 1))
        for i, name in enumerate(names):
            track = self._data.get(str(name))
            if track is None:
                continue
            sel = order[bounds[i] : bounds[i + 1]]
            t, pos, ex = track
            tq = t_q[sel].astype(np.float64)
            tf = t.astype(np.float64)
            for j in range(3):
                out[sel, j] = np.interp(tq, tf, pos[:, j])
            k = np.searchsorted(t, t_q[sel], side="right") - 1
            extra[sel] = ex[np.clip(k, 0, len(t) - 1)]
            known[sel] = True
        return out, extra, known


# ============================================================================ geometry helpers
def ellipsoid_axes(
    covariance_m2: ArrayLike, *, scale: float = math.sqrt(CHI2_3DOF_95)
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Half axes and orientation of confidence ellipsoids of 3x3 covariances.

    The ellipsoid ``{x : x^T C^-1 x <= scale^2}`` has half axes ``scale * sqrt(eig(C))``
    along the eigenvectors. The default scale makes it the 95 % region of a 3D Gaussian.

    Parameters
    ----------
    covariance_m2 : array_like, shape (K, 3, 3) [m^2]
    scale : float
        Mahalanobis radius.

    Returns
    -------
    half_sizes_m : ndarray, shape (K, 3) [m]
    quaternion_xyzw : ndarray, shape (K, 4)
        Rotation taking the local axes to the eigenvectors (Rerun's xyzw order).
    valid : ndarray of bool, shape (K,)
        False where the covariance is not finite (rows then hold zeros / identity).
    """
    c = np.asarray(covariance_m2, np.float64).reshape(-1, 3, 3)
    valid = np.all(np.isfinite(c), axis=(1, 2))
    half = np.zeros((c.shape[0], 3))
    quat = np.tile(np.array([0.0, 0.0, 0.0, 1.0]), (c.shape[0], 1))
    if valid.any():
        cs = 0.5 * (c[valid] + np.swapaxes(c[valid], 1, 2))
        w, v = np.linalg.eigh(cs)
        det = np.linalg.det(v)
        v[:, :, 2] *= np.sign(det)[:, None]  # proper rotation
        half[valid] = scale * np.sqrt(np.clip(w, 0.0, None))
        quat[valid] = _matrix_to_quat_xyzw(v)
    return half, quat, valid


def _matrix_to_quat_xyzw(r: FloatArray) -> FloatArray:
    """Unit quaternions (x, y, z, w) of rotation matrices ``(K, 3, 3)`` (Shepperd's method)."""
    m00, m11, m22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    tr = m00 + m11 + m22
    cand = np.stack([tr, m00, m11, m22], axis=1).argmax(axis=1)
    q = np.empty((r.shape[0], 4))
    for case in range(4):
        k = cand == case
        if not k.any():
            continue
        rk = r[k]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + tr[k])
            q[k] = np.stack([(rk[:, 2, 1] - rk[:, 1, 2]) / s, (rk[:, 0, 2] - rk[:, 2, 0]) / s,
                             (rk[:, 1, 0] - rk[:, 0, 1]) / s, 0.25 * s], axis=1)  # fmt: skip
        elif case == 1:
            s = 2.0 * np.sqrt(1.0 + m00[k] - m11[k] - m22[k])
            q[k] = np.stack([0.25 * s, (rk[:, 0, 1] + rk[:, 1, 0]) / s,
                             (rk[:, 0, 2] + rk[:, 2, 0]) / s, (rk[:, 2, 1] - rk[:, 1, 2]) / s], axis=1)  # fmt: skip
        elif case == 2:
            s = 2.0 * np.sqrt(1.0 + m11[k] - m00[k] - m22[k])
            q[k] = np.stack([(rk[:, 0, 1] + rk[:, 1, 0]) / s, 0.25 * s,
                             (rk[:, 1, 2] + rk[:, 2, 1]) / s, (rk[:, 0, 2] - rk[:, 2, 0]) / s], axis=1)  # fmt: skip
        else:
            s = 2.0 * np.sqrt(1.0 + m22[k] - m00[k] - m11[k])
            q[k] = np.stack([(rk[:, 0, 2] + rk[:, 2, 0]) / s, (rk[:, 1, 2] + rk[:, 2, 1]) / s,
                             0.25 * s, (rk[:, 1, 0] - rk[:, 0, 1]) / s], axis=1)  # fmt: skip
    return q / np.linalg.norm(q, axis=1, keepdims=True)


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


# ============================================================================ logging functions
def log_building(rec: rr.RecordingStream, building: BuildingOutline) -> None:
    """Static wireframe: floor outlines and the window band of each floor on the facade.

    Also sets ``world`` to a right-handed z-up frame (the building frame).
    """
    b = building
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    x0, x1, d = b.x_min_m, b.x_max_m, b.depth_m
    floors = []
    z0 = b.first_floor_z_m
    for k in range(b.n_floors + 1):
        z = z0 + k * b.floor_height_m
        floors.append([[x0, 0, z], [x1, 0, z], [x1, d, z], [x0, d, z], [x0, 0, z]])
    top = z0 + b.n_floors * b.floor_height_m
    for x, y in ((x0, 0), (x1, 0), (x1, d), (x0, d)):
        floors.append([[x, y, 0.0], [x, y, top]])
    rec.log(
        "world/building/floors",
        rr.LineStrips3D(floors, colors=[(160, 160, 170, 255)], radii=0.03),
        static=True,
    )
    windows, labels = [], []
    for k in range(b.n_floors):
        z_lo = z0 + k * b.floor_height_m + b.sill_height_m
        z_hi = z_lo + b.window_height_m
        windows.append([[x0, 0, z_lo], [x1, 0, z_lo], [x1, 0, z_hi], [x0, 0, z_hi], [x0, 0, z_lo]])
        labels.append(f"F{k} window")
    rec.log(
        "world/building/windows",
        rr.LineStrips3D(windows, colors=[(90, 170, 255, 255)], radii=0.05, labels=labels),
        static=True,
    )


def log_anchors(
    rec: rr.RecordingStream,
    anchors: AnchorColumns,
    *,
    history: AnchorColumns | None = None,
    trail_s: float = 30.0,
    trail_period_s: float = 0.5,
    trail_max_points: int = 60,
) -> None:
    """Anchor positions and their trails.

    Parameters
    ----------
    anchors : AnchorColumns
        The new rows to log.
    history : AnchorColumns, optional
        Earlier rows (already logged) used only to draw the beginning of the trails.
    trail_s : float [s]
        Trail length in measurement time.
    trail_period_s : float [s]
        A trail is re-drawn at most once per this period of measurement time (per anchor).
    trail_max_points : int
        Trails are subsampled to at most this many points.
    """
    if not len(anchors):
        return
    period_ns = max(1, int(trail_period_s * 1e9))
    trail_ns = int(trail_s * 1e9)
    for aid, rows in _group(anchors.anchor_id):
        rows = _sorted_by_time(anchors.t_ns, rows)
        t = anchors.t_ns[rows]
        pos = anchors.position_m[rows]
        color = anchor_color(aid)
        rec.send_columns(
            f"world/anchors/{aid}",
            indexes=[_time_column(t)],
            columns=rr.Points3D.columns(
                positions=pos,
                colors=_rgba([color] * len(rows)),
                radii=np.full(len(rows), 0.35, np.float32),
                labels=np.full(len(rows), aid),
            ),
        )
        # trails: full track = history + new rows; one strip per new trail bucket
        if history is not None and len(history):
            hsel = history.anchor_id == aid
            t_all = np.concatenate([history.t_ns[hsel], t])
            p_all = np.concatenate([history.position_m[hsel], pos])
            order = np.argsort(t_all, kind="stable")
            t_all, p_all = t_all[order], p_all[order]
            prev_bucket = history.t_ns[hsel].max() // period_ns if hsel.any() else None
        else:
            t_all, p_all, prev_bucket = t, pos, None
        bucket = t // period_ns
        first = np.ones(len(t), bool)
        first[1:] = bucket[1:] != bucket[:-1]
        if prev_bucket is not None:
            first &= bucket != prev_bucket
        emit_t = t[first]
        if not emit_t.size:
            continue
        lo = np.searchsorted(t_all, emit_t - trail_ns, side="left")
        hi = np.searchsorted(t_all, emit_t, side="right")
        strips = []
        for a, b in zip(lo, hi, strict=True):
            step = max(1, (b - a) // trail_max_points)
            idx = np.arange(b - 1, a - 1, -step)[::-1]
            strips.append(p_all[idx])
        rec.send_columns(
            f"world/anchors/{aid}/trail",
            indexes=[_time_column(emit_t)],
            columns=rr.LineStrips3D.columns(
                strips=strips,
                colors=_rgba([(*color[:3], 160)] * len(strips)),
                radii=np.full(len(strips), 0.08, np.float32),
            ),
        )


def log_truth(rec: rr.RecordingStream, truth: TruthColumns) -> None:
    """True node positions (emulation) as small white points ``world/nodes/<node>/truth``."""
    for nid, rows in _group(truth.node_id):
        rows = _sorted_by_time(truth.t_ns, rows)
        n = len(rows)
        rec.send_columns(
            f"world/nodes/{nid}/truth",
            indexes=[_time_column(truth.t_ns[rows])],
            columns=rr.Points3D.columns(
                positions=truth.position_m[rows],
                colors=_rgba([_TRUTH_COLOR] * n),
                radii=np.full(n, 0.12, np.float32),
            ),
        )


def _scalar_series(
    rec: rr.RecordingStream, path: str, t_ns: np.ndarray, values: np.ndarray
) -> None:
    ok = np.isfinite(values)
    if ok.any():
        rec.send_columns(
            path, indexes=[_time_column(t_ns[ok])], columns=rr.Scalars.columns(scalars=values[ok])
        )


@dataclass
class _EstimateState:
    """What log_estimates remembers between batches (live streaming)."""

    last_path_bucket: dict[str, int] = field(default_factory=dict)
    last_links: dict[str, dict[str, str]] = field(default_factory=dict)
    last_status: dict[str, str] = field(default_factory=dict)
    last_floor_bucket: int | None = None
    floors: dict[str, tuple[int, int]] = field(default_factory=dict)
    residual_styled: set[str] = field(default_factory=set)
    dropped_bad_time: int = 0


def _select_fixes(est: EstimateColumns, keep: NDArray[np.bool_]) -> EstimateColumns:
    """The fixes ``keep`` (bool, shape (K,)) of ``est`` with their links (re-indexed)."""
    new_index = np.cumsum(keep) - 1
    lk = keep[est.link_fix]
    return EstimateColumns(
        t_ns=est.t_ns[keep],
        node_id=est.node_id[keep],
        status=est.status[keep],
        position_m=est.position_m[keep],
        covariance_m2=est.covariance_m2[keep],
        peb_m=est.peb_m[keep],
        floor_index=est.floor_index[keep],
        link_fix=new_index[est.link_fix[lk]],
        link_anchor_id=est.link_anchor_id[lk],
        link_used=est.link_used[lk],
        link_residual_m=est.link_residual_m[lk],
        link_reason=est.link_reason[lk],
    )


def log_estimates(
    rec: rr.RecordingStream,
    est: EstimateColumns,
    *,
    anchors: Tracks | None = None,
    truth: Tracks | None = None,
    building: BuildingOutline | None = None,
    confidence_scale: float = math.sqrt(CHI2_3DOF_95),
    path_period_s: float = 0.5,
    floor_period_s: float = 1.0,
    state: _EstimateState | None = None,
) -> _EstimateState:
    """Estimates, uncertainty, diffraction paths, metrics, floor table and events.

    Parameters
    ----------
    est : EstimateColumns
        The fixes to log (any mix of nodes and times).
    anchors : Tracks, optional
        Anchor positions over time (from AnchorState); needed for the diffraction paths.
    truth : Tracks, optional
        True node positions over time with the true floor as ``extra``; gives the error
        series and the true floor.
    building : BuildingOutline, optional
        Gives the window edge of the estimated floor for the paths, and true floors from z.
    confidence_scale : float
        Mahalanobis radius of the drawn ellipsoid (default: 95 % in 3D).
    path_period_s : float [s]
        Diffraction paths of a node are drawn at most once per this measurement-time period.
    floor_period_s : float [s]
        The floor table is refreshed at most once per this period.
    state : optional
        Returned by the previous call (streaming); ``None`` for a single bulk call.

    Returns
    -------
    state
        Pass it to the next call when streaming.
    """
    st = state if state is not None else _EstimateState()
    bad_time = est.t_ns < 0
    if bad_time.any():  # invalid on the wire (times are ns since the Unix epoch): not drawn
        n_bad = int(bad_time.sum())
        st.dropped_bad_time += n_bad
        est = _select_fixes(est, ~bad_time)
        if len(est):
            log_events(
                rec,
                EventColumns(
                    [int(est.t_ns.max())],
                    [
                        f"{n_bad} estimates with a negative t_ns dropped (invalid time from the fusion)"
                    ],
                    ["ERROR"],
                ),
            )
    k = len(est)
    if k == 0:
        return st
    t = est.t_ns
    pos = est.position_m
    has_pos = np.all(np.isfinite(pos), axis=1)

    # ---- truth, errors, floors
    if truth is not None:
        true_pos, true_floor, known = truth.sample(est.node_id, t)
    else:
        true_pos = np.full((k, 3), np.nan)
        true_floor = np.full(k, -1, np.int64)
        known = np.zeros(k, bool)
    if building is not None:
        derived = building.floor_of(true_pos[:, 2])
        true_floor = np.where(known & (true_floor < 0), derived, true_floor)
    err_3d = np.linalg.norm(pos - true_pos, axis=1)
    err_z = pos[:, 2] - true_pos[:, 2]
    est_floor = est.floor_index
    if building is not None:
        est_floor = np.where((est_floor < 0) & has_pos, building.floor_of(pos[:, 2]), est_floor)

    half, quat, cov_ok = ellipsoid_axes(est.covariance_m2, scale=confidence_scale)
    cov_ok &= has_pos

    # ---- links: anchor positions and window-edge points (vectorised over all links)
    n_links = est.link_fix.size
    lf = est.link_fix
    anc_u, anc_c = np.unique(est.link_anchor_id, return_inverse=True)
    link_ok = np.zeros(n_links, bool)
    strips = np.zeros((n_links, 3, 3))
    if n_links and anchors is not None:
        a_pos, _, a_known = anchors.sample(None, t[lf], coded=(anc_u, anc_c))
        node = pos[lf]
        link_ok = a_known & has_pos[lf]
        if building is not None:
            fl = np.where(est_floor[lf] >= 0, est_floor[lf], building.floor_of(node[:, 2]))
            ze = building.upper_edge_z_m(fl)
            start = np.stack([np.full(n_links, building.x_min_m), np.zeros(n_links), ze], axis=1)
            end = start.copy()
            end[:, 0] = building.x_max_m
            with np.errstate(invalid="ignore"):
                q = diffraction_point(a_pos, node, start, end).point_m
        else:
            q = 0.5 * (a_pos + node)
        strips = np.stack([a_pos, q, node], axis=1)
        link_ok &= np.all(np.isfinite(strips), axis=(1, 2))
        # no path for bookkeeping exclusions (nothing was measured); gated ones are drawn red
        link_ok &= est.link_used | ~np.isin(est.link_reason, list(BOOKKEEPING_REASONS))
    link_colors = _rgba([anchor_color(str(a)) for a in anc_u])[anc_c]
    link_colors[~est.link_used] = _EXCLUDED_COLOR
    link_radii = np.where(est.link_used, 0.05, 0.03).astype(np.float32)

    status_colors = np.array(
        [_STATUS_COLORS.get(s, _OTHER_STATUS_COLOR) for s in np.unique(est.status)], np.uint8
    )
    status_idx = np.searchsorted(np.unique(est.status), est.status)
    colors = status_colors[status_idx]

    path_period_ns = max(1, int(path_period_s * 1e9))
    events_t: list[np.ndarray] = []
    events_text: list[list[str]] = []
    events_level: list[list[str]] = []

    for nid, rows in _group(est.node_id):
        rows = _sorted_by_time(t, rows)
        tr = t[rows]
        hp = has_pos[rows]
        n_pos = hp.astype(np.int64)
        label = [
            f"{nid} F{ef if ef >= 0 else '?'}" + (f" (true F{tf})" if 0 <= tf != ef else "")
            for ef, tf in zip(est_floor[rows].tolist(), true_floor[rows].tolist(), strict=True)
        ]
        sel = rows[hp]
        ok = cov_ok[rows]
        sel_c = rows[ok]
        # point and ellipsoid on one entity: one chunk per node and batch instead of two
        rec.send_columns(
            f"world/nodes/{nid}/estimate",
            indexes=[_time_column(tr)],
            columns=[
                *rr.Points3D.columns(
                    positions=pos[sel],
                    colors=colors[sel],
                    radii=np.full(sel.size, 0.25, np.float32),
                    labels=np.asarray(label)[hp],
                ).partition(n_pos),
                *rr.Ellipsoids3D.columns(
                    centers=pos[sel_c],
                    half_sizes=half[sel_c],
                    quaternions=quat[sel_c],
                    colors=colors[sel_c],
                    line_radii=np.full(sel_c.size, 0.02, np.float32),
                ).partition(ok.astype(np.int64)),
            ],
        )
        # diffraction paths, decimated in measurement time
        if n_links and anchors is not None:
            bucket = tr // path_period_ns
            first = np.ones(len(rows), bool)
            first[1:] = bucket[1:] != bucket[:-1]
            prev = st.last_path_bucket.get(nid)
            if prev is not None:
                first &= bucket != prev
            if first.any():
                st.last_path_bucket[nid] = int(bucket[-1])
                prow = rows[first]
                rank = np.full(k, -1, np.int64)
                rank[prow] = np.arange(prow.size)
                lsel = np.flatnonzero((rank[lf] >= 0) & link_ok)
                lsel = lsel[np.argsort(rank[lf[lsel]], kind="stable")]
                per_row = np.bincount(rank[lf[lsel]], minlength=prow.size)
                rec.send_columns(
                    f"world/nodes/{nid}/paths",
                    indexes=[_time_column(tr[first])],
                    columns=rr.LineStrips3D.columns(
                        strips=strips[lsel],
                        colors=link_colors[lsel],
                        radii=link_radii[lsel],
                    ).partition(per_row),
                )
        _scalar_series(rec, f"metrics/error_3d_m/{nid}", tr, err_3d[rows])
        _scalar_series(rec, f"metrics/error_z_m/{nid}", tr, err_z[rows])
        _scalar_series(rec, f"metrics/peb_m/{nid}", tr, est.peb_m[rows])

        # status changes -> events
        prev_status = st.last_status.get(nid)
        stat = est.status[rows]
        change = np.ones(len(rows), bool)
        change[1:] = stat[1:] != stat[:-1]
        if prev_status is not None:
            change[0] = stat[0] != prev_status
        elif stat[0] in GOOD_STATUSES:
            change[0] = False
        st.last_status[nid] = str(stat[-1])
        if change.any():
            ci = np.flatnonzero(change)
            events_t.append(tr[ci])
            txt, lvl = [], []
            for i in ci:
                s = str(stat[i])
                before = str(stat[i - 1]) if i > 0 else prev_status
                txt.append(
                    f"node {nid}: status {s}"
                    + (" (unidentifiable geometry)" if s in UNIDENTIFIABLE_STATUSES else "")
                )
                lvl.append(_status_level(before, s))
            events_text.append(txt)
            events_level.append(lvl)

        # latest floors for the floor table
        last = rows[-1]
        st.floors[nid] = (int(est_floor[last]), int(true_floor[last]))

    # ---- exclusions: an event when an anchor becomes excluded (or changes reason) for a node
    if n_links:
        # integer codes: sorting and comparing ints is much cheaper than strings
        node_u, node_c = np.unique(est.node_id, return_inverse=True)
        cur_str = np.where(est.link_used, "", est.link_reason)
        reason_u, reason_c = np.unique(cur_str, return_inverse=True)
        lorder = np.lexsort((t[lf], anc_c, node_c[lf]))
        ex_t, ex_txt, ex_lvl = [], [], []
        nl, al, cl, tl = node_c[lf][lorder], anc_c[lorder], reason_c[lorder], t[lf][lorder]
        empty = np.flatnonzero(reason_u == "")
        empty_code = int(empty[0]) if empty.size else -1
        first = np.ones(n_links, bool)
        first[1:] = (nl[1:] != nl[:-1]) | (al[1:] != al[:-1])
        changed = np.zeros(n_links, bool)
        changed[1:] = cl[1:] != cl[:-1]
        first_idx = np.flatnonzero(first)
        # the first link of each (node, anchor) pair compares with the previous batch's state
        for i in first_idx:
            before = st.last_links.get(str(node_u[nl[i]]), {}).get(str(anc_u[al[i]]), "")
            changed[i] = str(reason_u[cl[i]]) != before
        is_used = cl == empty_code
        prev_excluded = np.zeros(n_links, bool)
        prev_excluded[1:] = cl[:-1] != empty_code
        for i in first_idx:
            prev_excluded[i] = bool(
                st.last_links.get(str(node_u[nl[i]]), {}).get(str(anc_u[al[i]]), "")
            )
        events_idx = np.flatnonzero(changed & (~is_used | prev_excluded))
        first_set = set(first_idx.tolist())
        for i in events_idx:
            ex_t.append(tl[i])
            node_s, anc_s = node_u[nl[i]], anc_u[al[i]]
            if is_used[i]:
                if i in first_set:
                    before = st.last_links.get(str(node_s), {}).get(str(anc_s), "")
                else:
                    before = str(reason_u[cl[i - 1]])
                ex_txt.append(f"node {node_s}: anchor {anc_s} used again")
                ex_lvl.append("DEBUG" if before in BOOKKEEPING_REASONS else "INFO")
            else:
                reason = str(reason_u[cl[i]])
                ex_txt.append(f"node {node_s}: anchor {anc_s} excluded ({reason})")
                ex_lvl.append("DEBUG" if reason in BOOKKEEPING_REASONS else "WARN")
        last_idx = np.r_[first_idx[1:] - 1, n_links - 1]
        for i in last_idx:
            st.last_links.setdefault(str(node_u[nl[i]]), {})[str(anc_u[al[i]])] = str(
                reason_u[cl[i]]
            )
        if ex_t:
            events_t.append(np.asarray(ex_t, np.int64))
            events_text.append(ex_txt)
            events_level.append(ex_lvl)

        # residual scatter per anchor and gating counts per fusion time
        used = est.link_used & np.isfinite(est.link_residual_m)
        used_idx = np.flatnonzero(used)
        used_order = used_idx[np.argsort(anc_c[used_idx], kind="stable")]
        used_bounds = np.searchsorted(anc_c[used_order], np.arange(len(anc_u) + 1))
        for ai, aid in enumerate(anc_u.tolist()):
            li = used_order[used_bounds[ai] : used_bounds[ai + 1]]
            if not li.size:
                continue
            if aid not in st.residual_styled:
                st.residual_styled.add(aid)
                rec.log(
                    f"metrics/residual_m/{aid}",
                    rr.SeriesPoints(colors=[anchor_color(aid)], marker_sizes=[1.5], names=[aid]),
                    static=True,
                )
            li = li[np.argsort(t[lf[li]], kind="stable")]
            rec.send_columns(
                f"metrics/residual_m/{aid}",
                indexes=[_time_column(t[lf[li]])],
                columns=rr.Scalars.columns(scalars=est.link_residual_m[li]),
            )
        ut, inv = np.unique(t[lf], return_inverse=True)
        n_ex = np.bincount(inv, weights=(~est.link_used).astype(float), minlength=ut.size)
        n_used = np.bincount(inv, weights=est.link_used.astype(float), minlength=ut.size)
        rec.send_columns(
            "metrics/gating/excluded",
            indexes=[_time_column(ut)],
            columns=rr.Scalars.columns(scalars=n_ex),
        )
        rec.send_columns(
            "metrics/gating/used",
            indexes=[_time_column(ut)],
            columns=rr.Scalars.columns(scalars=n_used),
        )

    # ---- floor table, refreshed at most once per floor period (latest fix per node)
    floor_period_ns = max(1, int(floor_period_s * 1e9))
    fb = t // floor_period_ns
    ub = np.unique(fb)
    if st.last_floor_bucket is not None:
        ub = ub[ub != st.last_floor_bucket]
    if ub.size:
        # snapshot at the end of each bucket: latest fix per node up to that time
        snap_t = np.array([t[fb == b].max() for b in ub], np.int64)
        texts = _floor_tables(est, est_floor, true_floor, snap_t, st)
        st.last_floor_bucket = int(ub[-1])
        rec.send_columns(
            "floors",
            indexes=[_time_column(snap_t)],
            columns=rr.TextDocument.columns(text=texts, media_type=["text/markdown"] * len(texts)),
        )

    if events_t:
        log_events(
            rec,
            EventColumns(
                np.concatenate(events_t),
                [x for part in events_text for x in part],
                [x for part in events_level for x in part],
            ),
        )
    return st


def _floor_tables(
    est: EstimateColumns,
    est_floor: NDArray[np.int64],
    true_floor: NDArray[np.int64],
    snap_t: NDArray[np.int64],
    st: _EstimateState,
) -> list[str]:
    """Markdown tables (one per snapshot time) of the latest estimated/true floor per node."""
    groups = _group(est.node_id)
    nodes = sorted(set(st.floors) | {g for g, _ in groups})
    # latest (est, true) per node at each snapshot: (n_nodes, n_snap)
    est_m = np.full((len(nodes), snap_t.size), -2, np.int64)
    tru_m = np.full((len(nodes), snap_t.size), -2, np.int64)
    pos = {n: i for i, n in enumerate(nodes)}
    prior = dict(st.floors)
    for nid, i in pos.items():
        if nid in prior:
            est_m[i, :], tru_m[i, :] = prior[nid]
    for nid, rows in groups:
        rows = _sorted_by_time(est.t_ns, rows)
        k = np.searchsorted(est.t_ns[rows], snap_t, side="right") - 1
        have = k >= 0
        i = pos[nid]
        est_m[i, have] = est_floor[rows][k[have]]
        tru_m[i, have] = true_floor[rows][k[have]]
    fmt = lambda v: "?" if v < 0 else str(v)  # noqa: E731
    texts = []
    for j in range(snap_t.size):
        hits = [
            (e == tr) for e, tr in zip(est_m[:, j], tru_m[:, j], strict=True) if e >= 0 and tr >= 0
        ]
        if hits:
            head = f"**Floor estimate: {sum(hits)}/{len(hits)} nodes on the true floor**\n\n"
        elif np.any(tru_m[:, j] >= 0):
            head = "**Floor estimate**: no node has a fix\n\n"
        else:
            head = "**Floor estimate** (no ground truth)\n\n"
        rows = ["| node | estimated | true | |", "|---|---|---|---|"]
        for i, nid in enumerate(nodes):
            e, tr = est_m[i, j], tru_m[i, j]
            if e == -2:
                continue
            mark = "" if e < 0 or tr < 0 else ("ok" if e == tr else "**WRONG**")
            rows.append(f"| {nid} | {fmt(e)} | {fmt(tr)} | {mark} |")
        texts.append(head + "\n".join(rows))
    return texts


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
    """Fusion counters and anchor joined/left events from ``FusionDiagnostics`` messages.

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
            for a in sorted(live - now):
                ev_t.append(ti)
                ev_txt.append(f"anchor {a} left")
                ev_lvl.append("WARN")
        else:
            ev_t.append(ti)
            ev_txt.append("fusion sees anchors: " + (", ".join(sorted(now)) or "none"))
            ev_lvl.append("INFO")
        live = now
    st["live"] = live
    log_events(rec, EventColumns(np.asarray(ev_t, np.int64), ev_txt, ev_lvl))
    return st


# ============================================================================ blueprint
def default_blueprint() -> rrb.Blueprint:
    """The diffpos dashboard layout (embedded in every .rrd and sent to live viewers).

    Left: the 3D building view over the floor table and the event log. Right: time series
    of 3D error, z error and PEB per node, and tabs with residuals per anchor, gating counts
    and fusion counters.
    """
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(
                    origin="world",
                    name="Building (3D): anchors, estimates, 95% ellipsoids, diffraction paths",
                    line_grid=rrb.LineGrid3D(visible=True, spacing=5.0),
                    eye_controls=rrb.EyeControls3D(
                        position=(-20.0, -42.0, 30.0),
                        look_target=(6.0, 6.0, 12.0),
                        eye_up=(0, 0, 1),
                    ),
                ),
                rrb.Horizontal(
                    rrb.TextDocumentView(origin="floors", name="Floor: estimated vs true"),
                    rrb.TextLogView(
                        origin="events",
                        name="Events (DEBUG hidden: see the view's level filter)",
                        rows=rrb.TextLogRows(
                            filter_by_log_level=["INFO", "WARN", "ERROR", "CRITICAL"]
                        ),
                    ),
                    column_shares=[1, 2],
                ),
                row_shares=[3, 1],
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="metrics/error_3d_m", name="3D error per node [m]"),
                rrb.TimeSeriesView(origin="metrics/error_z_m", name="z error per node [m]"),
                rrb.TimeSeriesView(origin="metrics/peb_m", name="PEB per node [m]"),
                rrb.Tabs(
                    rrb.TimeSeriesView(
                        origin="metrics/residual_m", name="Range residuals per anchor [m]"
                    ),
                    rrb.TimeSeriesView(
                        origin="metrics/gating", name="Measurements used / excluded"
                    ),
                    rrb.TimeSeriesView(origin="metrics/fusion", name="Fusion counters"),
                ),
            ),
            column_shares=[0.96, 1.04],
        ),
        rrb.TimePanel(timeline=TIMELINE, play_state="following", state="collapsed"),
        collapse_panels=True,
    )


# ============================================================================ streaming + bulk
class Dashboard:
    """Streaming front end: feed batches of decoded bus messages, log them to ``rec``.

    Keeps the little state the live dashboard needs between batches (recent anchor and
    truth history for lookups and trails, last status/exclusion per node for the events).

    Parameters
    ----------
    rec : rerun.RecordingStream
        Where to log (its sinks are the caller's business).
    building : BuildingOutline, optional
        Drawn once at construction (static).
    history_s : float [s]
        How much anchor/truth history is kept for lookups and trails.
    """

    def __init__(
        self,
        rec: rr.RecordingStream,
        *,
        building: BuildingOutline | None = None,
        history_s: float = 60.0,
        path_period_s: float = 0.5,
        trail_s: float = 30.0,
    ) -> None:
        self.rec = rec
        self.building = building
        self.history_ns = int(history_s * 1e9)
        self.path_period_s = path_period_s
        self.trail_s = trail_s
        self._anchors = AnchorColumns(np.zeros(0, np.int64), [], np.zeros((0, 3)))
        self._truth = TruthColumns(np.zeros(0, np.int64), [], np.zeros((0, 3)))
        self._est_state = _EstimateState()
        self._diag_state: dict = {"live": None}
        self.counts = {
            "anchor_states": 0,
            "truth": 0,
            "estimates": 0,
            "diagnostics": 0,
            "events": 0,
        }
        if building is not None and rec.is_enabled():
            log_building(rec, building)

    def _trim(self, cols, t_now: int):
        keep = cols.t_ns >= t_now - self.history_ns
        return type(cols)(**{f: getattr(cols, f)[keep] for f in cols.__dataclass_fields__})

    def add(
        self,
        *,
        anchor_states: Sequence[Any] = (),
        truth: Sequence[Any] = (),
        estimates: Sequence[Any] = (),
        diagnostics: Sequence[Any] = (),
        events: EventColumns | None = None,
    ) -> None:
        """Log one batch of decoded messages (any of them may be empty).

        With a disabled recording stream (``--rerun off``) messages are only counted.
        """
        if not self.rec.is_enabled():
            self.counts["anchor_states"] += len(anchor_states)
            self.counts["truth"] += len(truth)
            self.counts["estimates"] += len(estimates)
            self.counts["diagnostics"] += len(diagnostics)
            return
        if anchor_states:
            new = anchor_columns_from_messages(anchor_states)
            log_anchors(self.rec, new, history=self._anchors, trail_s=self.trail_s)
            merged = AnchorColumns(
                np.concatenate([self._anchors.t_ns, new.t_ns]),
                np.concatenate([self._anchors.anchor_id, new.anchor_id]),
                np.concatenate([self._anchors.position_m, new.position_m]),
            )
            self._anchors = self._trim(merged, int(merged.t_ns.max()))
            self.counts["anchor_states"] += len(new)
        if truth:
            new_t = truth_columns_from_messages(truth)
            log_truth(self.rec, new_t)
            merged_t = TruthColumns(
                np.concatenate([self._truth.t_ns, new_t.t_ns]),
                np.concatenate([self._truth.node_id, new_t.node_id]),
                np.concatenate([self._truth.position_m, new_t.position_m]),
                np.concatenate([self._truth.floor_index, new_t.floor_index]),
            )
            if len(merged_t):
                self._truth = self._trim(merged_t, int(merged_t.t_ns.max()))
            self.counts["truth"] += len(new_t)
        if estimates:
            est = estimate_columns_from_messages(estimates)
            self._est_state = log_estimates(
                self.rec,
                est,
                anchors=Tracks(
                    self._anchors.t_ns, self._anchors.anchor_id, self._anchors.position_m
                ),
                truth=Tracks(
                    self._truth.t_ns,
                    self._truth.node_id,
                    self._truth.position_m,
                    self._truth.floor_index,
                )
                if len(self._truth)
                else None,
                building=self.building,
                path_period_s=self.path_period_s,
                state=self._est_state,
            )
            self.counts["estimates"] += len(est)
        if diagnostics:
            self._diag_state = log_diagnostics(self.rec, diagnostics, state=self._diag_state)
            self.counts["diagnostics"] += len(diagnostics)
        if events is not None and events.t_ns.size:
            log_events(self.rec, events)
            self.counts["events"] += int(events.t_ns.size)


def write_rrd(
    path: str | Path,
    *,
    building: BuildingOutline | None = None,
    anchors: AnchorColumns | None = None,
    truth: TruthColumns | None = None,
    estimates: EstimateColumns | None = None,
    diagnostics: Sequence[Any] = (),
    events: EventColumns | None = None,
    recording_id: str | None = None,
    path_period_s: float = 0.5,
) -> Path:
    """Write a complete dashboard .rrd from columns, in bulk, with the blueprint embedded.

    Returns the path written.
    """
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(APP_ID, recording_id=recording_id)
    rec.save(str(out), default_blueprint=default_blueprint())
    try:
        if building is not None:
            log_building(rec, building)
        if anchors is not None and len(anchors):
            log_anchors(rec, anchors)
        if truth is not None and len(truth):
            log_truth(rec, truth)
        if estimates is not None and len(estimates):
            log_estimates(
                rec,
                estimates,
                anchors=Tracks(anchors.t_ns, anchors.anchor_id, anchors.position_m)
                if anchors is not None
                else None,
                truth=Tracks(truth.t_ns, truth.node_id, truth.position_m, truth.floor_index)
                if truth is not None and len(truth)
                else None,
                building=building,
                path_period_s=path_period_s,
            )
        if diagnostics:
            log_diagnostics(rec, diagnostics)
        if events is not None:
            log_events(rec, events)
    finally:
        rec.flush()
        rec.disconnect()
    return out


_KIND_BY_CLASS = {
    "AnchorState": "anchor_state",
    "GroundTruth": "truth",
    "PositionEstimate": "estimate",
    "FusionDiagnostics": "diagnostics",
    "AnchorStateView": "anchor_state",
    "TruthView": "truth",
    "EstimateView": "estimate",
    "DiagnosticsView": "diagnostics",
}


def write_rrd_from_messages(
    messages: Iterable[Any],
    path: str | Path,
    *,
    building: Any = None,
    recording_id: str | None = None,
    events: EventColumns | None = None,
    path_period_s: float = 0.5,
) -> dict[str, int]:
    """Write the dashboard .rrd from decoded bus messages (e.g. read from an MCAP file).

    Parameters
    ----------
    messages : iterable
        Decoded messages in any order: ``AnchorState``, ``GroundTruth``, ``PositionEstimate``,
        ``FusionDiagnostics`` (others, e.g. ``RangeMeasurement``, are ignored). Items may
        also be ``(topic, message)`` or ``(topic, log_time_ns, message)`` tuples.
    path : str or Path
        Output .rrd.
    building : BuildingOutline or scenario building or mapping, optional
        Enables the wireframe, the window-edge diffraction points and floors from z.
    recording_id : str, optional
        Rerun recording id (e.g. the run id), so a live recording and its replay can be
        told apart or merged in the viewer.
    events : EventColumns, optional
        Extra events (e.g. liveliness changes recorded in the MCAP).

    Returns
    -------
    dict
        Number of messages used per kind.
    """
    groups: dict[str, list[Any]] = {
        "anchor_state": [],
        "truth": [],
        "estimate": [],
        "diagnostics": [],
    }
    for item in messages:
        msg = item[-1] if isinstance(item, tuple) else item
        kind = _KIND_BY_CLASS.get(type(msg).__name__)
        if kind is not None:
            groups[kind].append(msg)
    outline = BuildingOutline.from_object(building) if building is not None else None
    truth = truth_columns_from_messages(groups["truth"])
    write_rrd(
        path,
        building=outline,
        anchors=anchor_columns_from_messages(groups["anchor_state"]),
        truth=truth,
        estimates=estimate_columns_from_messages(groups["estimate"]),
        diagnostics=groups["diagnostics"],
        events=events,
        recording_id=recording_id,
        path_period_s=path_period_s,
    )
    return {k: len(v) for k, v in groups.items()} | {"truth_nodes": len(truth)}


# ============================================================================ MCAP -> .rrd
def _kind_scanner(path: str | Path, kinds: set[str]):
    """A damage-tolerant MCAP scanner plus the live set of topics of the wanted ``kinds``.

    ``McapScanner.iter_batches(topics)`` filters with ``topic in topics`` (a C-level set
    lookup); the set is filled as the scanner registers channels, so topics of other kinds
    (the many range messages) are skipped without being copied or decoded.
    """
    from diffpos_services.recording.mcap_io import McapScanner, parse_topic

    wanted: set[str] = set()

    classified: set[int] = set()

    class _Scanner(McapScanner):
        def _add_channel(self, body, pos=0):  # type: ignore[override]
            super()._add_channel(body, pos)
            # channel records repeat in every chunk: classify each channel id once
            for cid in self.channels.keys() - classified:
                classified.add(cid)
                topic = self.channels[cid].topic
                if parse_topic(topic)[0] in kinds:
                    wanted.add(topic)

    return _Scanner(path), wanted


def building_from_scenario_file(path: str | Path) -> BuildingOutline:
    """The building of a scenario: a TOML file, a shipped name (``paper``, ``large``) or
    ``default`` (the built-in scenario ``diffpos emulate`` runs without a file).

    Raises
    ------
    ValueError
        (``ScenarioError``) naming the file and the problem.
    """
    if str(path) == "default":
        from diffpos.scenario import default_scenario

        return BuildingOutline.from_object(default_scenario().building)
    from diffpos_services.scenario_io import load_scenario

    return BuildingOutline.from_object(load_scenario(path).building)


def building_for_option(value: str | None, *, option: str = "--scenario") -> BuildingOutline | None:
    """:func:`building_from_scenario_file` for a command-line option (``None`` if not given).

    Raises
    ------
    ConfigError
        Worded for the option: ``--scenario X: cannot read it (...)`` or the scenario error.
    """
    if not value:
        return None
    from diffpos_services.kit import ConfigError

    try:
        return building_from_scenario_file(value)
    except OSError as exc:
        raise ConfigError(f"{option} {value}: cannot read it ({exc.strerror})") from None
    except ValueError as exc:
        raise ConfigError(f"{option} {value}: {exc}") from None


def _building_from_attachments(attachments: Sequence[Any]) -> BuildingOutline | None:
    import tomllib

    from diffpos.scenario import Scenario

    for att in attachments:
        if str(att.name).endswith(".toml") or "toml" in str(att.media_type):
            try:
                scen = Scenario.from_dict(tomllib.loads(bytes(att.data).decode()))
            except Exception:  # not a scenario: ignore
                continue
            return BuildingOutline.from_object(scen.building)
    return None


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
    text = [
        f"{r.get('role')} {r.get('id') or ''} {'joined' if r.get('alive') else 'left'}".replace(
            "  ", " "
        )
        for r in recs
    ]
    level = ["INFO" if r.get("alive") else "WARN" for r in recs]
    return EventColumns(t_meas, text, level)


_LIST_DECODERS = {kind: msgspec.json.Decoder(list[dec.type]) for kind, dec in VIEW_DECODERS.items()}

_MCAP_KINDS = {
    "anchor_state": "AnchorState",
    "truth_node": "GroundTruth",
    "estimate": "PositionEstimate",
    "replay_estimate": "PositionEstimate",
    "diagnostics": "FusionDiagnostics",
    "liveliness": None,
}


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
    import functools
    import gc

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
    from diffpos_services.recording.mcap_io import parse_topic

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
                kind = kind_of[raw.topic] = parse_topic(raw.topic)[0]
            payloads.setdefault(kind, []).append(raw.data)
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
        outline = _building_from_attachments(sc.attachments)
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
    import rerun.chunk as rc

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


def key_of(msg: Any, *, site: str = "demo") -> str:
    """The bus key a message is published on (for writing synthetic runs to MCAP/Zenoh)."""
    from diffpos_services.wire.keys import Keys

    keys = Keys(site)
    name = type(msg).__name__
    if name == "AnchorState":
        return keys.anchor_state(msg.anchor_id)
    if name == "PositionEstimate":
        return keys.node_estimate(msg.node_id)
    if name == "GroundTruth":
        return keys.truth_node(msg.id) if msg.entity == "node" else keys.truth_anchor(msg.id)
    if name == "FusionDiagnostics":
        return keys.fusion_diagnostics()
    if name == "RangeMeasurement":
        return keys.anchor_range(msg.anchor_id, msg.node_id)
    raise ValueError(f"no bus key for message type {name}")
