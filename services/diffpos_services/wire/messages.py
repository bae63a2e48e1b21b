"""The bus messages: typed msgspec Structs, their JSON codec and their JSON Schemas.

Every message is a JSON object whose ``schema`` field names its type and version (for
example ``"diffpos.range.v1"``); a breaking change gets a new struct and a new ``.v2`` name.
Conventions: units in field names (``range_m``, ``snr_db``), times as integer nanoseconds
(``t_ns`` = measurement time in emulated/sensor time of the publisher's clock;
``*_wall_ns`` = ``time.time_ns()`` of the host that stamped it), vectors as ``[x, y, z]`` in
the building frame (front wall ``y = 0``, inside ``y > 0``, ``z`` up). Quantities that can be
undefined (an unidentifiable fix has no finite PEB) are ``null``, never NaN.

Estimates come in two versions: :class:`PositionEstimate` (``diffpos.estimate.v1``, the
D-NLS snapshot fix, still decoded: old recordings) and :class:`PositionEstimateV2`
(``diffpos.estimate.v2``, what the fusion publishes: the tracked or snapshot fix with floor
probabilities, the snapshot beside the filtered one, the mechanism per anchor);
:func:`estimate_decoder` reads both.

The checked-in ``schemas/<name>.v<N>.json`` files are generated from these structs::

    diffpos schemas --write schemas/

(:func:`write_schemas`) and ``tests/services/test_wire_contract.py`` fails when code and files drift apart.
"""

from __future__ import annotations

import inspect
import json
import math
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
from msgspec import Meta

from diffpos_services.errors import DiffposError
from diffpos_services.wire.ids import ID_PATTERN, id_checker

__all__ = [
    "DECISION_OPS",
    "ESTIMATE_TYPES",
    "GOOD_STATUSES",
    "MESSAGE_TYPES",
    "TRACK_STATUSES",
    "AnchorHealth",
    "AnchorLink",
    "AnchorState",
    "DecisionChunk",
    "DecodeError",
    "Exclusion",
    "FusionDiagnostics",
    "FusionDiagnosticsV1",
    "GroundTruth",
    "Heartbeat",
    "LatencyStats",
    "PositionEstimate",
    "PositionEstimateV2",
    "RangeBatch",
    "RangeMeasurement",
    "RunClock",
    "RunControl",
    "SnapshotFix",
    "decoder",
    "encode",
    "estimate_decoder",
    "finite_or_none",
    "json_schema",
    "schema_filename",
    "vec3",
    "write_schemas",
]

SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

# ----------------------------------------------------------------------------- field types
#: An identifier. The pattern is in the JSON Schema but not a msgspec constraint: msgspec
#: would run the regex on every id of every message (a 200-node RangeBatch decoded 4x slower);
#: :func:`diffpos_services.wire.messages.decoder` checks the ids after the decode instead,
#: against the set of ids already found valid (the regex runs once per distinct id).
Id = Annotated[
    str,
    Meta(
        extra_json_schema={"pattern": ID_PATTERN},
        description="Identifier, a single Zenoh key chunk (letters, digits, '_' and '-').",
    ),
]
#: Every integer on the wire is a signed 64-bit value (MCAP, numpy): larger JSON integers are
#: rejected by the decoder instead of overflowing later.
INT64_MIN = -(2**63)
INT64_MAX = 2**63 - 1
TimeNs = Annotated[
    int, Meta(ge=INT64_MIN, le=INT64_MAX, description="Time [ns] (integer nanoseconds).")
]
WallNs = Annotated[
    int, Meta(ge=0, le=INT64_MAX, description="Host wall-clock time, time.time_ns() [ns].")
]
Seq = Annotated[
    int, Meta(ge=0, le=INT64_MAX, description="Per-publisher sequence number, +1 per message.")
]
Vec3 = tuple[float, float, float]
PosM = Annotated[Vec3, Meta(description="Position [x, y, z] in building coordinates [m].")]
VelMS = Annotated[Vec3, Meta(description="Velocity [vx, vy, vz] in building coordinates [m/s].")]
SigmaM3 = Annotated[
    tuple[
        Annotated[float, Meta(ge=0)],
        Annotated[float, Meta(ge=0)],
        Annotated[float, Meta(ge=0)],
    ],
    Meta(description="One-sigma uncertainty per axis [m] (x, y, z)."),
]
NonNeg = Annotated[float, Meta(ge=0)]
Cov3 = Annotated[
    tuple[Vec3, Vec3, Vec3],
    Meta(description="3x3 covariance, row-major nested [[xx,xy,xz],[yx,yy,yz],[zx,zy,zz]] [m^2]."),
]

