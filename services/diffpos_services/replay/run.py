"""Offline replay of a recording through the fusion logic, and the accuracy report.

The recorded anchor states, ranges and anchor liveliness events are fed, in file order (the
recorder's receive order) with their recorded receive times as the fusion's wall clock, into
the same network-free :class:`diffpos_services.fusion.core.FusionCore` the live service runs; the
fusion's time decisions (epoch deadlines) therefore see the times the recorder saw, and the
result depends only on the file and the settings (deterministic, bit for bit). The fusion is
stepped whenever the recorded receive time advanced by ``step_ns`` (the live service steps
after each drain of its queue) and flushed at the end like the live service at shutdown.

:func:`replay` runs four named steps: :func:`replay_settings` (recorded or derived fusion
settings plus the what-ifs) -> :func:`_feed` (the recording into the fusion core) ->
:class:`_Outputs` (the fixes, and optionally an MCAP with them) -> :func:`_report` (metrics:
3D / horizontal / z error percentiles per node and overall against the recorded truth, floor
accuracy, PEB, fix status counts, gating decisions per anchor, message counts and sequence
gaps; optionally recorded-live vs replayed estimates side by side; see
:mod:`diffpos_services.replay.evaluate` and :mod:`diffpos.metrics`).
"""

from __future__ import annotations

import contextlib
import functools
import gc
import json
import logging
import os
import time
from array import array
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from diffpos._kernels import clock as kernel_clock  # first: it counts the loads after it
from diffpos._kernels import pool as kernel_pool
from diffpos_services.config import build_config
from diffpos_services.errors import ConfigError
from diffpos_services.fusion.config import (
    MAX_SHARDS,
    METHODS,
    TRACKER_KEYS,
    FusionConfig,
    complete_tracker,
    legacy_tracker_settings,
    merge_tracker,
    shard_of,
    with_legacy_defaults,
)
from diffpos_services.fusion.core import FusionCore
from diffpos_services.fusion.estimates import ColumnBatch, Estimates
from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.outputs import atomic_path, check_output
from diffpos_services.recording.reader import (
    McapScanner,
    PartsScanner,
    RawMessage,
    SideRecords,
    side_records,
)
from diffpos_services.recording.summary import (
    attached_scenario,
    live_fusion_settings,
    recorded_building,
)
from diffpos_services.recording.topics import natural_key, parse_topic
from diffpos_services.recording.writer import McapSink
from diffpos_services.replay.decided import DecisionReplayer
from diffpos_services.replay.report_stream import Recorded
from diffpos_services.replay.synthetic import FUSION_INPUT_KINDS, quiet_logger
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

__all__ = [
    "ReplayResult",
    "ReplaySettings",
    "ShardPlan",
    "derived_fusion_settings",
    "live_fusion_settings",
    "recorded_shards",
    "replay",
    "replay_settings",
    "shard_plan",
    "what_if_text",
]

#: chunks read ahead for the settings (until the first anchor state and diagnostics)
_READ_AHEAD_BATCHES = 64
#: ... and recording time past the first anchor state
_READ_AHEAD_NS = 10_000_000_000
#: how far apart (recording time) a fix, its truth and its live/replayed twin may be
_WINDOW_NS = 30_000_000_000
#: how often (recording time) the streamed report scores what the truth covers
_ADVANCE_NS = 1_000_000_000


# ----------------------------------------------------------------------------------------
# step 1: settings
# ----------------------------------------------------------------------------------------


def derived_fusion_settings(
    scanner: SideRecords | McapScanner, *, site: str, first_state: bytes | None
) -> tuple[dict[str, Any], str]:
    """Fusion settings as ``diffpos emulate`` would start the fusion, for recordings that do
    not store them (:meth:`FusionConfig.from_recording`): the fusion's defaults, the geometry
    of the attached scenario (TOML attachment; else the built-in paper scenario) and an epoch
    period of one ranging period of the anchors (``range_rate_hz`` of the first anchor state).

    Returns
    -------
    values : dict
    source : str
    """
    scenario, what = attached_scenario(scanner)
    run: dict[str, Any] = {"site": site}
    if first_state is not None:
        try:
            rate = M.decoder(M.AnchorState)(first_state).range_rate_hz
            run["range_rate_hz"] = rate
            what += f", epoch = 1/{rate:g} s from the anchors"
        except M.DecodeError:
            pass
    cfg = FusionConfig.from_recording(run, scenario)
    return msgspec.to_builtins(cfg), f"derived: fusion CLI defaults, {what}"


def _fusion_fields() -> set[str]:
    return set(FusionConfig.__struct_fields__)


@dataclass(frozen=True)
class ReplaySettings:
    """The fusion settings of a replay and where they came from.

    Attributes
    ----------
    config : FusionConfig
    source : str
        ``metadata fusion_config``, ``derived: ...``, ``defaults ...``.
    ignored_recorded_fields : list of str
        Recorded fields that are not (or no longer) fusion settings.
    overrides : dict
        The what-ifs applied on top.
    warning : str or None
        Set when the recording holds no fusion settings and defaults were used.
    tracker_note : str or None
        Set when the recorded settings hold no ``tracker``: which tracker settings the replay
        runs (:func:`~diffpos_services.fusion.config.legacy_tracker_settings`).
    recorded_shards : int
        Fusion shards of the live run as its run configuration says (1: one fusion, or not
        said).
    by_shard : tuple of FusionConfig
        Each live shard's recorded settings with the what-ifs (empty: not recorded; a shard
        then runs :attr:`config` with its ``shard`` / ``shards``).
    """

    config: FusionConfig
    source: str
    ignored_recorded_fields: list[str]
    overrides: dict[str, Any]
    warning: str | None = None
    tracker_note: str | None = None
    recorded_shards: int = 1
    by_shard: tuple[FusionConfig, ...] = ()


def read_ahead(
    scanner: McapScanner,
) -> tuple[list[list[RawMessage]], Iterator[list[RawMessage]], RawMessage | None,
           dict[int, M.FusionDiagnostics]]:
    """Read chunks until the first anchor state and the first fusion diagnostics of every
    live fusion shard (one without shards; at most 64 chunks, and at most 10 s of recording
    time past the first anchor state when they do not all come: a recording without a live
    fusion is not held in memory): when the recording holds no fusion settings, derived ones
    need the anchors' ranging rate; the diagnostics say whether each live fusion recorded its
    decisions. Returns the chunks read, the rest, the first anchor state and each shard's
    first diagnostics (by shard)."""
    batches = scanner.iter_batches()
    ahead: list[list[RawMessage]] = []
    first_state = None
    first_diag: dict[int, M.FusionDiagnostics] = {}
    layout = 0  # shards of the first diagnostics (0: none seen yet)
    dec = M.decoder(M.FusionDiagnostics)
    kinds: dict[str, str] = {}
    for batch in batches:
        ahead.append(batch)
        for m in batch:
            kind = kinds.get(m.topic)
            if kind is None:
                kind = kinds[m.topic] = parse_topic(m.topic)[0]
            if kind == "anchor_state" and first_state is None:
                first_state = m
            elif kind == "diagnostics":
                with contextlib.suppress(M.DecodeError):
                    d = dec(m.data)
                    layout = layout or d.shards
                    if d.shards == layout:
                        first_diag.setdefault(d.shard, d)
        if (first_state is not None and layout and len(first_diag) >= layout) or \
                len(ahead) >= _READ_AHEAD_BATCHES or (
                    first_state is not None and batch
                    and batch[-1].log_ns - first_state.log_ns > _READ_AHEAD_NS):
            break
    return ahead, batches, first_state, first_diag


