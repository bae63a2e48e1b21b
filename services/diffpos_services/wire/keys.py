"""Zenoh key expressions of the diffpos bus: the one place where they are spelled.

Every key lives under ``diffpos/<site>/``; a recorder or dashboard subscribing to
``diffpos/<site>/**`` sees every data message (liveliness tokens travel separately and are
watched with a liveliness subscriber on :meth:`Keys.alive_all`).

========================================== ===================== ===============================
key expression                              message (schemas/)     publisher -> subscribers
========================================== ===================== ===============================
``diffpos/<site>/anchor/<anchor>/state``    ``anchor_state.v1``    anchor -> fusion, recorder, UI
``diffpos/<site>/anchor/<anchor>/range/<node>`` ``range.v1``       anchor -> fusion, recorder, UI
``diffpos/<site>/anchor/<anchor>/ranges``   ``range_batch.v1``     anchor (--range-batch) -> fusion, recorder
``diffpos/<site>/node/<node>/estimate``     ``estimate.v1``        fusion -> recorder, UI, emulate
``diffpos/<site>/fusion/diagnostics``       ``fusion_diagnostics.v1`` fusion -> recorder, UI
``diffpos/<site>/truth/node/<node>``        ``truth.v1``           emulate -> recorder, UI (never fusion)
``diffpos/<site>/truth/anchor/<anchor>``    ``truth.v1``           emulate -> recorder, UI (never fusion)
``diffpos/<site>/run/control``              ``run_control.v1``     emulate -> anchors (start gate)
``diffpos/<site>/run/clock``                ``run_clock.v1``       emulate -> anchors (lockstep runs)
``diffpos/<site>/alive/anchor/<anchor>``    liveliness token       anchor -> fusion, emulate
``diffpos/<site>/alive/fusion``             liveliness token       fusion -> emulate
``diffpos/<site>/alive/recorder``           liveliness token       recorder -> emulate
``diffpos/<site>/heartbeat/<service>``       ``heartbeat.v1``       fusion, recorder, dashboard -> emulate
``diffpos/<site>/heartbeat/anchor/<anchor>`` ``heartbeat.v1``       anchor -> emulate
========================================== ===================== ===============================

Two more topics exist only in MCAP recordings (never on the bus):
``diffpos/<site>/recorder/liveliness`` (the recorder's liveliness events, one JSON object per
token appearing or disappearing: :meth:`Keys.recorder_liveliness`) and
``diffpos/<site>/replay/node/<node>/estimate`` (estimates written by ``diffpos replay
--write-mcap``, kept apart from the live ones: :meth:`Keys.replay_estimate`).

Identifiers (site, anchor and node ids) are single key chunks: letters, digits, ``_`` and
``-`` only (no ``/``, no wildcards).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any, Literal

from diffpos.scenario import ID_PATTERN

__all__ = [
    "HEARTBEAT_SERVICES",
    "PREFIX",
    "SEQUENCE_STREAMS",
    "KeyKind",
    "Keys",
    "ParsedKey",
    "check_id",
    "parse_key",
    "parse_recording_topic",
]

#: First chunk of every diffpos key.
PREFIX = "diffpos"

_ID_RE = ID_PATTERN  # one grammar for scenario files and the wire

#: message kind -> its sequence stream (the key pattern of one publisher's counter): an anchor
#: numbers its state and all its ranges with one counter, the fusion all its estimates
SEQUENCE_STREAMS: dict[str, str] = {
    "anchor_state": "anchor/{anchor}/**",
    "range": "anchor/{anchor}/**",
    "range_batch": "anchor/{anchor}/**",
    "estimate": "node/*/estimate",
    "replay_estimate": "replay/node/*/estimate",
}

KeyKind = Literal[
    "anchor_state",
    "range",
    "range_batch",
    "estimate",
    "diagnostics",
    "truth_node",
    "truth_anchor",
    "run_control",
    "run_clock",
    "alive_anchor",
    "alive_fusion",
    "alive_recorder",
    "alive_dashboard",
    "heartbeat",
]

#: services that publish a heartbeat under ``heartbeat/<service>`` (anchors: under
#: ``heartbeat/anchor/<anchor>``)
HEARTBEAT_SERVICES = ("fusion", "recorder", "dashboard")


def check_id(value: str, *, field: str = "id") -> str:
    """Return ``value`` if it is a valid key chunk, else raise ``ValueError`` naming ``field``.

    Valid: 1-64 characters from ``[A-Za-z0-9_-]``, not starting with ``-``.
    """
    if not isinstance(value, str) or not _ID_RE.fullmatch(value):
        raise ValueError(
            f"{field}={value!r} is not a valid identifier: use 1-64 characters from "
            "letters, digits, '_' and '-' (no '/', '*', '$', '?', '#' or spaces)"
        )
    return value


@dataclass(frozen=True)
class ParsedKey:
    """A concrete key split into its meaning.

    Attributes
    ----------
    kind : str
        One of :data:`KeyKind`.
    site : str
    anchor_id, node_id : str or None
        The identifiers present in the key.
    service : str or None
        A heartbeat's service (``fusion``, ``recorder``, ``dashboard``, ``anchor``).
    """

    kind: str
    site: str
    anchor_id: str | None = None
    node_id: str | None = None
    service: str | None = None


@dataclass(frozen=True)
class Keys:
    """Key expressions of one site.

    Parameters
    ----------
    site : str
        Site (deployment) name, a single key chunk such as ``"paper"`` or ``"demo"``.
    """

    site: str

    def __post_init__(self) -> None:
        check_id(self.site, field="site")

    @property
    def root(self) -> str:
        """``diffpos/<site>``."""
        return f"{PREFIX}/{self.site}"

    # -- concrete keys -------------------------------------------------------------------
    def anchor_state(self, anchor_id: str) -> str:
        return f"{self.root}/anchor/{anchor_id}/state"

    def anchor_range(self, anchor_id: str, node_id: str) -> str:
        return f"{self.root}/anchor/{anchor_id}/range/{node_id}"

    def anchor_range_batch(self, anchor_id: str) -> str:
        """All ranges of one anchor epoch in one message (large deployments)."""
        return f"{self.root}/anchor/{anchor_id}/ranges"

    def node_estimate(self, node_id: str) -> str:
        return f"{self.root}/node/{node_id}/estimate"

    def fusion_diagnostics(self) -> str:
        return f"{self.root}/fusion/diagnostics"

    def truth_node(self, node_id: str) -> str:
        return f"{self.root}/truth/node/{node_id}"

    def truth_anchor(self, anchor_id: str) -> str:
        return f"{self.root}/truth/anchor/{anchor_id}"

    def run_control(self) -> str:
        return f"{self.root}/run/control"

    def run_clock(self) -> str:
        return f"{self.root}/run/clock"

    def alive_anchor(self, anchor_id: str) -> str:
        """Liveliness token of one anchor."""
        return f"{self.root}/alive/anchor/{anchor_id}"

    def alive_fusion(self) -> str:
        """Liveliness token of the fusion service."""
        return f"{self.root}/alive/fusion"

    def alive_recorder(self) -> str:
        """Liveliness token of the MCAP recorder (declared once it is subscribed)."""
        return f"{self.root}/alive/recorder"

    def alive_dashboard(self) -> str:
        """Liveliness token of the live dashboard (declared once it is subscribed and its
        Rerun sink is open: ``diffpos emulate`` waits for it, so a saved .rrd misses nothing)."""
        return f"{self.root}/alive/dashboard"

    def heartbeat(self, service: str, anchor_id: str | None = None) -> str:
        """Heartbeat key of a service (:data:`HEARTBEAT_SERVICES`) or of one anchor."""
        if anchor_id is not None:
            return f"{self.root}/heartbeat/anchor/{anchor_id}"
        if service not in HEARTBEAT_SERVICES:
            raise ValueError(f"no heartbeat key for service {service!r}")
        return f"{self.root}/heartbeat/{service}"

    def of(self, msg: Any) -> str:
        """The key a message struct of :mod:`diffpos_services.wire.messages` is published on
        (by its type and ids; for writing synthetic runs to MCAP or the bus)."""
        name = type(msg).__name__
        if name == "AnchorState":
            return self.anchor_state(msg.anchor_id)
        if name == "RangeMeasurement":
            return self.anchor_range(msg.anchor_id, msg.node_id)
        if name == "RangeBatch":
            return self.anchor_range_batch(msg.anchor_id)
        if name in ("PositionEstimate", "PositionEstimateV2"):
            return self.node_estimate(msg.node_id)
        if name == "GroundTruth":
            return self.truth_node(msg.id) if msg.entity == "node" else self.truth_anchor(msg.id)
        if name in ("FusionDiagnostics", "FusionDiagnosticsV1"):
            return self.fusion_diagnostics()
        if name == "RunControl":
            return self.run_control()
        if name == "RunClock":
            return self.run_clock()
        if name == "Heartbeat":
            return self.heartbeat(msg.service, msg.anchor_id)
        raise ValueError(f"no bus key for message type {name}")

    # -- recording-only topics (MCAP channels, never published) ----------------------------
    def recorder_liveliness(self) -> str:
        """MCAP topic of the recorder's liveliness-event channel."""
        return f"{self.root}/recorder/liveliness"

    def replay_estimate(self, node_id: str) -> str:
        """MCAP topic of a replayed estimate (kept apart from the live ``node/<id>/estimate``)."""
        return f"{self.root}/replay/node/{node_id}/estimate"

    # -- patterns ------------------------------------------------------------------------
    def everything(self) -> str:
        """All data messages of the site (what a recorder subscribes to)."""
        return f"{self.root}/**"

    def anchor_states(self) -> str:
        return f"{self.root}/anchor/*/state"

    def anchor_ranges(self) -> str:
        return f"{self.root}/anchor/*/range/*"

    def anchor_range_batches(self) -> str:
        return f"{self.root}/anchor/*/ranges"

    def estimates(self) -> str:
        return f"{self.root}/node/*/estimate"

    def truth_all(self) -> str:
        return f"{self.root}/truth/**"

    def heartbeats(self) -> str:
        """Every heartbeat of the site."""
        return f"{self.root}/heartbeat/**"

    def alive_anchors(self) -> str:
        """Liveliness pattern matching every anchor token."""
        return f"{self.root}/alive/anchor/*"

    def alive_all(self) -> str:
        """Liveliness pattern matching every token of the site."""
        return f"{self.root}/alive/**"

    def fusion_inputs(self) -> tuple[str, ...]:
        """The data key expressions the fusion service subscribes to (no truth, by design)."""
        # one subscription: an anchor's state, ranges and range batches arrive in publish order
        return (f"{self.root}/anchor/**",)