FixStatusName = Annotated[
    str,
    Meta(
        description=(
            "Fix status, the name of diffpos.estimators.FixStatus (e.g. OK, DEGRADED, "
            "UNIDENTIFIABLE, NOT_CONVERGED, INSUFFICIENT)."
        ),
        pattern=r"^[A-Z][A-Z0-9_]*$(?!\n)",
    ),
]

#: statuses of a track (``diffpos.tracking.tracker.TrackStatus`` names) in estimate v2
TRACK_STATUSES = ("UNINITIALISED", "INITIALISING", "TRACKING", "COASTING", "LOST")
#: statuses of an estimate whose position can be used: a good snapshot fix (``FixResult.ok``
#: of the core, by name) or a track that publishes a position
GOOD_STATUSES = frozenset({"OK", "OK_UNVERIFIED", "INITIALISING", "TRACKING", "COASTING"})


def finite_or_none(value: float | None) -> float | None:
    """``float(value)`` if finite, else ``None`` (JSON has no NaN/inf)."""
    if value is None:
        return None
    v = float(value)
    return v if math.isfinite(v) else None


def vec3(values: Iterable[float]) -> Vec3:
    """A plain ``(x, y, z)`` float tuple from any 3-sequence (numpy row, list)."""
    x, y, z = (float(v) for v in values)
    return (x, y, z)


class _Msg(msgspec.Struct, frozen=True, gc=False, tag_field="schema", kw_only=True):
    """Base of all bus messages (tagged with their ``schema`` name)."""


# ----------------------------------------------------------------------------- messages
class AnchorState(_Msg, tag="diffpos.anchor_state.v1"):
    """Self-reported state of one UAV anchor (its own navigation solution, e.g. GNSS/baro).

    ``t_ns`` is the anchor's clock at the time the state is valid; ranges from the same
    anchor use the same clock, so the fusion interpolates this state at each range's ``t_ns``.
    """

    anchor_id: Id
    t_ns: TimeNs
    seq: Seq
    position_m: PosM
    velocity_m_s: VelMS
    position_sigma_m: SigmaM3
    velocity_sigma_m_s: Annotated[NonNeg, Meta(description="Velocity one-sigma per axis [m/s].")]
    range_rate_hz: Annotated[
        float, Meta(gt=0, description="Rate at which this anchor ranges to every node [Hz].")
    ]
    t_pub_wall_ns: WallNs


class RangeMeasurement(_Msg, tag="diffpos.range.v1"):
    """One first-arrival range from an anchor to a node.

    ``range_m``, ``sigma_m`` and ``snr_db`` are ``null`` when no path was detected (the anchor
    still reports, so the fusion knows not to wait for it).
    """

    anchor_id: Id
    node_id: Id
    t_ns: TimeNs
    seq: Seq
    range_m: Annotated[float, Meta(ge=0, description="Measured path length [m].")] | None
    sigma_m: (
        Annotated[float, Meta(gt=0, description="Ranging one-sigma (CRLB at the SNR) [m].")] | None
    )
    snr_db: Annotated[float, Meta(description="SNR of the first arriving path [dB].")] | None
    t_pub_wall_ns: WallNs