def _consume(ahead: list[list[RawMessage]],
             rest: Iterator[list[RawMessage]]) -> Iterator[list[RawMessage]]:
    """The chunks read ahead (each let go once handed out), then the rest."""
    ahead.reverse()
    while ahead:
        yield ahead.pop()
    yield from rest


def recorded_site(scanner: McapScanner) -> str | None:
    """The site with the most fusion-input channels seen so far (``None``: none)."""
    sites: Counter[str] = Counter()
    for ch in scanner.channels.values():
        kind, fields = parse_topic(ch.topic)
        if kind in FUSION_INPUT_KINDS:
            sites[fields["site"]] += 1
    return sites.most_common(1)[0][0] if sites else None


def replay_settings(
    scanner: McapScanner,
    *,
    side: SideRecords,
    first_state: RawMessage | None,
    overrides: dict[str, Any] | None = None,
    method: str | None = None,
    use_recorded_settings: bool = True,
) -> ReplaySettings:
    """Recorded settings (else derived, see :func:`derived_fusion_settings`) + what-ifs; and,
    for a run of fusion shards (``diffpos emulate --fusion-shards N``), each shard's recorded
    settings with the same what-ifs (:func:`recorded_shards`).

    Raises
    ------
    ConfigError
        An override that is not a fusion setting, an unknown method, an invalid value.
    """
    site = recorded_site(scanner)
    recorded, source = live_fusion_settings(side)
    warning = None
    if not recorded and use_recorded_settings:
        warning = (f"the recording holds no fusion settings (no metadata fusion_config / "
                   f"run_config, {len(side.metadata)} metadata records found by "
                   f"{side.source}): replaying with DEFAULT settings")
        if site is not None:
            recorded, source = derived_fusion_settings(
                side, site=site, first_state=None if first_state is None else first_state.data)
            warning += f" ({source})"
    if not use_recorded_settings:
        source = "defaults (--ignore-recorded-settings)"
    build = _SettingsBuilder(side, overrides, method, site, use_recorded_settings)
    config, ignored, tracker_note = build(recorded)
    n, per_shard = recorded_shards(side)
    by_shard: tuple[FusionConfig, ...] = ()
    if use_recorded_settings and per_shard is not None:
        by_shard = tuple(build(dict(d))[0] for d in per_shard)
    return ReplaySettings(config, source, ignored, dict(overrides or {}), warning, tracker_note,
                          recorded_shards=n, by_shard=by_shard)


@dataclass(frozen=True)
class _SettingsBuilder:
    """Recorded settings (a dict) -> the replay's :class:`FusionConfig`: the recorded values
    (completed for settings newer than the recording) with the what-ifs on top."""

    side: SideRecords
    overrides: dict[str, Any] | None
    method: str | None
    site: str | None
    use_recorded: bool

    def __call__(self, recorded: dict[str, Any]) -> tuple[FusionConfig, list[str], str | None]:
        overrides, side = self.overrides or {}, self.side
        base: dict[str, Any] = dict(recorded) if self.use_recorded else {}
        base = with_legacy_defaults(base)  # settings recorded before a newer setting existed
        tracker_note = None
        if self.use_recorded and "tracker" not in base:  # recorded before it was recorded
            base["tracker"], tracker_note = legacy_tracker_settings(base, _made_ns(side))
        elif self.use_recorded and isinstance(base["tracker"], dict):  # before newer keys
            base["tracker"], tracker_note = complete_tracker(base, _made_ns(side))
        known = _fusion_fields()
        ignored = sorted(set(base) - known)
        for f in ignored:
            base.pop(f)
        if isinstance(base.get("tracker"), dict):  # a newer recording's tracker settings
            gone = sorted(set(base["tracker"]) - set(TRACKER_KEYS))
            ignored += [f"tracker.{k}" for k in gone]
            base["tracker"] = {k: v for k, v in base["tracker"].items() if k not in gone}
        bad = sorted(set(overrides) - known)
        if bad:
            raise ConfigError(f"{', '.join(bad)}: not a fusion setting; known settings: "
                              f"{', '.join(sorted(known))}")
        base.update({k: v for k, v in overrides.items() if k != "tracker"})
        if "tracker" in overrides:  # what-ifs change single recorded tracker settings
            base["tracker"] = merge_tracker(base.get("tracker"), overrides["tracker"])
        if self.method is not None:
            if self.method not in METHODS:
                raise ConfigError(f"--method {self.method!r}: choose {', '.join(METHODS)}")
            base["method"] = self.method
        if "site" not in base and self.site is not None:
            base["site"] = self.site
        return build_config(FusionConfig, base), ignored, tracker_note


def recorded_shards(side: SideRecords) -> tuple[int, list[dict[str, Any]] | None]:
    """How many fusion shards the run had as its ``run_config`` says (``emulate`` ->
    ``fusion_shards``; 1 when it says nothing) and each shard's settings (``fusion_by_shard``,
    recorded since the shards' diagnostics say which shard sent them; ``None``: not
    recorded), from the metadata, else the ``run_config.json`` attachment."""
    n, per = _run_config_shards(side)
    return n or 1, per


def _run_config_shards(side: SideRecords) -> tuple[int | None, list[dict[str, Any]] | None]:
    """:func:`recorded_shards`, with ``None`` for a count the run configuration does not
    state (no ``run_config``, or one without ``emulate.fusion_shards``)."""
    doc: dict[str, Any] = {}
    for md in side.metadata:
        if md.name == "run_config":
            for k in ("emulate", "fusion_by_shard"):
                with contextlib.suppress(KeyError, TypeError, ValueError):
                    doc[k] = json.loads(md.metadata[k])
            break
    else:
        for att in side.attachments:
            if att.name == "run_config.json":
                with contextlib.suppress(ValueError, AttributeError):
                    doc = json.loads(att.data)
                break
    emu = doc.get("emulate") if isinstance(doc, dict) else None
    n = emu.get("fusion_shards") if isinstance(emu, dict) else None
    n = n if isinstance(n, int) and n >= 1 else None
    per = doc.get("fusion_by_shard") if isinstance(doc, dict) else None
    ok = isinstance(per, list) and len(per) == (n or 1) and all(isinstance(d, dict) for d in per)
    return n, per if ok else None


