"""The ray-traced channel of the live loop: trace a run's links before it starts, cache them.

``diffpos emulate --channel raytrace`` (and ``diffpos anchor --channel raytrace``) serve first
arrivals from paths Sionna RT traced along the run's actual trajectories (the anchors' and the
emulated nodes' of :func:`diffpos.emulation.emulation_nodes`): :func:`prepare_links` traces
every anchor's paths to every node on a time grid ``t_g = g * step_s`` covering the run (one
solver call per anchor and grid time: the anchor is the source, the nodes at ``t_g`` the
receivers, since one trace from a source serves all its receivers), and the anchors
interpolate between grid times (:func:`diffpos.channel.traced.paths_at`) with the emulator's
detector and noise. The grid does not depend on the run's ``--seed`` (which sets the anchors'
phases and the noise, both applied after the trace), so runs with other seeds share it.

Each traced path keeps its length, gain, interaction points and an identity key: its
interaction flags, the scene objects it meets and, per interaction point, which of the scene's
plane and edge coordinates it lies on (a reflection on the ceiling of floor 2, the lower edge of
floor 1's window band, ...), so a path traced at two grid times is recognised as the same one.

Cache: one ``.npz`` per anchor in :func:`cache_dir` (``$DIFFPOS_RAYTRACE_CACHE``, default
``~/.cache/diffpos/raytrace-live``), named by :func:`cache_key`: a SHA-256 of the scenario's
content, the anchor, the node ids and every traced position, the grid and the trace settings
(and the pinned Sionna version). A file is written once (to a temporary name, then renamed) and
never overwritten; a hit needs no Sionna.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from diffpos.channel.traced import TracedLinks
from diffpos.constants import SPEED_OF_LIGHT_M_S
from diffpos.scenario import Scenario
from diffpos_services.errors import ConfigError, DiffposError
from diffpos_services.logs import STATUS, log_event
from diffpos_services.raytrace.backend import SIONNA_REQUIREMENT, check_sionna
from diffpos_services.raytrace.corrections import CORRECTIONS
from diffpos_services.raytrace.paths import DIFFRACTION, DIFFUSE, SPECULAR
from diffpos_services.raytrace.scene import build_scene, building_surfaces
from diffpos_services.raytrace.tracing import _DIPOLE_DB, _dipole_orientation

__all__ = ["DEFAULT_DEPTH", "DEFAULT_SAMPLES", "DEFAULT_STEP_S", "LIVE_FORMAT", "TRACE_KEY_ORDER",
           "LiveTraceSettings", "Prepared", "anchor_links", "cache_dir", "cache_key",
           "grid_times", "live_settings", "load_links", "path_keys", "prepare_for_run",
           "prepare_links", "save_links", "trace_links"]

LIVE_FORMAT = "diffpos-raytrace-live/1"
#: ``Radio.channel_max_order`` as :func:`cache_key` writes it whatever the scenario's: the
#: order of the emulated channel changes no traced path, so a trace is shared by every order;
#: 2, the default when the caches before its change to 3 were written (docs/channel_mix.md
#: "Session 27"), so those stay valid
TRACE_KEY_ORDER = 2
#: rays per source: 3e5 finds ~1.5x the paths of 1e5 at ~2x the cost (1.3-1.9 s per trace
#: of 6 receivers here, depth 4); docs/raytrace.md, "The ray-traced channel in the live loop"
DEFAULT_SAMPLES = 300_000
#: interactions per path: partitions count as interactions, depth 3 hides third-order paths
DEFAULT_DEPTH = 4
#: grid step [s]: 0.5 s keeps a 20 s paper run (41 grid times x 4 anchors) near 5 minutes
DEFAULT_STEP_S = 0.5
_C = SPEED_OF_LIGHT_M_S
#: a vertex lies on a scene coordinate when within this distance [m]
_ON_TOL_M = 1e-3


@dataclass(frozen=True)
class LiveTraceSettings:
    """What the live trace depends on besides the scenario and the trajectories.

    Attributes
    ----------
    samples : int
        Rays shot per source (anchor) per grid time; the cost is about linear in it.
    depth : int
        Maximum interactions per path (each partition crossing counts: use >= 4).
    step_s : float [s]
        Grid step; the anchors interpolate between grid times.
    seed : int
        Sionna's sampling seed.
    overlap_m : float [m]
        Scene surfaces run this far past the surfaces they meet (:func:`build_scene`).
    """

    samples: int = DEFAULT_SAMPLES
    depth: int = DEFAULT_DEPTH
    step_s: float = DEFAULT_STEP_S
    seed: int = 1
    overlap_m: float = 0.05

    def __post_init__(self) -> None:
        if not 1_000 <= self.samples <= 100_000_000:
            raise ValueError(f"--raytrace-samples: {self.samples:g} is out of range "
                             "[1e3, 1e8] rays per source")
        if not 1 <= self.depth <= 8:
            raise ValueError(f"--raytrace-depth: {self.depth} is out of range [1, 8]")
        if not (math.isfinite(self.step_s) and 0.001 <= self.step_s <= 60.0):
            raise ValueError(f"--raytrace-step-s: {self.step_s} is out of range [0.001, 60] s")
        if self.seed < 0:
            raise ValueError(f"raytrace seed: must be >= 0, got {self.seed}")

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def grid_times(duration_s: float, step_s: float) -> NDArray[np.float64]:
    """Grid times ``0, step, ..., G step`` with ``G step >= duration_s`` (every epoch of a run
    of ``duration_s`` lies inside) [s]."""
    if not duration_s > 0:
        raise ValueError(f"duration: must be > 0 s, got {duration_s}")
    g = max(1, math.ceil(duration_s / step_s - 1e-9))
    return np.arange(g + 1) * float(step_s)


def cache_dir() -> Path:
    """``$DIFFPOS_RAYTRACE_CACHE``, else ``$XDG_CACHE_HOME/diffpos/raytrace-live`` (default
    ``~/.cache``)."""
    env = os.environ.get("DIFFPOS_RAYTRACE_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "diffpos" / "raytrace-live"


def _positions(scenario: Scenario, anchor_id: str, nodes: Sequence[tuple[str, Any]],
               times: NDArray) -> tuple[NDArray, NDArray]:
    """The anchor's ``(E, 3)`` and the nodes' ``(E, N, 3)`` positions at ``times`` [m]."""
    ids = [a.id for a in scenario.anchors]
    traj = scenario.anchors[ids.index(anchor_id)].trajectory
    e = len(times)
    a = np.asarray(traj.position_m(times), dtype=np.float64).reshape(e, 3)
    n = np.stack([np.asarray(tr.position_m(times), dtype=np.float64).reshape(e, 3)
                  for _, tr in nodes], axis=1)
    return a, n


def cache_key(scenario: Scenario, anchor_id: str, nodes: Sequence[tuple[str, Any]],
              times: NDArray, settings: LiveTraceSettings) -> str:
    """SHA-256 (hex) of everything one anchor's trace depends on: the format, the pinned
    Sionna version and the corrections made to it, the scenario's content (but the emulated
    channel's order, :data:`TRACE_KEY_ORDER`), the anchor, the node ids, every traced position
    (so any change of a trajectory is a new key), the grid and the settings."""
    a, n = _positions(scenario, anchor_id, nodes, times)
    scen = scenario.to_dict()
    scen["radio"]["channel_max_order"] = TRACE_KEY_ORDER  # the emulator's, not the trace's
    doc = {"format": LIVE_FORMAT, "sionna": SIONNA_REQUIREMENT,
           "corrections": CORRECTIONS.get(SIONNA_REQUIREMENT.split("==")[-1], ()),
           "scenario": scen, "anchor": anchor_id,
           "nodes": [nid for nid, _ in nodes], "t_s": np.asarray(times, float).tolist(),
           "positions_sha256": hashlib.sha256(np.ascontiguousarray(a).tobytes()
                                              + np.ascontiguousarray(n).tobytes()).hexdigest(),
           "settings": settings.as_dict()}
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _cache_path(directory: Path, anchor_id: str, key: str) -> Path:
    return directory / f"{anchor_id}-{key[:24]}.npz"


# ----------------------------------------------------------------------------- file
_ARRAYS = ("t_s", "anchor_m", "nodes_m", "valid", "key", "length_m", "gain_db", "vertices_m",
           "bends")


def save_links(path: Path, links: TracedLinks, metadata: dict[str, Any]) -> Path:
    """Write ``links`` to ``path`` (a new file: written under a temporary name and renamed;
    an existing file is never replaced, FileExistsError)."""
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path}: exists (the cache never overwrites a file)")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    arrays = {name: getattr(links, name) for name in _ARRAYS}
    arrays["vertices_m"] = arrays["vertices_m"].astype(np.float32)
    with open(tmp, "wb") as f:
        np.savez_compressed(f, metadata_json=np.array(json.dumps(metadata)), **arrays)
    try:
        os.link(tmp, path)  # fails if another process wrote it meanwhile: theirs is the same
    except FileExistsError:
        pass
    finally:
        tmp.unlink()
    return path


def load_links(path: Path, *, key: str | None = None) -> tuple[TracedLinks, dict[str, Any]]:
    """Read a cache file; with ``key``: ValueError unless the file was traced for it."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["metadata_json"]))
        if meta.get("format") != LIVE_FORMAT:
            raise ValueError(f"{path}: not a {LIVE_FORMAT} file (format {meta.get('format')!r})")
        if key is not None and meta.get("key") != key:
            raise ValueError(f"{path}: traced for key {meta.get('key')}, not {key}")
        arrays = {name: z[name] for name in _ARRAYS}
    arrays["vertices_m"] = arrays["vertices_m"].astype(np.float64)
    return TracedLinks(**arrays), meta