class RangeBatch(_Msg, tag="diffpos.range_batch.v1"):
    """All ranges of one anchor epoch in one message (columnar), for large deployments.

    Equivalent to one :class:`RangeMeasurement` per node with the same ``anchor_id``,
    ``t_ns`` and ``t_pub_wall_ns``; the lists are aligned with ``node_ids`` (``null`` entries
    where no path was detected). An anchor publishes either batches or single ranges.
    """

    anchor_id: Id
    t_ns: TimeNs
    seq: Seq
    node_ids: list[Id]
    range_m: Annotated[
        list[Annotated[float, Meta(ge=0)] | None], Meta(description="Measured path lengths [m].")
    ]
    sigma_m: Annotated[
        list[Annotated[float, Meta(gt=0)] | None], Meta(description="Ranging one-sigmas [m].")
    ]
    snr_db: Annotated[list[float | None], Meta(description="First-path SNRs [dB].")]
    t_pub_wall_ns: WallNs


class Exclusion(msgspec.Struct, frozen=True, gc=False):
    """An anchor not used in a fix and why."""

    anchor_id: Id
    reason: Annotated[
        str,
        Meta(
            description=(
                "Reason name: a diffpos.estimators.ExclusionReason name (gating) or a fusion "
                "reason: NOT_REPORTED, NOT_DETECTED, NO_ANCHOR_STATE, STALE, ANCHOR_LOST."
            )
        ),
    ]


class PositionEstimate(_Msg, tag="diffpos.estimate.v1"):
    """Position fix of one node for one fusion epoch (D-NLS with gating).

    When the geometry is degraded or unidentifiable the status says so and the position,
    covariance and bounds may be ``null``: the fusion never publishes a wrong fix as OK.
    """

    node_id: Id
    t_ns: Annotated[
        int, Meta(description="Fix reference time (mean of the used range times) [ns].")
    ]
    epoch: Annotated[int, Meta(description="Fusion epoch index floor(t / epoch_period).")]
    seq: Seq
    status: FixStatusName
    position_m: PosM | None
    covariance_m2: Cov3 | None
    peb_m: Annotated[float, Meta(ge=0, description="Position error bound [m].")] | None
    z_bound_m: Annotated[float, Meta(ge=0, description="z-axis error bound [m].")] | None
    floor_index: Annotated[int, Meta(description="Floor index, 0 = ground floor.")] | None
    used_anchors: list[Id]
    residuals_m: Annotated[
        list[float], Meta(description="Post-fit residual per used anchor, same order [m].")
    ]
    excluded: list[Exclusion]
    message: str
    t_input_wall_ns: Annotated[
        int, Meta(ge=0, description="Latest t_pub_wall_ns among the ranges of this fix [ns].")
    ]
    t_pub_wall_ns: WallNs


FloorProbs = Annotated[
    list[Annotated[float, Meta(ge=0, le=1)]],
    Meta(description="Probability of every floor of the building, index = floor index "
                     "(empty when the method gives none).")]


class AnchorLink(msgspec.Struct, frozen=True, gc=False):
    """What the fix made of one anchor's range: the path mechanism it was explained by."""

    anchor_id: Id
    mechanism: Annotated[str, Meta(description=(
        "Label of the first-arrival mechanism used for this range (diffpos.paths.mechanisms.MECHANISMS, "
        "e.g. 'Tx-D(lower)-Rx'); null where the range was not explained by one (an outlier, "
        "or a method without mechanisms)."))] | None
    residual_m: Annotated[float, Meta(description=(
        "Range minus the model path length at the published position [m]."))] | None


class SnapshotFix(msgspec.Struct, frozen=True, gc=False):
    """The snapshot (single-epoch) fix of the same ranges, beside the filtered estimate."""

    method: Annotated[str, Meta(description="Estimator, e.g. mnls.")]
    status: FixStatusName
    position_m: PosM | None
    covariance_m2: Cov3 | None
    floor_index: Annotated[int, Meta(description="Most probable floor, 0 = ground floor.")] | None
    floor_probabilities: FloorProbs


