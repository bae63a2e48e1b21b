"""``diffpos reproduce``'s computation: the paper's study end to end on a scenario.

Channels (the O2I emulator, or first arrivals from elsewhere: a ray trace or a saved array
file, loaded by the caller) -> first arrivals -> the MPC table and first-arrival statistics ->
the positioning study (:func:`diffpos.study.positioning_study`: the paper's four estimators
and M-NLS by default, each method's floor accuracy over all receivers, M-NLS's 95 % ellipsoid
coverage, the wall time of every method) -> the summary dict the writers and the terminal
report use. Pure numerics: the caller reads files and draws.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from diffpos.channel.emulator import Channel, emulate_channel, first_arrival, mpc_statistics
from diffpos.scenario import Scenario
from diffpos.study import (
    METHOD_LABELS,
    FirstArrivalData,
    PositioningStudy,
    first_arrival_statistics,
    floor_starts_m,
    method_label,
    positioning_study,
)

__all__ = [
    "ALL_METHODS",
    "DEFAULT_QUICK_NODES",
    "PAPER_TABLE",
    "REPRODUCE_METHODS",
    "Arrivals",
    "Progress",
    "ReproduceConfig",
    "Reproduction",
    "build_summary",
    "emulator_arrivals",
    "reproduce",
    "study_rngs",
]

#: The paper's Table "MPC through the windows" [%].
PAPER_TABLE: dict[str, dict[str, float]] = {
    "MPC-1": {"P_e": 3.47, "P_fap": 3.47},
    "MPC-2": {"P_e": 9.03, "P_fap": 1.60},
    "MPC-3": {"P_e": 91.52, "P_fap": 84.79},
    "MPC-4": {"P_e": 100.0, "P_fap": 10.12},
}
ALL_METHODS = [k for k in METHOD_LABELS if k != "peb"]
#: ``diffpos reproduce``'s default estimators: the paper's four and M-NLS.
REPRODUCE_METHODS: tuple[str, ...] = ("lls", "ippa", "dnls_case1", "dnls_case2", "mnls")
DEFAULT_QUICK_NODES = 1500


@dataclass(frozen=True)
class ReproduceConfig:
    """What to run.

    Attributes
    ----------
    seed : int
        Seed of the range noise and the ``quick`` subsample.
    quick : bool
        Keep a random subsample of ``quick_nodes`` receivers.
    quick_nodes : int
    methods : tuple of str
        Estimators (keys of :data:`diffpos.study.METHOD_LABELS` but ``"peb"``; default
        :data:`REPRODUCE_METHODS`).
    delta_m : float [m]
        D-NLS Case-2 model offset.
    """

    seed: int = 0
    quick: bool = False
    quick_nodes: int = DEFAULT_QUICK_NODES
    methods: tuple[str, ...] = REPRODUCE_METHODS
    delta_m: float = 1.5


class Progress(Protocol):
    """Progress sink: one task per stage (``key``), ``done`` of ``total``."""

    def add(self, key: str, label: str, total: int) -> None: ...

    def update(self, key: str, done: int) -> None: ...


class _NoProgress:
    def add(self, key: str, label: str, total: int) -> None:
        pass

    def update(self, key: str, done: int) -> None:
        pass


@dataclass(frozen=True)
class Arrivals:
    """First arrivals of a channel source; ``channel``/``table`` where the source has them."""

    data: FirstArrivalData
    channel: Channel | None = None
    table: dict[str, dict[str, float]] | None = None
    fap_by_mechanism: dict[str, float] | None = None


@dataclass(frozen=True)
class Reproduction:
    """Everything the writers need."""

    kind: str
    path: Any
    channel: Channel | None
    table: dict[str, dict[str, float]] | None
    data: FirstArrivalData
    study: PositioningStudy
    timing: dict[str, float] = field(default_factory=dict)
    fap_stats: dict[str, Any] = field(default_factory=dict)
    fap_by_mechanism: dict[str, float] | None = None


class _StageClock:
    """Forwards the study's progress and times every stage (methods run one after another).

    A stage's time runs from the previous stage's last update (or the clock's creation) to
    its own last update: the time of that method over all receivers, by wall clock and by
    process CPU time (the figure to compare when other processes share the cores).
    """

    def __init__(self, prog: Progress) -> None:
        self.prog = prog
        self.t_prev = (time.perf_counter(), time.process_time())
        self.last: dict[str, tuple[float, float]] = {}
        self.start: dict[str, tuple[float, float]] = {}

    def update(self, key: str, done: int, total: int) -> None:
        now = (time.perf_counter(), time.process_time())
        if key not in self.start:
            self.start[key] = max(self.last.values(), default=self.t_prev)
        self.last[key] = now
        self.prog.update(key, done)

    def durations(self, clock: int = 0) -> dict[str, float]:
        """Time per stage [s]: wall clock (``clock=0``) or process CPU time (``clock=1``)."""
        return {k: self.last[k][clock] - self.start[k][clock] for k in self.last}


def study_rngs(seed: int) -> tuple[np.random.Generator, np.random.Generator]:
    """The subsample and the range-noise generators of a run (two streams of ``seed``)."""
    ss = np.random.SeedSequence(seed)
    sub_rng, noise_rng = (np.random.default_rng(s) for s in ss.spawn(2))
    return sub_rng, noise_rng


def emulator_arrivals(scenario: Scenario, cfg: ReproduceConfig, sub_rng: np.random.Generator,
                      noise_rng: np.random.Generator) -> Arrivals:
    """The O2I emulator's channels and first arrivals on the scenario's receivers."""
    nodes = scenario.node_positions_m()
    if cfg.quick and cfg.quick_nodes < len(nodes):
        keep = np.sort(sub_rng.choice(len(nodes), cfg.quick_nodes, replace=False))
        nodes = nodes[keep]
    anchors = scenario.anchor_positions_m()
    channel = emulate_channel(anchors, nodes, building=scenario.building, radio=scenario.radio)
    fa = first_arrival(channel, radio=scenario.radio, rng=noise_rng)
    table = mpc_statistics(channel, fa)
    pairs = max(fa.slot.size, 1)
    by_mech = {lab: 100.0 * float(np.sum(fa.slot == k)) / pairs
               for k, lab in enumerate(channel.mechanism)}
    return Arrivals(data=FirstArrivalData.from_channel(fa, anchors, nodes), channel=channel,
                    table=table, fap_by_mechanism={k: v for k, v in by_mech.items() if v > 0})


def reproduce(
    scenario: Scenario,
    cfg: ReproduceConfig,
    *,
    kind: str = "emulator",
    path: Any = None,
    load: Callable[[np.random.Generator], Arrivals] | None = None,
    progress: Progress | None = None,
) -> Reproduction:
    """Run the whole study.

    ``load(noise_rng)`` gives the first arrivals of a source other than the emulator
    (``kind`` and ``path`` name it in the summary); they are subsampled like the emulator's
    receivers when ``cfg.quick``.
    """
    prog = progress or _NoProgress()
    sub_rng, noise_rng = study_rngs(cfg.seed)
    timing: dict[str, float] = {}
    t_all = t0 = time.perf_counter()
    if load is None:
        prog.add("channel", "channels + first arrival", 1)
        arr = emulator_arrivals(scenario, cfg, sub_rng, noise_rng)
        prog.update("channel", 1)
    else:
        arr = load(noise_rng)
    data = arr.data
    if load is not None and cfg.quick and cfg.quick_nodes < data.n_nodes:
        keep = np.sort(sub_rng.choice(data.n_nodes, cfg.quick_nodes, replace=False))
        data = data.subset(keep)
    timing["channel_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    for m in cfg.methods:
        prog.add(m, method_label(m, cfg.delta_m), data.n_nodes)
    prog.add("peb", "PEB / z bound", data.n_nodes)
    clock = _StageClock(prog)
    study = positioning_study(
        data, window_height_m=scenario.building.window_height_m,
        edge_x_m=scenario.building.edge_x_m, delta_case2_m=cfg.delta_m,
        methods=tuple(cfg.methods), progress=clock.update,
        z_starts_m=floor_starts_m(scenario.building),
        start_y_m=0.5 * scenario.building.depth_m,
        building=scenario.building, radio=scenario.radio,
    )
    timing["positioning_s"] = time.perf_counter() - t0
    timing["method_s"] = clock.durations()
    timing["method_cpu_s"] = clock.durations(1)
    timing["total_s"] = time.perf_counter() - t_all
    return Reproduction(kind=kind, path=path, channel=arr.channel, table=arr.table, data=data,
                        study=study, timing=timing, fap_stats=first_arrival_statistics(data),
                        fap_by_mechanism=arr.fap_by_mechanism if load is None else None)


def build_summary(cfg: ReproduceConfig, scenario: Scenario, res: Reproduction) -> dict[str, Any]:
    """The run's summary (what summary.json holds before JSON cleaning)."""
    data = res.data
    return {
        "scenario": scenario.name,
        "channel_source": res.kind + ("" if res.path is None else f":{res.path}"),
        "seed": cfg.seed,
        "quick": bool(cfg.quick),
        "n_receivers": data.n_nodes,
        "n_anchors": int(np.shape(data.anchors_m)[0]),
        "anchors_m": np.asarray(data.anchors_m).tolist(),
        "delta_case2_m": cfg.delta_m,
        "window_height_m": scenario.building.window_height_m,
        "mpc_table_pct": res.table,
        "first_arrival_mechanism_pct": res.fap_by_mechanism,
        "paper_mpc_table_pct": PAPER_TABLE,
        "first_arrival": res.fap_stats,
        "positioning_m": res.study.summary(),
        "timing_s": res.timing,
    }