def _made_ns(side: SideRecords) -> int | None:
    """When the recording was made [ns]: the ``started_ns`` of its ``run`` metadata (written
    by the recorder since before the tracker existed; ``None``: none)."""
    for md in side.metadata:
        if md.name == "run":
            with contextlib.suppress(KeyError, TypeError, ValueError):
                return int(md.metadata["started_ns"])
    return None


# ----------------------------------------------------------------------------------------
# steps 2 and 3: feed the fusion core, write the outputs
# ----------------------------------------------------------------------------------------


class _Outputs:
    """Where the replayed fixes go: the report's streams, with ``keep`` a list
    (``t_pub_wall_ns`` = the time of the step that computed the fix: the recorded receive
    time of the message after which it was computed, or the live fusion's step time when
    replaying by its decision record) and, with ``out_mcap``, an MCAP file with (a copy of
    the input and) the fixes on ``diffpos/<site>/replay/node/<id>/estimate``."""

    def __init__(self, out_mcap: str | Path | None, *, copy_input: bool, site: str,
                 header: dict[str, Any], side: SideRecords, rec: Recorded) -> None:
        self.rec = rec
        self.keys = Keys(site)
        self.sink = None
        self.count = 0
        if out_mcap is not None:  # the input's metadata and attachments first, then ours
            self.sink = McapSink(out_mcap, library="diffpos-replay")
            for md in side.metadata:
                self.sink.add_metadata(md.name, md.metadata)
            for a in side.attachments:
                self.sink.add_attachment(a.name, a.data, media_type=a.media_type,
                                         log_ns=a.log_time, create_ns=a.create_time)
            self.sink.add_metadata("replay", header)
        self.copy_input = copy_input and self.sink is not None

    def copy(self, m: RawMessage) -> None:
        """Copy one recorded message (when writing a copy of the input)."""
        if self.copy_input:
            self.sink.write(m.topic, m.data, m.log_ns, publish_ns=m.publish_ns,
                            sequence=m.sequence)

    def emit(self, ests: Sequence[Any], now_ns: int) -> None:
        """The estimates of a step: column batches by their columns
        (:meth:`FixStream.add_rows`) unless they are kept or written, the rest one by one."""
        rec = self.rec
        if rec.keep is None and self.sink is None:
            for part in ests.parts if isinstance(ests, Estimates) else (ests,):
                if isinstance(part, ColumnBatch):
                    self.count += len(part)
                    rec.replayed.add_rows(part.rows)
                    rec.compare.add_rows(1, part.rows, rec.t_last or 0)
                else:
                    self._emit_each(part, now_ns)
            return
        self._emit_each(ests, now_ns)

    def _emit_each(self, ests: Sequence[M.PositionEstimate], now_ns: int) -> None:
        rec = self.rec
        for e in ests:
            self.count += 1
            if rec.keep is not None or self.sink is not None:
                e = msgspec.structs.replace(e, t_pub_wall_ns=now_ns)
                if rec.keep is not None:
                    rec.keep[1].append(e)
                if self.sink is not None:
                    self.sink.write(self.keys.replay_estimate(e.node_id), M.encode(e), now_ns)
            rec.replayed.add(e)
            rec.compare.add(1, e, rec.t_last or 0)

    def close(self, final_metadata: dict[str, Any] | None = None) -> None:
        if self.sink is not None:
            self.sink.close(final_metadata=final_metadata)


class _CoreSet:
    """Replay cores that take the same calls (one live shard's decision record replayed as
    the shards of another layout, ``diffpos replay --shards M``): the estimates of the
    responders ``keep`` accepts (those the live shard owned), in core order."""

    def __init__(self, cores: list[FusionCore], keep: Callable[[str], bool]) -> None:
        self.cores, self.keep = cores, keep

    def on_sample(self, key: str, data: bytes, wall_ns: int) -> None:
        for c in self.cores:
            c.on_sample(key, data, wall_ns)

    def on_liveliness(self, anchor_id: str, alive: bool, wall_ns: int) -> None:
        for c in self.cores:
            c.on_liveliness(anchor_id, alive, wall_ns)

    def on_oversized(self, key: str, size: int) -> None:
        for c in self.cores:
            c.on_oversized(key, size)

    def step(self, wall_ns: int, *, limit: int | None = None) -> list:
        keep = self.keep
        return [e for c in self.cores for e in c.step(wall_ns, limit=limit) if keep(e.node_id)]

    def flush(self, wall_ns: int) -> list:
        keep = self.keep
        return [e for c in self.cores for e in c.flush(wall_ns) if keep(e.node_id)]