class PositionEstimateV2(_Msg, tag="diffpos.estimate.v2"):
    """Estimate of one node for one fusion epoch: the tracked position (or a snapshot fix).

    With tracking (``method`` ``mnls+tracking``) ``status`` is the track's:
    INITIALISING (initialised from a snapshot, not yet confirmed), TRACKING, COASTING (no
    usable range this epoch: predicted, the covariance grows), LOST (no position) or
    UNINITIALISED (too few ranges so far); ``snapshot`` holds the epoch's own mnls fix when it
    was computed. Without tracking ``status`` is the snapshot status (a
    diffpos.estimators.FixStatus name) and ``snapshot`` is null. ``position_m`` is null when
    there is no usable position; ``covariance_m2`` includes the floor mixture and the model
    uncertainty. ``used_anchors``/``residuals_m``/``excluded`` keep their v1 meaning;
    ``links`` gives every anchor's mechanism and residual.
    """

    node_id: Id
    t_ns: Annotated[
        int, Meta(description="Estimate time (mean of the used range times) [ns].")
    ]
    epoch: Annotated[int, Meta(description="Fusion epoch index floor(t / epoch_period).")]
    seq: Seq
    method: Annotated[str, Meta(description="mnls+tracking, mnls, dnls, lls or ippa.")]
    status: FixStatusName
    position_m: PosM | None
    covariance_m2: Cov3 | None
    peb_m: Annotated[float, Meta(ge=0, description=(
        "sqrt(trace(covariance)) [m].")) ] | None
    z_bound_m: Annotated[float, Meta(ge=0, description="sqrt(covariance zz) [m].")] | None
    floor_index: Annotated[int, Meta(description="Floor index, 0 = ground floor.")] | None
    floor_probabilities: FloorProbs
    snapshot: SnapshotFix | None
    links: Annotated[list[AnchorLink], Meta(description=(
        "Every anchor with a range in this epoch: mechanism and residual."))]
    used_anchors: list[Id]
    residuals_m: Annotated[
        list[float], Meta(description="Residual per used anchor, same order [m].")
    ]
    excluded: list[Exclusion]
    message: str
    t_input_wall_ns: Annotated[
        int, Meta(ge=0, description="Latest t_pub_wall_ns among the ranges of this fix [ns].")
    ]
    t_pub_wall_ns: WallNs


#: the estimate versions a reader accepts (:func:`estimate_decoder`)
ESTIMATE_TYPES = (PositionEstimate, PositionEstimateV2)


class LatencyStats(msgspec.Struct, frozen=True, gc=False):
    """Latency from the newest input's publish to the estimate's publish, over a window."""

    count: Annotated[int, Meta(ge=0)]
    p50_ms: NonNeg | None
    p99_ms: NonNeg | None
    max_ms: NonNeg | None


class AnchorHealth(msgspec.Struct, frozen=True, gc=False):
    """What the fusion knows about one anchor."""

    anchor_id: Id
    alive: bool
    states: Annotated[int, Meta(ge=0, description="AnchorState messages accepted.")]
    ranges: Annotated[int, Meta(ge=0, description="RangeMeasurement messages accepted.")]
    last_t_ns: TimeNs | None
    lost_wall_ns: Annotated[int, Meta(ge=0, description="When the anchor was lost [ns].")] | None


# what recordings made before FusionDiagnostics v2 hold (decoder() returns it as v2 with the
# new fields at their defaults); its docstring is the v1 schema's description: unchanged
class FusionDiagnosticsV1(_Msg, tag="diffpos.fusion_diagnostics.v1"):
    """Periodic counters of the fusion service (cumulative since start)."""

    t_wall_ns: WallNs
    watermark_ns: (
        Annotated[int, Meta(description="Newest measurement time seen from any anchor [ns].")]
        | None
    )
    received: Annotated[dict[str, int], Meta(description="Messages received per kind.")]
    rejected: Annotated[dict[str, int], Meta(description="Messages rejected per reason.")]
    gated: Annotated[int, Meta(ge=0, description="Measurements excluded by outlier gating.")]
    solved: Annotated[int, Meta(ge=0, description="Fixes computed.")]
    published: Annotated[int, Meta(ge=0, description="Estimates published.")]
    fixes_by_status: dict[str, int]
    late_ranges: Annotated[int, Meta(ge=0, description="Ranges for already-solved epochs.")]
    pending_epochs: Annotated[int, Meta(ge=0)]
    live_anchors: list[Id]
    anchors: list[AnchorHealth]
    latency: LatencyStats


