"""Anchor service: one UAV that flies its trajectory, ranges to every node and publishes.

Layers:

- :class:`AnchorEmulator` (no network): at each measurement epoch it evaluates the UAV's
  true position, runs the O2I channel emulator (``diffpos.channel``) to every node, takes
  the first-arriving path with noise at the ranging CRLB, and produces the messages the
  real UAV would send: its *own* navigation estimate (true position + GNSS/barometer error:
  a slowly varying Gauss-Markov bias plus white noise) and the ranges, all stamped with the
  anchor's clock (true time + constant offset + jitter).
- :func:`run_anchor` paces the emulator on a :class:`TimeBase` and publishes over Zenoh
  with congestion control BLOCK (nothing dropped), declaring a liveliness token.

Emulated time: ``t = t0_ns + speed * (wall - wall_t0_ns)``; trajectories are evaluated at
``(t - t0_ns) / 1e9`` seconds since the start of the run.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
import numpy as np
from msgspec import Meta

from diffpos_services.bus.session import ZenohSettings, open_session
from diffpos_services.kit import ConfigError, log_event
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, check_id

__all__ = [
    "AnchorConfig",
    "AnchorEmulator",
    "TimeBase",
    "emulation_nodes",
    "load_scenario_file",
    "run_anchor",
]


# ----------------------------------------------------------------------------- scenario
def load_scenario_file(path: str | Path | None):
    """The scenario of a TOML file (``None``: the built-in paper scenario).

    Raises :class:`ConfigError` naming the file and the bad field.
    """
    from diffpos.scenario import ScenarioError, default_scenario

    if path is None:
        return default_scenario()
    from diffpos_services.scenario_io import load_scenario

    try:
        return load_scenario(path)
    except FileNotFoundError:
        raise ConfigError(f"scenario file {str(path)!r} not found") from None
    except ScenarioError as exc:
        msg = str(exc)
        raise ConfigError(msg if str(path) in msg else f"scenario {path}: {msg}") from None
    except ValueError as exc:  # tomllib.TOMLDecodeError is a ValueError
        raise ConfigError(f"scenario {path}: {exc}") from None


def responders(building, *, count: int = 6, seed: int = 0, speed_m_s: float = 1.2) -> list[tuple[str, Any]]:
    """A handful of responders walking inside ``building`` and taking the stairs.

    Responder ``i`` starts on floor ``i mod n_floors``, walks along the facade at a fixed depth,
    climbs (or descends) one floor on a 6 m stair run near a side wall and walks back, in a
    loop, at ``speed_m_s``. On the level parts it is at the window's mid-height (the paper's
    Assumption 1); on the stairs it is not (a realistic model mismatch). Ids ``r01``...
    """
    from diffpos.trajectory import trajectory_from_dict

    rng = np.random.default_rng(seed)
    b = building
    x_lo, x_hi = b.edge_x_m
    h = b.nominal_node_height_m
    out = []
    for i in range(count):
        f0 = i % b.n_floors
        f1 = f0 + 1 if f0 + 1 < b.n_floors else f0 - 1
        z0 = float(b.floor_z_m(f0)) + h
        z1 = float(b.floor_z_m(f1)) + h
        y = float(rng.uniform(1.5, min(b.depth_m - 1.0, 10.0)))
        xa = float(rng.uniform(x_lo + 8.0, x_hi - 12.0))
        xs = x_hi - 4.0  # stairs start
        pts = [[xa, y, z0], [xs, y, z0], [xs, y + 2.0, z0], [xs - 6.0, y + 2.0, z1],
               [xa, y + 2.0, z1]]
        traj = trajectory_from_dict({"kind": "waypoints", "points_m": pts,
                                     "speed_m_s": speed_m_s, "loop": True})
        out.append((f"r{i + 1:02d}", traj))
    return out


def emulation_nodes(scenario, *, max_nodes: int = 0) -> list[tuple[str, Any]]:
    """``[(node_id, trajectory)]`` to emulate (a function of the scenario only, so every
    process of a run agrees on it).

    The scenario's explicit nodes; if it only has a study grid (the paper's scenario), six
    :func:`responders` (layout seed 0) moving between floors. ``max_nodes > 0`` caps the list.
    """
    nodes = [(n.id, n.trajectory) for n in scenario.nodes]
    if not nodes:
        nodes = responders(scenario.building, count=6, seed=0)
    if max_nodes > 0:
        nodes = nodes[:max_nodes]
    return nodes


# ----------------------------------------------------------------------------- time base
@dataclass(frozen=True)
class TimeBase:
    """Mapping between wall clock and emulated time.

    Attributes
    ----------
    t0_ns : int [ns]
        Emulated time at the start of the run (trajectories' ``t_s = 0``).
    wall_t0_ns : int [ns]
        ``time.time_ns()`` at which emulated time is ``t0_ns``.
    speed : float [-]
        Emulated seconds per wall second.
    duration_ns : int [ns]
        Run length in emulated time, 0 = unlimited.
    """

    t0_ns: int
    wall_t0_ns: int
    speed: float = 1.0
    duration_ns: int = 0

    def wall_of(self, t_ns: int) -> int:
        return self.wall_t0_ns + round((t_ns - self.t0_ns) / self.speed)

    def now_ns(self, wall_ns: int | None = None) -> int:
        w = time.time_ns() if wall_ns is None else wall_ns
        return self.t0_ns + round((w - self.wall_t0_ns) * self.speed)

    def t_s(self, t_ns: int | np.ndarray) -> Any:
        return (np.asarray(t_ns) - self.t0_ns) * 1e-9

    @classmethod
    def from_control(cls, rc: M.RunControl) -> TimeBase:
        return cls(rc.t0_ns, rc.wall_t0_ns, rc.speed, rc.duration_ns)

    @classmethod
    def free_running(cls) -> TimeBase:
        """Real time, origin at the start of the current UTC hour (shared by every process
        started within the hour without any coordination)."""
        now = time.time_ns()
        hour = 3600 * 10**9
        t0 = now - now % hour
        return cls(t0, t0, 1.0, 0)


# ----------------------------------------------------------------------------- config
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
    channel: Literal["emulator", "ideal"] = "emulator"
    range_batch: bool = False
    ideal_snr_db: float = 20.0

    def check(self) -> None:
        check_id(self.site, field="site")
        check_id(self.anchor_id, field="anchor_id")


# ----------------------------------------------------------------------------- emulator
class AnchorEmulator:
    """Measurements of one anchor (no network).

    Parameters
    ----------
    scenario : diffpos.scenario.Scenario
    config : AnchorConfig
    nodes : list of (str, Trajectory), optional
        Default :func:`emulation_nodes`.
    """

    def __init__(self, scenario, config: AnchorConfig, nodes: list | None = None) -> None:
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
        # independent streams per anchor and purpose, reproducible from (seed, anchor index)
        idx = ids.index(config.anchor_id)
        ss = np.random.SeedSequence([config.seed, idx])
        s_phase, s_nav, s_rng, s_clk = ss.spawn(4)
        self.rng_nav = np.random.default_rng(s_nav)
        self.rng_range = np.random.default_rng(s_rng)
        self.rng_clock = np.random.default_rng(s_clk)
        self.period_ns = round(1e9 / config.rate_hz)
        ph = (
            config.phase
            if config.phase is not None
            else float(np.random.default_rng(s_phase).uniform(0.05, 0.95))
        )
        self.phase_ns = round(ph * self.period_ns)
        self.sigma_nav = np.array(
            [config.gnss_sigma_h_m, config.gnss_sigma_h_m, config.gnss_sigma_v_m]
        )
        self.bias = (
            self.rng_nav.normal(0, 1, 3) * self.sigma_nav * np.sqrt(config.gnss_bias_fraction)
        )
        self.last_bias_t_s: float | None = None
        self.seq = 0
        self._warm_up()

    def _warm_up(self) -> None:
        """Import and exercise the channel code once (no random draws), so the first real
        epoch is not late by the import time."""
        t_s = np.zeros(1)
        p = np.asarray(self.traj.position_m(t_s), float).reshape(1, 3)
        n = np.asarray(self.nodes[0][1].position_m(t_s), float).reshape(1, 3)
        if self.config.channel == "ideal":
            from diffpos.geometry import window_edge_path

            window_edge_path(p, n, window_height_m=self.scenario.building.window_height_m)
        else:
            from diffpos.channel import emulate_channel, first_arrival

            ch = emulate_channel(p, n, building=self.scenario.building, radio=self.scenario.radio)
            first_arrival(ch, radio=self.scenario.radio, rng=None)

    def true_time_ns(self, k: int, tb: TimeBase) -> int:
        """True (emulated) time of measurement ``k`` [ns]."""
        return tb.t0_ns + self.phase_ns + k * self.period_ns

    def _nav_error(self, t_s: float) -> np.ndarray:
        cfg = self.config
        fb = cfg.gnss_bias_fraction
        if self.last_bias_t_s is not None:
            a = np.exp(-max(t_s - self.last_bias_t_s, 0.0) / cfg.gnss_tau_s)
            self.bias = a * self.bias + np.sqrt(1 - a * a) * np.sqrt(
                fb
            ) * self.sigma_nav * self.rng_nav.normal(0, 1, 3)
        self.last_bias_t_s = t_s
        white = self.rng_nav.normal(0, 1, 3) * self.sigma_nav * np.sqrt(1 - fb)
        return self.bias + white

    def block_size(self) -> int:
        """Epochs emulated per channel call (1: measured on this machine, batching epochs
        into one call did not pay off because the emulator's cost grows with B^2 N pairs)."""
        return 1

    def _first_arrivals(self, t_s: np.ndarray):
        """Range, sigma, snr, detected for each epoch time: arrays (B, N)."""
        from diffpos.linkbudget import db_to_linear, ranging_crlb_m

        b = t_s.size
        n = len(self.nodes)
        p_true = np.asarray(self.traj.position_m(t_s), float).reshape(b, 3)
        nodes_m = np.stack(
            [np.asarray(tr.position_m(t_s), float).reshape(b, 3) for _, tr in self.nodes], axis=1
        )  # (B, N, 3)
        if self.config.channel == "ideal":
            from diffpos.geometry import window_edge_path

            w = self.scenario.building.window_height_m
            path = window_edge_path(
                p_true[:, None, :],
                nodes_m,
                window_height_m=w,
                edge_x_m=self.scenario.building.edge_x_m,
            ).length_m
            snr = np.full((b, n), self.config.ideal_snr_db)
            sg = ranging_crlb_m(db_to_linear(snr), self.scenario.radio.bandwidth_hz)
            r = path + sg * self.rng_range.standard_normal((b, n))
            return r, sg, snr, np.ones((b, n), bool)
        import dataclasses

        from diffpos.channel import emulate_channel, first_arrival

        ch = emulate_channel(
            p_true,
            nodes_m.reshape(b * n, 3),
            building=self.scenario.building,
            radio=self.scenario.radio,
        )
        if b > 1:  # keep the (epoch e, node i) x anchor-at-epoch-e pairs only
            rows = np.arange(b * n)
            cols = np.repeat(np.arange(b), n)
            fields = {}
            for f in dataclasses.fields(ch):
                v = getattr(ch, f.name)
                if isinstance(v, np.ndarray) and v.ndim == 3 and v.shape[:2] == (b * n, b):
                    fields[f.name] = v[rows, cols][:, None, :]
            fields["anchors_m"] = p_true[:1]
            ch = dataclasses.replace(ch, **fields)
        fa = first_arrival(ch, radio=self.scenario.radio, rng=self.rng_range)
        r = fa.range_m[:, 0].reshape(b, n)
        sg = fa.sigma_m[:, 0].reshape(b, n)
        snr = fa.snr_db[:, 0].reshape(b, n)
        det = fa.detected[:, 0].reshape(b, n)
        return r, sg, snr, det

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
        jitter = int(self.rng_clock.normal(0, cfg.clock_jitter_ns)) if cfg.clock_jitter_ns else 0
        t_clock = int(t_true_ns + cfg.clock_offset_ns + jitter)
        wall = time.time_ns() if wall_ns is None else wall_ns
        p_rep = p_true + self._nav_error(t_s)
        v_rep = v_true + self.rng_nav.normal(0, cfg.velocity_sigma_m_s, 3)
        self.seq += 1
        state = M.AnchorState(
            anchor_id=cfg.anchor_id,
            t_ns=t_clock,
            seq=self.seq,
            position_m=M.vec3(p_rep),
            velocity_m_s=M.vec3(v_rep),
            position_sigma_m=M.vec3(self.sigma_nav),
            velocity_sigma_m_s=cfg.velocity_sigma_m_s,
            range_rate_hz=cfg.rate_hz,
            t_pub_wall_ns=wall,
        )
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
        return state, ranges

    def measure(self, t_true_ns: int, tb: TimeBase, *, wall_ns: int | None = None):
        """State and ranges at true time ``t_true_ns`` (one epoch, unbatched)."""
        t = np.array([t_true_ns], np.int64)
        r, sg, snr, det = self._first_arrivals(tb.t_s(t).astype(float))
        return self.messages(t_true_ns, tb, (r[0], sg[0], snr[0], det[0]), wall_ns=wall_ns)


# ----------------------------------------------------------------------------- process
def run_anchor(
    config: AnchorConfig,
    zenoh_config: Any,
    stop: threading.Event,
    *,
    scenario=None,
    logger: logging.Logger | None = None,
    timebase: TimeBase | None = None,
    on_epoch: Callable[[int], None] | None = None,
) -> int:
    """Fly and publish until ``stop`` is set or the run's duration is over.

    With ``config.wait_start`` the time base comes from the first ``RunControl`` message on
    ``diffpos/<site>/run/control``; otherwise real time (:meth:`TimeBase.free_running`).
    Returns the number of epochs published.
    """
    import zenoh

    log = logger or logging.getLogger("diffpos.anchor")
    scenario = scenario if scenario is not None else load_scenario_file(config.scenario)
    emu = AnchorEmulator(scenario, config)
    keys = Keys(config.site)
    got_control = threading.Event()
    control: list[M.RunControl] = []
    dec = M.decoder(M.RunControl)

    def on_control(sample: zenoh.Sample) -> None:
        if got_control.is_set():
            return
        try:
            control.append(dec(sample.payload.to_bytes()))
            got_control.set()
        except M.DecodeError as exc:
            log_event(log, logging.WARNING, "bad run control ignored", detail=str(exc)[:200])

    # lockstep runs: emulated time is released by RunClock messages
    clock_cv = threading.Condition()
    allowed_t = [-(2**62)]
    dec_clock = M.decoder(M.RunClock)

    def on_clock(sample: zenoh.Sample) -> None:
        try:
            rc = dec_clock(sample.payload.to_bytes())
        except M.DecodeError as exc:
            log_event(log, logging.WARNING, "bad run clock ignored", detail=str(exc)[:200])
            return
        with clock_cv:
            # (a clock overtaking the run control is kept: same orchestrator, same run)
            if (not control or rc.run_id == control[0].run_id) and rc.t_ns > allowed_t[0]:
                allowed_t[0] = rc.t_ns
                clock_cv.notify_all()

    epochs = 0
    bc = zenoh.CongestionControl.BLOCK
    enc = zenoh.Encoding.APPLICATION_JSON
    session = open_session(zenoh_config, stop, logger=log) if isinstance(
        zenoh_config, ZenohSettings) else zenoh.open(zenoh_config)
    if session is None:
        return 0
    with session:
        ctl_sub = session.declare_subscriber(keys.run_control(), on_control)
        clock_sub = session.declare_subscriber(keys.run_clock(), on_clock)
        state_pub = session.declare_publisher(
            keys.anchor_state(config.anchor_id), encoding=enc, congestion_control=bc
        )
        batch_pub = None
        range_pubs = {}
        if config.range_batch:
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
        log_event(
            log,
            logging.INFO,
            "anchor ready",
            anchor=config.anchor_id,
            nodes=len(emu.nodes),
            rate_hz=config.rate_hz,
            phase_ns=emu.phase_ns,
            wait_start=config.wait_start,
        )
        try:
            if timebase is not None:
                tb = timebase
            elif config.wait_start:
                while not got_control.wait(0.2):
                    if stop.is_set():
                        return 0
                tb = TimeBase.from_control(control[0])
                log_event(
                    log,
                    logging.INFO,
                    "run started",
                    run_id=control[0].run_id,
                    speed=tb.speed,
                    duration_s=tb.duration_ns * 1e-9,
                )
            else:
                tb = TimeBase.free_running()
            lockstep = bool(control and control[0].lockstep and timebase is None)
            # first epoch not in the past (lockstep: the first epoch of the run)
            k = 0 if lockstep else max(
                0, -(-(tb.now_ns() - tb.t0_ns - emu.phase_ns) // emu.period_ns))
            late = 0
            block: dict[int, tuple] = {}
            while not stop.is_set():
                t_true = emu.true_time_ns(k, tb)
                if tb.duration_ns and t_true - tb.t0_ns >= tb.duration_ns:
                    # run over: stay declared (idle) until told to stop, so the end of a
                    # run does not look like a lost anchor
                    log_event(log, logging.INFO, "run complete", anchor=config.anchor_id,
                              epochs=epochs)
                    stop.wait()
                    break
                if lockstep:
                    with clock_cv:
                        while allowed_t[0] < t_true and not stop.is_set():
                            clock_cv.wait(0.2)
                    if stop.is_set():
                        break
                else:
                    wait_s = (tb.wall_of(t_true) - time.time_ns()) * 1e-9
                    if wait_s > 0 and stop.wait(wait_s):  # pacing timer, not synchronisation
                        break
                    if wait_s < -0.5 / config.rate_hz:
                        late += 1
                if k not in block:
                    ts_, (rr, ss, nn, dd) = emu.measure_block(k, emu.block_size(), tb)
                    block = {int(k + i): (rr[i], ss[i], nn[i], dd[i]) for i in range(ts_.size)}
                state, ranges = emu.messages(t_true, tb, block.pop(k))
                state_pub.put(M.encode(state))
                if batch_pub is not None:
                    # one sequence per anchor over states and batches: state n, batch n + 1
                    emu.seq = state.seq + 1
                    batch_pub.put(M.encode(M.RangeBatch(
                        anchor_id=config.anchor_id, t_ns=state.t_ns, seq=emu.seq,
                        node_ids=[nid for nid, _ in ranges],
                        range_m=[m.range_m for _, m in ranges],
                        sigma_m=[m.sigma_m for _, m in ranges],
                        snr_db=[m.snr_db for _, m in ranges],
                        t_pub_wall_ns=state.t_pub_wall_ns)))
                else:
                    for nid, msg in ranges:
                        range_pubs[nid].put(M.encode(msg))
                epochs += 1
                if on_epoch is not None:
                    on_epoch(k)
                k += 1
        finally:
            token.undeclare()
            ctl_sub.undeclare()
            clock_sub.undeclare()
            log_event(
                log,
                logging.INFO,
                "anchor stopped",
                anchor=config.anchor_id,
                epochs=epochs,
                late_epochs=locals().get("late", 0),
            )
    return epochs
