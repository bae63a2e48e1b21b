"""Synthetic runs without Zenoh: the one place that makes up bus traffic.

* :func:`synthetic_run` - the fusion's inputs of an emulated run (anchor states, ranges or
  range batches, node truth) as ``(receive_ns, key, payload)`` per epoch, from a known
  geometry (tests, benchmarks, ``diffpos replay`` checks).
* :func:`display_run` - the fusion's outputs of a plausible run (anchor states, truth, fixes
  with covariances, exclusions, diagnostics) as message structs (the dashboard's demo, tests
  and benchmarks); :func:`keyed` puts any such list in the recorded ``(receive_ns, key,
  payload)`` form of :func:`synthetic_run`.
* :func:`write_synthetic_recording` - a :func:`synthetic_run` written like the recorder
  would, optionally with a live fusion's estimates.

The two runs keep their own geometry and random streams: tests pin their seeded data.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from diffpos.geometry import window_edge_path
from diffpos_services.config import build_config
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.core import FusionCore
from diffpos_services.recording.topics import parse_topic
from diffpos_services.recording.writer import McapSink
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

__all__ = [
    "DISPLAY_BUILDING",
    "FUSION_INPUT_KINDS",
    "SYNTHETIC_FUSION",
    "SyntheticRun",
    "display_run",
    "keyed",
    "quiet_logger",
    "synthetic_run",
    "write_late_recording",
    "write_synthetic_recording",
]

#: message kinds the fusion consumes (what replay feeds it)
FUSION_INPUT_KINDS = ("anchor_state", "range", "range_batch")


def quiet_logger() -> logging.Logger:
    """A logger for offline FusionCore runs that only reports errors."""
    lg = logging.getLogger("diffpos.replay.quiet")
    lg.setLevel(logging.ERROR)
    return lg


#: geometry of :func:`write_synthetic_recording` (the paper-like building of the scenario model)
SYNTHETIC_FUSION = {
    "window_height_m": 1.5,
    "edge_x_m": [-20.0, 20.0],
    "first_floor_z_m": 4.0,
    "floor_height_m": 3.0,
    "n_floors": 5,
    "epoch_period_s": 0.1,
    "deadline_s": 0.3,
}


@dataclass(frozen=True)
class SyntheticRun:
    """An emulated run without Zenoh (see :func:`synthetic_run`).

    Attributes
    ----------
    config : FusionConfig
        Fusion settings matching the geometry.
    anchor_ids, node_ids : list of str
    t0_ns : int [ns]
        Start of the run (emulated time).
    epochs : iterator of list of (rx_ns, key, payload)
        Per epoch, every message in receive order: anchor states, ranges and node truth.
    """

    config: FusionConfig
    anchor_ids: list[str]
    node_ids: list[str]
    t0_ns: int
    epochs: Iterator[list[tuple[int, str, bytes]]]


def synthetic_run(
    *,
    n_anchors: int = 5,
    n_nodes: int = 4,
    duration_s: float = 5.0,
    rate_hz: float = 10.0,
    sigma_m: float = 0.1,
    outlier_probability: float = 0.0,
    seed: int = 0,
    site: str = "synth",
    t0_ns: int = 100_000_000_000_000_000,
    range_batch: bool = False,
) -> SyntheticRun:
    """The fusion's inputs of an emulated run, generated without Zenoh.

    Anchors hover outside the facade (``y < 0``), nodes walk slowly on their floor inside
    (straight lines, reflected at the walls of a 39 m x 21.5 m floor);
    ranges are the diffraction path lengths over the window edge (the fusion's own model)
    plus Gaussian noise and, with ``outlier_probability``, positive NLoS-like biases of
    2-10 m. Each epoch an anchor reports its state and a range to every node at its own phase
    (one sequence counter per anchor, like the anchor service); receive times add 0.2-1.2 ms
    of latency. The default ``t0_ns`` (1e17 ns, 1973) keeps FusionCore's int64 sum of an
    epoch's range times from overflowing (present-day Unix times overflow with 5+ anchors:
    reported upstream).

    Parameters
    ----------
    n_anchors, n_nodes : int
    duration_s : float [s]
    rate_hz : float [Hz]
        Ranging rate of every anchor (= fusion epoch rate).
    sigma_m : float [m]
        Ranging noise one-sigma.
    outlier_probability : float
    seed : int
    site : str
    t0_ns : int [ns]
    range_batch : bool
        Anchors publish one :class:`RangeBatch` per epoch on ``anchor/<id>/ranges`` (like
        ``diffpos anchor --range-batch``) instead of one message per node.
    """
    scene = _HoverScene(n_anchors=n_anchors, n_nodes=n_nodes, rate_hz=rate_hz, sigma_m=sigma_m,
                        outlier_probability=outlier_probability, seed=seed, site=site,
                        t0_ns=t0_ns, range_batch=range_batch)
    config = build_config(
        FusionConfig, dict(SYNTHETIC_FUSION, site=site, epoch_period_s=1.0 / rate_hz)
    )
    return SyntheticRun(config, scene.anchor_ids, scene.node_ids, t0_ns,
                        scene.epochs(round(duration_s * rate_hz)))


class _HoverScene:
    """The geometry and random stream of :func:`synthetic_run` (the order of the random draws
    is part of the seeded data the tests pin)."""

    #: x, y extent of the nodes' walk [m]
    LO, HI = np.array([-19.5, 0.5]), np.array([19.5, 22.0])

    def __init__(self, *, n_anchors: int, n_nodes: int, rate_hz: float, sigma_m: float,
                 outlier_probability: float, seed: int, site: str, t0_ns: int,
                 range_batch: bool) -> None:
        self.rng = rng = np.random.default_rng(seed)
        self.keys = Keys(site)
        self.rate_hz, self.sigma_m, self.t0_ns = rate_hz, sigma_m, t0_ns
        self.outlier_probability, self.range_batch = outlier_probability, range_batch
        self.period_ns = round(1e9 / rate_hz)
        ang = np.linspace(0, np.pi, n_anchors)
        self.anchors = np.stack(
            [
                -18 + 36 * np.arange(n_anchors) / max(n_anchors - 1, 1),
                -8 - 10 * np.sin(ang),
                1.0 + 3.0 * (np.arange(n_anchors) % 2),
            ],
            axis=-1,
        )
        self.anchor_ids = [f"uav{i + 1}" for i in range(n_anchors)]
        self.floors = rng.integers(0, 5, n_nodes)
        self.start = np.stack(
            [rng.uniform(-15, 15, n_nodes), rng.uniform(2, 15, n_nodes),
             4.0 + 3.0 * self.floors + 1.5],
            axis=-1,
        )
        self.vel = np.concatenate([rng.normal(0, 0.5, (n_nodes, 2)), np.zeros((n_nodes, 1))],
                                  axis=-1)
        self.node_ids = [f"n{i + 1:02d}" for i in range(n_nodes)]
        self.phases = (0.05 + 0.9 * np.arange(n_anchors) / n_anchors) * self.period_ns
        self.seqs: Counter[str] = Counter()

    def node_state(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities: straight walks reflected at the walls of the floor, so
        long runs keep the nodes spread over the floor (not piled up in the corners)."""
        lo, hi, vel = self.LO, self.HI, self.vel
        raw = self.start + vel * ((t_ns - self.t0_ns) * 1e-9)
        span = hi - lo
        q = np.mod(raw[:, :2] - lo, 2.0 * span)
        back = q > span
        p, v = raw.copy(), vel.copy()
        p[:, :2] = lo + np.where(back, 2.0 * span - q, q)
        v[:, :2] = np.where(back, -vel[:, :2], vel[:, :2])
        return p, v

    def epochs(self, n_epochs: int) -> Iterator[list[tuple[int, str, bytes]]]:
        """Per epoch, every message in receive order."""
        for e in range(n_epochs):
            te = self.t0_ns + e * self.period_ns
            items: list[tuple[int, str, bytes]] = []
            for j, a in enumerate(self.anchor_ids):
                items += self.anchor_items(j, a, te + int(self.phases[j]))
            items += self.truth_items(te + self.period_ns // 2)
            items.sort(key=lambda x: x[0])
            yield items

    def anchor_items(self, j: int, a: str, t: int) -> list[tuple[int, str, bytes]]:
        """Anchor ``a``'s state and ranges (or range batch) measured at ``t``."""
        rng, keys, n_nodes, sigma_m = self.rng, self.keys, len(self.node_ids), self.sigma_m
        r = window_edge_path(
            self.anchors[j], self.node_state(t)[0], window_height_m=1.5, edge_x_m=(-20.0, 20.0)
        ).length_m
        r = r + rng.normal(0, sigma_m, n_nodes)
        if self.outlier_probability > 0:
            out = rng.random(n_nodes) < self.outlier_probability
            r = r + out * rng.uniform(2, 10, n_nodes)
        rx = t + int(rng.integers(200_000, 1_200_000))
        state = M.AnchorState(anchor_id=a, t_ns=t, seq=self._next_seq(a),
                              position_m=M.vec3(self.anchors[j]), velocity_m_s=(0.0, 0.0, 0.0),
                              position_sigma_m=(0.05, 0.05, 0.05), velocity_sigma_m_s=0.02,
                              range_rate_hz=self.rate_hz, t_pub_wall_ns=t)
        items = [(rx, keys.anchor_state(a), M.encode(state))]
        if self.range_batch:
            batch = M.RangeBatch(anchor_id=a, t_ns=t, seq=self._next_seq(a),
                                 node_ids=self.node_ids, range_m=r.tolist(),
                                 sigma_m=[sigma_m] * n_nodes, snr_db=[20.0] * n_nodes,
                                 t_pub_wall_ns=t)
            items.append((rx + 1000, keys.anchor_range_batch(a), M.encode(batch)))
            return items
        for i, n in enumerate(self.node_ids):
            rm = M.RangeMeasurement(anchor_id=a, node_id=n, t_ns=t, seq=self._next_seq(a),
                                    range_m=float(r[i]), sigma_m=sigma_m, snr_db=20.0,
                                    t_pub_wall_ns=t)
            items.append((rx + 1000 * (i + 1), keys.anchor_range(a, n), M.encode(rm)))
        return items

    def truth_items(self, tt: int) -> list[tuple[int, str, bytes]]:
        """Every node's truth at ``tt`` (received 0.3 ms later)."""
        pos_t, vel_t = self.node_state(tt)
        return [
            (tt + 300_000, self.keys.truth_node(n), M.encode(M.GroundTruth(
                entity="node", id=n, t_ns=tt, position_m=M.vec3(pos_t[i]),
                velocity_m_s=M.vec3(vel_t[i]), floor_index=int(self.floors[i]))))
            for i, n in enumerate(self.node_ids)
        ]

    def _next_seq(self, anchor_id: str) -> int:
        """The anchor's sequence counter (one per anchor over its state and ranges)."""
        s = self.seqs[anchor_id]
        self.seqs[anchor_id] = s + 1
        return s


def write_synthetic_recording(
    path: str | Path,
    *,
    live: bool = True,
    live_step_ms: float = 5.0,
    flush_every: int = 0,
    **run_kw: Any,
) -> dict[str, int]:
    """Write a recording of a :func:`synthetic_run` like the recorder would.

    With ``live`` a FusionCore run over the same stream (stepped every ``live_step_ms`` of
    receive time) plays the live fusion and its estimates are recorded on
    ``node/<id>/estimate``. The fusion settings are stored as metadata ``fusion_config``
    (what ``diffpos replay`` starts from).

    Parameters
    ----------
    path : path
        Output MCAP.
    live : bool
    live_step_ms : float [ms]
    flush_every : int
        Close a chunk every this many messages (0: only by size).
    **run_kw
        Passed to :func:`synthetic_run`.

    Returns
    -------
    counts : dict
        Messages written per kind.
    """
    run = synthetic_run(**run_kw)
    site = run.config.site
    keys = Keys(site)
    sink = McapSink(path, library="diffpos-synthetic")
    sink.add_metadata("run", {"scenario": "synthetic", "site": site, **run_kw})
    sink.add_metadata("fusion_config", msgspec.to_builtins(run.config))
    core = FusionCore(run.config, logger=quiet_logger()) if live else None
    counts: Counter[str] = Counter()
    for a in run.anchor_ids:
        sink.write_liveliness(site, keys.alive_anchor(a), True, run.t0_ns - 10_000_000)
        if core is not None:
            core.on_liveliness(a, True, run.t0_ns - 10_000_000)
    next_step = None
    step_ns = round(live_step_ms * 1e6)
    written = 0
    for items in run.epochs:
        for rx, k, payload in items:
            sink.write(k, payload, rx)
            kind = parse_topic(k)[0]
            counts[kind] += 1
            written += 1
            if flush_every and written % flush_every == 0:
                sink.flush()
            if core is None or kind not in FUSION_INPUT_KINDS:
                continue
            core.on_sample(k, payload, rx)
            if next_step is None or rx >= next_step:
                for est in core.step(rx):
                    est = msgspec.structs.replace(est, t_pub_wall_ns=rx)
                    sink.write(keys.node_estimate(est.node_id), M.encode(est), rx + 50_000)
                    counts["estimate"] += 1
                next_step = rx + step_ns
    sink.close()
    return dict(counts)


def write_late_recording(path: str | Path, *, late_fraction: float = 0.1,
                         late_ns: int = 500_000_000, step_ms: float = 5.0, seed: int = 0,
                         restart_at_s: float | None = None, restart_gap_s: float = 1.0,
                         shards: int = 1, **run_kw: Any) -> dict[str, int]:
    """Like :func:`write_synthetic_recording`, but the live fusion receives in ITS order: a
    seeded ``late_fraction`` of the anchors' epochs reaches it ``late_ns`` late (a loaded
    machine; each anchor's messages stay in publish order), while the recorder gets every
    message on time. The fusion publishes diagnostics (with its decision record) every second
    of its time and flushes at the end, like the live service; so replay only reproduces the
    live fixes by the record, not by the recorder's order.

    ``restart_at_s`` (from the first epoch): the live fusion dies there (what is in its inbox
    and its pending epochs are lost, nothing flushed) and a new one (a fresh core, another
    ``instance`` in its diagnostics, a decision record from chunk 0) starts ``restart_gap_s``
    later, seeing the anchors' tokens alive; the recorder records throughout.

    ``shards`` > 1: that many live fusions (``diffpos fusion --shard K/N``), each with its
    own late epochs (its own machine), its own diagnostics (saying which shard it is) and
    estimates of its responders; the run's settings are recorded as ``diffpos emulate``
    records them (``run_config``: the whole run's, each shard's, the shard count).
    """
    run = synthetic_run(seed=seed, **run_kw)
    keys, site = Keys(run.config.site), run.config.site
    sink = McapSink(path, library="diffpos-synthetic")
    sink.add_metadata("run", {"scenario": "synthetic-late", "site": site, **run_kw})
    sink.add_metadata("fusion_config", msgspec.to_builtins(run.config))
    configs = [msgspec.structs.replace(run.config, shard=k, shards=shards)
               for k in range(shards)]
    if shards > 1:
        sink.add_metadata("run_config", {
            "fusion": msgspec.to_builtins(run.config), "emulate": {"fusion_shards": shards},
            "fusion_by_shard": msgspec.to_builtins(configs)})
    counts: Counter[str] = Counter()
    t_alive = run.t0_ns - 10_000_000
    for a in run.anchor_ids:
        sink.write_liveliness(site, keys.alive_anchor(a), True, t_alive)
    die_ns = None if restart_at_s is None else run.t0_ns + round(restart_at_s * 1e9)
    back_ns = None if die_ns is None else die_ns + round(restart_gap_s * 1e9)
    fusions = [_LateFusion(cfg, run, sink, counts, seed=seed + 7919 + k, late=(
        late_fraction, late_ns), step_ns=round(step_ms * 1e6), die_ns=die_ns)
               for k, cfg in enumerate(configs)]
    for f in fusions:
        f.alive(t_alive)
    for items in run.epochs:
        for rx, k, payload in items:
            sink.write(k, payload, rx)
            kind, fields = parse_topic(k)
            counts[kind] += 1
            if back_ns is not None and rx >= back_ns:
                for f in fusions:
                    f.restart(back_ns)
                back_ns = None
            for f in fusions:
                if kind in FUSION_INPUT_KINDS and (
                        back_ns is None or (die_ns is not None and rx < die_ns)):
                    f.receive(fields["anchor"], rx, k, payload)
                f.until(rx)
    for f in fusions:
        f.finish()
    sink.close()
    return dict(counts)


class _LateFusion:
    """One live fusion of :func:`write_late_recording` (its inbox, late epochs, restarts)."""

    def __init__(self, config: FusionConfig, run: SyntheticRun, sink: McapSink,
                 counts: Counter[str], *, seed: int, late: tuple[float, int], step_ns: int,
                 die_ns: int | None) -> None:
        self.config, self.run, self.sink, self.counts = config, run, sink, counts
        self.keys = Keys(config.site)
        self.core = FusionCore(config, logger=quiet_logger())
        self.rng = np.random.default_rng(seed)
        self.late_fraction, self.late_ns = late
        self.step_ns, self.die_ns = step_ns, die_ns
        self.period_ns = round(config.epoch_period_s * 1e9)
        self.queue: list[tuple[int, int, str, bytes]] = []  # inbox: (rx, n, key, payload)
        self.last_rx: dict[str, int] = {}
        self.late: dict[tuple[str, int], bool] = {}
        self.state = {"next_step": 0, "next_diag": run.t0_ns + 1_000_000_000, "n": 0,
                      "instance": 0}

    def alive(self, t: int) -> None:
        for a in self.run.anchor_ids:
            self.core.on_liveliness(a, True, t)

    def diagnostics(self, t: int) -> bytes:
        cfg = self.config
        name = f"synthetic-{self.state['instance']}" + (
            f"-shard{cfg.shard}" if cfg.shards > 1 else "")
        return M.encode(msgspec.structs.replace(
            self.core.diagnostics(t), instance=name, shard=cfg.shard, shards=cfg.shards))

    def restart(self, t: int) -> None:
        self.queue.clear()
        self.core = FusionCore(self.config, logger=quiet_logger())
        self.alive(t)
        self.state.update(next_step=0, next_diag=t + 1_000_000_000,
                          instance=self.state["instance"] + 1)

    def receive(self, anchor: str, rx: int, key: str, payload: bytes) -> None:
        slot = (anchor, rx // self.period_ns)
        if slot not in self.late:
            self.late[slot] = bool(self.rng.random() < self.late_fraction)
        frx = max(rx + (self.late_ns if self.late[slot] else 0), self.last_rx.get(anchor, 0) + 1)
        self.last_rx[anchor] = frx
        self.state["n"] += 1
        self.queue.append((frx, self.state["n"], key, payload))

    def until(self, t: int) -> None:
        if self.die_ns is not None and t >= self.die_ns:
            die, self.die_ns = self.die_ns, None
            self.until(die - 1)
            self.queue.clear()
        queue, state, core = self.queue, self.state, self.core
        queue.sort()
        while queue and queue[0][0] <= t:
            rx, _, k, payload = queue.pop(0)
            core.on_sample(k, payload, rx)
            if rx >= state["next_step"]:
                self.publish(core.step(rx), rx)
                state["next_step"] = rx + self.step_ns
            if rx >= state["next_diag"]:
                self.sink.write(self.keys.fusion_diagnostics(), self.diagnostics(rx), rx + 1)
                state["next_diag"] = rx + 1_000_000_000

    def publish(self, ests: list, now: int) -> None:
        for est in ests:
            self.sink.write(self.keys.node_estimate(est.node_id), M.encode(est), now + 50_000)
            self.counts["estimate"] += 1

    def finish(self) -> None:
        end = max([q[0] for q in self.queue], default=0) + self.late_ns
        self.until(end)
        self.publish(self.core.flush(end), end)
        self.sink.write(self.keys.fusion_diagnostics(), self.diagnostics(end), end + 1)


# ----------------------------------------------------------------------------------------
# the fusion's outputs (what the dashboard draws)
# ----------------------------------------------------------------------------------------

#: the building of :func:`display_run` (the fields of the dashboard's ``BuildingOutline``;
#: first floor at z = 0)
DISPLAY_BUILDING: dict[str, float] = {
    "x_min_m": -12.0,
    "x_max_m": 12.0,
    "depth_m": 14.0,
    "n_floors": 4,
    "floor_height_m": 3.5,
    "sill_height_m": 0.9,
    "window_height_m": 1.6,
}


def display_run(
    *,
    n_anchors: int = 4,
    n_nodes: int = 6,
    duration_s: float = 20.0,
    rate_hz: float = 10.0,
    seed: int = 0,
    t0_ns: int = 1_700_000_000_000_000_000,
) -> tuple[dict[str, float], list[Any]]:
    """A plausible run as the fusion's outputs, for demos, tests and benchmarks of the
    dashboard (:func:`keyed` turns the list into recorded form).

    Anchors circle outside the facade (y < 0), nodes walk slowly on their floor at the
    window mid-height, estimates are truth plus Gaussian noise drawn from their own
    covariance; every 7th fix of node 0 excludes one anchor (``RAIM``) and node 1
    is ``NOT_IDENTIFIABLE`` (no position) for one second in the middle. The last anchor leaves
    the fusion's live set after two thirds of the run (FusionDiagnostics every second).

    Returns
    -------
    building : dict
        :data:`DISPLAY_BUILDING`.
    messages : list
        ``AnchorState``, ``GroundTruth`` (nodes), ``PositionEstimate`` and
        ``FusionDiagnostics`` structs of :mod:`diffpos_services.wire.messages`, in time order.
    """
    tracks = _DisplayTracks(n_anchors=n_anchors, n_nodes=n_nodes, duration_s=duration_s,
                            rate_hz=rate_hz, seed=seed, t0_ns=t0_ns)
    return dict(DISPLAY_BUILDING), tracks.messages()


def _floor_of(z_m: np.ndarray) -> np.ndarray:
    """Floor index of heights in :data:`DISPLAY_BUILDING` (clipped; -1 where z is NaN)."""
    b = DISPLAY_BUILDING
    z = np.asarray(z_m, dtype=np.float64)
    k = np.floor((np.where(np.isfinite(z), z, 0.0) - 0.0) / b["floor_height_m"])
    k = np.clip(k, 0, b["n_floors"] - 1).astype(np.int64)
    return np.where(np.isfinite(z), k, -1)


class _DisplayTracks:
    """Every seeded array of :func:`display_run`, drawn in one fixed order (part of the data
    the dashboard tests pin); :meth:`messages` only reads them."""

    WALL_NS = 1_800_000_000_000_000_000  # the publishers' wall clock at t0

    def __init__(self, *, n_anchors: int, n_nodes: int, duration_s: float, rate_hz: float,
                 seed: int, t0_ns: int) -> None:
        b = DISPLAY_BUILDING
        rng = np.random.default_rng(seed)
        self.rate_hz, self.t0_ns = rate_hz, t0_ns
        n_t = self.n_t = max(1, round(duration_s * rate_hz))
        self.t_ns = t0_ns + (np.arange(n_t) * (1e9 / rate_hz)).astype(np.int64)
        ts = (self.t_ns - t0_ns) / 1e9
        # anchors: ellipses outside the facade
        phase = rng.uniform(0, 2 * np.pi, n_anchors)
        ang = phase[None, :] + 0.05 * ts[:, None]
        self.a_pos = np.stack(
            [
                14.0 * np.cos(ang),
                -12.0 - 4.0 * np.sin(ang),
                np.linspace(4.0, 14.0, n_anchors)[None, :] + 1.0 * np.sin(2 * ang),
            ],
            axis=-1,
        )  # (T, A, 3)
        self.a_ids = [f"uav{i + 1}" for i in range(n_anchors)]
        # nodes: random walk on a floor at window mid-height
        self.floors = rng.integers(0, b["n_floors"], n_nodes)
        z_mid = self.floors * b["floor_height_m"] + b["sill_height_m"] + 0.5 * b["window_height_m"]
        start = np.stack([rng.uniform(-9, 9, n_nodes), rng.uniform(2, 12, n_nodes), z_mid],
                         axis=-1)
        steps = rng.normal(0.0, 0.03, (n_t, n_nodes, 3))
        steps[..., 2] = 0.0
        self.n_pos = start[None] + np.cumsum(steps, axis=0)
        self.n_pos[..., 0] = np.clip(self.n_pos[..., 0], -11, 11)
        self.n_pos[..., 1] = np.clip(self.n_pos[..., 1], 0.5, 13.5)
        self.n_ids = [f"n{i:02d}" for i in range(n_nodes)]
        # estimates: per fix a random covariance (axes 0.2..1.5 m, random rotation)
        sig = rng.uniform(0.2, 1.5, (n_t, n_nodes, 3))
        q, _ = np.linalg.qr(rng.normal(size=(n_t, n_nodes, 3, 3)))
        self.cov = q @ (sig[..., :, None] ** 2 * np.swapaxes(q, -1, -2))
        noise = np.einsum("...ij,...j->...i", q, sig * rng.normal(size=(n_t, n_nodes, 3)))
        self.e_pos = self.n_pos + noise
        self.peb = np.sqrt(np.einsum("...ii->...", self.cov))
        self.e_floor = _floor_of(self.e_pos[..., 2])
        self.res = rng.normal(0.0, 0.3, (n_t, n_nodes, n_anchors))
        self.leave_at = int(n_t * 2 / 3)

    def messages(self) -> list[Any]:
        out: list[Any] = []
        for i in range(self.n_t):
            t = int(self.t_ns[i])
            wall = self.WALL_NS + t - self.t0_ns
            live = self.a_ids if i < self.leave_at else self.a_ids[:-1]
            out += self.anchor_states(i, t, wall)
            for k in range(len(self.n_ids)):
                out += self.node_messages(i, k, t, wall, live)
            if i % max(1, round(self.rate_hz)) == 0:
                out.append(self.diagnostics(i, t, wall, live))
        return out

    def anchor_states(self, i: int, t: int, wall: int) -> list[M.AnchorState]:
        return [
            M.AnchorState(anchor_id=aid, t_ns=t, seq=i, position_m=M.vec3(self.a_pos[i, j]),
                          velocity_m_s=(0.0, 0.0, 0.0), position_sigma_m=(0.1, 0.1, 0.2),
                          velocity_sigma_m_s=0.05, range_rate_hz=self.rate_hz,
                          t_pub_wall_ns=wall)
            for j, aid in enumerate(self.a_ids)
            if not (j == len(self.a_ids) - 1 and i >= self.leave_at)
        ]

    def node_messages(self, i: int, k: int, t: int, wall: int, live: list[str]) -> list[Any]:
        """Node ``k``'s truth and fix at step ``i``."""
        nid, a_ids = self.n_ids[k], self.a_ids
        truth = M.GroundTruth(entity="node", id=nid, t_ns=t, position_m=M.vec3(self.n_pos[i, k]),
                              velocity_m_s=(0.0, 0.0, 0.0), floor_index=int(self.floors[k]))
        used = list(live)
        excluded = []
        if k == 0 and i % 7 == 3 and len(used) > 3:
            excluded.append(M.Exclusion(anchor_id=used.pop(1), reason="RAIM"))
        if i >= self.leave_at:
            excluded.append(M.Exclusion(anchor_id=a_ids[-1], reason="ANCHOR_LOST"))
        unident = k == 1 and self.n_t // 2 <= i < self.n_t // 2 + int(self.rate_hz)
        cov = self.cov[i, k]
        fix = M.PositionEstimate(
            node_id=nid, t_ns=t, epoch=i, seq=i,
            status="NOT_IDENTIFIABLE" if unident else "OK",
            position_m=None if unident else M.vec3(self.e_pos[i, k]),
            covariance_m2=None if unident else tuple(M.vec3(r) for r in cov),
            peb_m=None if unident else float(self.peb[i, k]),
            z_bound_m=None if unident else float(np.sqrt(cov[2, 2])),
            floor_index=None if unident else int(self.e_floor[i, k]),
            used_anchors=used,
            residuals_m=[float(self.res[i, k, a_ids.index(a)]) for a in used],
            excluded=excluded, message="", t_input_wall_ns=wall,
            t_pub_wall_ns=wall + 1_000_000,
        )
        return [truth, fix]

    def diagnostics(self, i: int, t: int, wall: int, live: list[str]) -> M.FusionDiagnostics:
        n = len(self.n_ids)
        return M.FusionDiagnostics(
            t_wall_ns=wall, watermark_ns=t, received={"range": i * n}, rejected={},
            gated=i // 7, solved=i * n, published=i * n, fixes_by_status={"OK": i * n},
            late_ranges=0, pending_epochs=0, live_anchors=list(live), anchors=[],
            latency=M.LatencyStats(count=0, p50_ms=None, p99_ms=None, max_ms=None),
        )


def keyed(messages: Iterable[Any], *, site: str = "demo",
          latency_ns: int = 2_000_000) -> list[tuple[int, str, bytes]]:
    """Synthetic messages in recorded form: ``(receive_ns, key, payload)`` with the receive
    time ``latency_ns`` after the message's own time (``t_ns``, else ``watermark_ns``), the
    form :func:`synthetic_run` yields and :class:`McapSink.write` takes."""
    keys = Keys(site)
    out = []
    for x in messages:
        t_ns = getattr(x, "t_ns", None) or x.watermark_ns
        out.append((t_ns + latency_ns, keys.of(x), M.encode(x)))
    return out