class _Fusion:
    """The replay of one live fusion (or of one live fusion shard): a fresh core per live
    fusion instance.

    The live fusion's diagnostics name its process (``instance``, a nonce per start); a
    restarted fusion starts from nothing (no tracks, no anchors' state, a decision record from
    chunk 0 again). So where ``instance`` changes the replay starts a fresh core too: by the
    new instance's decision record when it begins in the file (chunk 0: every live estimate
    of that instance is reproduced), else in the recording's order. Live estimates of an
    instance the replay cannot reproduce (its record does not begin in the file: it started
    before the recording, or while the recorder was down) are counted with the reason
    (:meth:`not_reproducible`). Anchors alive when a core is replaced are made alive on the
    new one when replaying in recorded order (the restarted fusion sees the live tokens).

    ``make_core()`` returns the driver (a core, or a :class:`_CoreSet`) and its cores;
    ``active`` is the decision replayer in use (``None``: recorded order).
    """

    def __init__(self, make_core: Callable[[], tuple[Any, list[FusionCore]]],
                 emit: Callable[[list, int], None], *, use_decisions: bool, decided: bool,
                 attach: Callable[[FusionCore], None], shard: int = 0) -> None:
        self.make_core, self.emit, self.shard = make_core, emit, shard
        self.use_decisions, self.attach = use_decisions, attach
        self.core, self.cores = make_core()
        self.decided: DecisionReplayer | None = None
        self.active: DecisionReplayer | None = None
        self.instance: str | None = None
        #: per live instance, in recording order: its start [ns] (its record's first call,
        #: else its first diagnostics), last diagnostics, how replayed, why not by record
        self.instances: list[dict[str, Any]] = []
        self.live_log_ns = array("q")  # receive times of the live estimates (attribution)
        self._recent: deque[tuple[int, str, bytes]] = deque()  # inputs, to seed a record
        self._alive: dict[str, bool] = {}
        if decided:  # the file starts with the first instance's record
            self.decided = self.active = DecisionReplayer(self.core, emit, window_ns=_WINDOW_NS)

    def on_input(self, topic: str, data: bytes, log_ns: int) -> None:
        """A fusion input: to the decision replayer, else to the core (recorded order)."""
        if self.active is not None:
            self.active.add_input(topic, data, log_ns)
            return
        self.core.on_sample(topic, data, log_ns)
        if self.use_decisions:  # a later instance's record may name it (bounded: 30 s)
            recent = self._recent
            recent.append((log_ns, topic, data))
            while recent[0][0] < log_ns - _WINDOW_NS:
                recent.popleft()

    def on_liveliness(self, anchor_id: str, alive: bool, log_ns: int) -> None:
        """An anchor's recorded liveliness event (to the core unless replaying by record)."""
        self._alive[anchor_id] = alive
        if self.active is None:
            self.core.on_liveliness(anchor_id, alive, log_ns)

    def step_recorded(self, now_ns: int) -> bool:
        """Step the core when replaying in recorded order; ``True`` if it was."""
        if self.active is not None:
            return False
        self.emit(self.core.step(now_ns), now_ns)
        return True

    def on_diagnostics(self, d: M.FusionDiagnostics, log_ns: int) -> None:
        if d.instance != self.instance or self.instance is None:
            self._start(d, log_ns)
        self.instances[-1]["last_diagnostics_ns"] = log_ns
        if self.active is not None and d.decisions is not None:
            self.active.add_chunk(d.decisions, log_ns)

    def _start(self, d: M.FusionDiagnostics, log_ns: int) -> None:
        """The first diagnostics of a live fusion instance: a fresh core, unless it is the
        first instance and the replay started in its mode (by its record from the file's
        start, or in recorded order)."""
        first = self.instance is None
        self.instance = d.instance
        by_record = self.use_decisions and d.decisions is not None and d.decisions.chunk == 0
        reason = None if by_record else (
            "use_decisions off" if not self.use_decisions
            else "no decision record (a fusion older than the record)" if d.decisions is None
            else f"its decision record begins at chunk {d.decisions.chunk}, not 0: the "
                 "instance started before the recording or while the recorder was down")
        start = log_ns
        if d.decisions is not None and d.decisions.wall_delta_ns:  # its first call seen
            start = min(log_ns, d.decisions.wall_delta_ns[0])
        self.instances.append({"instance": d.instance, "shard": self.shard, "start_ns": start,
                               "replayed_by": "decisions" if by_record else "recorded order",
                               "reason": reason})
        if first and by_record == (self.active is not None):
            return
        if self.active is None:  # recorded order: solve what the old core has pending
            self.emit(self.core.step(log_ns), log_ns)
        self.core, cores = self.make_core()
        self.cores += cores
        for c in cores:
            self.attach(c)
        if self.decided is not None:  # the old record's calls go to the old core, then ends
            self.decided.restart(self.core, log_ns)
        if not by_record:
            self.active = None
            for a, alive in self._alive.items():
                if alive:
                    self.core.on_liveliness(a, True, log_ns)
            return
        if self.decided is None:
            self.decided = DecisionReplayer(self.core, self.emit, window_ns=_WINDOW_NS)
        self.active = self.decided
        while self._recent:  # inputs fed in recorded order: the new record may name them
            t, topic, data = self._recent.popleft()
            self.decided.add_input(topic, data, t)

    def not_reproducible(self) -> Counter[str]:
        """Live estimates the replay cannot reproduce, by reason: those of instances replayed
        without their record, and those an instance followed by another (it died) published
        after its last diagnostics (the record of their calls died with it). An estimate
        belongs to the instance that started last before it was received."""
        by_reason: Counter[str] = Counter()
        inst = self.instances
        if inst and self.use_decisions:
            t = np.frombuffer(self.live_log_ns, np.int64)
            starts = np.asarray([i["start_ns"] for i in inst], np.int64)
            idx = np.maximum(np.searchsorted(starts, t, side="right") - 1, 0)
            for k, i in enumerate(inst):
                mine = t[idx == k]
                if i["reason"] is not None:
                    by_reason[i["reason"]] += mine.size
                elif k + 1 < len(inst):  # it was followed by another: it died
                    by_reason["published after the instance's last diagnostics (killed: the "
                              "record of their calls died with it)"] += int(
                                  np.count_nonzero(mine > i["last_diagnostics_ns"]))
        return by_reason


class _Shards:
    """One :class:`_Fusion` per live fusion shard (one without shards): every input and
    liveliness event goes to each, a diagnostics message to the shard it names (so each
    shard's decision record drives its own replay core(s), with its own settings), a live
    estimate is attributed to the shard that owns its node.

    ``plans[k]``: the replay cores' settings of live shard ``k`` (one config: that shard;
    several: the shards of another layout, each keeping shard ``k``'s responders).
    ``by_instance=False``: the diagnostics do not say which shard sent them (a sharded run
    recorded before they did): nothing is replayed by record and no instance change starts
    a fresh core (two shards' interleaved instances are not restarts).
    """

    def __init__(self, plans: list[list[FusionConfig]], new_core: Callable[..., FusionCore],
                 emit: Callable[[list, int], None], rec: Recorded, *, use_decisions: bool,
                 decided: set[int], attach: Callable[[FusionCore], None],
                 by_instance: bool = True) -> None:
        self.live, self.rec, self.by_instance = len(plans), rec, by_instance
        self.fusions = [
            _Fusion(functools.partial(self._make, new_core, cfgs, k), emit,
                    use_decisions=use_decisions and by_instance, decided=k in decided,
                    attach=attach, shard=k)
            for k, cfgs in enumerate(plans)]
        self.other_layout = 0  # diagnostics of a shard outside the live layout
        self.unattributed: str | None = None  # why no live estimate can be reproduced
        self._dec_diag = M.decoder(M.FusionDiagnostics)
        self._owner: dict[str, int] = {}

    def _make(self, new_core: Callable[..., FusionCore], cfgs: list[FusionConfig],
              k: int) -> tuple[Any, list[FusionCore]]:
        cores = [new_core(c) for c in cfgs]
        if self.live == 1 or (len(cores) == 1 and cores[0].config.shards == self.live):
            return cores[0], cores  # the live shard's own layout: its estimates only
        return _CoreSet(cores, lambda node: self.owner(node) == k), cores

    @property
    def cores(self) -> list[FusionCore]:
        return [c for f in self.fusions for c in f.cores]

    @property
    def first_core(self) -> FusionCore:
        return self.fusions[0].cores[0]

    def owner(self, node_id: str) -> int:
        """The live shard that owns ``node_id``."""
        k = self._owner.get(node_id)
        if k is None:
            k = self._owner[node_id] = shard_of(node_id, self.live)
        return k

    def on_input(self, topic: str, data: bytes, log_ns: int) -> None:
        for f in self.fusions:
            f.on_input(topic, data, log_ns)

    def on_liveliness(self, m: RawMessage) -> None:
        with contextlib.suppress(ValueError, TypeError, KeyError, AttributeError):
            ev = json.loads(m.data)
            if ev.get("role") == "anchor" and ev.get("id"):
                for f in self.fusions:
                    f.on_liveliness(str(ev["id"]), bool(ev["alive"]), m.log_ns)

    def on_live_estimate(self, node: str | None, log_ns: int) -> None:
        self.fusions[0 if node is None or self.live == 1 else self.owner(node)] \
            .live_log_ns.append(log_ns)

    def on_diagnostics(self, m: RawMessage) -> None:
        try:
            d = self._dec_diag(m.data)
        except (msgspec.DecodeError, ValueError):
            self.rec.bad_payloads["diagnostics"] += 1
            return
        if not self.by_instance:
            return
        if d.shards != self.live or d.shard >= self.live:
            self.other_layout += 1
            return
        self.fusions[d.shard].on_diagnostics(d, m.log_ns)

    def in_recorded_order(self) -> bool:
        """Whether any shard replays in recorded order (else :meth:`step_recorded` does
        nothing: every shard follows its decision record). Changes only with a live
        instance's diagnostics (:meth:`on_diagnostics`)."""
        return any(f.active is None for f in self.fusions)

    def step_recorded(self, now_ns: int) -> bool:
        """Step the shards replayed in recorded order; ``True`` if any was."""
        stepped = False
        for f in self.fusions:
            stepped = f.step_recorded(now_ns) or stepped
        return stepped

    def finish(self, emit: Callable[[list, int], None], t_last_ns: int) -> None:
        """End of the recording: each record's remaining calls, then solve what is pending
        and flush (:func:`_drain`)."""
        for f in self.fusions:
            if f.active is not None:
                f.active.finish()
        for f in self.fusions:
            _drain(f.core, emit, t_last_ns)

    def decisions_report(self) -> dict[str, Any] | None:
        """The decision replayers' counts, summed over the shards (``None``: none)."""
        reports = [f.decided.report for f in self.fusions if f.decided is not None]
        if not reports:
            return None
        return {k: sum(r[k] for r in reports) for k in reports[0]}

    def not_reproducible(self) -> dict[str, Any]:
        by_reason: Counter[str] = Counter()
        for f in self.fusions:
            by_reason.update(f.not_reproducible())
        if self.unattributed is not None:
            by_reason[self.unattributed] += sum(len(f.live_log_ns) for f in self.fusions)
        by_reason = +by_reason
        return {"estimates": int(sum(by_reason.values())), "by_reason": dict(by_reason),
                "instances": [i for f in self.fusions for i in f.instances]}


