"""Helpers shared by the benchmark scripts (benchmarks/README.md indexes the scripts).

Every script runs as ``python benchmarks/SCRIPT.py``: Python puts ``benchmarks/`` first on
``sys.path``, so a script imports this module as ``from common import ...`` (and the held-out
geometry generator as ``from heldout import ...``); no script imports another script and none
edits ``sys.path``. Tests that import a script put ``benchmarks/`` on their path the same way.

- the machine line every report starts with (:func:`machine`);
- the one scorer of a recording, every node-epoch after the first ``SKIP_S`` against its
  recorded truth (:func:`score_recording`: bench_accuracy.py, bench_floor_calibration.py);
- a live run's scenario and its processes' CPU and memory from /proc (:func:`scenario_toml`,
  :func:`cpu_s`, :func:`rss_mb`: bench_latency.py, bench_soak.py, bench_workers.py);
- the estimator benchmarks' random scene and the scipy reference fix (:func:`scene`,
  :func:`scipy_fix`: bench_estimators.py, bench_solve.py).
"""

from __future__ import annotations

import os
import platform
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
from diffpos_services.recording.reader import McapScanner, side_records
from diffpos_services.recording.summary import recorded_building
from diffpos_services.recording.topics import parse_topic
from diffpos_services.recording.writer import part_path
from diffpos_services.wire import messages as M
from scipy.optimize import least_squares

from diffpos.floor_calibration import probability_rows
from diffpos.geometry import window_edge_path
from diffpos.metrics import percentiles, score, truth_at

SKIP_S = 2.0  # node-epochs of a run's first seconds are not scored (start-up)
PERIOD_NS = 100_000_000  # the fusion epoch of the live benchmarks (10 Hz)
W_M = 1.2  # window height of the estimator benchmarks' scene [m]
SIGMA_M = 0.05  # range noise of the estimator benchmarks' scene [m]


# ----------------------------------------------------------------------------- the machine
def machine() -> str:
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return (f"{platform.node()} {platform.machine()} {os.cpu_count()} cores, "
            f"{platform.processor() or platform.system()}, Python {platform.python_version()}, "
            f"load avg {load[0]:.1f}")


# ----------------------------------------------------------------------------- scoring
def tree_env(tree: str | Path | None) -> dict[str, str]:
    """This process' environment with ``tree`` (a checkout) and its ``services`` first on
    ``PYTHONPATH`` (None: this process' own): a child process runs that checkout's code."""
    env = dict(os.environ)
    if tree is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(tree), str(Path(tree) / "services")])
    return env


def recording_parts(path: str | Path) -> list[Path]:
    """``path`` and the parts the recorder split the run into (``<stem>_0001.mcap``, ...:
    :func:`diffpos_services.recording.writer.part_path`), in order."""
    parts = [Path(path)]
    while part_path(path, len(parts)).exists():
        parts.append(part_path(path, len(parts)))
    return parts


def _truth_tracks(truth: list) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per node its truth samples' times, positions and floors, in time order."""
    by: dict[str, list] = {}
    for g in sorted(truth, key=lambda g: (g.id, g.t_ns)):
        by.setdefault(g.id, []).append(g)
    return {k: (np.array([g.t_ns for g in v], np.int64), np.array([g.position_m for g in v]),
                np.array([g.floor_index for g in v])) for k, v in by.items()}