# ----------------------------------------------------------------------------- path keys
def _scene_coordinates(scenario: Scenario, overlap_m: float) -> list[NDArray[np.float64]]:
    """Per axis, every coordinate a scene surface's plane or edge has (sorted)."""
    coords: list[set[float]] = [set(), set(), set()]
    for s in building_surfaces(scenario.building, scenario.anchor_positions_m(),
                               overlap_m=overlap_m):
        for axis, c, (u0, u1), (v0, v1) in s.rects:
            u_ax, v_ax = [ax for ax in range(3) if ax != axis]
            coords[axis].add(float(c))
            coords[u_ax].update((float(u0), float(u1)))
            coords[v_ax].update((float(v0), float(v1)))
    return [np.array(sorted(c)) for c in coords]


def path_keys(interactions: NDArray, objects: NDArray, vertices: NDArray,
              coordinates: list[NDArray[np.float64]]) -> NDArray[np.int64]:
    """Identity of every path: a 64-bit hash of its interaction flags, the objects it meets
    and, per interaction point, the scene coordinates (planes, edges) it lies on.

    Parameters
    ----------
    interactions, objects : ndarray, shape (D, ...)
        Sionna's per-depth flags (0: none) and object ids.
    vertices : ndarray, shape (D, ..., 3) [m]
    coordinates : list of 3 sorted arrays
        From :func:`_scene_coordinates`.

    Returns
    -------
    ndarray of int64, shape (...), never 0
    """
    h = np.full(interactions.shape[1:], 1469598103934665603, dtype=np.uint64)
    prime = np.uint64(1099511628211)

    def mix(h: NDArray[np.uint64], v: NDArray) -> NDArray[np.uint64]:
        return (h ^ (np.asarray(v).astype(np.int64).astype(np.uint64) + np.uint64(1))) * prime

    with np.errstate(over="ignore"):
        for d in range(interactions.shape[0]):
            used = interactions[d] != 0
            h = mix(h, np.where(used, interactions[d], 0))
            h = mix(h, np.where(used, objects[d].astype(np.int64), -1))
            for ax in range(3):
                c = coordinates[ax]
                v = np.nan_to_num(vertices[d][..., ax].astype(np.float64), nan=np.inf)
                i = np.clip(np.searchsorted(c, v), 1, len(c) - 1)
                near = np.where(np.abs(c[i - 1] - v) <= np.abs(c[i] - v), i - 1, i)
                on = used & (np.abs(c[near] - v) < _ON_TOL_M)
                h = mix(h, np.where(on, near, -1))
    key = h.view(np.int64)
    return np.where(key == 0, 1, key)