def _windowed(batches: Iterable[list[RawMessage]], rec: Recorded, start_s: float | None,
              end_s: float | None) -> Iterator[list[RawMessage]]:
    """The messages received from ``start_s`` to ``end_s`` seconds into the recording (after
    its first message, ``rec.t_origin``; ``None``: its start / end), plus the anchor liveliness
    events before the window (which anchors are up when it opens); reading stops past it."""
    lo = None if start_s is None else round(start_s * 1e9)
    hi = None if end_s is None else round(end_s * 1e9)
    live: dict[str, bool] = {}
    for batch in batches:
        if rec.t_origin is None and batch:
            rec.t_origin = batch[0].log_ns
        if lo is None and hi is None:
            yield batch
            continue
        keep = []
        for m in batch:
            t = m.log_ns - rec.t_origin
            if hi is not None and t > hi:
                if keep:
                    yield keep
                return
            if lo is None or t >= lo:
                if lo is not None and (rec.t_first is None or rec.t_first < rec.t_origin + lo):
                    rec.t_first = m.log_ns  # the window's first message: its span from here
                keep.append(m)
            else:
                is_live = live.get(m.topic)
                if is_live is None:
                    is_live = live[m.topic] = parse_topic(m.topic)[0] == "liveliness"
                if is_live:
                    keep.append(m)
        if keep:
            yield keep


def _feed(
    fusion: _Shards,
    batches: Iterable[list[RawMessage]],
    outputs: _Outputs,
    rec: Recorded,
    *,
    step_ns: int,
    after_batch: Callable[[], None],
) -> Recorded:
    """Every recorded message in file order into the cores (fusion inputs; through each live
    shard's decision record when there is one) or the collector, stepping the cores each
    ``step_ns`` of receive time (without a decision record); a fresh core where the live
    fusion restarted (:class:`_Fusion`); then solve what is pending."""
    routes: dict[str, tuple] = {}  # topic -> (kind, node, sequence stream, is input)
    per_topic: Counter[str] = Counter()
    seq = rec.seq
    copy = outputs.copy if outputs.copy_input else None
    next_step = next_advance = None
    stepping = fusion.in_recorded_order()  # (else step_recorded is a no-op: not called)
    for batch in batches:
        if rec.t_first is None and batch:
            rec.t_first = batch[0].log_ns
        for m in batch:
            topic = m.topic
            route = routes.get(topic)
            if route is None:
                kind, fields = parse_topic(topic)
                route = routes[topic] = (kind, fields.get("node"), seq.stream_of(topic),
                                         kind in FUSION_INPUT_KINDS)
            per_topic[topic] += 1
            if route[2] is not None:
                seq.add_stream(route[2], m.sequence)
            now = rec.t_last = m.log_ns
            if copy is not None:
                copy(m)
            if route[3]:
                fusion.on_input(topic, m.data, now)
            elif route[0] == "diagnostics":
                fusion.on_diagnostics(m)
                stepping = fusion.in_recorded_order()
            elif route[0] == "liveliness":
                fusion.on_liveliness(m)
            else:
                if route[0] == "estimate":
                    fusion.on_live_estimate(route[1], now)
                rec.take(route[0], m, route[1])
                if route[0] == "heartbeat":
                    continue  # no step point: the services' liveness, nothing the fusion heard
            if stepping and (next_step is None or now >= next_step) \
                    and fusion.step_recorded(now):
                next_step = now + step_ns
        if rec.t_last is not None and (next_advance is None or rec.t_last >= next_advance):
            rec.advance(rec.t_last)  # score what the truth covers (bounded memory)
            next_advance = rec.t_last + _ADVANCE_NS
        after_batch()
    for topic, n in per_topic.items():
        rec.counts[routes[topic][0]] += n
    return rec


def _drain(core: Any, emit: Callable[[list, int], None], t_last_ns: int) -> None:
    """Solve what is pending (far past every deadline), then flush like the live service at
    shutdown (after a complete decision record: nothing is pending any more)."""
    emit(core.step(t_last_ns + 10**12), t_last_ns)
    emit(core.flush(t_last_ns), t_last_ns)


# ----------------------------------------------------------------------------------------
# step 4: metrics and report
# ----------------------------------------------------------------------------------------


