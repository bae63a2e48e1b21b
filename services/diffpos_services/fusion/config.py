"""The fusion's configuration and its path-model rule, in one place.

:class:`FusionConfig` is the typed, validated configuration of the fusion service. It is built
from a scenario by :meth:`FusionConfig.from_scenario` (the ``diffpos fusion`` and ``diffpos
emulate`` path) or, for a recording that does not store its settings, by
:meth:`FusionConfig.from_recording` (``diffpos replay``). Both apply the one window-edge rule
(:func:`model_edge`): ``"upper"`` is the paper's D-NLS, ``"lower"`` is the same model one window
height lower (``Delta + w``), and ``"auto"`` asks :func:`diffpos.scenario.first_arrival_edge`.

The mechanism-aware methods (``mnls``, and the tracker on top of it) need the whole building
(window band per floor, floor and ceiling planes, depth, edge ends): :attr:`FusionConfig.building`
carries the scenario's ``[building]`` table as a plain dict (so it travels in the recorded run
configuration and a replay rebuilds the same :class:`~diffpos.scenario.Building`).
:meth:`FusionConfig.from_scenario` fills it and selects ``mnls`` + tracking unless told
otherwise; :meth:`FusionConfig.from_recording` (recordings that do not store their settings,
which were all made by the D-NLS fusion) keeps ``dnls``.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import typing
import zlib
from collections.abc import Mapping
from typing import Annotated, Any, Literal

import msgspec
from msgspec import Meta

from diffpos.alignment import AlignmentConfig
from diffpos.scenario import Building, Radio, Scenario, ScenarioError, first_arrival_edge
from diffpos.tracking.state import TrackerConfig
from diffpos_services.config import build_config
from diffpos_services.errors import ConfigError
from diffpos_services.wire.keys import check_id

__all__ = ["DEFAULT_DNLS_EXCLUSION_STARTS", "DEFAULT_KERNEL_THREADS", "DEFAULT_METHOD",
           "DEFAULT_WORKERS", "EDGES",
           "LEGACY_CONFIDENT_SNAPSHOT_PERIOD_S", "LEGACY_DNLS_EXCLUSION_SEARCH",
           "LEGACY_DNLS_EXCLUSION_STARTS", "MAX_SHARDS", "METHODS",
           "TRACKER_KEYS", "FusionConfig", "TrackerSettings", "building_of", "channel_edge",
           "legacy_tracker_settings", "merge_tracker", "model_edge", "parse_shard",
           "parse_tracker_items", "shard_of", "tracker_argv", "tracker_help"]

#: The estimators of the solve step (``--method``).
METHODS = ("mnls", "dnls", "lls", "ippa")
#: What ``diffpos fusion``, :meth:`FusionConfig.from_scenario` and ``diffpos emulate`` run:
#: the first-arrival model with the per-responder tracker. With the compiled SNR prediction
#: (diffpos/channel/snr_nb.py) a real-time ``diffpos emulate`` of the paper's geometry
#: keeps up on 2 cores (2026-11-27, load 3: 100 % availability, 86.3 % right floor, end-to-end
#: latency p50 34 / p99 249 ms); ``scenarios/large.toml`` (8 x 50) does not yet at real time.
DEFAULT_METHOD = "mnls"

#: The window edges of the path model (``--edge``).
EDGES = ("upper", "lower", "auto")

# the building geometry a scenario gives the fusion (FusionConfig field names)
_GEOMETRY = ("window_height_m", "edge_x_m", "first_floor_z_m", "floor_height_m", "n_floors")
# of those, the ones that are also fields of the building table
_BUILDING_OVERRIDES = ("window_height_m", "first_floor_z_m", "floor_height_m", "n_floors")


def _shell(table: Mapping[str, Any]) -> dict[str, Any]:
    """A placeholder anchor and one node in the middle of the building of ``table``:
    Scenario.from_dict validates a building (or radio) only inside a scenario (the one
    validation of diffpos.scenario, with its field paths)."""
    dflt = Building()
    get = lambda k: table.get(k, getattr(dflt, k))  # noqa: E731
    try:
        node = [float(get("center_x_m")), 0.5 * float(get("depth_m")),
                float(get("first_floor_z_m")) + 0.5 * float(get("floor_height_m"))]
    except (TypeError, ValueError):
        node = [0.0, 1.0, 1.0]  # the building's own validation names the bad field
    return {"anchors": [{"id": "a", "position_m": [0.0, -10.0, 1.0]}],
            "nodes": {"list": [{"id": "n", "position_m": node}]}}


def building_of(table: Mapping[str, Any]) -> Building:
    """The :class:`~diffpos.scenario.Building` of a scenario's ``[building]`` table.

    Raises
    ------
    ValueError
        The table is invalid (the message names the field, e.g. ``building.n_floors``).
    """
    try:
        return Scenario.from_dict({"building": dict(table), **_shell(table)}).building
    except ScenarioError as exc:
        raise ValueError(str(exc)) from None


def model_edge(edge: str, scenario: Scenario | None = None) -> tuple[str, str]:
    """The window edge of the path model that ``edge`` selects, and why.

    ``"upper"`` and ``"lower"`` are taken as given; ``"auto"`` is the edge whose diffracted
    path arrives first for the scenario's anchors (:func:`diffpos.scenario.first_arrival_edge`:
    lower when every anchor flies below the lowest window), or the paper's upper edge when
    there is no scenario.

    Returns
    -------
    edge : {"upper", "lower"}
    why : str
        One line for the log and the run configuration.
    """
    if edge != "auto":
        return edge, f"--edge {edge}"
    if scenario is None:
        return "upper", "auto without a scenario: the paper's upper edge"
    chosen, why = first_arrival_edge(scenario)
    return chosen, f"auto: {why}"


def channel_edge(edge: str, channel: str) -> str:
    """The ``edge`` a fusion fed by an emulated ``channel`` is started with.

    ``auto`` is left to :func:`model_edge` (the fusion decides from the scenario), except on
    the ideal channel (``diffpos emulate --channel ideal``): it generates the upper-edge path,
    so it gets the upper edge.
    """
    return "upper" if edge == "auto" and channel == "ideal" else edge


#: ``max_backlog_s`` of the live fusion (``diffpos fusion``, ``diffpos emulate``) [s]: turns the
#: overload policy on (``FusionConfig.max_backlog_s``): a fusion slower than its input solves
#: each node's newest epochs in rounds (the older ones counted as ``superseded``) and never
#: publishes an epoch more than this much older than the newest (``overloaded``).
LIVE_MAX_BACKLOG_S = 2.0


#: ``supersede_after_s`` when not given [s]: five epochs at 10 Hz; a stall or a start-up burst
#: shorter than this costs no estimate, a fusion persistently behind lags about this much.
DEFAULT_SUPERSEDE_AFTER_S = 0.5
#: ``supersede_after_s`` of a replay of a live fusion recorded before the setting existed
#: (2026-11-27: its ``fusion_config`` has ``max_backlog_s`` but no ``supersede_after_s``) [s]:
#: that fusion did not coalesce per node (only the ``max_backlog_s`` drop), nor does the replay.
#: Finite (a JSON number in the replay's settings); 1e9 s: no backlog spans it.
LEGACY_SUPERSEDE_AFTER_S = 1e9


#: ``admit_lag_s`` when not given [s]: half of :data:`DEFAULT_SUPERSEDE_AFTER_S`, so a fusion
#: taking on new tracks stops doing so well before its backlog would cost anybody's epoch, and
#: still places new tracks while a little behind. Measured on the 16 x 200 soak (200
#: responders switched on at once; 2-core VM; docs/measurements.md, 2026-11-28 session 16):
#: without admission the start-up's initialisations (11-19 ms CPU of a step for two, with
#: their rounds) and unconfirmed tracks (every hypothesis updated) put the fusion up to ~1.7 s
#: behind, and the overload policy superseded 1,002-4,655 node-epochs in 10 of 16 runs of 60
#: s; with it (the newest-epoch initialisation of ``TrackBank.hold_inits``, unconfirmed tracks
#: never superseded) 0 in each of six quiet runs, the responders' first position p90 1.0-1.8
#: s (0.8-0.9 s when the old policy lost nothing).
DEFAULT_ADMIT_LAG_S = 0.25
#: ``admit_lag_s`` of a replay of a live fusion recorded before the setting existed
#: (2026-11-28: its ``fusion_config`` has no ``admit_lag_s``) [s]: that fusion admitted new
#: tracks by the epochs a step solved alone, nor does the replay (1e9 s: no backlog spans it).
LEGACY_ADMIT_LAG_S = 1e9


#: ``confident_snapshot_period_s`` of a replay of a live fusion recorded before the setting
#: existed (2026-12-06: its ``fusion_config`` has no ``confident_snapshot_period_s``) [s]: that
#: fusion gave a confident track an mnls snapshot every 10 s of measurement time.
LEGACY_CONFIDENT_SNAPSHOT_PERIOD_S = 10.0


#: ``snapshot_at_start`` of a replay of a live fusion recorded before the setting existed
#: (2026-12-06: its ``fusion_config`` has no ``snapshot_at_start``): that fusion gave a node an
#: mnls snapshot fix in the epoch its track started.
LEGACY_SNAPSHOT_AT_START = True


#: ``dnls_exclusion_search`` of a replay of a live fusion recorded before the setting existed
#: (2026-12-06: its ``fusion_config`` has no ``dnls_exclusion_search``): that fusion solved
#: every exclusion candidate from all starts.
LEGACY_DNLS_EXCLUSION_SEARCH = "exhaustive"


#: ``dnls_exclusion_starts`` of new runs: ``"local"`` since 2026-12-07 (docs/performance.md,
#: "Session 24: D-NLS settings": the cold fixes' kernel CPU 0.39-0.45x on three 30 s ``large``
#: replays, right floor and availability over every node-epoch the same within 0.2 point).
DEFAULT_DNLS_EXCLUSION_STARTS = "local"


#: ``dnls_exclusion_starts`` of a replay of a live fusion recorded before the setting existed
#: (2026-12-07: its ``fusion_config`` has no ``dnls_exclusion_starts``): that fusion started a
#: cold fix's exclusion candidates from the whole height grid.
LEGACY_DNLS_EXCLUSION_STARTS = "grid"


def with_legacy_defaults(recorded: dict[str, Any]) -> dict[str, Any]:
    """Recorded fusion settings (a recording's ``fusion_config``; empty: none) with the
    settings that did not exist when it was made set to what that fusion did
    (:data:`LEGACY_SUPERSEDE_AFTER_S`, :data:`LEGACY_ADMIT_LAG_S`,
    :data:`LEGACY_CONFIDENT_SNAPSHOT_PERIOD_S`, :data:`LEGACY_SNAPSHOT_AT_START`,
    :data:`LEGACY_DNLS_EXCLUSION_SEARCH`, :data:`LEGACY_DNLS_EXCLUSION_STARTS`), so a replay by its decision record drops,
    initialises and checks what the live fusion did."""
    out = dict(recorded)
    if out.get("max_backlog_s") and "supersede_after_s" not in out:
        out["supersede_after_s"] = LEGACY_SUPERSEDE_AFTER_S
    if out and "admit_lag_s" not in out:
        out["admit_lag_s"] = LEGACY_ADMIT_LAG_S
    if out and "confident_snapshot_period_s" not in out:
        out["confident_snapshot_period_s"] = LEGACY_CONFIDENT_SNAPSHOT_PERIOD_S
    if out and "snapshot_at_start" not in out:
        out["snapshot_at_start"] = LEGACY_SNAPSHOT_AT_START
    if out and "dnls_exclusion_search" not in out:
        out["dnls_exclusion_search"] = LEGACY_DNLS_EXCLUSION_SEARCH
    if out and "dnls_exclusion_starts" not in out:
        out["dnls_exclusion_starts"] = LEGACY_DNLS_EXCLUSION_STARTS
    return out


#: ``kernel_threads`` when not given: 1. Live on a 2-core machine shared with the run's anchors,
#: router and recorder, 2 threads published fewer soak estimates and raised the large run's
#: latency (no core is free for the second thread: benchmarks/bench_fusion_cost.py); give
#: ``--kernel-threads 2`` where a core is free (a replay on an idle machine: wall x0.72).
DEFAULT_KERNEL_THREADS = 1


#: ``workers`` when not given: 1 (no worker process; see ``FusionConfig.workers``).
DEFAULT_WORKERS = 1
#: Largest ``workers`` accepted.
MAX_WORKERS = 64
#: Largest ``shards`` accepted.
MAX_SHARDS = 1024


def shard_of(node_id: str, shards: int) -> int:
    """The shard (``0 .. shards - 1``) that owns responder ``node_id``: CRC-32 of its id's
    UTF-8 bytes modulo ``shards``, the same in every process, on every machine and in every
    Python (unlike ``hash()``, salted per process)."""
    return zlib.crc32(node_id.encode("utf-8")) % shards if shards > 1 else 0


def parse_shard(text: str, *, option: str = "--shard") -> tuple[int, int]:
    """``(K, N)`` of ``K/N`` (``0 <= K < N <= MAX_SHARDS``).

    Raises
    ------
    ConfigError
        Not of that form, naming what is expected.
    """
    k, sep, n = text.partition("/")
    try:
        kk, nn = int(k), int(n)
    except ValueError:
        kk = nn = -1
    if not sep or not (0 <= kk < nn <= MAX_SHARDS):
        raise ConfigError(f"{option} {text!r}: expected K/N with 0 <= K < N <= {MAX_SHARDS}, "
                          f"e.g. {option} 0/2 (this process owns the responders whose id's "
                          "CRC-32 modulo N is K)")
    return kk, nn


# ------------------------------------------------------------------------- tracker settings
# FusionConfig.tracker: every field of diffpos.tracking.state.TrackerConfig (the one source of
# the fields, their types, defaults and meaning), with the range each one accepts.

#: The range a tracker setting accepts (msgspec ``Meta`` keywords); a number not listed: >= 0.
_TRACKER_RANGES: dict[str, dict[str, float]] = {
    "stairs_weight": {"gt": 0, "lt": 1},  # log(w), log(1 - w)
    "outlier_weight": {"gt": 0, "lt": 1},  # log(w)
    "outlier_span_m": {"gt": 0},
    "box_sigma_m": {"gt": 0},  # 1 / sigma^2
    "height_sigma_m": {"gt": 0},
    "init_grid_m": {"gt": 0},
    "start_grid_m": {"ge": 0},
    "nis_limit": {"gt": 0},
    "nis_alpha": {"ge": 0, "le": 1},
    "dormant_refresh_s": {"gt": 0},
    "dormant_floor_p": {"ge": 0, "le": 1},
    "floor_evidence_lag1_corr": {"ge": 0, "lt": 1},
    "gn_iterations": {"ge": 1},
    "select_passes": {"ge": 1},
    "init_starts": {"ge": 1},
    "min_ranges_init": {"ge": 1},
    "diverge_epochs": {"ge": 1},
    "reseed_epochs": {"ge": 1},
}
#: The choices of the tracker's text settings (``TrackerConfig.mixing``, ``family_weight``,
#: ``family_gate``, ``family_fit``, ``cov_published_floors``, ``cov_few_floors``,
#: ``snr_edge_model``).
_CHOICES: dict[str, tuple[str, ...]] = {"mixing": ("select", "imm"),
                                        "family_weight": ("mechanism", "one", "outlier"),
                                        "family_gate": ("misfit", "outlier"),
                                        "family_fit": ("prior", "residual"),
                                        "cov_published_floors": ("off", "all", "credible"),
                                        "cov_few_floors": ("off", "temper", "model"),
                                        "snr_edge_model": ("halfplane", "wedge")}
#: Unit of a tracker setting by the end of its name (the house naming rule); else ``-``
#: (dimensionless) or ``count`` (integers).
_UNIT_SUFFIXES = (("_m2_s3", "m^2/s^3"), ("_m_s", "m/s"), ("_hz", "1/s"), ("_nats", "nats"),
                  ("_m", "m"), ("_s", "s"))
_TRACKER_TYPES = typing.get_type_hints(TrackerConfig)
_TRACKER_DEFAULTS = {f.name: f.default for f in dataclasses.fields(TrackerConfig)}
#: Every tracker setting (``FusionConfig.tracker``), in :class:`TrackerConfig`'s order.
TRACKER_KEYS = tuple(_TRACKER_DEFAULTS)


def _tracker_type(key: str) -> Any:
    tp = _TRACKER_TYPES[key]
    if key in _CHOICES:
        return Literal[_CHOICES[key]]
    if tp is bool:
        return bool
    return Annotated[tp, Meta(**_TRACKER_RANGES.get(key, {"ge": 0}))]


def _tracker_unit(key: str) -> str:
    for suffix, unit in _UNIT_SUFFIXES:
        if key.endswith(suffix):
            return unit
    return "count" if _TRACKER_TYPES[key] is int else "-"


def _text(value: Any) -> str:
    """A tracker value as ``--tracker`` takes it (JSON for booleans, shortest exact float)."""
    return json.dumps(value) if isinstance(value, bool) else str(value)


TrackerSettings = msgspec.defstruct(
    "TrackerSettings", [(k, _tracker_type(k), _TRACKER_DEFAULTS[k]) for k in TRACKER_KEYS],
    kw_only=True, frozen=True, forbid_unknown_fields=True, module=__name__)
TrackerSettings.__doc__ = """The per-responder tracker's settings (``FusionConfig.tracker``): a
field per field of :class:`diffpos.tracking.state.TrackerConfig`, its default and meaning
(see its docstring), with the range each accepts; :meth:`FusionConfig.tracker_config` is the
TrackerConfig the fusion runs."""


def tracker_help() -> str:
    """Every tracker setting with its default and unit, for ``--help``."""
    def one(key: str) -> str:
        d = _text(_TRACKER_DEFAULTS[key])
        if key in _CHOICES:
            return f"{key}={d} ({'|'.join(_CHOICES[key])})"
        if _TRACKER_TYPES[key] is bool:
            return f"{key}={d} (true|false)"
        return f"{key}={d} [{_tracker_unit(key)}]"

    return ", ".join(one(k) for k in TRACKER_KEYS)


def _takes(key: str) -> str:
    """What ``key`` accepts, e.g. ``a number >= 0 [m^2/s^3], default 1.5``."""
    if key in _CHOICES:
        what = " or ".join(_CHOICES[key])
    elif _TRACKER_TYPES[key] is bool:
        what = "true or false"
    else:
        ops = {"gt": ">", "ge": ">=", "lt": "<", "le": "<="}
        bounds = " and ".join(f"{ops[k]} {v:g}"
                              for k, v in _TRACKER_RANGES.get(key, {"ge": 0}).items())
        kind = "an integer" if _TRACKER_TYPES[key] is int else "a number"
        what = f"{kind} {bounds} [{_tracker_unit(key)}]"
    return f"{what}, default {_text(_TRACKER_DEFAULTS[key])}"


def tracker_value(key: str, value: Any, *, where: str) -> Any:
    """``value`` (text from the command line, or a JSON value) as tracker setting ``key``.

    Raises
    ------
    ConfigError
        One line starting with ``where``: an unknown key (naming every valid key) or a value
        the key does not take (naming what it takes, its unit and default).
    """
    if key not in _TRACKER_DEFAULTS:
        raise ConfigError(f"{where}: {key!r} is not a tracker setting; valid keys: "
                          f"{', '.join(TRACKER_KEYS)}")
    try:
        return msgspec.convert(value, _tracker_type(key), strict=False)
    except msgspec.ValidationError:
        raise ConfigError(f"{where}: {key} takes {_takes(key)}") from None


def parse_tracker_items(items: list[str] | None, *, option: str = "--tracker") -> dict[str, Any]:
    """The tracker settings of repeated ``option KEY=VALUE`` (checked, converted).

    Raises
    ------
    ConfigError
        A malformed item, an unknown key or a bad value (:func:`tracker_value`).
    """
    out: dict[str, Any] = {}
    for item in items or ():
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"{option} {item!r}: expected KEY=VALUE, e.g. {option} nis_limit=12;"
                              f" valid keys: {', '.join(TRACKER_KEYS)}")
        out[key.strip()] = tracker_value(key.strip(), value.strip(), where=f"{option} {item}")
    return out


def tracker_argv(tracker: Mapping[str, Any], *, option: str = "--tracker") -> list[str]:
    """``option KEY=VALUE`` for every setting of ``tracker`` (:func:`parse_tracker_items` gives
    the same values back, floats exactly)."""
    return [a for k, v in tracker.items() for a in (option, f"{k}={_text(v)}")]


def merge_tracker(base: Mapping[str, Any] | None, changes: Any) -> dict[str, Any]:
    """Tracker settings ``base`` (e.g. recorded) with ``changes`` (a mapping of keys to values,
    each checked by :func:`tracker_value`; errors start with ``tracker.KEY=VALUE``)."""
    if not isinstance(changes, Mapping):
        raise ConfigError(f"tracker={changes!r}: give tracker settings one by one "
                          f"(tracker.KEY=VALUE) or as a JSON object; valid keys: "
                          f"{', '.join(TRACKER_KEYS)}")
    out = dict(base or {})
    for k, v in changes.items():
        out[k] = tracker_value(k, v, where=f"tracker.{k}={_text(v)}")
    return out


#: When the tracker's defaults changed since the tracker entered the fusion (ca1ad09,
#: 2026-11-23 16:53 UTC; found with ``git log -p`` of diffpos/tracking.py,
#: diffpos/tracking_state.py and diffpos/tracking/state.py): (commit time [UTC], commit, the
#: values before it), newest first. A setting added with a default that changed what the
#: tracker did is listed with the value that does what the tracker did before it (SNR reuse
#: margins 0: no reuse; lag-1 correlation 0: untempered; dormant off: every hypothesis
#: updated). Since the newest entry no default changed: a recording made after it without
#: tracker settings ran with today's defaults.
_TRACKER_DEFAULT_CHANGES: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ("2026-12-08T02:53:17Z", "3c15012", {"stairs_follow": 0, "stairs_follow_settled_s": 0.0,
                                         "stairs_follow_m": 0.0, "stairs_follow_min_links": 0}),
    ("2026-12-08T02:23:59Z", "4c798f4", {"family_few_links": 0, "family_fit_links": 0,
                                         "cov_few_floors": "off"}),
    ("2026-12-07T23:50:16Z", "76801b1", {"floor_hold_max_links": 0}),
    ("2026-12-07T20:27:35Z", "2ac62e4", {"family_worst_min_links": 0}),
    ("2026-12-07T17:20:12Z", "424510e", {"snr_diffraction_slack_db": 0.0,
                                         "snr_slack_max_links": 0}),
    ("2026-12-07T14:54:35Z", "0164933", {"reseed_outliers": 0, "cov_published_floors": "off"}),
    ("2026-12-07T11:48:16Z", "dd88bf2", {"edge_retry_margin_m": 0.0, "edge_retry_node": False,
                                         "mechanism_prior_min_links": 0,
                                         "mechanism_switch_p": 0.0}),
    ("2026-12-07T07:58:12Z", "6f921de", {"first_arrival_prior": 0.0}),
    ("2026-12-07T04:54:55Z", "617a6ba", {"floor_contest_s": 0.0}),
    ("2026-12-07T03:24:31Z", "208fb2e", {"reseed_max": 0, "reseed_min_links": 0}),
    ("2026-12-06T20:57:01Z", "52c5723", {"family_learned_links": 0}),
    ("2026-12-06T19:37:46Z", "7103507", {"family_min_links": 4}),
    ("2026-12-06T18:23:41Z", "c77e4db", {"max_order": 2, "family_minority": False}),
    ("2026-12-06T17:06:42Z", "7858211", {"max_order": 3}),
    # family_first was on by default only from e94ad45 to 384cae1 (then without the cap of
    # its first-arrival probability: a recording of that window replays with the cap)
    ("2026-12-06T16:05:42Z", "384cae1", {"family_first": True}),
    ("2026-12-06T15:58:21Z", "e94ad45", {"family_first": False}),
    ("2026-12-06T15:30:15Z", "182c287", {"max_order": 2, "family_history": 0,
                                         "family_min_links": 0}),
    ("2026-12-06T14:17:03Z", "2fd5568", {"max_order": 3}),
    ("2026-12-06T12:31:20Z", "431695e", {"max_order": 2, "family_weight": "outlier",
                                         "family_gate": "outlier"}),
    ("2026-12-06T10:19:50Z", "f926bf5", {"floor_model_doubt": False}),
    ("2026-12-06T08:09:51Z", "d3f1e35", {"lost_on_gap": False, "min_anchors_tracking": 0}),
    ("2026-12-06T07:51:29Z", "ab8d4d9", {"link_learn": False, "snr_cost_cap_nats": 0.0}),
    ("2026-11-27T13:36:18Z", "30c1dda", {"snr_reuse_m": 0.0, "snr_reuse_anchor_m": 0.0}),
    ("2026-11-27T09:41:59Z", "73459d9", {"floor_evidence_lag1_corr": 0.0}),
    ("2026-11-27T08:55:33Z", "02e873d", {"dormant_floor_p": 0.99}),
    ("2026-11-27T08:50:30Z", "9c5836f", {"dormant_floor_p": 0.0}),
    ("2026-11-27T08:17:26Z", "2f23e13", {"dormant": False}),
    ("2026-11-23T19:57:53Z", "06f1b49", {"init_grid_m": 1.0, "init_starts": 2}),
)


def _utc(text: str) -> datetime.datetime:
    return datetime.datetime.fromisoformat(text.replace("Z", "+00:00"))


def legacy_tracker_settings(recorded: Mapping[str, Any], made_ns: int | None
                            ) -> tuple[dict[str, Any], str]:
    """The tracker settings a recording without them (recorded fusion settings ``recorded``
    without ``tracker``, made at ``made_ns``, ``None``: unknown) ran with, and one line for
    the replay report that says which.

    Made after the last change of a default (:data:`_TRACKER_DEFAULT_CHANGES`), or unknown:
    today's defaults; earlier: the defaults of that time, today's for the settings that did
    not change (the tracker's code differed then too: said in the line).
    """
    today = {k: _TRACKER_DEFAULTS[k] for k in TRACKER_KEYS}
    since, commit, _ = _TRACKER_DEFAULT_CHANGES[0]
    since_when = f"{since[:10]} {since[11:16]} UTC"
    since_text = f"{since_when}, commit {commit}"
    if recorded.get("method", "dnls") != "mnls" or not recorded.get("tracking", True):
        return today, (f"not recorded; no tracker ran live (method {recorded.get('method', 'dnls')}"
                       f"{'' if recorded.get('tracking', True) else ', no tracking'}): "
                       "today's defaults")
    if made_ns is None:
        return today, ("not recorded, recording time unknown: today's defaults (unchanged "
                       f"since {since_text}; a recording made before ran other defaults)")
    made = datetime.datetime.fromtimestamp(made_ns / 1e9, tz=datetime.UTC)
    made_text = made.strftime("%Y-%m-%d %H:%M UTC")
    older = [values for when, _, values in _TRACKER_DEFAULT_CHANGES if _utc(when) > made]
    if not older:
        return today, (f"not recorded (recording of {made_text}): today's defaults, which it "
                       f"ran with (unchanged since {since_text})")
    then: dict[str, Any] = {}
    for values in older:  # newest first: an older change overwrites a newer one
        then.update(values)
    changed = ", ".join(f"{k}={_text(v)}" for k, v in then.items() if v != today[k])
    return {**today, **then}, (
        f"not recorded (recording of {made_text}): the defaults of then ({changed or 'as today'}"
        f"), today's for the rest; the tracker's code before {since_when} differed too, so "
        "this replay can differ from live")


def complete_tracker(recorded: Mapping[str, Any], made_ns: int | None
                     ) -> tuple[dict[str, Any], str | None]:
    """Recorded tracker settings (``recorded["tracker"]``) completed with the keys they lack
    (settings added after the recording was made) at the values of the recording's time
    (:func:`legacy_tracker_settings`), and a line for the report naming them (None: nothing
    was missing)."""
    have = dict(recorded["tracker"])
    missing = [k for k in TRACKER_KEYS if k not in have]
    if not missing:
        return have, None
    then, _ = legacy_tracker_settings(recorded, made_ns)
    filled = {k: then[k] for k in missing}
    text = ", ".join(f"{k}={_text(v)}" for k, v in filled.items())
    return {**filled, **have}, (f"recorded without {len(missing)} newer setting(s): the values "
                                f"of the recording's time ({text})")


class FusionConfig(msgspec.Struct, kw_only=True, frozen=True):
    """Typed, validated configuration of the fusion service (see ``diffpos fusion --help``)."""

    site: str = "demo"
    method: Literal["mnls", "dnls", "lls", "ippa"] = "dnls"
    """Estimator of the solve step: ``mnls`` (mechanism-aware NLS on the first-arrival path
    model of :attr:`building`, floor probabilities; the default of ``diffpos fusion`` and
    :meth:`from_scenario`), ``dnls`` (diffraction-aware D-NLS with gating and warm starts, the
    struct's default for settings that do not name a method: recordings made before mnls),
    ``lls`` (line-of-sight linear least squares, the paper's baseline) or ``ippa`` (iterative
    parallel projection, every range possibly NLoS). Gating, the window-edge geometry and warm
    starts are D-NLS-only; ``lls``/``ippa`` get the same (motion-compensated) ranges,
    effective sigmas and masks."""
    tracking: bool = True
    """With ``mnls``: run the per-responder tracker (:mod:`diffpos.tracking.tracker`: floor x
    {level, vertical} hypotheses, one iterated EKF each) on every epoch's ranges and publish
    its filtered estimate (the mnls snapshot fix rides along); ignored by the other methods."""
    snapshot_period_s: Annotated[float, Meta(ge=0)] = 1.0
    """Tracking: a node the tracker places (INITIALISING, TRACKING, COASTING) gets an mnls
    snapshot fix at most once per this much measurement time (0: every epoch); a node it
    does not place (UNINITIALISED, LOST: the snapshot is then its only fix) and a node's
    first epoch get one every epoch; a *confident* confirmed track (TRACKING, floor
    probability >= 0.99, averaged NIS <= 4) every :attr:`confident_snapshot_period_s`
    (default: never after its first). The snapshot is published beside the
    tracked estimate and never feeds the tracker; it costs several times the tracker's
    update (3-4 ms vs ~1 ms CPU with 8 anchors). The live service's steps do at most a few
    snapshots and track initialisations each (``tracked.heavy_budget``): a due snapshot that
    does not fit stays due for the node's next epoch."""
    confident_snapshot_period_s: Annotated[float, Meta(ge=0)] | None = None
    """Tracking: the mnls snapshot period of a *confident* confirmed track (TRACKING, floor
    probability >= ``tracked.CONFIDENT_FLOOR_PROBABILITY``, averaged NIS <=
    ``tracked.CONFIDENT_NIS``) [s of measurement time]; the longer of this and
    :attr:`snapshot_period_s`. ``None`` (the default since 2026-12-06): none after its first,
    snapshots run only where they decide something: where the tracker gives no position
    (the snapshot is the only fix), where its floor is in doubt or its residuals misfit, and
    for unconfirmed tracks. The snapshot never feeds the tracker and nothing in the project
    reads a published one, so the tracked estimates do not depend on this, except through
    the budgeted live steps (``tracked.heavy_budget``: a snapshot not done leaves room for a
    track initialisation) and the decision record replays those steps. Replay of
    the 30 s lockstep ``large`` recording: 140 of its 156 snapshots were of confident tracks,
    ~1.2 s of ~9.6 s of the replay's CPU (docs/performance.md). Recordings made before the
    setting replay with 10 s (:data:`LEGACY_CONFIDENT_SNAPSHOT_PERIOD_S`)."""
    snapshot_at_start: bool = False
    """Tracking: an mnls snapshot fix also in the epoch the tracker initialises a node's track
    (its grid snapshot places the node then). ``False`` (the default since 2026-12-06): the
    track's start counts as the node's last check, so its first mnls snapshot comes
    :attr:`snapshot_period_s` later if its track is not confident by then (none if it is); a
    node the tracker does not place gets one every epoch as before. Changes only the published
    ``snapshot`` field (and, live, what the budgeted steps' heavy work holds): the tracked
    estimates of a replay of every epoch are the same bit for bit. A 16-anchor snapshot costs
    ~17-22 ms CPU (2-core VM): the 200 of a 16 x 200 soak's first second were ~4 s of CPU (260
    -> 60 snapshots in the 10 s soak replay, docs/soak.md). Recordings made before the setting
    replay with ``True`` (:data:`LEGACY_SNAPSHOT_AT_START`)."""
    mnls_measured_threshold: bool = False
    """With mnls: the M-NLS fixes (the snapshot fixes; with ``tracking`` off the estimates)
    take the detector threshold as at least the measured first arrival's SNR less the
    radio's ``fap_threshold_db`` (the strongest path is at least as strong as the reported
    one), not only the predicted strongest path's
    (:class:`diffpos.estimators.mnls.rules.SnrRule` ``measured_threshold``). ``False`` (the
    default; recordings made before the setting ran without it): M-NLS as it was. The
    tracker does not read M-NLS's fixes: no tracked estimate depends on it."""
    mnls_first_arrival_prior: Annotated[float, Meta(ge=0, lt=1)] = 0.0
    """With mnls: weight of M-NLS's soft skip prior of the detector's earlier paths, which
    replaces its hard rule (:class:`diffpos.estimators.mnls.rules.SnrRule`
    ``first_arrival_prior``); 0 (the default; recordings made before the setting): off."""
    mnls_keep_hard_rule: bool = False
    """With mnls and :attr:`mnls_first_arrival_prior` > 0: keep M-NLS's hard rule beside the
    skip prior (``SnrRule.keep_hard_rule``); ``False`` (the default): the prior replaces it."""
    mnls_dielectric_edges: Annotated[float, Meta(ge=0, le=1)] = 0.0
    """With mnls: prior probability that the window's sill and lintel diffract as a dielectric
    sheet of the walls' material (the channel's edge at channel order >= 3) rather than as the
    radio's order-2 perfect conductor: 1, M-NLS predicts the diffraction SNR with the sheet;
    between 0 and 1, each slot's SNR term mixes both predictions
    (``diffpos.estimators.mnls.rules.SnrRule.dielectric_edges``); 0 (the default; recordings
    made before the setting): the radio's own order. No tracked estimate depends on it (the
    tracker does not read M-NLS's fixes)."""
    mnls_floor_box: bool = False
    """With mnls: each floor's Laplace mass in M-NLS's floor posterior counts only its share
    inside the floor's box (``diffpos.estimators.mnls.rules.SnrRule.floor_box``); ``False``
    (the default; recordings made before the setting): the whole Gaussian. No tracked estimate
    depends on it (the tracker does not read M-NLS's fixes); docs/raytrace_study.md
    "Session 29"."""
    mnls_max_order: Annotated[int, Meta(ge=2, le=4)] = 2
    """With mnls: the M-NLS fixes' mechanism order (``diffpos.estimators.mnls.solver.mnls``
    ``max_order``): 2 (the default; recordings made before the setting) the emulator's 18
    mechanisms; 3 or 4 adds the higher-order families (slab image series, ground bounce before
    the edge, wall and, on a building with partitions, partition reflections) as candidates
    of every link, as ``diffpos reproduce --mnls-max-order`` and the tracker's
    ``max_order`` do. No tracked estimate depends on it (the tracker does not read M-NLS's
    fixes); docs/raytrace_study.md "Session 28"."""
    tracker: TrackerSettings = msgspec.field(default_factory=TrackerSettings)
    """With mnls + tracking: the per-responder tracker's settings, every field of
    :class:`diffpos.tracking.state.TrackerConfig` (:class:`TrackerSettings`; ``diffpos fusion
    --tracker KEY=VALUE``, ``diffpos replay --set tracker.KEY=VALUE``); recorded with the
    other settings (key ``tracker``), so a replay runs the tracker that ran live. A recording
    without them replays with the defaults it ran with (:func:`legacy_tracker_settings`)."""
    building: dict[str, Any] | None = None
    """The scenario's ``[building]`` table (:func:`building_of`); ``None``: the paper's
    building with this config's window height, edge ends and floors."""
    radio: dict[str, Any] | None = None
    """The scenario's ``[radio]`` table: with it mnls compares each range's measured SNR with
    the free-space link budget (a link too strong for any diffracted path); ``None``: no SNR
    test."""
    window_height_m: Annotated[float, Meta(gt=0)] = 1.5
    delta_m: float = 0.0
    edge_x_m: tuple[float, float] | None = None
    first_floor_z_m: float = 3.0
    floor_height_m: Annotated[float, Meta(gt=0)] = 3.0
    n_floors: Annotated[int, Meta(ge=1)] = 5
    epoch_period_s: Annotated[float, Meta(gt=0, le=10)] = 0.1
    clock_tolerance_s: Annotated[float, Meta(ge=0, le=1)] = 0.005
    deadline_s: Annotated[float, Meta(gt=0, le=60)] = 0.3
    max_state_extrapolation_s: Annotated[float, Meta(ge=0)] = 0.5
    node_speed_sigma_m_s: Annotated[float, Meta(ge=0)] = 1.0
    velocity_sigma_m_s: Annotated[float, Meta(ge=0)] = 0.3
    motion_compensation: bool = True
    gating: bool = True
    dnls_exclusion_search: Literal["bounded", "exhaustive"] = "bounded"
    """With dnls and gating: how the exclusion search (the fix's anchors left out one at a
    time when the all-anchor fit fails the chi-square test) is run. ``"bounded"`` (the default
    since 2026-12-06): candidates solved just far enough to rank them, the best continued to
    full convergence, the all-starts recheck only near consistency, hopeless candidates given
    up early (:func:`diffpos.estimators.dnls.solver.dnls`'s ``exclusion_*`` defaults; about
    half the kernel's work on the 30 s ``large`` replay, same accuracy: docs/dnls_cost.md).
    ``"exhaustive"``: every candidate from all starts to full convergence, as before; a
    recording made before the setting existed replays with it
    (:data:`LEGACY_DNLS_EXCLUSION_SEARCH`)."""
    dnls_exclusion_starts: Literal["grid", "local"] = DEFAULT_DNLS_EXCLUSION_STARTS
    """With dnls and gating: the starts of a *cold* fix's exclusion candidates (a fix without a
    warm start: a node without a recent track, or the cold retry of a failed warm fix).
    ``"local"`` (the default since 2026-12-07, :data:`DEFAULT_DNLS_EXCLUSION_STARTS`): the
    candidate's own LLS position and the current solution only (two starts, nothing screened
    or rechecked; the floor search is left to the fix's own multi-start); ``"grid"``: every
    start of the fix's own multi-start (the height grid and the LLS position, screened) plus
    the current solution, as before. Warm fixes are the same with either; so are fixes with 4
    anchors (no candidate can be solved). ``diffpos.estimators.dnls.solver.dnls(exclusion_starts=...)``; cost and accuracy
    side by side in docs/performance.md ("Session 23: D-NLS replay", "Session 24: D-NLS
    settings"). Recorded with the other settings; a recording made before the setting
    existed (with or without stored settings) replays with ``"grid"``
    (:data:`LEGACY_DNLS_EXCLUSION_STARTS`)."""
    false_alarm_probability: Annotated[float, Meta(gt=0, lt=1)] = 1e-3
    min_snr_db: float | None = None
    warm_start_max_age_s: Annotated[float, Meta(ge=0)] = 1.0
    cold_retry_period_s: Annotated[float, Meta(ge=0)] = 1.0
    diagnostics_period_s: Annotated[float, Meta(gt=0)] = 1.0
    queue_size: Annotated[int, Meta(ge=16)] = 8192
    max_queued_bytes: Annotated[int, Meta(ge=1 << 20)] = 32 << 20
    state_history_s: Annotated[float, Meta(gt=0, le=3600)] = 60.0
    max_fixes_per_step: Annotated[int, Meta(ge=1)] = 4096
    max_backlog_s: Annotated[float, Meta(gt=0)] | None = None
    """The overload policy of steps with a ``limit`` (the live service), applied when more
    epochs are ready than the step takes (the fusion is slower than its input; a fusion that
    keeps up is not affected): (1) once the ready epochs span more than
    :attr:`supersede_after_s`, of each node's ready epochs only the newest
    ``overload.BEHIND_KEEP_EPOCHS`` (1) are kept, the nodes queued least recently served
    first, the others dropped unsolved and counted in ``rejected["superseded"]`` (every node
    is served in rounds with its newest data, the latency is about one round, the work per
    round bounded by the number of nodes); (2) a ready epoch still more than this much
    measurement time older than the newest ready one is dropped unsolved
    (``rejected["overloaded"]``: a round of all nodes takes longer, or a node's ranges
    stopped). So a fusion slower than its input degrades to a lower update rate per node at
    low latency and bounded memory instead of an ever-growing backlog. Both decisions depend
    only on the released epochs, the earlier steps and the step's ``limit`` (in the decision
    record: a replay by it drops the same; :mod:`diffpos_services.fusion.overload`).
    ``None`` (the struct's default: replay without decisions, tests): never drop anything.
    ``diffpos fusion`` and ``diffpos emulate`` use :data:`LIVE_MAX_BACKLOG_S` (a lockstep
    ``emulate --speed 0`` none: its input is paced by the fusion's own estimates, it cannot
    fall behind real time)."""
    supersede_after_s: Annotated[float, Meta(ge=0)] = DEFAULT_SUPERSEDE_AFTER_S
    """With :attr:`max_backlog_s`: the per-node coalescing (``rejected["superseded"]``) acts
    only once the ready epochs span more than this much measurement time (newest - oldest);
    a shorter backlog (a stall, a burst of new tracks at start-up) is worked off without
    loss, as before the policy. A fusion persistently slower than its input then runs at most
    about this much behind plus one round of all nodes. 0: coalesce as soon as a step cannot
    take every ready epoch."""
    admit_lag_s: Annotated[float, Meta(ge=0)] = DEFAULT_ADMIT_LAG_S
    """Admission of new-track work by a budgeted step (the live service's): a step that leaves
    ready epochs spanning more than this much measurement time (the fusion is behind its
    input) does at most ``tracked.HEAVY_MIN_OPERATIONS`` track initialisations and snapshot
    fixes instead of its share of the epochs it solves (``tracked.heavy_budget``). A burst of
    new responders then waits for headroom: each of their epochs is published on time
    without a position (UNINITIALISED) until the track starts, where the extra work would
    have pushed the backlog past :attr:`supersede_after_s` and cost estimates of every node.
    With it on, the overload policy never supersedes an epoch of a node without a confirmed
    track (UNINITIALISED, LOST: it costs no update and is published without a position;
    INITIALISING: admission bounds how many), and such epochs do not count in the span that
    :attr:`supersede_after_s` bounds. A function of the ready queue and the tracks (the
    decision record replays it). 1e9 or more (:data:`LEGACY_ADMIT_LAG_S`): off, as before."""
    bounded_steps: bool = True
    """The live service bounds each solve step's work (an epoch limit from the measured step
    cost, and at most :func:`~diffpos_services.fusion.tracked.heavy_budget` track
    initialisations and snapshot fixes per step), so a burst of new responders cannot hold
    every node's estimate back. The bound depends on how many epochs happen to be ready when a
    step runs, i.e. on timing and CPU load: two lockstep runs of the same ranges started a
    track one epoch apart and ended with one responder right on 0 % or 80 % of its epochs
    (docs/tracking_evidence.md "Session 24, lead"). False (``diffpos fusion
    --unbounded-steps``; lockstep ``diffpos emulate --speed 0``, whose input waits for the
    fusion): every step solves all ready epochs with every initialisation and snapshot due,
    so the estimates are a function of the ranges alone, whatever the load (the decision
    record keeps the steps either way; a replay re-runs them)."""
    linger_s: Annotated[float, Meta(ge=0, le=0.05)] = 0.0003
    kernel_threads: Annotated[int, Meta(ge=1, le=64)] = DEFAULT_KERNEL_THREADS
    """Threads running the row chunks of the compiled kernels (:mod:`diffpos._kernels.pool`:
    the tracker's SNR prediction and paths, the initialisation's grid search, M-NLS's LM
    steps), the fusion's own thread included; the estimates are bit-identical for any count.
    Applied by the service at its start and by replay (one pool per process). It pays only
    where a core is free: replaying the 16 x 200 soak, wall x0.72 with 2; live on 2 cores
    shared with the run's anchors and router, 2 was worse (benchmarks/bench_fusion_cost.py)."""
    workers: Annotated[int, Meta(ge=1, le=MAX_WORKERS)] = DEFAULT_WORKERS
    """Processes sharing the per-node work of mnls + tracking (the tracker update and the
    snapshot fixes: ~79 % of the soak's fusion CPU), the fusion's own included: ``N - 1``
    worker processes are started (:mod:`diffpos_services.fusion.workers`, ``spawn``, warmed
    up before the service is ready) and a call's rows are split between them and the fusion's
    process; the estimates are bit-identical for any count (a recording made with any value
    replays to the same estimates). Applied by the service and by replay; 1: no process.
    Default 1: 2 pays only where the second core is free (the soak: ~100k of 120,000
    estimates with 2 in a run while the machine was otherwise idle; in 5 alternating pairs
    while another job used ~0.7 core, 34-62k with 2 vs 39-58k with 1; the split costs
    +2.5 % CPU on the soak's 200-row calls, +35-45 % on 50-row ones:
    diffpos_services/fusion/workers.py)."""
    shard: Annotated[int, Meta(ge=0)] = 0
    """With :attr:`shards` > 1: the share of the responders this fusion owns (``diffpos fusion
    --shard K/N``): the nodes with :func:`shard_of` ``(id, shards) == shard``; it ingests
    every anchor state and liveliness but only its nodes' ranges, and solves and publishes
    only their estimates. The responders' estimates are independent of each other, so N
    fusions with shards ``0 .. N - 1`` together publish what one fusion publishes (tested:
    tests/services/test_fusion_shards.py). Recorded with the other settings: a replay of one
    shard's recording runs that shard."""
    shards: Annotated[int, Meta(ge=1, le=MAX_SHARDS)] = 1
    """How many fusions share the responders (1: this one owns them all)."""
    # ---- what is accepted (docs/bad_input.md)
    anchors: tuple[str, ...] | None = None
    """Allow-list of anchor ids (``None``: any anchor with a valid id)."""
    nodes: tuple[str, ...] | None = None
    """Allow-list of node ids (``None``: any node with a valid id)."""
    max_anchors: Annotated[int, Meta(ge=1, le=100_000)] = 256
    max_nodes: Annotated[int, Meta(ge=1, le=10_000_000)] = 100_000
    max_message_bytes: Annotated[int, Meta(ge=1024)] = 4 * 1024 * 1024
    max_range_m: Annotated[float, Meta(gt=0)] = 10_000.0
    min_sigma_m: Annotated[float, Meta(ge=0)] = 1e-4
    max_sigma_m: Annotated[float, Meta(gt=0)] = 1_000.0
    max_coordinate_m: Annotated[float, Meta(gt=0)] = 100_000.0
    max_speed_m_s: Annotated[float, Meta(gt=0)] = 1_000.0
    max_future_s: Annotated[float, Meta(gt=0, le=3600)] = 1.0
    max_past_s: Annotated[float, Meta(gt=0, le=86_400)] = 30.0
    time_resync_after: Annotated[int, Meta(ge=1, le=10_000)] = 20

    def check(self) -> None:
        check_id(self.site, field="site")
        if self.shard >= self.shards:
            raise ValueError(f"shard={self.shard} must be < shards={self.shards}")
        if self.edge_x_m is not None and self.edge_x_m[0] == self.edge_x_m[1]:
            raise ValueError("edge_x_m: the two x limits must differ")
        for name in ("anchors", "nodes"):
            for i, v in enumerate(getattr(self, name) or ()):
                check_id(v, field=f"{name}[{i}]")
        if self.min_sigma_m >= self.max_sigma_m:
            raise ValueError(f"min_sigma_m={self.min_sigma_m} must be < max_sigma_m="
                             f"{self.max_sigma_m} [m]")
        self.building_model()
        self.radio_model()

    def owns(self, node_id: str) -> bool:
        """True if this fusion's shard owns responder ``node_id`` (always without shards)."""
        return self.shards == 1 or shard_of(node_id, self.shards) == self.shard

    def radio_model(self) -> Radio | None:
        """The :class:`~diffpos.scenario.Radio` of :attr:`radio` (``None`` without one)."""
        if self.radio is None:
            return None
        try:
            return Scenario.from_dict({"radio": dict(self.radio), **_shell({})}).radio
        except ScenarioError as exc:
            raise ValueError(str(exc)) from None

    def building_model(self) -> Building:
        """The :class:`~diffpos.scenario.Building` of the path model (mnls, tracker).

        From :attr:`building` when set; else the paper's building with this config's window
        height, edge ends, first floor, floor height and number of floors.
        """
        if self.building is not None:
            return building_of(self.building)
        table: dict[str, Any] = {k: getattr(self, k) for k in _BUILDING_OVERRIDES}
        if self.edge_x_m is not None:
            x0, x1 = sorted(self.edge_x_m)
            table.update(width_m=x1 - x0, center_x_m=0.5 * (x0 + x1))
        # the default sill must leave room for the window in the floor
        table["sill_height_m"] = min(0.75, max(self.floor_height_m - self.window_height_m, 0.0))
        return building_of(table)

    def tracker_config(self) -> TrackerConfig:
        """The :class:`~diffpos.tracking.state.TrackerConfig` of :attr:`tracker`."""
        return TrackerConfig(**msgspec.structs.asdict(self.tracker))

    def alignment(self) -> AlignmentConfig:
        return AlignmentConfig(
            epoch_period_ns=round(self.epoch_period_s * 1e9),
            clock_tolerance_ns=round(self.clock_tolerance_s * 1e9),
            deadline_ns=round(self.deadline_s * 1e9),
            max_state_extrapolation_ns=round(self.max_state_extrapolation_s * 1e9),
            node_speed_sigma_m_s=self.node_speed_sigma_m_s,
            velocity_sigma_m_s=self.velocity_sigma_m_s,
            max_future_ns=round(self.max_future_s * 1e9),
        )

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_scenario(cls, scenario: Scenario | None, *, edge: str = "upper",
                      **overrides: Any) -> FusionConfig:
        """The fusion's configuration for ``scenario``'s building, with ``overrides``.

        The method is :data:`DEFAULT_METHOD` (``mnls``) unless ``overrides`` name one
        (``method="mnls"``: the first-arrival model with the per-responder tracker).

        Parameters
        ----------
        scenario : Scenario or None
            Gives the building geometry (window height, edge x limits, floors, and the whole
            ``[building]`` table as :attr:`building`); ``None`` keeps the defaults.
        edge : {"upper", "lower", "auto"}
            Window edge of the path model (:func:`model_edge`); the lower edge is the upper
            edge one window height lower, so it adds ``window_height_m`` to ``delta_m``.
        **overrides
            Any :class:`FusionConfig` field; they win over the scenario's geometry
            (e.g. ``window_height_m``).

        Raises
        ------
        ConfigError
            Naming the invalid field.
        """
        values = {"method": DEFAULT_METHOD}
        values.update({k: v for k, v in overrides.items() if k not in _GEOMETRY})
        geometry = {k: v for k, v in overrides.items() if k in _GEOMETRY}
        if scenario is not None:
            b = scenario.building
            values.update(
                window_height_m=b.window_height_m,
                edge_x_m=tuple(b.edge_x_m),
                first_floor_z_m=b.first_floor_z_m,
                floor_height_m=b.floor_height_m,
                n_floors=b.n_floors,
            )
            tables = scenario.to_dict()
            if "building" not in overrides:
                table = tables["building"]
                table.update({k: v for k, v in geometry.items() if k in _BUILDING_OVERRIDES})
                values["building"] = table
            if "radio" not in overrides:
                values["radio"] = tables["radio"]
        values.update(geometry)
        cfg = build_config(cls, values)
        if model_edge(edge, scenario)[0] == "lower":
            # the lower edge is the upper edge one window height lower: Delta + w
            cfg = msgspec.structs.replace(cfg, delta_m=cfg.delta_m + cfg.window_height_m)
        return cfg

    @classmethod
    def from_recording(cls, run_metadata: Mapping[str, Any],
                       scenario: Scenario | None) -> FusionConfig:
        """The settings ``diffpos emulate`` starts the fusion with, for a recording that does
        not store them.

        Parameters
        ----------
        run_metadata : mapping
            ``site`` (str) and, if known, ``range_rate_hz`` (float, the anchors' ranging
            rate from the first anchor state: the epoch period is one ranging period).
            ``method`` (optional): default ``dnls``, the fusion every recording without
            stored settings was made with.
        scenario : Scenario or None
            The recording's scenario (its building geometry).
        """
        overrides: dict[str, Any] = {"site": run_metadata["site"],
                                     "method": run_metadata.get("method", "dnls"),
                                     # made before the setting existed
                                     "dnls_exclusion_starts": LEGACY_DNLS_EXCLUSION_STARTS}
        rate = run_metadata.get("range_rate_hz")
        if rate is not None:
            overrides["epoch_period_s"] = 1.0 / rate
        return cls.from_scenario(scenario, **overrides)
