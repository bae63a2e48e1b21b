"""Tracing: solver settings and :func:`trace` (every anchor x receiver link of a scenario)."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.constants import SPEED_OF_LIGHT_M_S
from diffpos.scenario import Scenario
from diffpos_services.raytrace.backend import check_sionna
from diffpos_services.raytrace.dataset import DATASET_FORMAT, RaytraceDataset
from diffpos_services.raytrace.paths import classify_chains, encode_chains
from diffpos_services.raytrace.scene import build_scene, building_surfaces

#: 10 log10 of the short dipole's directivity (Sionna's dipole pattern includes it).
_DIPOLE_DB = 10.0 * math.log10(1.5)
_C = SPEED_OF_LIGHT_M_S


@dataclass(frozen=True)
class RaytraceSettings:
    """Solver settings (recorded in the dataset's metadata).

    Attributes
    ----------
    max_depth : int
        Maximum interactions per path (3 covers ``Tx-D-T-T-Rx``).
    samples_per_src : int
        Rays shot per transmitter (cost grows linearly with it).
    seed : int
    batch_size : int
        Receivers per solver call.
    overlap_m : float [m]
        Surfaces run this far past the surfaces they meet.
    deterministic : bool
        Sionna's deterministic candidate generator (reproducible, slower).
    diffuse : bool
        Also trace diffuse reflections (off by default, as in the paper).
    """

    max_depth: int = 3
    samples_per_src: int = 100_000
    seed: int = 1
    batch_size: int = 2000
    overlap_m: float = 0.05
    deterministic: bool = False
    diffuse: bool = False

    def __post_init__(self) -> None:
        if not 1 <= self.max_depth <= 4:
            raise ValueError(f"max_depth: {self.max_depth} is out of range (allowed [1, 4])")
        if self.samples_per_src < 1000:
            raise ValueError(f"samples_per_src: {self.samples_per_src} is too small (>= 1000)")
        if self.batch_size < 1:
            raise ValueError(f"batch_size: must be >= 1, got {self.batch_size}")
        if not 0.0 < self.overlap_m < 1.0:
            raise ValueError(f"overlap_m: {self.overlap_m} must be in (0, 1) m")
        if self.seed < 0:
            raise ValueError(f"seed: must be >= 0, got {self.seed}")


def _dipole_orientation(e0: Sequence[float]) -> tuple[float, float, float]:
    """Sionna orientation (yaw about z, pitch about y, roll) putting local z along ``e0``."""
    e = np.asarray(e0, dtype=np.float64)
    e = e / np.linalg.norm(e)
    return (float(math.atan2(e[1], e[0])), float(math.acos(np.clip(e[2], -1.0, 1.0))), 0.0)


def _trace_batch(scene: Any, solver: Any, rt: Any, mi: Any, nodes: NDArray, settings:
                 RaytraceSettings) -> dict[str, NDArray]:
    names = [f"rx{i}" for i in range(len(nodes))]
    for name, p in zip(names, nodes, strict=True):
        scene.add(rt.Receiver(name, position=mi.Point3f(*(float(x) for x in p))))
    try:
        paths = solver(scene, max_depth=settings.max_depth,
                       samples_per_src=int(settings.samples_per_src),
                       max_num_paths_per_src=max(1_000_000, 200 * len(nodes)),
                       diffuse_reflection=settings.diffuse, refraction=True, diffraction=True,
                       edge_diffraction=True, seed=int(settings.seed))
        valid = np.asarray(paths.valid, dtype=bool)[:, 0, :]  # (R, P)
        tau = np.asarray(paths.tau, dtype=np.float64)[:, 0, :]
        ar, ai = paths.a
        power = (np.asarray(ar, dtype=np.float64) ** 2
                 + np.asarray(ai, dtype=np.float64) ** 2).sum(axis=(1, 3))[:, 0, :]
        inter = np.asarray(paths.interactions)[:, :, 0, :]  # (D, R, P)
        all_verts = np.asarray(paths.vertices, dtype=np.float32)[:, :, 0, :, :]  # (D, R, P, 3)
        verts = all_verts[0]  # (R, P, 3)
        theta_t = np.asarray(paths.theta_t, dtype=np.float64)[:, 0, :]
        theta_r = np.asarray(paths.theta_r, dtype=np.float64)[:, 0, :]
    finally:
        for name in names:
            scene.remove(name)
    chain = encode_chains(inter)
    verts = np.where((chain != 0)[..., None], verts, np.nan).astype(np.float32)
    chain_v = np.moveaxis(all_verts, 0, 2)  # (R, P, D, 3)
    used = (inter != 0).transpose(1, 2, 0)[..., None]  # (R, P, D, 1)
    chain_v = np.where(used, chain_v, np.nan).astype(np.float32)
    with np.errstate(divide="ignore"):
        gain_db = 10.0 * np.log10(power) - _DIPOLE_DB
    return {"valid": valid & np.isfinite(tau) & (power > 0), "length": tau * _C,
            "gain_db": gain_db, "chain": chain, "vertex": verts, "vertices": chain_v,
            "aod": np.degrees(theta_t), "aoa": np.degrees(theta_r)}


def _pack(batches: list[dict[str, NDArray]]) -> dict[str, NDArray]:
    """Sort the valid paths of each link by delay and pad to a common K."""
    k = max(int(bt["valid"].sum(axis=1).max(initial=0)) for bt in batches)
    k = max(k, 1)
    out: dict[str, list[NDArray]] = {n: [] for n in ("valid", "length", "gain_db", "chain",
                                                     "vertex", "vertices", "aod", "aoa")}
    for bt in batches:
        key = np.where(bt["valid"], bt["length"], np.inf)
        order = np.argsort(key, axis=1, kind="stable")
        take = lambda a, o=order: np.take_along_axis(  # noqa: E731
            a, o.reshape(o.shape + (1,) * (a.ndim - 2)), axis=1)
        p = bt["valid"].shape[1]
        for name in out:
            arr = take(bt[name])
            if p < k:
                pad = [(0, 0), (0, k - p)] + [(0, 0)] * (arr.ndim - 2)
                fill = False if name == "valid" else (0 if name == "chain" else np.nan)
                arr = np.pad(arr, pad, constant_values=fill)
            out[name].append(arr[:, :k])
    res = {n: np.concatenate(v, axis=0) for n, v in out.items()}
    bad = ~res["valid"]
    res["length"] = np.where(bad, np.nan, res["length"])
    res["chain"] = np.where(bad, 0, res["chain"]).astype(np.uint16)
    return res


def _check_nodes(scenario: Scenario, nodes_m: ArrayLike | None) -> NDArray[np.float64]:
    """The receivers ``(N, 3)``: the scenario's by default; all inside the building's floors."""
    nodes = (scenario.node_positions_m() if nodes_m is None
             else np.atleast_2d(np.asarray(nodes_m, dtype=np.float64)))
    if nodes.ndim != 2 or nodes.shape[1] != 3 or len(nodes) == 0:
        raise ValueError(f"nodes_m: expected shape (N, 3) with N >= 1, got {nodes.shape}")
    bad = ~scenario.building.inside(nodes)
    if np.any(bad):
        raise ValueError(f"nodes_m: {int(bad.sum())} receiver(s) outside the building's floors, "
                         f"e.g. {nodes[bad][0].tolist()}")
    return nodes


def _stack_anchors(per_anchor: list[dict[str, NDArray]]) -> dict[str, NDArray]:
    """The anchors' packed paths padded to one K and stacked: ``(N, M, K, ...)``."""
    k = max(p["valid"].shape[1] for p in per_anchor)
    arrays: dict[str, NDArray] = {}
    for name in per_anchor[0]:
        cols = []
        for p in per_anchor:
            arr = p[name]
            if arr.shape[1] < k:
                pad = [(0, 0), (0, k - arr.shape[1])] + [(0, 0)] * (arr.ndim - 2)
                fill = False if name == "valid" else (0 if name == "chain" else np.nan)
                arr = np.pad(arr, pad, constant_values=fill)
            cols.append(arr)
        arrays[name] = np.stack(cols, axis=1)  # (N, M, K, ...)
    return arrays


def _metadata(scenario: Scenario, settings: RaytraceSettings, versions: dict[str, str],
              elapsed: float, timings: list[tuple[int, float]]) -> dict[str, Any]:
    """The dataset's metadata: format, scenario, settings, versions, run time, surfaces."""
    anchors = scenario.anchor_positions_m()
    steady = [t for n_, t in timings[1:]] or [timings[0][1]]
    n_steady = [n_ for n_, _ in timings[1:]] or [timings[0][0]]
    return {
        "format": DATASET_FORMAT,
        "scenario": scenario.to_dict(),
        "settings": dataclasses.asdict(settings),
        "versions": versions,
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "elapsed_s": elapsed,
        "s_per_1000_links": 1000.0 * sum(steady) / max(sum(n_steady), 1),
        "surfaces": [{"name": s.name, "material": s.material, "thickness_m": s.thickness_m,
                      "rects": [list(map(lambda v: list(v) if isinstance(v, tuple) else v, r))
                                for r in s.rects]}
                     for s in building_surfaces(scenario.building, anchors,
                                                overlap_m=settings.overlap_m)],
    }


def trace(
    scenario: Scenario,
    nodes_m: ArrayLike | None = None,
    *,
    settings: RaytraceSettings | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> RaytraceDataset:
    """Ray trace every anchor x receiver link of a scenario.

    Parameters
    ----------
    scenario : Scenario
        Building, radio and anchors (positions at ``t = 0``).
    nodes_m : array_like, shape (N, 3) [m], optional
        Receivers; default ``scenario.node_positions_m()``.
    settings : RaytraceSettings, optional
    progress : callable ``(done, total, label)``, optional
        Called after every solver call with the number of links done.

    Returns
    -------
    RaytraceDataset

    Raises
    ------
    RaytraceUnavailable
        Sionna RT missing (message says how to install it).
    ValueError
        Receivers outside the building's floors, or an unusable material.
    """
    settings = settings or RaytraceSettings()
    versions = check_sionna()
    # sionna/mitsuba are the optional extra: imported here, never at module level
    import mitsuba as mi
    import sionna.rt as rt

    nodes = _check_nodes(scenario, nodes_m)
    anchors = scenario.anchor_positions_m()
    t0 = time.perf_counter()
    scene = build_scene(scenario, overlap_m=settings.overlap_m)
    solver = rt.PathSolver(deterministic=settings.deterministic)
    yaw, pitch, roll = _dipole_orientation(scenario.radio.polarization)
    per_anchor = []
    total, done = len(nodes) * len(anchors), 0
    timings: list[tuple[int, float]] = []
    for j, (aid, pos) in enumerate(zip(scenario.anchor_ids, anchors, strict=True)):
        tx = rt.Transmitter(f"tx{j}", position=mi.Point3f(*(float(x) for x in pos)),
                            orientation=mi.Point3f(yaw, pitch, roll))
        scene.add(tx)
        batches = []
        for s in range(0, len(nodes), settings.batch_size):
            chunk = nodes[s:s + settings.batch_size]
            tb = time.perf_counter()
            batches.append(_trace_batch(scene, solver, rt, mi, chunk, settings))
            timings.append((len(chunk), time.perf_counter() - tb))
            done += len(chunk)
            if progress is not None:
                progress(done, total, aid)
        scene.remove(f"tx{j}")
        per_anchor.append(_pack(batches))
    elapsed = time.perf_counter() - t0
    arrays = _stack_anchors(per_anchor)
    metadata = _metadata(scenario, settings, versions, elapsed, timings)
    return RaytraceDataset(
        nodes_m=nodes, anchors_m=anchors, anchor_ids=tuple(scenario.anchor_ids),
        path_valid=arrays["valid"], path_length_m=arrays["length"],
        path_gain_db=arrays["gain_db"].astype(np.float32),
        path_aod_deg=arrays["aod"].astype(np.float32),
        path_aoa_deg=arrays["aoa"].astype(np.float32),
        path_chain=arrays["chain"].astype(np.uint16),
        path_class=np.where(arrays["valid"], classify_chains(arrays["chain"]), 0).astype(np.int8),
        path_vertex_m=arrays["vertex"].astype(np.float32), metadata=metadata,
        path_vertices_m=arrays["vertices"].astype(np.float32),
    )