@dataclass
class ReplayResult:
    """Everything a replay produced.

    Attributes
    ----------
    estimates : list of PositionEstimate
        Replayed fixes in the order produced (``t_pub_wall_ns`` = the time of the step that
        computed it, so the list is reproducible); empty unless ``keep_estimates``.
    live_estimates : list of PositionEstimate
        The estimates recorded from the live fusion (empty unless ``keep_estimates``).
    report : dict
        JSON-able report (see ``diffpos replay --help``); ``report["timing"]`` is the only
        part that changes between identical runs.
    errors : dict of ndarray
        Overall replayed error arrays (``e3``, ``ez``, ``eh`` [m]) for plots;
        ``live_errors`` the same for the live estimates.
    """

    estimates: list[M.PositionEstimate]
    live_estimates: list[M.PositionEstimate]
    report: dict[str, Any]
    errors: dict[str, np.ndarray]
    live_errors: dict[str, np.ndarray]


@contextlib.contextmanager
def _fewer_gc_passes() -> Iterator[None]:
    """Run the cyclic garbage collector less often for the duration (restored after).

    The feed allocates many short-lived objects (decoded messages, pending epochs) without
    reference cycles; with the default thresholds the collector traverses the long-lived ones
    again and again (measured: 17 % of a 2-minute replay when every estimate was kept).
    Cycles are still collected, just in larger batches.
    """
    old = gc.get_threshold()
    gc.set_threshold(max(old[0], 100_000), max(old[1], 50), max(old[2], 1000))
    try:
        yield
    finally:
        gc.set_threshold(*old)


def _messages_section(rec: Recorded, cores: list[FusionCore]) -> dict[str, Any]:
    received: Counter[str] = Counter()
    rejected: Counter[str] = Counter()
    for core in cores:  # one per live fusion instance
        received.update(core.received)
        rejected.update(core.rejected)
    return {
        "by_kind": dict(sorted(rec.counts.items())),
        "total": sum(rec.counts.values()),
        "skipped_unknown": rec.counts.get("unknown", 0),
        "undecodable": dict(rec.bad_payloads),
        "gaps": rec.seq.total_gaps,
        "gaps_by_stream": dict(sorted(rec.seq.gaps.items())[:200]),
        "out_of_order": rec.seq.total_out_of_order,
        "fusion_received": dict(received),
        "fusion_rejected": dict(rejected),
        "late_ranges": sum(core.book.late for core in cores),
    }


def what_if_text(overrides: dict[str, Any]) -> str:
    """The what-ifs as ``FIELD=VALUE, ...`` (tracker settings as ``tracker.KEY=VALUE``;
    ``""``: none)."""
    items: list[str] = []
    for k, v in overrides.items():
        items += ([f"{k}.{kk}={vv}" for kk, vv in v.items()] if isinstance(v, dict)
                  else [f"{k}={v}"])
    return ", ".join(items)


#: An anchor or node counts as dropped by the replay when its replayed fixes (that use the
#: anchor; with a position, for a node) are fewer than this share of the recorded live ones.
DROPPED_SHARE = 0.1


def _dropped(rec: Recorded, cores: list[FusionCore]) -> dict[str, Any]:
    """Anchors and nodes the replayed fixes (nearly) lost: :data:`DROPPED_SHARE` of the live
    fixes or fewer; without live fixes, an anchor that sent data and no fix used, a node with
    truth and no positioned fix. Each with the numbers and the fusion's reasons."""
    out, live = rec.replayed, rec.live
    has_live = live.total > 0
    seen = set().union(*(c.anchors for c in cores))  # one core per live fusion instance
    rejected: Counter[str] = Counter()
    for c in cores:
        rejected.update(c.rejected)
    anchors: dict[str, Any] = {}
    for a in sorted(seen | set(out.used) | set(live.used), key=natural_key):
        r, lv = out.used.get(a, 0), live.used.get(a, 0)
        if (r <= DROPPED_SHARE * lv) if has_live else r == 0:
            if has_live and lv == 0:
                continue  # the live fusion did not use it either
            why = out.excluded.get(a) or {}
            anchors[a] = {"replayed_used": r, "live_used": lv if has_live else None,
                          "excluded": dict(why.most_common(3)) if why else {}}
    nodes: dict[str, Any] = {}
    for n in sorted(set(out.fixes_by_node) | set(live.fixes_by_node) | set(rec.truth.t),
                    key=natural_key):
        r, lv = out.positioned.get(n, 0), live.positioned.get(n, 0)
        if (lv > 0 and r <= DROPPED_SHARE * lv) if has_live else (r == 0 and n in rec.truth.t):
            nodes[n] = {"replayed_positioned": r, "live_positioned": lv if has_live else None,
                        "replayed_fixes": out.fixes_by_node.get(n, 0)}
    return {"anchors": anchors, "nodes": nodes,
            "fusion_rejected": dict(sorted(rejected.items()))}


def _report(path: str | Path, scanner: McapScanner, settings: ReplaySettings, fusion: _Shards,
            rec: Recorded, *, step_ms: float, t_wall0: float, warm_up_s: float,
            window: tuple[float | None, float | None], shards: dict[str, Any]) -> ReplayResult:
    """Accuracy of the replayed (and recorded live) fixes, and the JSON report."""
    rec.advance(rec.t_last or 0, final=True)
    out, live = rec.replayed, rec.live
    accuracy, errs = out.accuracy()
    live_accuracy, live_errs = live.accuracy() if live.total else (None, {})
    config = settings.config
    duration_s = ((rec.t_last or 0) - (rec.t_first or 0)) / 1e9
    wall = time.perf_counter() - t_wall0
    nodes = set(out.fixes_by_node) | set(rec.truth.t)
    report: dict[str, Any] = {
        "file": str(path),
        "complete": scanner.complete,
        "parts": [p.path.name for p in getattr(scanner, "parts", [scanner])],
        "damage": {**scanner.damage.__dict__, "ok": scanner.damage.ok},
        "settings": msgspec.to_builtins(config),
        "settings_source": settings.source,
        "settings_warning": settings.warning,
        "tracker_settings": settings.tracker_note,
        "ignored_recorded_fields": settings.ignored_recorded_fields,
        "overrides": settings.overrides,
        "what_if": what_if_text(settings.overrides),
        "method": config.method,
        "step_ms": step_ms,
        "decisions": fusion.decisions_report(),
        "shards": {**shards, "diagnostics_of_other_shards": fusion.other_layout},
        "fusion_instances": (instances := fusion.not_reproducible()),
        "recording_s": duration_s,
        "truth_s": (None if rec.truth.first_t is None
                    else (rec.truth.last_t - rec.truth.first_t) / 1e9),
        "truth_floor": rec.truth_floor,
        "messages": _messages_section(rec, fusion.cores),
        "fixes": {"total": out.total, "by_status": dict(sorted(out.by_status.items()))},
        "nodes": sorted(nodes, key=natural_key),
        "anchors": sorted(set().union(*(c.anchors for c in fusion.cores)), key=natural_key),
        "accuracy": accuracy,
        "node_epochs": out.node_epochs(),
        "gating": out.gating(),
        "live": None if live_accuracy is None else {
            "fixes": live.total,
            "by_status": dict(sorted(live.by_status.items())),
            "accuracy": live_accuracy,
            "node_epochs": live.node_epochs(),
            "gating": live.gating(),
        },
        "compare": None if not live.total else {
            **rec.compare.result(),
            "live_not_reproducible": instances["estimates"],
            "live_not_reproducible_by_reason": instances["by_reason"]},
        "origin_ns": rec.t_origin,
        "window": None if window == (None, None) else {"start_s": window[0], "end_s": window[1]},
        "dropped": _dropped(rec, fusion.cores),
        "timing": {
            # the kernels: imports, cache loads (a compile on a fresh machine) and the
            # fusion's warm-up, before the replay's clock starts
            "warm_up_s": warm_up_s,
            # of this process's wall time so far, the seconds numba spent loading (or
            # compiling) kernels, warm-up and run together (docs/startup.md)
            "kernel_load_s": kernel_clock.kernel_load_s(),
            "wall_s": wall,
            "speedup_x": (duration_s / wall) if wall > 0 and duration_s > 0 else None,
        },
    }
    kept = rec.keep or ([], [])
    return ReplayResult(estimates=kept[1], live_estimates=kept[0], report=report,
                        errors=errs, live_errors=live_errs)