# ----------------------------------------------------------------------------- tracing
class _Tracer:
    """A Sionna scene of the building with one transmitter and N receivers, moved per call."""

    def __init__(self, scenario: Scenario, n_nodes: int, settings: LiveTraceSettings) -> None:
        self.versions = check_sionna()
        # sionna/mitsuba are the optional extra: imported here, never at module level
        import mitsuba as mi
        import sionna.rt as rt

        self.mi, self.settings = mi, settings
        self.scene = build_scene(scenario, overlap_m=settings.overlap_m)
        self.objects = {o.object_id: name for name, o in self.scene.objects.items()}
        self.coordinates = _scene_coordinates(scenario, settings.overlap_m)
        yaw, pitch, roll = _dipole_orientation(scenario.radio.polarization)
        self.tx = rt.Transmitter("tx", position=mi.Point3f(0.0, -1.0, 1.0),
                                 orientation=mi.Point3f(yaw, pitch, roll))
        self.scene.add(self.tx)
        self.rx = [rt.Receiver(f"rx{i}", position=mi.Point3f(0.0, 1.0, 1.0 + 0.01 * i))
                   for i in range(n_nodes)]
        for r in self.rx:
            self.scene.add(r)
        self.solver = rt.PathSolver()

    def trace(self, anchor_m: NDArray, nodes_m: NDArray) -> dict[str, NDArray]:
        """Every path from ``anchor_m`` (3,) to each of ``nodes_m`` (N, 3): arrays (N, P)
        (``vertices`` (N, P, D, 3), ``bends`` (N, P, D))."""
        mi, s = self.mi, self.settings
        self.tx.position = mi.Point3f(*(float(x) for x in anchor_m))
        for r, p in zip(self.rx, nodes_m, strict=True):
            r.position = mi.Point3f(*(float(x) for x in p))
        paths = self.solver(self.scene, max_depth=s.depth, samples_per_src=int(s.samples),
                            max_num_paths_per_src=1_000_000, diffuse_reflection=False,
                            refraction=True, diffraction=True, edge_diffraction=True,
                            seed=int(s.seed))
        valid = np.asarray(paths.valid, dtype=bool)[:, 0, :]  # (N, P)
        tau = np.asarray(paths.tau, dtype=np.float64)[:, 0, :]
        ar, ai = paths.a
        power = (np.asarray(ar, dtype=np.float64) ** 2
                 + np.asarray(ai, dtype=np.float64) ** 2).sum(axis=(1, 3))[:, 0, :]
        inter = np.asarray(paths.interactions)[:, :, 0, :]  # (D, N, P)
        objects = np.asarray(paths.objects)[:, :, 0, :]
        verts = np.asarray(paths.vertices, dtype=np.float64)[:, :, 0, :, :]  # (D, N, P, 3)
        keys = path_keys(inter, objects, verts, self.coordinates)
        bends = np.isin(inter, (SPECULAR, DIFFUSE, DIFFRACTION))  # (D, N, P)
        used = (inter != 0)[..., None]
        valid &= np.isfinite(tau) & (power > 0)
        with np.errstate(divide="ignore"):
            gain_db = 10.0 * np.log10(power) - _DIPOLE_DB
        return {"valid": valid, "key": np.where(valid, keys, 0), "length_m": tau * _C,
                "gain_db": gain_db, "vertices_m": np.moveaxis(np.where(used, verts, np.nan), 0, 2),
                "bends": np.moveaxis(bends, 0, 2)}