#: operation codes of :class:`DecisionChunk` (``ops``): sample, oversized, alive, lost, step,
#: flush
DECISION_OPS = (0, 1, 2, 3, 4, 5)


class DecisionChunk(msgspec.Struct, frozen=True, gc=False):
    """A part of the fusion's decision record (``diffpos_services.fusion.decisions``): its
    state-changing calls in order, as columns. ``ops[i]``: 0 sample (``keys[refs[i]]`` is
    the key, ``values[i]`` the CRC-32 of the payload, the wall time its receive time), 1
    oversized sample (``values[i]`` its size), 2/3 anchor ``keys[refs[i]]`` alive/lost, 4
    step (``values[i]`` its limit, -1 none), 5 flush. Wall times are deltas from the
    previous event of the chunk (the first one absolute)."""

    chunk: Annotated[int, Meta(ge=0, description=(
        "Chunks with events before this one (a gap: a lost chunk).")) ]
    keys: list[str]
    ops: list[Annotated[int, Meta(ge=0, le=5)]]
    refs: list[Annotated[int, Meta(ge=0)]]
    values: list[int]
    wall_delta_ns: list[int]
    dropped: Annotated[int, Meta(ge=0, description="Events not recorded (record overflow).")]


class FusionDiagnostics(_Msg, tag="diffpos.fusion_diagnostics.v2"):
    """Periodic counters of the fusion service (cumulative since start), v2: v1 plus why fixes
    were lost (late ranges per anchor, the release rule in force, how epochs were released)
    and the fusion's decision record since the previous diagnostics (``decisions``: what
    ``diffpos replay`` needs to make the live fusion's decisions again). With shards
    (``diffpos fusion --shard K/N``) each fusion publishes its own on the one diagnostics key,
    saying which it is (``shard``, ``shards``)."""

    t_wall_ns: WallNs
    watermark_ns: (
        Annotated[int, Meta(description="Newest measurement time seen from any anchor [ns].")]
        | None
    )
    received: Annotated[dict[str, int], Meta(description="Messages received per kind.")]
    rejected: Annotated[dict[str, int], Meta(description="Messages rejected per reason.")]
    gated: Annotated[int, Meta(ge=0, description="Measurements excluded by outlier gating.")]
    solved: Annotated[int, Meta(ge=0, description="Fixes computed.")]
    published: Annotated[int, Meta(ge=0, description="Estimates published.")]
    fixes_by_status: dict[str, int]
    late_ranges: Annotated[int, Meta(ge=0, description="Ranges for already-solved epochs.")]
    pending_epochs: Annotated[int, Meta(ge=0)]
    live_anchors: list[Id]
    anchors: list[AnchorHealth]
    latency: LatencyStats
    late_by_anchor: Annotated[dict[str, int], Meta(description=(
        "Ranges dropped as late (their epoch already released), per anchor."))] = {}
    deadline_ns: Annotated[int, Meta(ge=0, description=(
        "Lateness allowance in force: an epoch is released when the measurement watermark "
        "passed its end by this much [ns]."))] | None = None
    max_lag_ns: Annotated[int, Meta(ge=0, description=(
        "Largest allowance (and the wall-clock fallback) [ns]."))] | None = None
    lag_by_anchor: Annotated[dict[str, int], Meta(description=(
        "Each anchor's largest recent lag behind the watermark [ns]."))] = {}
    releases: Annotated[dict[str, int], Meta(description=(
        "Epochs released per reason: complete (every live anchor reported), watermark "
        "(closed by measurement time), wall_fallback (a wall-clock timeout), flush."))] = {}
    decisions: DecisionChunk | None = None
    instance: Annotated[str, Meta(description=(
        "The fusion process that sent this (a random nonce per process start, as in its "
        "heartbeat): a restarted fusion starts a new decision record under a new instance."
        ))] = ""
    duplicate_publishers: Annotated[dict[str, int], Meta(description=(
        "Per anchor: how often a second publisher appeared under its key (another process "
        "nonce, or a sequence number that did not advance); the anchor is not used while "
        "two publish at once."))] = {}
    contested_anchors: Annotated[list[Id], Meta(description=(
        "Anchors not used now because two publishers share their key."))] = []
    shard: Annotated[int, Meta(ge=0, description=(
        "The share of the responders this fusion owns (diffpos fusion --shard K/N: K; 0 "
        "without shards): it publishes the estimates of the responders whose CRC-32 of the "
        "id modulo shards is this, and its decision record is replayed on a core of that "
        "shard."))] = 0
    shards: Annotated[int, Meta(ge=1, description=(
        "How many fusions share the responders (N of --shard K/N; 1: one fusion owns all). "
        "Absent in recordings made before shards were recorded: read as 0 of 1."))] = 1