# ----------------------------------------------------------------------------------------
# replay
# ----------------------------------------------------------------------------------------


@_fewer_gc_passes()  # a contextmanager is also a decorator (fresh per call)
def replay(
    path: str | Path,
    *,
    overrides: dict[str, Any] | None = None,
    method: str | None = None,
    step_ms: float = 5.0,
    use_recorded_settings: bool = True,
    out_mcap: str | Path | None = None,
    copy_input: bool = True,
    max_truth_gap_s: float = 0.5,
    progress: Callable[[int, int], None] | None = None,
    logger: logging.Logger | None = None,
    keep_estimates: bool = True,
    use_decisions: bool = True,
    start_s: float | None = None,
    end_s: float | None = None,
    shards: int | None = None,
) -> ReplayResult:
    """Re-run the fusion on a recording.

    Parameters
    ----------
    path : path
        MCAP recording (complete or truncated: a truncated one is replayed up to its last
        complete chunk, and the report says so).
    overrides : dict, optional
        FusionConfig fields to change (e.g. ``{"gating": False}``,
        ``{"false_alarm_probability": 1e-4}``); applied on top of the recorded settings.
    method : {"mnls", "dnls", "lls", "ippa"}, optional
        Estimator (``FusionConfig.method``; default: the recorded setting, else D-NLS).
        Overrides a ``method`` in ``overrides``.
    step_ms : float [ms]
        Fusion step granularity in recorded receive time (0 = after every message).
    use_recorded_settings : bool
        Start from the fusion settings stored in the recording (else the defaults).
    out_mcap : path, optional
        Write a new MCAP: (a copy of the input if ``copy_input``) plus the replayed estimates
        on ``diffpos/<site>/replay/node/<id>/estimate``.
    max_truth_gap_s : float [s]
        Estimates farther than this from any truth sample are not evaluated.
    progress : callable, optional
        ``progress(bytes_read, bytes_total)`` after each chunk.
    logger : logging.Logger, optional
        Logger handed to the fusion (default: a quiet one).
    keep_estimates : bool
        Also return every live and replayed estimate (``ReplayResult.estimates``; ~5 KB per
        fix). Without, memory stays ~40 bytes per fix: the report is computed as a stream.
    use_decisions : bool
        Replay by the live fusion's decision record when the recording holds one (from its
        first diagnostics on): the live run's ingest order, liveliness and step times, so the
        fixes are the live ones bit for bit (``report["decisions"]`` counts what matched).
        Without (or without a record) the recording's order and ``step_ms`` are used.
    start_s, end_s : float, optional [s]
        Replay only the messages received this long after the recording's first message
        (the anchors' liveliness events before ``start_s`` too); the decision record is then
        not used (it covers the whole run). ``report["window"]`` says so.
    shards : int, optional
        Run the replay as this many fusion shards (``FusionConfig.shard`` / ``shards``).
        Default: as live. A run of N fusion shards (``diffpos fusion --shard K/N``, whose
        diagnostics say which shard sent them) is replayed on one core per live shard, each
        with its recorded settings and by its own decision record: every live estimate bit
        for bit. Another count (e.g. 1: one fusion) replays each live shard's record (or
        the recorded order) on that many cores, keeping the live shard's responders: with
        1, one fusion making each live shard's calls (``report["shards"]`` says what ran).

    Raises
    ------
    RecordingError
        Not MCAP, missing, or no fusion input (anchor states / ranges) in it.
    ConfigError
        Invalid settings (names the field).
    """
    if start_s is not None and end_s is not None and end_s <= start_s:
        raise ConfigError(f"the window ends ({end_s:g} s) before it starts ({start_s:g} s)")
    if start_s is not None and start_s < 0:
        raise ConfigError(f"start {start_s:g} s: must be >= 0 (seconds into the recording)")
    if out_mcap is not None:
        check_output(out_mcap, option="out_mcap", inputs=[path])
    if shards is not None and not 1 <= shards <= MAX_SHARDS:
        raise ConfigError(f"shards={shards}: must be in [1, {MAX_SHARDS}]")
    scanner = PartsScanner(path)  # a split recording's parts in turn
    side = side_records(path)
    ahead, rest, first_state, first_diags = read_ahead(scanner)
    settings = replay_settings(scanner, side=side, first_state=first_state, overrides=overrides,
                               method=method, use_recorded_settings=use_recorded_settings)
    log = logger or logging.getLogger("diffpos.replay")
    if settings.warning:
        log.warning("%s", settings.warning)
    plan = shard_plan(settings, first_diags, shards,
                      use_decisions=use_decisions and start_s is None and end_s is None)
    if plan.note:
        log.warning("%s", plan.note)
    with contextlib.ExitStack() as stack:
        tmp = None if out_mcap is None else stack.enter_context(atomic_path(out_mcap))
        # the estimates' sequence streams: of the shard count the run configuration records
        # (else inferred from the sequence numbers, recording.topics.SeqTracker)
        # the true floor of a fix: the recorded building's floor of the true position then
        building, where = recorded_building(side)
        rec = Recorded(FUSION_INPUT_KINDS, max_truth_gap_ns=round(max_truth_gap_s * 1e9),
                       keep_estimates=keep_estimates, window_ns=_WINDOW_NS,
                       estimate_shards=_run_config_shards(side)[0],
                       floor_of=None if building is None else building.floor_index,
                       truth_floor=f"the floor of the true position in the building of {where}"
                       if building is not None else "the nearest truth sample's (no building "
                       "recorded)")
        return _run(path, scanner, settings, ahead, rest, tmp, rec, side=side,
                    copy_input=copy_input, step_ms=step_ms, progress=progress, logger=logger,
                    plan=plan, use_decisions=use_decisions, window=(start_s, end_s))


