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
import gc
import json
import logging
import os
import time
from array import array
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from diffpos._kernels import pool as kernel_pool
from diffpos_services.config import build_config
from diffpos_services.errors import ConfigError
from diffpos_services.fusion.config import (
    METHODS,
    TRACKER_KEYS,
    FusionConfig,
    complete_tracker,
    legacy_tracker_settings,
    merge_tracker,
    with_legacy_defaults,
)
from diffpos_services.fusion.core import FusionCore
from diffpos_services.fusion.workers import start_workers
from diffpos_services.recording.errors import RecordingError
from diffpos_services.recording.outputs import atomic_path, check_output
from diffpos_services.recording.reader import (
    McapScanner,
    PartsScanner,
    RawMessage,
    SideRecords,
    side_records,
)
from diffpos_services.recording.summary import attached_scenario, live_fusion_settings
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
    "derived_fusion_settings",
    "live_fusion_settings",
    "replay",
    "replay_settings",
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
    """

    config: FusionConfig
    source: str
    ignored_recorded_fields: list[str]
    overrides: dict[str, Any]
    warning: str | None = None
    tracker_note: str | None = None


def read_ahead(
    scanner: McapScanner,
) -> tuple[list[list[RawMessage]], Iterator[list[RawMessage]], RawMessage | None,
           M.FusionDiagnostics | None]:
    """Read chunks until the first anchor state and the first fusion diagnostics (at most 64
    chunks, and at most 10 s of recording time past the first anchor state when no
    diagnostics come: a recording without a live fusion is not held in memory): when the
    recording holds no fusion settings, derived ones need the anchors' ranging rate; the
    diagnostics say whether the live fusion recorded its decisions.
    Returns the chunks read, the rest, the first anchor state and the first diagnostics."""
    batches = scanner.iter_batches()
    ahead: list[list[RawMessage]] = []
    first_state = first_diag = None
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
            elif kind == "diagnostics" and first_diag is None:
                with contextlib.suppress(M.DecodeError):
                    first_diag = dec(m.data)
        if (first_state is not None and first_diag is not None) or \
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
    """Recorded settings (else derived, see :func:`derived_fusion_settings`) + what-ifs.

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
    base: dict[str, Any] = dict(recorded) if use_recorded_settings else {}
    base = with_legacy_defaults(base)  # settings recorded before a newer setting existed
    if not use_recorded_settings:
        source = "defaults (--ignore-recorded-settings)"
    tracker_note = None
    if use_recorded_settings and "tracker" not in base:  # recorded before it was recorded
        base["tracker"], tracker_note = legacy_tracker_settings(
            base, _made_ns(side))
    elif use_recorded_settings and isinstance(base["tracker"], dict):  # before newer keys
        base["tracker"], tracker_note = complete_tracker(base, _made_ns(side))
    known = _fusion_fields()
    ignored = sorted(set(base) - known)
    for f in ignored:
        base.pop(f)
    if isinstance(base.get("tracker"), dict):  # a newer recording's tracker settings
        gone = sorted(set(base["tracker"]) - set(TRACKER_KEYS))
        ignored += [f"tracker.{k}" for k in gone]
        base["tracker"] = {k: v for k, v in base["tracker"].items() if k not in gone}
    bad = sorted(set(overrides or {}) - known)
    if bad:
        raise ConfigError(
            f"{', '.join(bad)}: not a fusion setting; known settings: {', '.join(sorted(known))}"
        )
    base.update({k: v for k, v in (overrides or {}).items() if k != "tracker"})
    if "tracker" in (overrides or {}):  # what-ifs change single recorded tracker settings
        base["tracker"] = merge_tracker(base.get("tracker"), overrides["tracker"])
    if method is not None:
        if method not in METHODS:
            raise ConfigError(f"--method {method!r}: choose {', '.join(METHODS)}")
        base["method"] = method
    if "site" not in base and site is not None:
        base["site"] = site
    config = build_config(FusionConfig, base)
    return ReplaySettings(config, source, ignored, dict(overrides or {}), warning, tracker_note)


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

    def emit(self, ests: list[M.PositionEstimate], now_ns: int) -> None:
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