class Heartbeat(_Msg, tag="diffpos.heartbeat.v1"):
    """A service's progress, published every ``period_ns`` by a thread of its own (the
    supervisor of ``diffpos emulate`` treats a process whose progress stops while its
    liveliness token lives as hung: a SIGSTOPped process sends nothing, a stuck one repeats
    the same ``progress`` with work ``pending``).

    ``progress`` is a counter of work done that only grows: the fusion's samples ingested plus
    epochs solved, the recorder's samples taken from the bus, an anchor's epochs published.
    """

    service: Annotated[str, Meta(description="fusion, recorder, anchor or dashboard.")]
    instance: Annotated[str, Meta(description="Random nonce of this process start.")]
    pid: Annotated[int, Meta(ge=0)]
    seq: Seq
    t_wall_ns: WallNs
    period_ns: Annotated[int, Meta(gt=0, description="Heartbeat period [ns].")]
    progress: Annotated[int, Meta(ge=0, description="Work done so far (only grows).")]
    pending: Annotated[int, Meta(ge=0, description=(
        "Work waiting (queued samples, epochs to solve); 0 = idle, no progress expected."))]
    last_epoch: Annotated[int, Meta(description=(
        "Fusion: newest epoch solved; anchor: last epoch published."))] | None
    published: Annotated[int, Meta(ge=0, description=(
        "Fusion: estimates published; recorder: messages written; anchor: messages sent."))]
    anchor_id: Id | None = None


class GroundTruth(_Msg, tag="diffpos.truth.v1"):
    """Emulation ground truth of a node or an anchor (its own key: fusion never reads it)."""

    entity: Literal["node", "anchor"]
    id: Id
    t_ns: TimeNs
    position_m: PosM
    velocity_m_s: VelMS
    floor_index: Annotated[int, Meta(description="Floor index of a node, 0 = ground.")] | None


class RunControl(_Msg, tag="diffpos.run_control.v1"):
    """Time base of an emulated run, published by the orchestrator to start the anchors.

    Emulated time ``t = t0_ns + speed * (time.time_ns() - wall_t0_ns)``; with ``lockstep``
    it is instead released step by step by :class:`RunClock` messages (as fast as the fusion
    keeps up).
    """

    run_id: str
    t0_ns: TimeNs
    wall_t0_ns: WallNs
    speed: Annotated[float, Meta(gt=0, description="Emulated seconds per wall second.")]
    duration_ns: Annotated[int, Meta(ge=0, description="Emulated run length, 0 = unlimited [ns].")]
    seed: Annotated[int, Meta(ge=0)]
    lockstep: Annotated[
        bool, Meta(description="Emulated time advances only with RunClock messages.")
    ] = False