@dataclass(frozen=True)
class ShardPlan:
    """What the replay runs for the live fusion shards.

    Attributes
    ----------
    configs : list of list of FusionConfig
        Per live shard (one entry without shards): the settings of its replay cores (one:
        that shard's own; several: the shards of another layout).
    decided : frozenset of int
        The live shards replayed by their decision record from the start of the file.
    by_instance : bool
        False when the diagnostics cannot say which shard sent them (see :class:`_Shards`).
    note : str or None
        What cannot be reproduced and why (one line), or how the layout differs from live.
    report : dict
        ``report["shards"]``.
    """

    configs: list[list[FusionConfig]]
    decided: frozenset[int]
    by_instance: bool
    note: str | None
    report: dict[str, Any]


def shard_plan(settings: ReplaySettings, first_diags: dict[int, M.FusionDiagnostics],
               shards: int | None, *, use_decisions: bool) -> ShardPlan:
    """The replay's cores for the live layout: the live fusion shards as their diagnostics
    say (``shards``; else the run configuration's ``fusion_shards``), each with its recorded
    settings (:attr:`ReplaySettings.by_shard`; else the run's with its ``shard``/``shards``),
    replayed as ``shards`` shards (``None``: as live)."""
    diag = next(iter(first_diags.values()), None)
    live = diag.shards if diag is not None else settings.recorded_shards
    by_instance, note = True, None
    if diag is not None and live == 1 and settings.recorded_shards > 1:
        by_instance, note = False, (
            f"the run had {settings.recorded_shards} fusion shards but their diagnostics do "
            "not say which shard sent them (recorded before diffpos.fusion_diagnostics.v2 "
            "carried shard/shards): replayed as one fusion in recorded order; the live "
            "estimates cannot be reproduced bit for bit")
    m = live if shards is None else shards
    if live == 1:
        own = [settings.config]
    elif len(settings.by_shard) == live:
        own = list(settings.by_shard)
    else:
        own = [msgspec.structs.replace(settings.config, shard=k, shards=live)
               for k in range(live)]
    configs = [[c] if m == live else [msgspec.structs.replace(c, shard=j, shards=m)
                                      for j in range(m)] for c in own]
    decided = frozenset(
        k for k, d in first_diags.items()
        if use_decisions and by_instance and d.shards == live and d.decisions is not None
        and d.decisions.chunk == 0)
    if m != live and note is None:
        note = (f"replayed as {m} fusion shard(s) instead of the live {live}: each live "
                f"shard's {'decision record' if decided else 'recorded order'} on {m} "
                f"core(s), keeping that shard's responders")
    report = {"live": live, "replayed": m, "recorded": settings.recorded_shards,
              "settings": ("recorded per shard" if live > 1 and len(settings.by_shard) == live
                           else "the run's" + (" with each shard's K/N" if live > 1 else "")),
              "cores": [[f"{c.shard}/{c.shards}" for c in cfgs] for cfgs in configs],
              "by_record": sorted(decided), "note": note}
    return ShardPlan(configs, decided, by_instance, note, report)


def _run(path, scanner, settings, ahead, rest, tmp, rec, *, side, copy_input, step_ms,
         progress, logger, plan, use_decisions, window) -> ReplayResult:
    """Steps 2-4 of :func:`replay` (``tmp``: where the output MCAP goes until complete)."""
    config = settings.config
    kernel_pool.set_threads(config.kernel_threads)  # the process's kernel pool (threads)
    t_warm = time.perf_counter()
    outputs = _Outputs(tmp, copy_input=copy_input, site=config.site, side=side, rec=rec, header={
        "source": str(path),
        "method": config.method,
        "step_ms": step_ms,
        "settings": msgspec.to_builtins(config),
        "settings_source": settings.source,
    })

    def after_batch() -> None:
        if progress is not None:
            progress(scanner.offset, scanner.size_bytes)

    def new_core(cfg: FusionConfig) -> FusionCore:
        return FusionCore(cfg, logger=quiet_logger() if logger is None else logger,
                          record_decisions=False)

    pool: list[Any] = []

    def attach(core: FusionCore) -> None:  # a fresh core shares the worker processes
        if pool and core.bank is not None:
            core.bank.pool = pool[0]

    fusion = _Shards(plan.configs, new_core, outputs.emit, rec, use_decisions=use_decisions,
                     decided=set(plan.decided), attach=attach, by_instance=plan.by_instance)
    if not plan.by_instance:
        fusion.unattributed = ("a sharded run's diagnostics that do not say which shard sent "
                               "them: no shard's decision record can be replayed")
    first = fusion.first_core
    first.warm_up()  # the kernels loaded (or compiled) now: not counted as replay time
    # FusionConfig.workers: the same estimates for any count, so never more processes than
    # this machine has cores (a recording made on a bigger machine)
    n_proc = min(first.config.workers, os.cpu_count() or 1)
    rows = None
    if n_proc > 1 and first.bank is not None:  # a pool (start_workers: mnls + its tracker)
        # imported here: a replay without a pool (D-NLS, one process) never imports it
        from diffpos_services.fusion.workers import start_workers

        rows = start_workers(first, max_processes=n_proc)
    try:
        if rows is not None:
            pool.append(rows)
            for c in fusion.cores[1:]:  # the other shards' cores share the workers
                attach(c)
            rows.wait_ready()
        t_wall0 = time.perf_counter()  # the replay's clock: from here to the report
        _feed(fusion, _windowed(_consume(ahead, rest), rec, *window), outputs, rec,
              step_ns=max(0, round(step_ms * 1e6)), after_batch=after_batch)
        if rec.fusion_inputs == 0:
            outputs.close()
            raise RecordingError(
                f"{path} has no anchor states or ranges under diffpos/<site>/anchor/...: "
                "nothing to replay (is it a diffpos recording? see diffpos inspect)"
            )
        fusion.finish(outputs.emit, rec.t_last or 0)
    finally:
        if rows is not None:
            rows.close()
    outputs.close(final_metadata={"replayed_estimates": outputs.count})
    result = _report(path, scanner, settings, fusion, rec, step_ms=step_ms, t_wall0=t_wall0,
                     warm_up_s=t_wall0 - t_warm, window=window, shards=plan.report)
    # the processes that ran the fusion's rows (FusionConfig.workers, this one included; the
    # same estimates for any count): not a result, so with the timing
    result.report["timing"]["processes"] = 1 if rows is None else n_proc
    return result