class _Fusion:
    """The replayed fusion: a fresh core per live fusion instance.

    The live fusion's diagnostics name its process (``instance``, a nonce per start); a
    restarted fusion starts from nothing (no tracks, no anchors' state, a decision record from
    chunk 0 again). So where ``instance`` changes the replay starts a fresh core too: by the
    new instance's decision record when it begins in the file (chunk 0: every live estimate
    of that instance is reproduced), else in the recording's order. Live estimates of an
    instance the replay cannot reproduce (its record does not begin in the file: it started
    before the recording, or while the recorder was down) are counted with the reason
    (:meth:`not_reproducible`). Anchors alive when a core is replaced are made alive on the
    new one when replaying in recorded order (the restarted fusion sees the live tokens).
    """

    def __init__(self, make_core: Callable[[], FusionCore], emit: Callable[[list, int], None],
                 rec: Recorded, *, use_decisions: bool, decided: bool,
                 attach: Callable[[FusionCore], None]) -> None:
        self.make_core, self.emit, self.rec = make_core, emit, rec
        self.use_decisions, self.attach = use_decisions, attach
        self.core = make_core()
        self.cores = [self.core]
        self.decided: DecisionReplayer | None = None
        self.instance: str | None = None
        #: per live instance, in recording order: its start [ns] (its record's first call,
        #: else its first diagnostics), last diagnostics, how replayed, why not by record
        self.instances: list[dict[str, Any]] = []
        self.live_log_ns = array("q")  # receive times of the live estimates (attribution)
        self._recent: deque[tuple[int, str, bytes]] = deque()  # inputs, to seed a record
        self._alive: dict[str, bool] = {}
        self._dec_diag = M.decoder(M.FusionDiagnostics)
        if decided:  # the file starts with the first instance's record
            self.decided = rec.decided = DecisionReplayer(self.core, emit, window_ns=_WINDOW_NS)

    def on_input(self, topic: str, data: bytes, log_ns: int) -> bool:
        """A fusion input; ``True`` when the core took it directly (recorded order)."""
        if self.rec.decided is not None:
            self.rec.decided.add_input(topic, data, log_ns)
            return False
        self.core.on_sample(topic, data, log_ns)
        if self.use_decisions:  # a later instance's record may name it (bounded: 30 s)
            recent = self._recent
            recent.append((log_ns, topic, data))
            while recent[0][0] < log_ns - _WINDOW_NS:
                recent.popleft()
        return True

    def on_liveliness(self, m: RawMessage) -> None:
        with contextlib.suppress(ValueError, TypeError, KeyError, AttributeError):
            ev = json.loads(m.data)
            if ev.get("role") == "anchor" and ev.get("id"):
                self._alive[str(ev["id"])] = bool(ev["alive"])

    def on_diagnostics(self, m: RawMessage) -> None:
        try:
            d = self._dec_diag(m.data)
        except (msgspec.DecodeError, ValueError):
            self.rec.bad_payloads["diagnostics"] += 1
            return
        if d.instance != self.instance or self.instance is None:
            self._start(d, m.log_ns)
        self.instances[-1]["last_diagnostics_ns"] = m.log_ns
        if self.rec.decided is not None and d.decisions is not None:
            self.rec.decided.add_chunk(d.decisions, m.log_ns)

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
        self.instances.append({"instance": d.instance, "start_ns": start,
                               "replayed_by": "decisions" if by_record else "recorded order",
                               "reason": reason})
        if first and by_record == (self.rec.decided is not None):
            return
        old = self.core
        if self.rec.decided is None:  # recorded order: solve what the old core has pending
            self.emit(old.step(log_ns), log_ns)
        self.core = self.make_core()
        self.cores.append(self.core)
        self.attach(self.core)
        if self.decided is not None:  # the old record's calls go to the old core, then ends
            self.decided.restart(self.core, log_ns)
        if not by_record:
            self.rec.decided = None
            for a, alive in self._alive.items():
                if alive:
                    self.core.on_liveliness(a, True, log_ns)
            return
        if self.decided is None:
            self.decided = DecisionReplayer(self.core, self.emit, window_ns=_WINDOW_NS)
        self.rec.decided = self.decided
        while self._recent:  # inputs fed in recorded order: the new record may name them
            t, topic, data = self._recent.popleft()
            self.decided.add_input(topic, data, t)

    def not_reproducible(self) -> dict[str, Any]:
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
        by_reason = +by_reason
        return {"estimates": int(sum(by_reason.values())), "by_reason": dict(by_reason),
                "instances": inst}


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
    fusion: _Fusion,
    batches: Iterable[list[RawMessage]],
    outputs: _Outputs,
    rec: Recorded,
    *,
    step_ns: int,
    after_batch: Callable[[], None],
) -> Recorded:
    """Every recorded message in file order into the core (fusion inputs; through the
    decision record when there is one) or the collector, stepping the core each ``step_ns``
    of receive time (without a decision record); a fresh core where the live fusion
    restarted (:class:`_Fusion`); then solve what is pending."""
    routes: dict[str, tuple] = {}  # topic -> (kind, node, sequence stream, is input)
    per_topic: Counter[str] = Counter()
    seq = rec.seq
    copy = outputs.copy if outputs.copy_input else None
    live_log_ns = fusion.live_log_ns
    next_step = next_advance = None
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
                if not fusion.on_input(topic, m.data, now):
                    continue
            elif route[0] == "diagnostics":
                fusion.on_diagnostics(m)
            else:
                if route[0] == "liveliness":
                    fusion.on_liveliness(m)
                elif route[0] == "estimate":
                    live_log_ns.append(now)
                rec.take(route[0], m, fusion.core, route[1])
            if rec.decided is None and (next_step is None or now >= next_step):
                outputs.emit(fusion.core.step(now), now)
                next_step = now + step_ns
        if rec.t_last is not None and (next_advance is None or rec.t_last >= next_advance):
            rec.advance(rec.t_last)  # score what the truth covers (bounded memory)
            next_advance = rec.t_last + _ADVANCE_NS
        after_batch()
    for topic, n in per_topic.items():
        rec.counts[routes[topic][0]] += n
    if rec.decided is not None:
        rec.decided.finish()
    return rec


