"""The dashboard's partial views of the bus messages and their fast JSON decoders.

The dashboard is a viewer: it decodes only the fields it draws (msgspec skips the others),
type-checks them and leaves the value constraints of the full schemas
(:mod:`diffpos_services.wire.messages`) to the fusion and the wire-contract tests."""

from __future__ import annotations

import msgspec


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


_LIST_DECODERS = {kind: msgspec.json.Decoder(list[dec.type]) for kind, dec in VIEW_DECODERS.items()}
