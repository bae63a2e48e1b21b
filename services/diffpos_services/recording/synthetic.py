"""Synthetic runs without Zenoh: bus messages with receive times, and recordings of them.

* :func:`synthetic_run` - the fusion's inputs of an emulated run (anchor states, ranges or
  range batches, node truth) as ``(receive_ns, key, payload)`` per epoch, from a known
  geometry (tests, benchmarks, ``diffpos replay`` checks).
* :func:`write_synthetic_recording` - such a run written like the recorder would, optionally
  with a live fusion's estimates.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from diffpos.geometry import window_edge_path
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.core import FusionCore
from diffpos_services.kit import build_config
from diffpos_services.recording.topics import parse_topic
from diffpos_services.recording.writer import McapSink
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

__all__ = [
    "FUSION_INPUT_KINDS",
    "SYNTHETIC_FUSION",
    "SyntheticRun",
    "quiet_logger",
    "synthetic_run",
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
