"""Independent check of the channel emulator with a real ray tracer (Sionna RT, optional extra).

The scenario's building is rebuilt as a Sionna RT scene, every anchor x receiver link is
ray traced (line of sight, specular reflection, refraction and first-order edge/wedge
diffraction), each path is classified into the paper's MPC groups 1..4 and the result is
written to a dataset file that ``diffpos reproduce --channel raytrace:FILE`` consumes instead
of the emulator (see :func:`load_dataset`, :func:`dataset_first_arrival`).

Scene (all surfaces are *thin* single-sided meshes carrying an ITU-R P.2040 radio material
with the scenario's thickness; Sionna models a wall as one surface, not as a slab):

- facade ``y = 0``: the solid wall below the first window sill and one horizontal strip
  (spandrel) between consecutive window bands; the window bands are *holes*, so the upper and
  lower window edges are free edges (they need ``edge_diffraction=True``);
- side walls ``x = x_1, x_2``, back wall ``y = depth``, floor slabs and roof ``z = floor_z``;
- interior partitions (vertical planes through all floors);
- the ground (``z = 0``, or 1 cm below the lowest anchor if one sits at ``z <= 0``).

Every surface is extended by ``overlap_m`` (5 cm) past each junction, so walls *cross* instead
of merely meeting: surfaces that only touch leak diffracted paths through their free edges.
The partitions are extended too, so they protrude ``overlap_m`` through the window plane.
Windows are open (the paper: plain glass with negligible loss); ``glass_loss_db`` is not
applied. Transmitters are short dipoles along ``radio.polarization`` (Sionna's dipole pattern
minus its 1.76 dBi directivity, i.e. the emulator's normalisation); receivers are isotropic and
dual-polarised (the power of both polarisations is summed), as in the emulator.

Path classification (paper, Table "MPC through the windows"), from Sionna's per-interaction
bit flags (1 specular, 2 diffuse, 4 refraction/transmission, 8 diffraction):

=====  ===========================================  ======================================
group  chains                                       rule
=====  ===========================================  ======================================
1      ``Tx-Rx``, ``Tx-T-Rx``, ...                  no reflection, no diffraction
2      ``Tx-R-Rx`` (also with transmissions)        exactly one reflection, no diffraction
3      ``Tx-D-Rx``, ``Tx-D-T-Rx``, ``Tx-D-T-T-Rx``  diffraction first, then transmissions only
4      everything else                              ``Tx-R-R-..``, ``Tx-D-R-..``, ``Tx-T-D-..``
=====  ===========================================  ======================================

First arrival (paper's definition, identical to :func:`diffpos.channel.first_arrival`): the
path with the smallest delay among those with ``SNR >= max(P_max - fap_threshold_db,
detection_snr_db)``, SNR = received power + processing gain - kTB.

Known limits of the ray tracer (measured, see docs/raytrace.md): no corner (vertex)
diffraction and first-order diffraction only; transmissions are sampled in proportion to the
transmitted energy, so paths through concrete (about -90 dB per wall, -136 dB per slab) are
found only now and then (harmless: far below the first-arrival threshold), and diffraction
paths that then cross partitions (``Tx-D-T-Rx``) are found only partly at 1e5 samples; the
LLVM backend needs Debian's ``libllvm19`` (LLVM 14 is refused, LLVM 15 aborts).

Dataset file (``numpy.savez_compressed``; N receivers, M anchors, K paths per link, padded;
paths of a link are sorted by delay, the padding has ``path_valid == False``):

=====================  ==============  ======================================================
array                  shape, dtype    meaning
=====================  ==============  ======================================================
``nodes_m``            (N, 3) f8       receiver positions [m]
``anchors_m``          (M, 3) f8       anchor (transmitter) positions [m]
``anchor_ids``         (M,) str        anchor ids
``path_valid``         (N, M, K) bool  a path (before any power threshold)
``path_length_m``      (N, M, K) f8    ``c tau`` [m] (NaN where not valid)
``path_gain_db``       (N, M, K) f4    ``10 log10 sum |a|^2`` over both receive polarisations,
                                       isotropic receiver, 0 dBi dipole transmitter [dB]
``path_aod_deg``       (N, M, K) f4    departure zenith angle at the anchor [deg]
``path_aoa_deg``       (N, M, K) f4    arrival zenith angle (towards the last interaction)
                                       [deg]; 90 = horizontal
``path_chain``         (N, M, K) u2    interaction flags, 4 bits per depth (depth 0 in bits
                                       0-3), see :func:`chain_label`
``path_class``         (N, M, K) i1    MPC group 1..4 (0 = padding)
``path_vertex_m``      (N, M, K, 3) f4 first interaction point (NaN for ``Tx-Rx``) [m]
``metadata_json``      () str          JSON: format, scenario (as a dict), solver settings,
                                       versions, run time, the scene surfaces
=====================  ==============  ======================================================

Powers are *not* stored: SNRs are recomputed from ``path_gain_db`` with the scenario's radio
(:func:`path_snr_db`), so a dataset can be re-evaluated for another transmit power or
threshold without re-tracing.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.channel import MECHANISMS, Channel, FirstArrival, first_arrival
from diffpos.constants import SPEED_OF_LIGHT_M_S
from diffpos.geometry import diffraction_point
from diffpos.linkbudget import noise_floor_dbm
from diffpos.scenario import Building, Radio, Scenario

__all__ = [
    "DATASET_FORMAT",
    "DEFAULT_LLVM_PATH",
    "INSTALL_HINT",
    "RaytraceDataset",
    "RaytraceSettings",
    "RaytraceUnavailable",
    "Surface",
    "build_scene",
    "building_surfaces",
    "chain_label",
    "check_sionna",
    "classify_chains",
    "compare_with_emulator",
    "dataset_channel",
    "dataset_first_arrival",
    "dataset_mpc_statistics",
    "edge_fermat_check",
    "encode_chains",
    "load_dataset",
    "save_dataset",
    "trace",
]

DATASET_FORMAT = "diffpos-raytrace/1"
DEFAULT_LLVM_PATH = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
SIONNA_REQUIREMENT = "sionna-rt==2.2.0"
VARIANT = "llvm_ad_mono_polarized"
INSTALL_HINT = (
    "the ray tracer is an optional extra. Install it with\n"
    "    pip install -e '.[raytrace]'          (sionna-rt 2.2.0, about 350 MB)\n"
    "    apt-get install libllvm19             (Dr.Jit's CPU backend; LLVM 14/15 do not work)\n"
    f"and, if libLLVM is not at {DEFAULT_LLVM_PATH}, point DRJIT_LIBLLVM_PATH at it."
)

#: Sionna's interaction flags.
SPECULAR, DIFFUSE, REFRACTION, DIFFRACTION = 1, 2, 4, 8
_LETTER = {SPECULAR: "R", DIFFUSE: "S", REFRACTION: "T", DIFFRACTION: "D"}
#: 10 log10 of the short dipole's directivity (Sionna's dipole pattern includes it).
_DIPOLE_DB = 10.0 * math.log10(1.5)
_C = SPEED_OF_LIGHT_M_S


class RaytraceUnavailable(RuntimeError):
    """Sionna RT or its LLVM backend is missing; the message says how to install it."""


# --------------------------------------------------------------------------------------------
# availability
# --------------------------------------------------------------------------------------------


def check_sionna() -> dict[str, str]:
    """Import Sionna RT with the LLVM variant, or explain how to install it.

    Sets ``DRJIT_LIBLLVM_PATH`` to :data:`DEFAULT_LLVM_PATH` if it is unset and that file
    exists (Debian's ``libllvm19``).

    Returns
    -------
    dict
        Versions: ``{"sionna-rt": ..., "mitsuba": ..., "drjit": ..., "libllvm": path}``.

    Raises
    ------
    RaytraceUnavailable
        With an installation hint naming what is missing.
    """
    if "DRJIT_LIBLLVM_PATH" not in os.environ and Path(DEFAULT_LLVM_PATH).exists():
        os.environ["DRJIT_LIBLLVM_PATH"] = DEFAULT_LLVM_PATH
    try:
        import drjit  # noqa: F401
        import mitsuba as mi
    except ImportError as exc:
        raise RaytraceUnavailable(f"sionna-rt is not installed ({exc}): {INSTALL_HINT}") from None
    llvm = os.environ.get("DRJIT_LIBLLVM_PATH", "")
    try:
        mi.set_variant(VARIANT)
    except Exception as exc:  # Dr.Jit raises ImportError/RuntimeError/AttributeError here
        where = f"DRJIT_LIBLLVM_PATH={llvm}" if llvm else "no DRJIT_LIBLLVM_PATH set"
        raise RaytraceUnavailable(
            f"Mitsuba could not start its LLVM backend ({where}): {exc}. {INSTALL_HINT}"
        ) from None
    import drjit as dr

    try:
        llvm_version = tuple(dr.detail.llvm_version())
    except Exception:  # pragma: no cover - older Dr.Jit without the query
        llvm_version = ()
    if llvm_version and llvm_version[0] <= 15:
        # LLVM 14 is refused by Dr.Jit, LLVM 15 loads but aborts the process on the first solve
        raise RaytraceUnavailable(
            f"Dr.Jit loaded LLVM {'.'.join(map(str, llvm_version))} "
            f"({llvm or 'found on the library path'}), which crashes the ray tracer; "
            f"{INSTALL_HINT}")
    try:
        import sionna.rt as rt
    except Exception as exc:
        raise RaytraceUnavailable(f"sionna.rt failed to import ({exc}): {INSTALL_HINT}") from None

    return {"sionna-rt": str(getattr(rt, "__version__", "?")), "mitsuba": mi.__version__,
            "drjit": dr.__version__, "libllvm": llvm, "variant": VARIANT,
            "llvm": ".".join(map(str, llvm_version))}


# --------------------------------------------------------------------------------------------
# scene geometry (pure numpy)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Surface:
    """One thin scene object: a union of axis-aligned rectangles with one radio material.

    Attributes
    ----------
    name : str
    material : str
        ITU-R P.2040 material name (Sionna ``itu_type``).
    thickness_m : float [m]
    rects : tuple of (axis, coord, (lo_u, hi_u), (lo_v, hi_v))
        Rectangle in the plane ``p[axis] = coord``; ``u``, ``v`` are the two other axes in
        increasing order (for axis 1, u = x and v = z) [m].
    """

    name: str
    material: str
    thickness_m: float
    rects: tuple[tuple[int, float, tuple[float, float], tuple[float, float]], ...]

    def mesh(self) -> tuple[NDArray[np.float64], NDArray[np.uint32]]:
        """Vertices ``(4 R, 3)`` [m] and triangles ``(2 R, 3)`` of the rectangles."""
        verts, faces = [], []
        for i, (axis, c, (u0, u1), (v0, v1)) in enumerate(self.rects):
            u_ax, v_ax = [a for a in range(3) if a != axis]
            quad = np.zeros((4, 3))
            quad[:, axis] = c
            quad[:, u_ax] = [u0, u1, u1, u0]
            quad[:, v_ax] = [v0, v0, v1, v1]
            verts.append(quad)
            b = 4 * i
            faces += [(b, b + 1, b + 2), (b, b + 2, b + 3)]
        return np.concatenate(verts), np.asarray(faces, dtype=np.uint32)


def building_surfaces(
    building: Building,
    anchors_m: ArrayLike,
    *,
    overlap_m: float = 0.05,
    ground_margin_m: float = 30.0,
) -> list[Surface]:
    """The scene of :func:`build_scene` as plain rectangles (see the module docstring).

    Parameters
    ----------
    building : Building
    anchors_m : array_like, shape (M, 3) [m]
        Used for the extent and height of the ground.
    overlap_m : float [m]
        How far each surface runs past the surfaces it meets.
    ground_margin_m : float [m]
        Ground extends this far beyond the anchors and the building.

    Returns
    -------
    list of Surface
    """
    b = building
    a = np.atleast_2d(np.asarray(anchors_m, dtype=np.float64))
    ov = float(overlap_m)
    x0, x1 = b.edge_x_m
    depth, top = b.depth_m, b.top_z_m
    ground_z = min(0.0, float(a[:, 2].min()) - 0.01)
    xa0, xa1 = x0 - ov, x1 + ov
    # facade: solid below the first sill, spandrels between window bands, parapet above
    lo, hi = b.window_z_m(np.arange(b.n_floors))
    bands = [(ground_z - ov, float(lo[0]))]
    bands += [(float(hi[k]), float(lo[k + 1])) for k in range(b.n_floors - 1)]
    bands.append((float(hi[-1]), top + ov))
    facade = tuple((1, 0.0, (xa0, xa1), band) for band in bands if band[1] > band[0])
    walls = (
        (0, x0, (-ov, depth + ov), (ground_z - ov, top + ov)),
        (0, x1, (-ov, depth + ov), (ground_z - ov, top + ov)),
        (1, depth, (xa0, xa1), (ground_z - ov, top + ov)),
    )
    slabs = tuple((2, float(z), (xa0, xa1), (-ov, depth + ov))
                  for z in b.floor_z_m(np.arange(b.n_floors + 1)))
    g = ground_margin_m
    ground = ((2, ground_z, (min(x0, a[:, 0].min()) - g, max(x1, a[:, 0].max()) + g),
               (float(a[:, 1].min()) - g, depth + ov)),)
    out = [
        Surface("facade", b.wall_material, b.wall_thickness_m, facade),
        Surface("walls", b.wall_material, b.wall_thickness_m, walls),
        Surface("slabs", b.slab_material, b.slab_thickness_m, slabs),
        Surface("ground", b.ground_material, 0.5, ground),
    ]
    z_span = (float(b.first_floor_z_m) - ov, top + ov)
    for i, p in enumerate(b.partitions):
        span = (p.span_m[0] - ov, p.span_m[1] + ov)
        rect = (0, p.position_m, span, z_span) if p.axis == "x" else (1, p.position_m, span,
                                                                       z_span)
        out.append(Surface(f"partition{i}", p.material, p.thickness_m, (rect,)))
    return out


# --------------------------------------------------------------------------------------------
# path classification (pure numpy)
# --------------------------------------------------------------------------------------------


def encode_chains(interactions: ArrayLike) -> NDArray[np.uint16]:
    """Pack per-depth interaction flags ``(D, ...)`` into one code per path (4 bits/depth).

    Parameters
    ----------
    interactions : array_like of int, shape (D, ...)
        Sionna's ``paths.interactions`` (0 = none, 1 R, 2 diffuse, 4 T, 8 D), ``D <= 4``.

    Returns
    -------
    ndarray of uint16, shape (...)
    """
    it = np.asarray(interactions).astype(np.uint16)
    if it.shape[0] > 4:
        raise ValueError("at most 4 interactions per path fit in a uint16 chain code")
    code = np.zeros(it.shape[1:], dtype=np.uint16)
    for d in range(it.shape[0]):
        code |= (it[d] & 0xF) << np.uint16(4 * d)
    return code


def _decode(code: NDArray[np.uint16]) -> list[NDArray[np.uint16]]:
    return [(code >> np.uint16(4 * d)) & np.uint16(0xF) for d in range(4)]


def chain_label(code: int) -> str:
    """Human-readable chain, e.g. ``0x48`` -> ``"Tx-D-T-Rx"`` (``S`` = diffuse)."""
    letters = [_LETTER.get(int(f), "?") for f in _decode(np.uint16(code)) if int(f)]
    return "-".join(["Tx", *letters, "Rx"])


def classify_chains(code: ArrayLike) -> NDArray[np.int8]:
    """MPC group 1..4 of chain codes (module docstring table).

    Parameters
    ----------
    code : array_like of uint16
        From :func:`encode_chains`.

    Returns
    -------
    ndarray of int8
        Same shape as ``code``.
    """
    c = np.asarray(code, dtype=np.uint16)
    flags = _decode(c)
    n_r = sum(((f == SPECULAR) | (f == DIFFUSE)).astype(np.int8) for f in flags)
    n_d = sum((f == DIFFRACTION).astype(np.int8) for f in flags)
    n_other = sum(((f != 0) & (f != REFRACTION) & (f != SPECULAR) & (f != DIFFUSE)
                   & (f != DIFFRACTION)).astype(np.int8) for f in flags)
    d_first = flags[0] == DIFFRACTION
    cls = np.full(c.shape, 4, dtype=np.int8)
    cls = np.where((n_r == 0) & (n_d == 0), 1, cls)
    cls = np.where((n_r == 1) & (n_d == 0), 2, cls)
    cls = np.where((n_r == 0) & (n_d == 1) & d_first, 3, cls)
    return np.where(n_other > 0, 4, cls).astype(np.int8)


# --------------------------------------------------------------------------------------------
# the Sionna scene and the solver
# --------------------------------------------------------------------------------------------


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


def build_scene(scenario: Scenario, *, overlap_m: float = 0.05) -> Any:
    """The scenario's building as a ``sionna.rt.Scene`` (requires the optional extra).

    Returns
    -------
    sionna.rt.Scene
        With the carrier frequency, the dipole transmit array and the dual-polarised
        isotropic receive array set; no transmitters or receivers yet.

    Raises
    ------
    RaytraceUnavailable
        If Sionna RT cannot be imported.
    ValueError
        If a material is undefined at the carrier (Sionna's ITU table).
    """
    check_sionna()
    import mitsuba as mi
    import sionna.rt as rt

    b, r = scenario.building, scenario.radio
    scene = rt.load_scene()
    scene.frequency = float(r.frequency_hz)
    scene.bandwidth = float(r.bandwidth_hz)
    materials: dict[tuple[str, float], Any] = {}
    objects = []
    for s in building_surfaces(b, scenario.anchor_positions_m(), overlap_m=overlap_m):
        key = (s.material, float(s.thickness_m))
        if key not in materials:
            materials[key] = rt.ITURadioMaterial(f"{s.material}-{len(materials)}", s.material,
                                                 thickness=float(s.thickness_m))
        v, f = s.mesh()
        mesh = mi.Mesh(s.name, len(v), len(f), has_vertex_normals=False,
                       has_vertex_texcoords=False)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(v.astype(np.float32).ravel())
        params["faces"] = mi.UInt32(f.ravel())
        params.update()
        objects.append(rt.SceneObject(mi_mesh=mesh, name=s.name, radio_material=materials[key]))
    try:
        scene.edit(add=objects)
    except Exception as exc:
        raise ValueError(f"Sionna could not build the scene at {r.frequency_hz / 1e9:g} GHz: "
                         f"{exc} (check the building's materials)") from None
    scene.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="dipole", polarization="V")
    scene.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="VH")
    return scene


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
        verts = np.asarray(paths.vertices, dtype=np.float32)[0, :, 0, :, :]  # (R, P, 3)
        theta_t = np.asarray(paths.theta_t, dtype=np.float64)[:, 0, :]
        theta_r = np.asarray(paths.theta_r, dtype=np.float64)[:, 0, :]
    finally:
        for name in names:
            scene.remove(name)
    chain = encode_chains(inter)
    verts = np.where((chain != 0)[..., None], verts, np.nan).astype(np.float32)
    with np.errstate(divide="ignore"):
        gain_db = 10.0 * np.log10(power) - _DIPOLE_DB
    return {"valid": valid & np.isfinite(tau) & (power > 0), "length": tau * _C,
            "gain_db": gain_db, "chain": chain, "vertex": verts,
            "aod": np.degrees(theta_t), "aoa": np.degrees(theta_r)}


def _pack(batches: list[dict[str, NDArray]]) -> dict[str, NDArray]:
    """Sort the valid paths of each link by delay and pad to a common K."""
    k = max(int(bt["valid"].sum(axis=1).max(initial=0)) for bt in batches)
    k = max(k, 1)
    out: dict[str, list[NDArray]] = {n: [] for n in ("valid", "length", "gain_db", "chain",
                                                     "vertex", "aod", "aoa")}
    for bt in batches:
        key = np.where(bt["valid"], bt["length"], np.inf)
        order = np.argsort(key, axis=1, kind="stable")
        take = lambda a, o=order: np.take_along_axis(  # noqa: E731
            a, o if a.ndim == 2 else o[..., None], axis=1)
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
    import mitsuba as mi
    import sionna.rt as rt

    nodes = (scenario.node_positions_m() if nodes_m is None
             else np.atleast_2d(np.asarray(nodes_m, dtype=np.float64)))
    if nodes.ndim != 2 or nodes.shape[1] != 3 or len(nodes) == 0:
        raise ValueError(f"nodes_m: expected shape (N, 3) with N >= 1, got {nodes.shape}")
    bad = ~scenario.building.inside(nodes)
    if np.any(bad):
        raise ValueError(f"nodes_m: {int(bad.sum())} receiver(s) outside the building's floors, "
                         f"e.g. {nodes[bad][0].tolist()}")
    anchors = scenario.anchor_positions_m()
    t0 = time.perf_counter()
    scene = build_scene(scenario, overlap_m=settings.overlap_m)
    solver = rt.PathSolver(deterministic=settings.deterministic)
    yaw, pitch, roll = _dipole_orientation(scenario.radio.polarization)
    per_anchor = []
    total, done = len(nodes) * len(anchors), 0
    timings = []
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
    steady = [t for n_, t in timings[1:]] or [timings[0][1]]
    n_steady = [n_ for n_, _ in timings[1:]] or [timings[0][0]]
    metadata = {
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
    return RaytraceDataset(
        nodes_m=nodes, anchors_m=anchors, anchor_ids=tuple(scenario.anchor_ids),
        path_valid=arrays["valid"], path_length_m=arrays["length"],
        path_gain_db=arrays["gain_db"].astype(np.float32),
        path_aod_deg=arrays["aod"].astype(np.float32),
        path_aoa_deg=arrays["aoa"].astype(np.float32),
        path_chain=arrays["chain"].astype(np.uint16),
        path_class=np.where(arrays["valid"], classify_chains(arrays["chain"]), 0).astype(np.int8),
        path_vertex_m=arrays["vertex"].astype(np.float32), metadata=metadata,
    )


# --------------------------------------------------------------------------------------------
# the dataset
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RaytraceDataset:
    """Ray-traced paths of every receiver x anchor link (module docstring: array table).

    Attributes
    ----------
    nodes_m : ndarray, shape (N, 3) [m]
    anchors_m : ndarray, shape (M, 3) [m]
    anchor_ids : tuple of str
    path_valid : ndarray of bool, shape (N, M, K)
    path_length_m : ndarray, shape (N, M, K) [m]
    path_gain_db : ndarray, shape (N, M, K) [dB]
    path_aod_deg, path_aoa_deg : ndarray, shape (N, M, K) [deg]
    path_chain : ndarray of uint16, shape (N, M, K)
    path_class : ndarray of int8, shape (N, M, K)
    path_vertex_m : ndarray, shape (N, M, K, 3) [m]
    metadata : dict
    """

    nodes_m: NDArray[np.float64]
    anchors_m: NDArray[np.float64]
    anchor_ids: tuple[str, ...]
    path_valid: NDArray[np.bool_]
    path_length_m: NDArray[np.float64]
    path_gain_db: NDArray[np.float32]
    path_aod_deg: NDArray[np.float32]
    path_aoa_deg: NDArray[np.float32]
    path_chain: NDArray[np.uint16]
    path_class: NDArray[np.int8]
    path_vertex_m: NDArray[np.float32]
    metadata: dict[str, Any]

    @property
    def scenario(self) -> Scenario:
        """The scenario the dataset was traced for (from the metadata)."""
        return Scenario.from_dict(self.metadata["scenario"])

    def subset(self, nodes: ArrayLike) -> RaytraceDataset:
        """The dataset restricted to receivers ``nodes`` (indices or a boolean mask)."""
        idx = np.asarray(nodes)
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for name, v in fields.items():
            if name.startswith("path_") or name == "nodes_m":
                fields[name] = v[idx]
        return RaytraceDataset(**fields)


_ARRAYS = ("nodes_m", "anchors_m", "path_valid", "path_length_m", "path_gain_db", "path_aod_deg",
           "path_aoa_deg", "path_chain", "path_class", "path_vertex_m")


def save_dataset(path: str | os.PathLike[str], ds: RaytraceDataset) -> Path:
    """Write ``ds`` to ``path`` (``.npz``, compressed); returns the path written."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    arrays = {n: getattr(ds, n) for n in _ARRAYS}
    with p.open("wb") as f:
        np.savez_compressed(f, anchor_ids=np.asarray(ds.anchor_ids, dtype=str),
                            metadata_json=np.asarray(json.dumps(ds.metadata)), **arrays)
    return p


def load_dataset(path: str | os.PathLike[str], *, scenario: Scenario | None = None
                 ) -> RaytraceDataset:
    """Read a dataset written by :func:`save_dataset` / ``diffpos raytrace``.

    Parameters
    ----------
    path : path-like
    scenario : Scenario, optional
        If given, its anchors must match the dataset's (the ray trace is only valid for the
        geometry it was computed for) and its building must be the traced one.

    Raises
    ------
    ValueError
        Not a dataset, wrong format version, inconsistent shapes, or a scenario mismatch; the
        message names the file and the problem.
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{p}: no such ray-trace dataset (create it with 'diffpos raytrace')")
    try:
        with np.load(p, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:
        raise ValueError(f"{p}: not a readable .npz ray-trace dataset ({exc})") from None
    missing = [n for n in (*_ARRAYS, "anchor_ids", "metadata_json") if n not in data]
    if missing:
        raise ValueError(f"{p}: not a diffpos ray-trace dataset (missing {', '.join(missing)})")
    meta = json.loads(str(data["metadata_json"]))
    if meta.get("format") != DATASET_FORMAT:
        raise ValueError(f"{p}: format {meta.get('format')!r}, expected {DATASET_FORMAT!r}")
    ds = RaytraceDataset(anchor_ids=tuple(str(s) for s in data["anchor_ids"]), metadata=meta,
                         **{n: data[n] for n in _ARRAYS})
    n, m = len(ds.nodes_m), len(ds.anchors_m)
    for name in _ARRAYS[2:]:
        if getattr(ds, name).shape[:2] != (n, m):
            raise ValueError(f"{p}: {name} has shape {getattr(ds, name).shape}, expected "
                             f"({n}, {m}, K)")
    if scenario is not None:
        a = scenario.anchor_positions_m()
        if a.shape != ds.anchors_m.shape or not np.allclose(a, ds.anchors_m, atol=1e-6):
            raise ValueError(f"{p}: traced for anchors {ds.anchors_m.tolist()}, but the scenario "
                             f"has {a.tolist()}; re-run 'diffpos raytrace' for this scenario")
        if scenario.building != ds.scenario.building:
            raise ValueError(f"{p}: traced for a different building than the scenario's; "
                             "re-run 'diffpos raytrace' for this scenario")
    return ds


# --------------------------------------------------------------------------------------------
# evaluation: SNR, first arrival, statistics, comparison
# --------------------------------------------------------------------------------------------


def _pattern_db(zenith_deg: NDArray, hpbw_deg: float | None, peak_deg: float) -> NDArray:
    if hpbw_deg is None:
        return np.zeros(np.shape(zenith_deg))
    return -np.minimum(12.0 * ((zenith_deg - peak_deg) / hpbw_deg) ** 2, 30.0)


def path_snr_db(ds: RaytraceDataset, radio: Radio) -> NDArray[np.float64]:
    """SNR of every path with ``radio``'s link budget (same formula as the emulator) [dB].

    ``P_tx + G_tx + G_rx + pattern_tx(aod) + pattern_rx(aoa) + path gain + processing gain -
    kTB``; ``-inf`` for padding.
    """
    r = radio
    n0 = float(noise_floor_dbm(r.bandwidth_hz, temperature_k=r.noise_temperature_k,
                               noise_figure_db=r.noise_figure_db))
    aod = ds.path_aod_deg.astype(np.float64)
    aoa = ds.path_aoa_deg.astype(np.float64)
    snr = (r.tx_power_dbm + r.tx_gain_dbi + r.rx_gain_dbi + ds.path_gain_db.astype(np.float64)
           + _pattern_db(aod, r.tx_hpbw_deg, r.tx_peak_deg)
           + _pattern_db(aoa, r.rx_hpbw_deg, r.rx_peak_deg) + r.processing_gain_db - n0)
    return np.where(ds.path_valid, snr, -np.inf)


def dataset_channel(ds: RaytraceDataset, radio: Radio) -> Channel:
    """The ray-traced paths as a :class:`diffpos.channel.Channel` (K = paths per link).

    ``mpc_class`` of the returned channel is a placeholder (the group varies per link); use
    ``ds.path_class`` or :func:`dataset_first_arrival`. Phases are not stored (gain is real).
    """
    snr = path_snr_db(ds, radio)
    n0 = float(noise_floor_dbm(radio.bandwidth_hz, temperature_k=radio.noise_temperature_k,
                               noise_figure_db=radio.noise_figure_db))
    valid = ds.path_valid
    k = valid.shape[-1]
    gain = np.where(valid, 10.0 ** (ds.path_gain_db.astype(np.float64) / 20.0), 0.0)
    return Channel(
        delay_s=ds.path_length_m / _C, length_m=ds.path_length_m, gain=gain.astype(np.complex128),
        power_dbm=np.where(valid, snr - radio.processing_gain_db + n0, -np.inf), snr_db=snr,
        aod_deg=ds.path_aod_deg.astype(np.float64), aoa_deg=ds.path_aoa_deg.astype(np.float64),
        valid=valid, exists=valid & (snr >= radio.detection_snr_db),
        mpc_class=np.zeros(k, dtype=np.int8), mechanism=tuple(f"path{i}" for i in range(k)),
        nodes_m=ds.nodes_m, anchors_m=ds.anchors_m,
    )


def dataset_first_arrival(
    ds: RaytraceDataset,
    *,
    radio: Radio | None = None,
    rng: np.random.Generator | None = None,
) -> FirstArrival:
    """First-arriving path and measured range per link, from the ray-traced paths.

    Uses :func:`diffpos.channel.first_arrival` (same detector, same noise model and random
    stream as the emulator) on :func:`dataset_channel`; ``mpc_class`` is the ray-traced group
    of the selected path and ``slot`` its index in the link's path list.

    Parameters
    ----------
    ds : RaytraceDataset
    radio : Radio, optional
        Link budget and detector; default the traced scenario's radio.
    rng : numpy.random.Generator, optional
        Range noise; ``None`` gives noise-free ranges.

    Returns
    -------
    diffpos.channel.FirstArrival
        Arrays of shape (N, M) that the positioning study consumes like the emulator's.
    """
    radio = radio or ds.scenario.radio
    fap = first_arrival(dataset_channel(ds, radio), radio=radio, rng=rng)
    slot = np.maximum(fap.slot, 0)
    cls = np.take_along_axis(ds.path_class, slot[..., None], axis=-1)[..., 0]
    return dataclasses.replace(fap, mpc_class=np.where(fap.detected, cls, 0).astype(np.int8))


def dataset_mpc_statistics(ds: RaytraceDataset, fap: FirstArrival, *,
                           radio: Radio | None = None) -> dict[str, dict[str, float]]:
    """The paper's ``P_e`` / ``P_fap`` table from the ray trace (same keys as
    :func:`diffpos.channel.mpc_statistics`) [%]."""
    radio = radio or ds.scenario.radio
    exists = ds.path_valid & (path_snr_db(ds, radio) >= radio.detection_snr_db)
    pairs = exists.shape[0] * exists.shape[1]
    out: dict[str, dict[str, float]] = {}
    for g in (1, 2, 3, 4):
        pe = np.any(exists & (ds.path_class == g), axis=-1).sum()
        out[f"MPC-{g}"] = {"P_e": 100.0 * pe / pairs,
                           "P_fap": 100.0 * np.sum(fap.mpc_class == g) / pairs}
    out["none"] = {"P_fap": 100.0 * np.sum(~fap.detected) / pairs}
    return out


def edge_fermat_check(ds: RaytraceDataset, *, tol_m: float = 0.02) -> dict[str, NDArray]:
    """Ray-traced single-diffraction paths over a horizontal window edge vs the Fermat length.

    Selects every valid path whose chain is a diffraction followed only by transmissions
    (group 3) and whose diffraction point lies on a horizontal window edge (``y = 0``,
    ``z`` within ``tol_m`` of a window edge height, strictly inside the edge's x-extent), and
    computes the analytic length with :func:`diffpos.geometry.diffraction_point` for that
    edge.

    Returns
    -------
    dict
        ``index`` (P, 3) int (node, anchor, path), ``traced_m``, ``analytic_m``, ``error_m``
        (traced - analytic) [m], ``edge`` ("upper"/"lower" as 1/0), ``same_floor`` (edge on
        the receiver's floor), ``on_edge`` (the analytic point is inside the edge).
    """
    b = ds.scenario.building
    lo, hi = b.window_z_m(np.arange(b.n_floors))
    heights = np.concatenate([lo, hi])
    v = ds.path_vertex_m.astype(np.float64)
    sel = ds.path_valid & (ds.path_class == 3)
    dz = np.abs(v[..., 2][..., None] - heights)
    near = np.nanmin(np.where(np.isfinite(dz), dz, np.inf), axis=-1) < tol_m
    x0, x1 = b.edge_x_m
    sel &= near & (np.abs(v[..., 1]) < tol_m) & (v[..., 0] > x0 + tol_m) & (v[..., 0] < x1 - tol_m)
    idx = np.argwhere(sel)
    if len(idx) == 0:
        empty = np.zeros(0)
        return {"index": idx, "traced_m": empty, "analytic_m": empty, "error_m": empty,
                "edge": empty.astype(int), "same_floor": empty.astype(bool),
                "on_edge": empty.astype(bool)}
    n, m, k = idx.T
    z_edge = heights[np.argmin(np.abs(v[n, m, k, 2][:, None] - heights), axis=1)]
    p0 = np.stack([np.full(len(n), x0), np.zeros(len(n)), z_edge], axis=-1)
    p1 = np.stack([np.full(len(n), x1), np.zeros(len(n)), z_edge], axis=-1)
    dp = diffraction_point(ds.anchors_m[m], ds.nodes_m[n], p0, p1)
    edge_floor = b.floor_index(z_edge - b.sill_height_m + 1e-6)
    is_upper = np.isin(z_edge, hi)
    traced = ds.path_length_m[n, m, k]
    return {"index": idx, "traced_m": traced, "analytic_m": dp.length_m,
            "error_m": traced - dp.length_m, "edge": is_upper.astype(int),
            "same_floor": edge_floor == b.floor_index(ds.nodes_m[n, 2]),
            "on_edge": dp.on_edge}


def compare_with_emulator(ds: RaytraceDataset, *, radio: Radio | None = None) -> dict[str, Any]:
    """First-arrival agreement of the emulator and the ray tracer on the same receivers.

    Runs :func:`diffpos.channel.emulate_channel` for the dataset's receivers and anchors and
    compares the noise-free first arrivals.

    Returns
    -------
    dict
        ``links``; ``class_agreement`` (fraction of links with the same first-arrival group,
        undetected = group 0); ``found_emulator_fap`` (fraction of the emulator's detected
        first-arrival paths that the ray tracer has too, same length to 1 mm) and
        ``class_agreement_found`` (group agreement on those links); ``confusion`` (5 x 5 counts, rows emulator group 0..4, columns
        ray tracer); ``both_mpc3`` (links where both first arrivals are group 3);
        ``path_diff_m`` (ray tracer - emulator first-arrival length on those links, array);
        ``path_diff_all_m`` (on every link detected by both, array); ``stats_emulator`` and
        ``stats_raytrace`` (P_e / P_fap tables); ``fermat`` (:func:`edge_fermat_check`
        summary: count, max and 99th-percentile |error| [m]).
    """
    from diffpos.channel import emulate_channel, mpc_statistics

    scenario = ds.scenario
    radio = radio or scenario.radio
    ch = emulate_channel(ds.anchors_m, ds.nodes_m, building=scenario.building, radio=radio)
    fe = first_arrival(ch, radio=radio)
    fr = dataset_first_arrival(ds, radio=radio)
    conf = np.zeros((5, 5), dtype=int)
    np.add.at(conf, (fe.mpc_class.ravel(), fr.mpc_class.ravel()), 1)
    both3 = (fe.mpc_class == 3) & (fr.mpc_class == 3)
    both = fe.detected & fr.detected
    fc = edge_fermat_check(ds)
    err = np.abs(fc["error_m"])
    dmin = np.where(ds.path_valid, np.abs(ds.path_length_m - fe.true_path_m[..., None]),
                    np.inf).min(axis=-1)
    found = fe.detected & (dmin < 1e-3)
    return {
        "found_emulator_fap": float(found.sum() / max(fe.detected.sum(), 1)),
        "class_agreement_found": float(np.mean((fe.mpc_class == fr.mpc_class)[found]))
        if found.any() else float("nan"),
        "links": int(fe.mpc_class.size),
        "class_agreement": float(np.mean(fe.mpc_class == fr.mpc_class)),
        "confusion": conf,
        "both_mpc3": int(both3.sum()),
        "path_diff_m": (fr.true_path_m - fe.true_path_m)[both3],
        "path_diff_all_m": (fr.true_path_m - fe.true_path_m)[both],
        "emulator_mechanism": np.asarray(MECHANISMS, dtype=object),
        "fap_emulator": fe,
        "fap_raytrace": fr,
        "stats_emulator": mpc_statistics(ch, fe),
        "stats_raytrace": dataset_mpc_statistics(ds, fr, radio=radio),
        "fermat": {"count": int(err.size),
                   "max_abs_m": float(err.max()) if err.size else float("nan"),
                   "p99_abs_m": float(np.percentile(err, 99)) if err.size else float("nan")},
    }