class RunClock(_Msg, tag="diffpos.run_clock.v1"):
    """Lockstep emulation: anchors may measure up to emulated time ``t_ns`` (inclusive)."""

    run_id: str
    t_ns: TimeNs


class _Untagged(_Msg, tag="diffpos.never-sent"):
    """Sentinel member of the decoders' tagged unions (no message has this tag)."""


#: message struct -> schema file stem
MESSAGE_TYPES: dict[type[msgspec.Struct], str] = {
    AnchorState: "anchor_state.v1",
    RangeMeasurement: "range.v1",
    RangeBatch: "range_batch.v1",
    PositionEstimate: "estimate.v1",
    PositionEstimateV2: "estimate.v2",
    FusionDiagnosticsV1: "fusion_diagnostics.v1",
    FusionDiagnostics: "fusion_diagnostics.v2",
    GroundTruth: "truth.v1",
    RunControl: "run_control.v1",
    RunClock: "run_clock.v1",
    Heartbeat: "heartbeat.v1",
}

#: older versions :func:`decoder` still reads (and returns as the newest): recordings
_OLDER_VERSIONS: dict[type, tuple[type, ...]] = {FusionDiagnostics: (FusionDiagnosticsV1,)}

_ENCODER = msgspec.json.Encoder()
_AT_RE = re.compile(r"- at `([^`]*)`")
_MISSING_RE = re.compile(r"missing required field `([^`]*)`")
_DECODERS: dict[type, msgspec.json.Decoder] = {}


class DecodeError(DiffposError, ValueError):
    """A payload that is not a valid message of the expected type.

    The services catch it per message (counted, logged); one that reaches the command line
    ends it with exit code 1, as an uncaught error did before.

    Attributes
    ----------
    reason : str
        ``"json"`` (not UTF-8 JSON, or nested deeper than the decoder's recursion limit) or
        ``"schema"`` (valid JSON that is not this message: wrong or missing ``schema`` tag,
        e.g. another version; a missing field; a wrong type; a value out of its range).
    detail : str
        msgspec's message, e.g. ``Expected `int` >= 0 - at `$.seq```.
    field : str or None
        The JSON path of the offending field (``"$.seq"``, ``"$.range_m[3]"``) when known.
    """

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail
        m = _AT_RE.search(detail) or _MISSING_RE.search(detail)
        self.field: str | None = None
        if m is not None:
            self.field = m.group(1) if m.re is _AT_RE else "$." + m.group(1)


def encode(msg: msgspec.Struct) -> bytes:
    """JSON bytes of a message."""
    return _ENCODER.encode(msg)


def decoder(kind: type[msgspec.Struct]):
    """A function ``bytes -> kind`` raising :class:`DecodeError` (reason ``json``/``schema``).

    It never raises anything else, whatever the bytes (fuzzed in ``tests/test_fuzz.py``).
    Unknown extra fields are ignored (forward compatibility within a version). For
    :class:`FusionDiagnostics` it also reads v1 (recordings made before v2) and returns it as
    v2 with the new fields at their defaults.
    """
    older = _OLDER_VERSIONS.get(kind, ())
    dec = _DECODERS.get(kind)
    if dec is None:
        # a tagged union (with a never-sent sentinel) makes msgspec require the ``schema`` tag:
        # decoding the struct alone would accept a message without one
        target = kind | _Untagged if issubclass(kind, _Msg) else kind
        for old in older:
            target = target | old
        dec = _DECODERS[kind] = msgspec.json.Decoder(target)
    if not older:
        return _checked_decode(dec, (kind,))
    checked = _checked_decode(dec, (kind, *older))

    def decode_upgraded(payload: bytes | bytearray | memoryview) -> Any:
        msg = checked(payload)
        return msg if type(msg) is kind else _upgrade(kind, msg)

    return decode_upgraded