def parse_key(key: str) -> ParsedKey | None:
    """Classify a concrete diffpos key; ``None`` if it is not one of ours.

    >>> parse_key("diffpos/demo/anchor/uav1/range/n03")
    ParsedKey(kind='range', site='demo', anchor_id='uav1', node_id='n03')

    Cached (the same few thousand keys arrive over and over; results are immutable).
    """
    return _parse_key(str(key))


@functools.lru_cache(maxsize=1 << 14)
def _parse_key(key: str) -> ParsedKey | None:
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != PREFIX:
        return None
    site, rest = parts[1], parts[2:]
    match rest:
        case ["anchor", a, "state"]:
            return ParsedKey("anchor_state", site, anchor_id=a)
        case ["anchor", a, "range", n]:
            return ParsedKey("range", site, anchor_id=a, node_id=n)
        case ["anchor", a, "ranges"]:
            return ParsedKey("range_batch", site, anchor_id=a)
        case ["node", n, "estimate"]:
            return ParsedKey("estimate", site, node_id=n)
        case ["fusion", "diagnostics"]:
            return ParsedKey("diagnostics", site)
        case ["truth", "node", n]:
            return ParsedKey("truth_node", site, node_id=n)
        case ["truth", "anchor", a]:
            return ParsedKey("truth_anchor", site, anchor_id=a)
        case ["run", "control"]:
            return ParsedKey("run_control", site)
        case ["run", "clock"]:
            return ParsedKey("run_clock", site)
        case ["alive", "anchor", a]:
            return ParsedKey("alive_anchor", site, anchor_id=a)
        case ["alive", "fusion"]:
            return ParsedKey("alive_fusion", site)
        case ["alive", "recorder"]:
            return ParsedKey("alive_recorder", site)
        case ["alive", "dashboard"]:
            return ParsedKey("alive_dashboard", site)
        case ["heartbeat", "anchor", a]:
            return ParsedKey("heartbeat", site, anchor_id=a, service="anchor")
        case ["heartbeat", svc] if svc in HEARTBEAT_SERVICES:
            return ParsedKey("heartbeat", site, service=svc)
    return None


def parse_recording_topic(topic: str) -> ParsedKey | None:
    """:func:`parse_key` plus the recording-only topics: kinds ``liveliness``
    (:meth:`Keys.recorder_liveliness`) and ``replay_estimate`` (:meth:`Keys.replay_estimate`).
    """
    parts = topic.split("/")
    if len(parts) >= 4 and parts[0] == PREFIX:
        if parts[2:] == ["recorder", "liveliness"]:
            return ParsedKey("liveliness", parts[1])
        if len(parts) == 6 and parts[2:4] == ["replay", "node"] and parts[5] == "estimate":
            return ParsedKey("replay_estimate", parts[1], node_id=parts[4])
    return parse_key(topic)
