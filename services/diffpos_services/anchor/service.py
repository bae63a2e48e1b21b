"""Anchor service: one UAV that flies its trajectory, ranges to every node and publishes.

Layers:

- :class:`AnchorEmulator` (no network): at each measurement epoch it evaluates the UAV's
  true position, takes the first-arriving path to every node (:func:`diffpos.emulation.
  first_arrivals`: the O2I channel emulator with noise at the ranging CRLB), and produces the
  messages the real UAV would send: its *own* navigation estimate (true position +
  :class:`diffpos.emulation.NavigationError`) and the ranges, all stamped with the anchor's
  clock (:func:`diffpos.emulation.clock_time_ns`: true time + constant offset + jitter). The
  measurement model is in :mod:`diffpos.emulation` (pure, seeded); this module wires it.
- :func:`run_anchor` paces the emulator on a :class:`~diffpos.emulation.TimeBase` and
  publishes over Zenoh with congestion control BLOCK (nothing dropped), declaring a
  liveliness token. Every message carries the process nonce as its attachment (two processes
  publishing under one anchor key are told apart by the fusion:
  :class:`diffpos_services.bus.integrity.PublisherGuard`), and a heartbeat thread says how
  many epochs were published (:mod:`diffpos_services.bus.heartbeat`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any, Literal

import msgspec
import numpy as np
import zenoh
from msgspec import Meta

from diffpos.emulation import (
    NavigationError,
    TimeBase,
    clock_time_ns,
    emulation_nodes,
    first_arrivals,
    warm_up_channel,
)
from diffpos.trajectory import Static
from diffpos_services.bus.heartbeat import HeartbeatThread, Progress, process_nonce
from diffpos_services.bus.session import ZenohSettings, open_session
from diffpos_services.errors import ConfigError
from diffpos_services.logs import log_event
from diffpos_services.scenario_io import load_scenario_option
from diffpos_services.shutdown import wait_event
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, check_id

__all__ = ["BATCH_MIN_NODES", "AnchorConfig", "AnchorEmulator", "run_anchor"]


# ----------------------------------------------------------------------------- config
#: Above this many nodes an anchor publishes its ranges as one RangeBatch per epoch unless
#: told otherwise (``range_batch``): measured, a per-range message costs the fusion ~11 us
#: more CPU than the same range in a batch (16 anchors x 200 nodes: ingest 48 vs 13 ms per
#: epoch), so 8 anchors x 50 nodes x 10 Hz per range is ~45 ms of CPU per second. Small
#: deployments keep one message per node (their keys name the node: easy to inspect).
BATCH_MIN_NODES = 8

class AnchorConfig(msgspec.Struct, kw_only=True, frozen=True):
    """Typed, validated configuration of one anchor process."""

    site: str = "demo"
    anchor_id: str = "uav1"
    scenario: str | None = None
    rate_hz: Annotated[float, Meta(gt=0, le=1000)] = 10.0
    seed: Annotated[int, Meta(ge=0)] = 0
    phase: Annotated[float, Meta(ge=0, lt=1)] | None = None
    gnss_sigma_h_m: Annotated[float, Meta(ge=0)] = 0.02
    gnss_sigma_v_m: Annotated[float, Meta(ge=0)] = 0.03
    gnss_bias_fraction: Annotated[float, Meta(ge=0, le=1)] = 0.5
    gnss_tau_s: Annotated[float, Meta(gt=0)] = 30.0
    velocity_sigma_m_s: Annotated[float, Meta(ge=0)] = 0.05
    clock_offset_ns: int = 0
    clock_jitter_ns: Annotated[int, Meta(ge=0)] = 20_000
    max_nodes: Annotated[int, Meta(ge=0)] = 0
    wait_start: bool = False
    channel: Literal["emulator", "ideal", "raytrace"] = "emulator"
    #: ``raytrace``: the run's length the links are traced for [s] and the trace settings
    #: (``None``: the defaults of :mod:`diffpos_services.raytrace.live`)
    raytrace_duration_s: Annotated[float, Meta(gt=0)] = 20.0
    raytrace_samples: Annotated[int, Meta(ge=1)] | None = None
    raytrace_depth: Annotated[int, Meta(ge=1)] | None = None
    raytrace_step_s: Annotated[float, Meta(gt=0)] | None = None
    #: one RangeBatch per epoch instead of one message per node; None: when the anchor
    #: ranges more than :data:`BATCH_MIN_NODES` nodes
    range_batch: bool | None = None
    ideal_snr_db: float = 20.0

    def check(self) -> None:
        check_id(self.site, field="site")
        check_id(self.anchor_id, field="anchor_id")
        if self.channel == "raytrace" and not self.wait_start:
            raise ConfigError("--channel raytrace serves the epochs of a run traced from its "
                              "start: use --wait-start (diffpos emulate starts the run)")


# ----------------------------------------------------------------------------- emulator
class AnchorEmulator:
    """Measurements of one anchor (no network).

    Parameters
    ----------
    scenario : diffpos.scenario.Scenario
    config : AnchorConfig
    nodes : list of (str, Trajectory), optional
        Default :func:`~diffpos.emulation.emulation_nodes`.
    traced : diffpos.channel.traced.TracedLinks, optional
        ``channel == "raytrace"`` (required then): this anchor's traced paths to ``nodes``
        (``diffpos anchor`` loads them: :func:`diffpos_services.raytrace.live.anchor_links`).
    """

    def __init__(self, scenario, config: AnchorConfig, nodes: list | None = None, *,
                 traced=None) -> None:
        ids = [a.id for a in scenario.anchors]
        if config.anchor_id not in ids:
            raise ConfigError(
                f"anchor_id={config.anchor_id!r} is not in the scenario (anchors: {', '.join(ids)})"
            )
        self.scenario = scenario
        self.config = config
        self.traj = scenario.anchors[ids.index(config.anchor_id)].trajectory
        self.nodes = (
            nodes
            if nodes is not None
            else emulation_nodes(scenario, max_nodes=config.max_nodes)
        )
        if not self.nodes:
            raise ConfigError(f"scenario {scenario.name!r} has no nodes to range to")
        self.batched = (len(self.nodes) > BATCH_MIN_NODES if config.range_batch is None
                        else bool(config.range_batch))
        self._static_m = np.array([tr.position if isinstance(tr, Static) else (np.nan,) * 3
                                   for _, tr in self.nodes], float).reshape(-1, 3)
        self._moving = [i for i, (_, tr) in enumerate(self.nodes) if not isinstance(tr, Static)]
        # independent streams per anchor and purpose, reproducible from (seed, anchor index)
        idx = ids.index(config.anchor_id)
        ss = np.random.SeedSequence([config.seed, idx])
        s_phase, s_nav, s_rng, s_clk = ss.spawn(4)
        self.rng_range = np.random.default_rng(s_rng)
        self.rng_clock = np.random.default_rng(s_clk)
        self.period_ns = round(1e9 / config.rate_hz)
        ph = (
            config.phase
            if config.phase is not None
            else float(np.random.default_rng(s_phase).uniform(0.05, 0.95))
        )
        self.phase_ns = round(ph * self.period_ns)
        self.nav = NavigationError(
            sigma_h_m=config.gnss_sigma_h_m, sigma_v_m=config.gnss_sigma_v_m,
            bias_fraction=config.gnss_bias_fraction, tau_s=config.gnss_tau_s,
            velocity_sigma_m_s=config.velocity_sigma_m_s, rng=np.random.default_rng(s_nav))
        self.seq = 0
        if config.channel == "raytrace" and traced is None:
            raise ConfigError("--channel raytrace: the anchor needs its traced paths "
                              "(diffpos anchor loads them from the ray tracer's cache)")
        self.traced = traced
        self._warm_up()

    def _warm_up(self) -> None:
        """Exercise the channel code once (no random draws), so the first real epoch is not
        late by the first-call costs."""
        t_s = np.zeros(1)
        p = np.asarray(self.traj.position_m(t_s), float).reshape(1, 3)
        n = np.asarray(self.nodes[0][1].position_m(t_s), float).reshape(1, 3)
        warm_up_channel(p, n, self.scenario, channel=self.config.channel)

    def true_time_ns(self, k: int, tb: TimeBase) -> int:
        """True (emulated) time of measurement ``k`` [ns]."""
        return tb.t0_ns + self.phase_ns + k * self.period_ns

    def block_size(self) -> int:
        """Epochs emulated per channel call (1: the compiled per-pair detector costs ~0.5 ms
        CPU per epoch of 50 nodes, so batching epochs saves little and would delay ranges)."""
        return 1

    def _first_arrivals(self, t_s: np.ndarray):
        """Range, sigma, snr, detected for each epoch time: arrays (B, N)."""
        b = t_s.size
        p_true = np.asarray(self.traj.position_m(t_s), float).reshape(b, 3)
        nodes_m = np.repeat(self._static_m[None], b, axis=0)  # (B, N, 3)
        for i in self._moving:  # (static nodes: their fixed position, not one call each)
            nodes_m[:, i] = np.asarray(self.nodes[i][1].position_m(t_s), float).reshape(b, 3)
        return first_arrivals(p_true, nodes_m, self.scenario, channel=self.config.channel,
                              ideal_snr_db=self.config.ideal_snr_db, rng=self.rng_range,
                              traced=self.traced, t_s=t_s)

    def measure_block(self, k0: int, count: int, tb: TimeBase):
        """True-time channel results of epochs ``k0 .. k0 + count - 1`` (no messages yet)."""
        t_true = np.array([self.true_time_ns(k, tb) for k in range(k0, k0 + count)], np.int64)
        return t_true, self._first_arrivals(tb.t_s(t_true).astype(float))

    def messages(self, t_true_ns: int, tb: TimeBase, fa_row, *, wall_ns: int | None = None):
        """State and ranges of one epoch from its channel results ``(r, sigma, snr, det)``
        rows, stamped with the anchor clock and the publish wall time."""
        cfg = self.config
        t_s = float(tb.t_s(t_true_ns))
        p_true = np.asarray(self.traj.position_m(t_s), float)
        v_true = np.asarray(self.traj.velocity_m_s(t_s), float)
        t_clock = clock_time_ns(t_true_ns, offset_ns=cfg.clock_offset_ns,
                                jitter_ns=cfg.clock_jitter_ns, rng=self.rng_clock)
        wall = time.time_ns() if wall_ns is None else wall_ns
        p_rep = p_true + self.nav.position(t_s)
        v_rep = v_true + self.nav.velocity()
        self.seq += 1
        state = M.AnchorState(
            anchor_id=cfg.anchor_id,
            t_ns=t_clock,
            seq=self.seq,
            position_m=M.vec3(p_rep),
            velocity_m_s=M.vec3(v_rep),
            position_sigma_m=M.vec3(self.nav.sigma_m),
            velocity_sigma_m_s=cfg.velocity_sigma_m_s,
            range_rate_hz=cfg.rate_hz,
            t_pub_wall_ns=wall,
        )
        return state, self._ranges(t_clock, wall, fa_row)

    def _ranges(self, t_clock: int, wall: int, fa_row) -> list[tuple[str, M.RangeMeasurement]]:
        """``(node_id, RangeMeasurement)`` of one epoch (null range when not detected)."""
        cfg = self.config
        r, sg, snr, det = fa_row
        det = det & np.isfinite(r) & np.isfinite(sg) & (sg > 0)
        ranges = []
        for i, (nid, _) in enumerate(self.nodes):
            self.seq += 1
            ok = bool(det[i])
            ranges.append(
                (
                    nid,
                    M.RangeMeasurement(
                        anchor_id=cfg.anchor_id,
                        node_id=nid,
                        t_ns=t_clock,
                        seq=self.seq,
                        range_m=max(float(r[i]), 0.0) if ok else None,
                        sigma_m=float(sg[i]) if ok else None,
                        snr_db=float(snr[i]) if ok else None,
                        t_pub_wall_ns=wall,
                    ),
                )
            )
        return ranges

    def measure(self, t_true_ns: int, tb: TimeBase, *, wall_ns: int | None = None):
        """State and ranges at true time ``t_true_ns`` (one epoch, unbatched)."""
        t = np.array([t_true_ns], np.int64)
        r, sg, snr, det = self._first_arrivals(tb.t_s(t).astype(float))
        return self.messages(t_true_ns, tb, (r[0], sg[0], snr[0], det[0]), wall_ns=wall_ns)


# ----------------------------------------------------------------------------- process
class _RunSignals:
    """The run's control messages as they arrive on Zenoh's threads: the first
    ``RunControl`` (time base, lockstep) and, in lockstep runs, the emulated time released
    by ``RunClock`` messages."""

    def __init__(self, log: logging.Logger) -> None:
        self.log = log
        self.got_control = threading.Event()
        self.control: list[M.RunControl] = []
        self.clock_cv = threading.Condition()
        self.allowed_t = -(2**62)
        self._dec = M.decoder(M.RunControl)
        self._dec_clock = M.decoder(M.RunClock)

    def on_control(self, sample: zenoh.Sample) -> None:
        if self.got_control.is_set():
            return
        try:
            self.control.append(self._dec(sample.payload.to_bytes()))
            self.got_control.set()
        except M.DecodeError as exc:
            log_event(self.log, logging.WARNING, "bad run control ignored", detail=str(exc)[:200])

    def on_clock(self, sample: zenoh.Sample) -> None:
        try:
            rc = self._dec_clock(sample.payload.to_bytes())
        except M.DecodeError as exc:
            log_event(self.log, logging.WARNING, "bad run clock ignored", detail=str(exc)[:200])
            return
        with self.clock_cv:
            # (a clock overtaking the run control is kept: same orchestrator, same run)
            if (not self.control or rc.run_id == self.control[0].run_id) \
                    and rc.t_ns > self.allowed_t:
                self.allowed_t = rc.t_ns
                self.clock_cv.notify_all()

    def wait_clock(self, t_ns: int, stop: threading.Event) -> None:
        """Block until emulated time ``t_ns`` is released (or ``stop``)."""
        with self.clock_cv:
            while self.allowed_t < t_ns and not stop.is_set():
                self.clock_cv.wait(0.2)


@dataclass
class _Outputs:
    """What the anchor declared on its session."""

    subs: list[Any]
    state_pub: Any
    batch_pub: Any
    range_pubs: dict[str, Any]
    token: Any
    nonce: bytes = b""
    sent: int = 0

    def publish(self, emu: AnchorEmulator, state: M.AnchorState,
                ranges: list[tuple[str, M.RangeMeasurement]]) -> None:
        """The epoch's state, then its ranges (one batch, or one message per node), each
        with the process nonce attached."""
        att = self.nonce
        self.state_pub.put(M.encode(state), attachment=att)
        if self.batch_pub is not None:
            # one sequence per anchor over states and batches: state n, batch n + 1
            emu.seq = state.seq + 1
            self.batch_pub.put(M.encode(M.RangeBatch(
                anchor_id=emu.config.anchor_id, t_ns=state.t_ns, seq=emu.seq,
                node_ids=[nid for nid, _ in ranges],
                range_m=[m.range_m for _, m in ranges],
                sigma_m=[m.sigma_m for _, m in ranges],
                snr_db=[m.snr_db for _, m in ranges],
                t_pub_wall_ns=state.t_pub_wall_ns)), attachment=att)
            self.sent += 2
        else:
            for nid, msg in ranges:
                self.range_pubs[nid].put(M.encode(msg), attachment=att)
            self.sent += 1 + len(ranges)

    def undeclare(self) -> None:
        self.token.undeclare()
        for s in self.subs:
            s.undeclare()


def _declare(session: Any, keys: Keys, config: AnchorConfig, emu: AnchorEmulator,
             signals: _RunSignals) -> _Outputs:
    bc = zenoh.CongestionControl.BLOCK
    enc = zenoh.Encoding.APPLICATION_JSON
    subs = [session.declare_subscriber(keys.run_control(), signals.on_control),
            session.declare_subscriber(keys.run_clock(), signals.on_clock)]
    state_pub = session.declare_publisher(
        keys.anchor_state(config.anchor_id), encoding=enc, congestion_control=bc
    )
    batch_pub = None
    range_pubs = {}
    if emu.batched:
        batch_pub = session.declare_publisher(
            keys.anchor_range_batch(config.anchor_id), encoding=enc, congestion_control=bc
        )
    else:
        range_pubs = {
            nid: session.declare_publisher(
                keys.anchor_range(config.anchor_id, nid), encoding=enc, congestion_control=bc
            )
            for nid, _ in emu.nodes
        }
    token = session.liveliness().declare_token(keys.alive_anchor(config.anchor_id))
    return _Outputs(subs, state_pub, batch_pub, range_pubs, token,
                    bytes.fromhex(process_nonce()))


def _time_base(config: AnchorConfig, timebase: TimeBase | None, signals: _RunSignals,
               stop: threading.Event, log: logging.Logger) -> TimeBase | None:
    """The given time base, the run control's (``wait_start``; None if stopped first), or
    free-running real time."""
    if timebase is not None:
        return timebase
    if not config.wait_start:
        return TimeBase.free_running(time.time_ns())
    while not signals.got_control.wait(0.2):
        if stop.is_set():
            return None
    rc = signals.control[0]
    tb = TimeBase.from_control(rc)
    log_event(log, logging.INFO, "run started", run_id=rc.run_id, speed=tb.speed,
              duration_s=tb.duration_ns * 1e-9)
    return tb


@dataclass
class _Flight:
    """One anchor's run: the emulator paced on a time base, publishing every epoch."""

    emu: AnchorEmulator
    tb: TimeBase
    lockstep: bool
    out: _Outputs
    signals: _RunSignals
    stop: threading.Event
    log: logging.Logger
    on_epoch: Callable[[int], None] | None
    epochs: int = 0
    late: int = 0
    last_k: int | None = None

    def first_epoch(self) -> int:
        """The first epoch not in the past (lockstep: the first epoch of the run)."""
        if self.lockstep:
            return 0
        emu, tb = self.emu, self.tb
        return max(0, -(-(tb.now_ns(time.time_ns()) - tb.t0_ns - emu.phase_ns) // emu.period_ns))

    def wait_for(self, t_true: int) -> bool:
        """Wait until epoch time ``t_true`` is due; False if stopped meanwhile."""
        if self.lockstep:
            self.signals.wait_clock(t_true, self.stop)
            return not self.stop.is_set()
        wait_s = (self.tb.wall_of(t_true) - time.time_ns()) * 1e-9
        if wait_s > 0 and self.stop.wait(wait_s):  # pacing timer, not synchronisation
            return False
        if wait_s < -0.5 / self.emu.config.rate_hz:
            self.late += 1
        return True

    def fly(self) -> None:
        """Measure and publish epoch after epoch until stopped or the run is over."""
        emu, tb = self.emu, self.tb
        k = self.first_epoch()
        block: dict[int, tuple] = {}
        while not self.stop.is_set():
            t_true = emu.true_time_ns(k, tb)
            if tb.duration_ns and t_true - tb.t0_ns >= tb.duration_ns:
                # run over: stay declared (idle) until told to stop, so the end of a run
                # does not look like a lost anchor
                log_event(self.log, logging.INFO, "run complete", anchor=emu.config.anchor_id,
                          epochs=self.epochs)
                wait_event(self.stop)  # in slices: a signal must reach its handler
                break
            if not self.wait_for(t_true):
                break
            if k not in block:
                ts_, (rr, ss, nn, dd) = emu.measure_block(k, emu.block_size(), tb)
                block = {int(k + i): (rr[i], ss[i], nn[i], dd[i]) for i in range(ts_.size)}
            state, ranges = emu.messages(t_true, tb, block.pop(k))
            self.out.publish(emu, state, ranges)
            self.epochs += 1
            self.last_k = k
            if self.on_epoch is not None:
                self.on_epoch(k)
            k += 1


def run_anchor(
    config: AnchorConfig,
    zenoh_config: Any,
    stop: threading.Event,
    *,
    scenario=None,
    logger: logging.Logger | None = None,
    timebase: TimeBase | None = None,
    on_epoch: Callable[[int], None] | None = None,
    traced=None,
) -> int:
    """Fly and publish until ``stop`` is set or the run's duration is over.

    With ``config.wait_start`` the time base comes from the first ``RunControl`` message on
    ``diffpos/<site>/run/control``; otherwise real time (:meth:`TimeBase.free_running`).
    Returns the number of epochs published. ``traced``: the ``raytrace`` channel's paths
    (:class:`AnchorEmulator`).
    """
    log = logger or logging.getLogger("diffpos.anchor")
    scenario = scenario if scenario is not None else load_scenario_option(config.scenario)
    emu = AnchorEmulator(scenario, config, traced=traced)
    keys = Keys(config.site)
    signals = _RunSignals(log)
    session = open_session(zenoh_config, stop, logger=log) if isinstance(
        zenoh_config, ZenohSettings) else zenoh.open(zenoh_config)
    if session is None:
        return 0
    flight = None
    with session:
        out = _declare(session, keys, config, emu, signals)

        def progress() -> Progress:
            f = flight
            return Progress(progress=f.epochs if f else 0, last_epoch=f.last_k if f else None,
                            published=out.sent)

        beat = HeartbeatThread(session, keys.heartbeat("anchor", config.anchor_id), "anchor",
                               progress, anchor_id=config.anchor_id, logger=log).start()
        log_event(log, logging.INFO, "anchor ready", anchor=config.anchor_id,
                  nodes=len(emu.nodes), rate_hz=config.rate_hz, phase_ns=emu.phase_ns,
                  wait_start=config.wait_start, range_batch=emu.batched)
        try:
            tb = _time_base(config, timebase, signals, stop, log)
            if tb is None:
                return 0
            lockstep = bool(signals.control and signals.control[0].lockstep and timebase is None)
            flight = _Flight(emu, tb, lockstep, out, signals, stop, log, on_epoch)
            flight.fly()
        finally:
            beat.stop()
            out.undeclare()
            log_event(log, logging.INFO, "anchor stopped", anchor=config.anchor_id,
                      epochs=flight.epochs if flight else 0,
                      late_epochs=flight.late if flight else 0)
    return flight.epochs