def _stack(per_epoch: list[dict[str, NDArray]]) -> dict[str, NDArray]:
    """Each epoch's paths sorted by length, padded to one K, stacked: (E, N, K, ...)."""
    k = max(1, max(int(p["valid"].sum(axis=1).max(initial=0)) for p in per_epoch))
    fill = {"valid": False, "key": 0, "length_m": np.nan, "gain_db": -np.inf,
            "vertices_m": np.nan, "bends": False}
    out: dict[str, list[NDArray]] = {name: [] for name in fill}
    for p in per_epoch:
        order = np.argsort(np.where(p["valid"], p["length_m"], np.inf), axis=1, kind="stable")
        for name in fill:
            arr = p[name]
            arr = np.take_along_axis(arr, order.reshape(order.shape + (1,) * (arr.ndim - 2)),
                                     axis=1)[:, :k]
            if arr.shape[1] < k:
                pad = [(0, 0), (0, k - arr.shape[1])] + [(0, 0)] * (arr.ndim - 2)
                arr = np.pad(arr, pad, constant_values=fill[name])
            out[name].append(arr)
    res = {name: np.stack(v) for name, v in out.items()}
    bad = ~res["valid"]
    res["length_m"] = np.where(bad, np.nan, res["length_m"])
    res["gain_db"] = np.where(bad, -np.inf, res["gain_db"])
    res["key"] = np.where(bad, 0, res["key"]).astype(np.int64)
    return res


