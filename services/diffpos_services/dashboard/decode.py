"""The dashboard's partial views of the bus messages and their fast JSON decoders.

The dashboard is a viewer: it decodes only the fields it draws (msgspec skips the others),
type-checks them and leaves the value constraints of the full schemas
(:mod:`diffpos_services.wire.messages`) to the fusion and the wire-contract tests."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import msgspec
import numpy as np


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


class LinkView(msgspec.Struct, frozen=True, gc=False):
    """The part of ``messages.AnchorLink`` (estimate v2) the dashboard reads."""

    anchor_id: str
    mechanism: str | None = None
    residual_m: float | None = None


class EstimateView(msgspec.Struct, frozen=True, gc=False):
    """The part of ``diffpos.estimate.v1`` and ``diffpos.estimate.v2`` the dashboard reads
    (the v2-only fields default to empty for v1: no floor probabilities, no mechanisms)."""

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
    floor_probabilities: list[float] = []
    links: list[LinkView] = []


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


_LIST_DECODERS = {kind: msgspec.json.Decoder(list[dec.type]) for kind, dec in VIEW_DECODERS.items()}


def estimate_extras(msgs: Sequence[Any]) -> dict[str, Any]:
    """The estimate-v2 columns the dashboard draws beyond ``EstimateColumns``' v1 fields,
    aligned with :func:`~diffpos_services.dashboard.columns.estimate_columns_from_messages`
    (links: every fix's used anchors, then every fix's excluded ones).

    Returns
    -------
    dict
        ``link_mechanism`` (ndarray of str, shape (L,): the mechanism label of each used link,
        ``""`` where unknown: v1, excluded) and ``floor_probability`` (ndarray, shape (K,):
        the probability of the estimated floor, NaN where unknown) and
        ``floor_probabilities`` (ndarray, shape (K, F): every floor's, NaN padded).
    """
    used = []
    for m in msgs:
        mech = {lk.anchor_id: lk.mechanism or "" for lk in getattr(m, "links", ())}
        used += [mech.get(a, "") for a in m.used_anchors]
    n_ex = sum(len(m.excluded) for m in msgs)
    prob = np.full(len(msgs), np.nan)
    vectors = [getattr(m, "floor_probabilities", None) or () for m in msgs]
    probs = np.full((len(msgs), max((len(v) for v in vectors), default=0)), np.nan)
    for i, (m, p) in enumerate(zip(msgs, vectors, strict=True)):
        probs[i, :len(p)] = p
        if p and m.floor_index is not None and 0 <= m.floor_index < len(p):
            prob[i] = p[m.floor_index]
    return {"link_mechanism": np.array(used + [""] * n_ex, dtype=str),
            "floor_probability": prob, "floor_probabilities": probs}
