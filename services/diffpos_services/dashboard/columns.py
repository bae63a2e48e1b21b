"""Input columns of the logging functions (one row per message) and their builders from
decoded bus messages."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from diffpos_services.dashboard.building import FloatArray
from diffpos_services.dashboard.common import _check_len, _str_array
from diffpos_services.dashboard.decode import estimate_extras


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
    link_mechanism : ndarray of str, shape (L,)
        Estimate v2: the first-arrival mechanism the fusion explained the link's range by (a
        label of :data:`diffpos.paths.mechanisms.MECHANISMS`); ``""`` where unknown (v1, excluded).
        Default: all ``""``.
    floor_probability : ndarray, shape (K,)
        Estimate v2: the probability of the estimated floor; NaN where unknown (v1).
        Default: all NaN.
    floor_probabilities : ndarray, shape (K, F)
        Estimate v2: the probability of every floor (NaN padded to the most floors of the
        batch); shape (K, 0) where none is known (v1). Default: (K, 0).
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
    link_mechanism: NDArray[np.str_] | None = None
    floor_probability: FloatArray | None = None
    floor_probabilities: FloatArray | None = None

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
        n_links = self.link_fix.shape[0]
        s(self, "link_mechanism", np.full(n_links, "", "<U1") if self.link_mechanism is None
          else _str_array(self.link_mechanism))
        s(self, "floor_probability", np.full(n, np.nan) if self.floor_probability is None
          else np.asarray(self.floor_probability, np.float64).reshape(-1))
        s(self, "floor_probabilities", np.zeros((n, 0)) if self.floor_probabilities is None
          else np.asarray(self.floor_probabilities, np.float64).reshape(n, -1))
        for name in ("node_id", "status", "peb_m", "floor_index", "floor_probability"):
            _check_len(f"EstimateColumns.{name}", getattr(self, name), n)
        for name in ("link_anchor_id", "link_used", "link_residual_m", "link_reason",
                     "link_mechanism"):
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
    """Columns from ``PositionEstimate`` messages (diffpos.estimate.v1 or v2: with v2 the
    mechanism of each used link and the estimated floor's probability,
    :func:`~diffpos_services.dashboard.decode.estimate_extras`)."""
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
        **estimate_extras(msgs),
    )
