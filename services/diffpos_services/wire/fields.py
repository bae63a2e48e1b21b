"""Field types and the message base shared by :mod:`diffpos_services.wire.messages` (split
out to keep that module readable; import them from ``messages``)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Annotated

import msgspec
from msgspec import Meta

SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

# ----------------------------------------------------------------------------- field types
#: What an identifier is on the wire ("(?!\n)": Python's "$", as msgspec's and jsonschema's,
#: also matches before a final newline).
ID_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_\-]{0,63}$(?!\n)"
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