def trace_links(scenario: Scenario, nodes: Sequence[tuple[str, Any]], times: NDArray,
                anchor_ids: Sequence[str], settings: LiveTraceSettings, *,
                progress: Callable[[int, int, str], None] | None = None,
                done: Callable[[str, TracedLinks, dict[str, Any]], None] | None = None,
                ) -> dict[str, TracedLinks]:
    """Trace each anchor's paths to every node at every grid time (Sionna RT).

    Parameters
    ----------
    progress : callable ``(traces done, traces in all, anchor id)``, optional
        Called after every solver call.
    done : callable ``(anchor id, links, metadata)``, optional
        Called when an anchor's trace is complete (the cache writes it then).

    Raises
    ------
    RaytraceUnavailable
        Sionna RT missing (the message says how to install it).
    """
    tracer = _Tracer(scenario, len(nodes), settings)
    total, count = len(times) * len(anchor_ids), 0
    out = {}
    for aid in anchor_ids:
        a, n = _positions(scenario, aid, nodes, times)
        t0 = time.perf_counter()
        per_epoch = []
        for e in range(len(times)):
            per_epoch.append(tracer.trace(a[e], n[e]))
            count += 1
            if progress is not None:
                progress(count, total, aid)
        arrays = _stack(per_epoch)
        links = TracedLinks(t_s=np.asarray(times, dtype=np.float64), anchor_m=a, nodes_m=n,
                            **arrays)
        meta = {"format": LIVE_FORMAT, "anchor": aid, "settings": settings.as_dict(),
                "versions": tracer.versions, "nodes": [nid for nid, _ in nodes],
                "elapsed_s": round(time.perf_counter() - t0, 3),
                "s_per_trace": round((time.perf_counter() - t0) / len(times), 4),
                "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        out[aid] = links
        if done is not None:
            done(aid, links, meta)
    return out


# ----------------------------------------------------------------------------- cache
@dataclass(frozen=True)
class Prepared:
    """The traced links of a run's anchors (:func:`prepare_links`).

    Attributes
    ----------
    links : dict of anchor id -> TracedLinks
    keys : dict of anchor id -> str
        Cache keys (:func:`cache_key`).
    files : dict of anchor id -> str
    traced : tuple of str
        Anchors traced now (the others were cache hits).
    elapsed_s : float [s]
    settings : LiveTraceSettings
    t_s : ndarray
        The grid [s].
    """

    links: dict[str, TracedLinks]
    keys: dict[str, str]
    files: dict[str, str]
    traced: tuple[str, ...]
    elapsed_s: float
    settings: LiveTraceSettings
    t_s: NDArray[np.float64]

    def record(self) -> dict[str, Any]:
        """What the run's recording keeps (run config ``emulate.raytrace``)."""
        return {"format": LIVE_FORMAT, "settings": self.settings.as_dict(),
                "grid": {"t0_s": float(self.t_s[0]), "t1_s": float(self.t_s[-1]),
                         "epochs": len(self.t_s)},
                "cache_keys": dict(self.keys), "cache_files": dict(self.files),
                "traced_now": list(self.traced), "prepare_s": round(self.elapsed_s, 2),
                "sionna": SIONNA_REQUIREMENT}


def prepare_links(scenario: Scenario, nodes: Sequence[tuple[str, Any]], *, duration_s: float,
                  settings: LiveTraceSettings, anchor_ids: Sequence[str] | None = None,
                  directory: Path | None = None,
                  progress: Callable[[int, int, str], None] | None = None) -> Prepared:
    """Each anchor's traced links for a run of ``duration_s``: from the cache, or traced now
    (and cached).

    Raises
    ------
    RaytraceUnavailable
        A trace is needed and Sionna RT is missing (the message says how to install it).
    """
    t0 = time.perf_counter()
    directory = cache_dir() if directory is None else Path(directory)
    ids = list(anchor_ids) if anchor_ids is not None else [a.id for a in scenario.anchors]
    times = grid_times(duration_s, settings.step_s)
    keys = {aid: cache_key(scenario, aid, nodes, times, settings) for aid in ids}
    files = {aid: _cache_path(directory, aid, keys[aid]) for aid in ids}
    links = {aid: load_links(files[aid], key=keys[aid])[0]
             for aid in ids if files[aid].exists()}
    missing = [aid for aid in ids if aid not in links]
    if missing:
        def done(aid: str, traced: TracedLinks, meta: dict[str, Any]) -> None:
            save_links(files[aid], traced, {**meta, "key": keys[aid]})

        links.update(trace_links(scenario, nodes, times, missing, settings, progress=progress,
                                 done=done))
    return Prepared(links=links, keys=keys, files={a: str(f) for a, f in files.items()},
                    traced=tuple(missing), elapsed_s=time.perf_counter() - t0,
                    settings=settings, t_s=times)


# ----------------------------------------------------------------------------- services
def live_settings(samples: float | None = None, depth: int | None = None,
                  step_s: float | None = None) -> LiveTraceSettings:
    """The settings of the ``--raytrace-*`` options (``None``: the default); ConfigError
    names the option out of range."""
    try:
        return LiveTraceSettings(
            samples=DEFAULT_SAMPLES if samples is None else int(samples),
            depth=DEFAULT_DEPTH if depth is None else int(depth),
            step_s=DEFAULT_STEP_S if step_s is None else float(step_s))
    except (ValueError, OverflowError) as exc:
        raise ConfigError(str(exc)) from None


class _Stopped(DiffposError):
    """The run was stopped (Ctrl-C) while tracing (caught by :func:`prepare_for_run`)."""

    exit_code = 130


class _Progress:
    """A moving bar on the status line (a terminal) and a log line every 10 %; raises
    :class:`_Stopped` once ``stop`` is set."""

    def __init__(self, log: logging.Logger | None, what: str,
                 stop: threading.Event | None = None) -> None:
        self.log, self.what, self.stop = log, what, stop
        self.t0 = time.monotonic()
        self.logged = 0

    def __call__(self, done: int, total: int, aid: str) -> None:
        if self.stop is not None and self.stop.is_set():
            raise _Stopped
        el = time.monotonic() - self.t0
        left = el / done * (total - done)
        filled = round(20 * done / total)
        STATUS.show(f"{self.what}: [{'#' * filled}{'.' * (20 - filled)}] {done}/{total} traces "
                    f"({aid}), {el:.0f} s, ~{left:.0f} s left")
        tenth = (10 * done) // total
        if self.log is not None and tenth > self.logged:
            self.logged = tenth
            log_event(self.log, logging.INFO, "ray tracing", done=done, total=total, anchor=aid,
                      elapsed_s=round(el, 1), left_s=round(left, 1))


def prepare_for_run(scenario: Scenario, nodes: Sequence[tuple[str, Any]], options: Any,
                    log: logging.Logger, stop: threading.Event | None = None
                    ) -> dict[str, Any] | None:
    """``diffpos emulate --channel raytrace``: every anchor's links of the run, traced now or
    from the cache, before any service starts; what the recording keeps about them (``None``
    when ``stop`` was set while tracing: the anchors traced by then stay cached).

    ``options``: ``duration_s``, ``raytrace_samples``, ``raytrace_depth``, ``raytrace_step_s``
    (``diffpos_services.emulate.options.EmulationOptions``).

    Raises
    ------
    RaytraceUnavailable
        A trace is needed and Sionna RT is missing (the message says how to install it).
    """
    settings = live_settings(options.raytrace_samples, options.raytrace_depth,
                             options.raytrace_step_s)
    STATUS.show("ray-traced channel: looking up the cache ...")
    try:
        prep = prepare_links(scenario, nodes, duration_s=options.duration_s, settings=settings,
                             progress=_Progress(log, "ray tracing the run's channel", stop))
    except _Stopped:
        log_event(log, logging.WARNING, "stopped while ray tracing (anchors traced so far are "
                  "cached)")
        return None
    finally:
        STATUS.show("")
    rec = prep.record()
    log_event(log, logging.INFO, "ray-traced channel ready", traced=",".join(prep.traced) or "-",
              cached=len(prep.keys) - len(prep.traced), seconds=rec["prepare_s"],
              samples=settings.samples, depth=settings.depth, step_s=settings.step_s,
              grid_times=len(prep.t_s), cache=str(cache_dir()))
    return rec


def anchor_links(scenario: Scenario, anchor_id: str, nodes: Sequence[tuple[str, Any]], *,
                 duration_s: float, samples: float | None = None, depth: int | None = None,
                 step_s: float | None = None, log: logging.Logger | None = None
                 ) -> TracedLinks:
    """One anchor's traced links (``diffpos anchor --channel raytrace``): from the cache
    (``diffpos emulate`` traced them before starting the anchor), else traced now.

    Raises
    ------
    RaytraceUnavailable
        A trace is needed and Sionna RT is missing.
    """
    settings = live_settings(samples, depth, step_s)
    prep = prepare_links(scenario, nodes, duration_s=duration_s, settings=settings,
                         anchor_ids=[anchor_id], progress=_Progress(log, f"ray tracing {anchor_id}"))
    if log is not None:
        log_event(log, logging.INFO, "ray-traced channel loaded", anchor=anchor_id,
                  traced_now=bool(prep.traced), key=prep.keys[anchor_id][:16],
                  seconds=round(prep.elapsed_s, 2))
    return prep.links[anchor_id]