def _drain(core: FusionCore, outputs: _Outputs, t_last_ns: int) -> None:
    """Solve what is pending (far past every deadline), then flush like the live service at
    shutdown (after a complete decision record: nothing is pending any more)."""
    outputs.emit(core.step(t_last_ns + 10**12), t_last_ns)
    outputs.emit(core.flush(t_last_ns), t_last_ns)


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


def _report(path: str | Path, scanner: McapScanner, settings: ReplaySettings, fusion: _Fusion,
            rec: Recorded, *, step_ms: float, t_wall0: float, warm_up_s: float,
            window: tuple[float | None, float | None]) -> ReplayResult:
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
        "decisions": None if fusion.decided is None else fusion.decided.report,
        "fusion_instances": (instances := fusion.not_reproducible()),
        "recording_s": duration_s,
        "truth_s": (None if rec.truth.first_t is None
                    else (rec.truth.last_t - rec.truth.first_t) / 1e9),
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
    scanner = PartsScanner(path)  # a split recording's parts in turn
    side = side_records(path)
    ahead, rest, first_state, first_diag = read_ahead(scanner)
    settings = replay_settings(scanner, side=side, first_state=first_state, overrides=overrides,
                               method=method, use_recorded_settings=use_recorded_settings)
    if settings.warning:
        (logger or logging.getLogger("diffpos.replay")).warning("%s", settings.warning)
    with contextlib.ExitStack() as stack:
        tmp = None if out_mcap is None else stack.enter_context(atomic_path(out_mcap))
        decided = (use_decisions and first_diag is not None and start_s is None
                   and end_s is None
                   and first_diag.decisions is not None and first_diag.decisions.chunk == 0)
        rec = Recorded(FUSION_INPUT_KINDS, max_truth_gap_ns=round(max_truth_gap_s * 1e9),
                       keep_estimates=keep_estimates, window_ns=_WINDOW_NS)
        return _run(path, scanner, settings, ahead, rest, tmp, rec, side=side,
                    copy_input=copy_input, step_ms=step_ms, progress=progress, logger=logger,
                    decided=decided, use_decisions=use_decisions, window=(start_s, end_s))


def _run(path, scanner, settings, ahead, rest, tmp, rec, *, side, copy_input, step_ms,
         progress, logger, decided, use_decisions, window) -> ReplayResult:
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

    def make_core() -> FusionCore:
        return FusionCore(config, logger=quiet_logger() if logger is None else logger,
                          record_decisions=False)

    pool: list[Any] = []

    def attach(core: FusionCore) -> None:  # a fresh core shares the worker processes
        if pool and core.bank is not None:
            core.bank.pool = pool[0]

    fusion = _Fusion(make_core, outputs.emit, rec, use_decisions=use_decisions,
                     decided=decided, attach=attach)
    fusion.core.warm_up()  # the kernels loaded (or compiled) now: not counted as replay time
    # FusionConfig.workers: the same estimates for any count, so never more processes than
    # this machine has cores (a recording made on a bigger machine)
    rows = start_workers(fusion.core, max_processes=os.cpu_count() or 1)
    try:
        if rows is not None:
            pool.append(rows)
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
        _drain(fusion.core, outputs, rec.t_last or 0)
    finally:
        if rows is not None:
            rows.close()
    outputs.close(final_metadata={"replayed_estimates": outputs.count})
    return _report(path, scanner, settings, fusion, rec, step_ms=step_ms, t_wall0=t_wall0,
                   warm_up_s=t_wall0 - t_warm, window=window)