def _upgrade(kind: type[msgspec.Struct], msg: msgspec.Struct) -> Any:
    """An older version of ``kind`` as ``kind`` (the fields it lacks at their defaults)."""
    return kind(**{f: getattr(msg, f) for f in msg.__struct_fields__})


def _checked_decode(dec: msgspec.json.Decoder, accepted: tuple[type, ...]):
    """``bytes -> message`` through ``dec``, every failure a :class:`DecodeError`, and a
    message of another type than ``accepted`` (the never-sent sentinel) rejected, and so is
    one with an invalid id (:func:`~diffpos_services.wire.ids.id_checker`)."""
    ids = {kind: id_checker(kind) for kind in accepted}

    def decode(payload: bytes | bytearray | memoryview) -> Any:
        try:
            msg = dec.decode(payload)
        except msgspec.ValidationError as exc:
            raise DecodeError("schema", str(exc)) from None
        except msgspec.DecodeError as exc:
            raise DecodeError("json", str(exc)) from None
        except RecursionError:
            # msgspec skips unknown fields recursively: ~1000 nested arrays exhaust the stack
            raise DecodeError("json", "JSON nested too deeply") from None
        if type(msg) not in accepted:
            raise DecodeError("schema", f"Invalid value {_Untagged.__struct_config__.tag!r} - "
                              "at `$.schema`")
        check = ids.get(type(msg))
        if check is not None:
            try:
                check(msg)
            except ValueError as exc:
                raise DecodeError("schema", str(exc)) from None
        return msg

    return decode


def estimate_decoder():
    """A function ``bytes -> PositionEstimate | PositionEstimateV2`` (by the ``schema`` tag),
    raising :class:`DecodeError` like :func:`decoder`: the consumers of estimates read both
    versions (v1 in recordings made before estimate v2)."""
    dec = _DECODERS.get(PositionEstimateV2 | PositionEstimate)
    if dec is None:
        dec = _DECODERS[PositionEstimateV2 | PositionEstimate] = msgspec.json.Decoder(
            PositionEstimate | PositionEstimateV2 | _Untagged)
    return _checked_decode(dec, ESTIMATE_TYPES)


def schema_filename(kind: type[msgspec.Struct]) -> str:
    """``<stem>.json`` file name of a message type."""
    return MESSAGE_TYPES[kind] + ".json"


def json_schema(kind: type[msgspec.Struct]) -> dict[str, Any]:
    """JSON Schema (2020-12) of a message type, with the object at the top level.

    msgspec puts the struct in ``$defs`` behind a top-level ``$ref``; viewers such as
    Foxglove want ``"type": "object"`` at the top, so the struct is lifted and the remaining
    definitions (nested structs) stay in ``$defs`` with internal references only.
    """
    raw = msgspec.json.schema(kind)
    defs = dict(raw.get("$defs", {}))
    name = raw["$ref"].rsplit("/", 1)[-1]
    body = defs.pop(name)
    schema: dict[str, Any] = {
        "$schema": SCHEMA_DIALECT,
        "$id": f"https://diffpos.invalid/schemas/{MESSAGE_TYPES[kind]}.json",
    }
    schema.update(body)
    schema["title"] = f"diffpos.{MESSAGE_TYPES[kind]}"
    if defs:
        schema["$defs"] = defs
    for obj in [schema, *defs.values()]:
        if "description" in obj:
            obj["description"] = inspect.cleandoc(obj["description"])
    return schema


def schema_text(kind: type[msgspec.Struct]) -> str:
    """The exact text of the checked-in schema file."""
    return json.dumps(json_schema(kind), indent=2, sort_keys=True) + "\n"


def write_schemas(directory: str | Path) -> list[Path]:
    """Write every message schema into ``directory``; return the paths."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for kind in MESSAGE_TYPES:
        path = out / schema_filename(kind)
        path.write_text(schema_text(kind), encoding="utf-8")
        paths.append(path)
    return paths