def score_recording(path: str | Path, *, skip_s: float = SKIP_S,
                    rows_out: list | None = None, replayed: bool = False) -> dict[str, Any]:
    """Every node-epoch of a recording (all its parts) after ``skip_s`` against its recorded
    truth.

    The node-epochs are the recorded truth samples of the nodes (one per node and fusion
    epoch of the run); the estimate of a node-epoch is the recorded live estimate of that node
    and epoch (v1 or v2) with a usable position (status in ``GOOD_STATUSES``), else a miss.
    An estimate is compared with the truth at its own ``t_ns``
    (:func:`diffpos.metrics.truth_at`), as ``emulate``'s summary and ``replay``'s report do:
    the position interpolated then, and the floor of that position in the recorded building
    (:func:`diffpos_services.recording.summary.recorded_building`; the recorded floor of the
    nearest truth sample only when the recording names no building). ``truth_floor`` of the
    result says which, and ``truth_floor_disagrees`` counts the truth samples whose recorded
    floor is not that building's floor of their height (0: the building is the truth's).
    ``rows_out``: a list that receives one ``(node, t_ns, true floor, published floor or -1,
    its probability or NaN, true z [m], the true floor's probability or NaN)`` per node-epoch
    (bench_floor_calibration.py). ``replayed``: score the replayed estimates a
    ``diffpos replay --write-mcap`` output holds (topic kind ``replay_estimate``) instead of the
    recorded live ones (which that output also holds, copied from its input).
    """
    est_kind = "replay_estimate" if replayed else "estimate"
    dec_est, dec_truth = M.estimate_decoder(), M.decoder(M.GroundTruth)
    dec_rc = M.decoder(M.RunControl)
    truth_d, est, t0, period = {}, {}, None, None
    parts = recording_parts(path)
    for part in parts:
        for batch in McapScanner(part).iter_batches():
            for m in batch:
                kind = parse_topic(m.topic)[0]
                if kind == "truth_node":
                    g = dec_truth(m.data)
                    truth_d[(g.id, g.t_ns)] = g
                elif kind == est_kind:
                    e = dec_est(m.data)
                    est[(e.node_id, e.epoch)] = e
                elif kind == "run_control" and t0 is None:
                    t0 = dec_rc(m.data).t0_ns
    truth = list(truth_d.values())
    if t0 is None or not truth:
        raise RuntimeError(f"{path}: no run control or no truth recorded")
    ts = np.unique([g.t_ns for g in truth])
    period = int(np.min(np.diff(ts))) if ts.size > 1 else 100_000_000
    rows = [g for g in truth if g.t_ns >= t0 + round(skip_s * 1e9)]
    n = len(rows)
    pos, cov = np.full((n, 3), np.nan), np.full((n, 3, 3), np.nan)
    e_floor, t_floor = np.full(n, -1), np.array([g.floor_index for g in rows])
    vectors = [()] * n  # the reported floor probabilities of each node-epoch's estimate
    tru = np.array([g.position_m for g in rows], float)
    tracks = _truth_tracks(truth)
    floor_of, truth_floor, disagree = _floor_of(parts[0], tracks)
    if floor_of is not None:  # a miss: the floor of its truth sample's position
        t_floor = np.asarray(floor_of(tru[:, 2]), np.int64).reshape(-1)
    status: dict[str, int] = {}
    for i, g in enumerate(rows):
        e = est.get((g.id, g.t_ns // period))
        if e is None:
            status["(none)"] = status.get("(none)", 0) + 1
            continue
        status[e.status] = status.get(e.status, 0) + 1
        if e.position_m is None or e.status not in M.GOOD_STATUSES:
            continue
        p, f = truth_at([e.t_ns], *tracks[g.id], floor_of=floor_of)  # at the estimate's time
        tru[i], t_floor[i] = p[0], f[0]
        pos[i] = e.position_m
        if e.covariance_m2 is not None:
            cov[i] = e.covariance_m2
        e_floor[i] = -1 if e.floor_index is None else e.floor_index
        vectors[i] = getattr(e, "floor_probabilities", ())
    probs = probability_rows(vectors)  # None: estimate v1
    n_floors = 0 if probs is None else probs.shape[1]
    probs = np.full((n, 0), np.nan) if probs is None else probs
    s = score(pos, tru, estimate_floor=e_floor, truth_floor=t_floor, covariance_m2=cov,
              floor_probabilities=probs if n_floors else None, q=(50, 90))
    if rows_out is not None:
        ok = (e_floor >= 0) & (e_floor < n_floors)
        okt = ok & (t_floor >= 0) & (t_floor < n_floors)
        p_pub, p_true = (np.where(k, probs[np.arange(n), np.where(k, f, 0)] if n_floors
                                  else np.nan, np.nan)
                         for k, f in ((ok, e_floor), (okt, t_floor)))
        rows_out += [(g.id, g.t_ns, int(t_floor[i]), int(e_floor[i]), float(p_pub[i]),
                      float(tru[i, 2]), float(p_true[i])) for i, g in enumerate(rows)]
    lat = [(e.t_pub_wall_ns - e.t_input_wall_ns) * 1e-6 for e in est.values()
           if e.t_input_wall_ns > 0]
    return {"node_epochs": s.node_epochs, "availability": s.availability,
            "floor": s.floor_accuracy_all, "floor_fixes": s.floor_accuracy_fixes,
            "p50_3d": s.error_3d_m["p50"], "p90_3d": s.error_3d_m["p90"],
            "p50_z": s.error_z_m["p50"], "p90_z": s.error_z_m["p90"],
            "coverage95": s.ellipsoid_coverage, "floor_calibration": s.floor_calibration,
            "latency_ms": percentiles(lat, (50, 99), max_mean=False),
            "status": dict(sorted(status.items())),
            "nodes": len({g.id for g in truth}), "method": _method(est.values()),
            "recording_parts": len(parts),
            "truth_floor": truth_floor, "truth_floor_disagrees": disagree}


def _floor_of(path: Path, tracks: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
              ) -> tuple[Any, str, int]:
    """The recorded building's ``floor_index`` (None: no building recorded), what it is, and
    how many truth samples' recorded floors differ from it at their heights."""
    building, source = recorded_building(side_records(path))
    if building is None:
        return None, "the nearest truth sample's (no building recorded)", 0
    disagree = sum(int(np.count_nonzero(building.floor_index(p[:, 2]) != f))
                   for _, p, f in tracks.values())
    return (building.floor_index, f"the floor of the true position in the building of {source}",
            disagree)


def _method(ests: Iterable[Any]) -> str:
    for e in ests:
        return getattr(e, "method", "dnls (estimate v1)")
    return "-"


# ----------------------------------------------------------------------------- live runs
def scenario_toml(n_anchors: int, n_nodes: int, seed: int = 0) -> str:
    """A scenario with the paper's building, n hovering anchors and n static nodes."""
    rng = np.random.default_rng(seed)
    lines = [
        'name = "bench"',
        f'description = "benchmark: {n_anchors} UAVs, {n_nodes} static nodes"',
        "[building]",
        "first_floor_z_m = 4.0",
        "floor_height_m = 3.0",
        "n_floors = 5",
        "sill_height_m = 0.75",
        "window_height_m = 1.5",
    ]
    for j in range(n_anchors):
        x = -18.0 + 36.0 * j / max(n_anchors - 1, 1)
        y = -8.0 - 12.0 * ((j * 7) % n_anchors) / max(n_anchors, 1)
        z = float(rng.uniform(0.0, 4.0))
        lines += ["[[anchors]]", f'id = "uav{j + 1}"',
                  f"position_m = [{x:.2f}, {y:.2f}, {z:.2f}]"]
    for i in range(n_nodes):
        floor = i % 5
        x = float(rng.uniform(-17, 17))
        y = float(rng.uniform(1.0, 15.0))
        z = 4.0 + 3.0 * floor + 0.75 + 0.75
        lines += ["[[nodes.list]]", f'id = "n{i + 1:03d}"', f"position_m = [{x:.2f}, {y:.2f}, {z:.2f}]"]
    return "\n".join(lines) + "\n"


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def cpu_s(pid: int) -> float | None:
    """User + system CPU time of a process so far [s] (None if it is gone)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


# ----------------------------------------------------------------------------- estimators
def scene(rng: np.random.Generator, n: int, m: int, *, delta_m: float = 0.0):
    """Random anchors outside (y in [-40, -5] m, z in [0, 40] m), nodes on 9 floors."""
    anchors = np.stack([rng.uniform(-30, 30, (n, m)), rng.uniform(-40, -5, (n, m)),
                        rng.uniform(0, 40, (n, m))], axis=-1)
    nodes = np.stack([rng.uniform(-15, 15, n), rng.uniform(1, 15, n),
                      1.5 + 3.0 * rng.integers(0, 9, n)], axis=-1)
    p = window_edge_path(anchors, nodes[:, None, :], window_height_m=W_M, delta_m=delta_m)
    return anchors, nodes, p.length_m


def scipy_fix(anchors: np.ndarray, ranges: np.ndarray, sigma: float, starts: np.ndarray):
    """One fix with scipy: MINPACK LM from every start, keep the lowest cost."""

    def fun(x):
        return (ranges - window_edge_path(anchors, x, window_height_m=W_M).length_m) / sigma

    def jac(x):
        return -window_edge_path(anchors, x, window_height_m=W_M).jacobian / sigma

    best = None
    for x0 in starts:
        sol = least_squares(fun, x0, jac=jac, method="lm")
        if best is None or sol.cost < best.cost:
            best = sol
    x = best.x.copy()
    x[1] = abs(x[1])
    return x
