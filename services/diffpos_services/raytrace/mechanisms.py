"""Ray-traced paths -> the first-arrival mechanisms of :mod:`diffpos.paths.model` (pure numpy).

Every interaction of a traced path (its flag from ``path_chain`` and its point from
``path_vertices_m``) is named by the surface or edge it lies on, with the scene's geometry
(:func:`diffpos_services.raytrace.scene.building_surfaces` builds the same planes):

=================  ==========================================================================
token              interaction
=================  ==========================================================================
``D(upper)``       diffraction on the facade (``y = 0``) at the upper window edge height of
``D(lower)``       the receiver's floor (lower edge), strictly between the edge ends
``R(floor)``       specular reflection on the receiver floor's floor / ceiling plane, its back
``R(ceiling)``     wall (``y = depth``), its side walls (``x = x0``, ``x1``), inside the
``R(back)``, ...   building; ``R(ground)``: on the ground outside (``y < 0``)
``T(partition)``   transmission through an interior partition: dropped (a thin slab does not
                   bend the ray, so it does not change the path length)
anything else      e.g. ``D(edge floor+1)`` (a window edge of another floor), ``D(vertical)``
                   (a vertical wall edge), ``T(concrete)`` (through the facade or a slab),
                   ``R(facade)`` (outside of the facade), ``R(partition)``, ``S`` (diffuse)
=================  ==========================================================================

The tokens joined (``Tx-D(lower)-R(ceiling)-Rx``) are the mechanism's label; a label of the
mechanism set (``mechanisms=``, a :class:`diffpos.paths.mechanisms.MechanismSet`; default the
18 of :data:`diffpos.paths.mechanisms.MECHANISMS`) gives its slot, every other label is "other"
and is reported by name (e.g. the triple bounce ``Tx-R(ceiling)-R(floor)-R(ceiling)-Rx``, which
the 18 leave out and ``mechanism_set(3)`` has). :func:`mechanism_length_check` then compares
every classified path's traced length with the model's closed-form length for that mechanism
on the receiver's floor.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from diffpos.paths.mechanisms import MechanismSet, mechanism_set
from diffpos.paths.model import first_arrival_paths, graded_paths
from diffpos.scenario import Building
from diffpos_services.raytrace.dataset import RaytraceDataset
from diffpos_services.raytrace.paths import DIFFRACTION, DIFFUSE, REFRACTION, SPECULAR

#: Code of a path that is none of the mechanisms (its label says what it is).
OTHER = -1
#: Code of padding (no path).
NO_PATH = -2
#: Points within this distance of a plane lie on it [m] (vertices are single precision).
PLANE_TOL_M = 2e-3
#: A vertical-edge diffraction point this close to the facade plane is on the window's
#: vertical edge of the receiver's floor [m]: the traced scene's side walls run 5 cm past the
#: facade (:func:`diffpos_services.raytrace.scene.building_surfaces` ``overlap_m``), so its
#: vertical edges lie at ``y = -0.05``.
VERTICAL_EDGE_TOL_M = 0.1
#: A traced entry this close to a window-band limit counts as "on the boundary" [m].
BAND_TIE_M = 1e-4


@dataclass(frozen=True)
class Mechanisms:
    """The mechanism of every traced path.

    Attributes
    ----------
    code : ndarray of int, shape (N, M, K)
        Slot of the mechanism set (default :data:`diffpos.paths.mechanisms.MECHANISMS`),
        :data:`OTHER` or :data:`NO_PATH`.
    label : ndarray of object (str), shape (N, M, K)
        The token label of every path (``""`` for padding).
    """

    code: NDArray[np.int_]
    label: NDArray[np.object_]


def ground_z_m(ds: RaytraceDataset) -> float:
    """Height of the traced scene's ground plane (1 cm below an anchor at ``z <= 0``)."""
    return min(0.0, float(ds.anchors_m[:, 2].min()) - 0.01)


def _on(v: NDArray, c: float) -> NDArray[np.bool_]:
    return np.abs(v - c) < PLANE_TOL_M


def _reflection_token(p: NDArray, node_floor: NDArray, b: Building, z_ground: float,
                      parts: list[tuple[int, float]]) -> NDArray[np.object_]:
    """Name the surface of reflection points ``p`` (..., 3) for receivers on ``node_floor``."""
    x0, x1 = b.edge_x_m
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    inside = y > PLANE_TOL_M
    z_f = b.floor_z_m(node_floor)
    tok = np.full(p.shape[:-1], "R(other)", dtype=object)
    for cond, name in ((_on(y, 0.0), "R(facade)"),
                       (_on(z, z_ground) & (y < 0), "R(ground)"),
                       (inside & _on(z, z_f), "R(floor)"),
                       (inside & _on(z, z_f + b.floor_height_m), "R(ceiling)"),
                       (_on(y, b.depth_m), "R(back)"),
                       (inside & _on(x, x0), "R(side x1)"),
                       (inside & _on(x, x1), "R(side x2)")):
        tok = np.where((tok == "R(other)") & cond, name, tok)
    for axis, pos in parts:
        tok = np.where((tok == "R(other)") & inside & _on(p[..., axis], pos), "R(partition)", tok)
    return tok


def _diffraction_token(p: NDArray, node_floor: NDArray, b: Building) -> NDArray[np.object_]:
    """Name the edge of diffraction points ``p`` (..., 3) for receivers on ``node_floor``."""
    x0, x1 = b.edge_x_m
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    on_facade = _on(y, 0.0) & (x > x0 + PLANE_TOL_M) & (x < x1 - PLANE_TOL_M)
    tok = np.full(p.shape[:-1], "D(other)", dtype=object)
    tok = np.where(_on(x, x0) | _on(x, x1), "D(vertical)", tok)
    lo, hi = b.window_z_m(node_floor)
    in_band = (z > lo) & (z < hi) & (np.abs(y) < VERTICAL_EDGE_TOL_M)
    for xe, name in ((x0, "D(vertical x1)"), (x1, "D(vertical x2)")):
        tok = np.where(in_band & _on(x, xe), name, tok)
    for k in range(b.n_floors):
        lo, hi = (float(v) for v in b.window_z_m(k))
        same = node_floor == k
        for zc, name in ((hi, "upper"), (lo, "lower")):
            hit = on_facade & _on(z, zc)
            tok = np.where(hit & same, f"D({name})", tok)
            for off in range(-b.n_floors + 1, b.n_floors):
                if off:
                    tok = np.where(hit & (k - node_floor == off), f"D({name} floor{off:+d})",
                                   tok)
    return tok


def _partition_last(label: str) -> str:
    """A chain with one partition reflection among the slab reflections (after the edge if
    there is one), as the path model's partition families name it (the partition last: where
    the ray meets it among the slab bounces does not change the length)."""
    toks = label.split("-")
    if toks.count("R(partition)") != 1:
        return label
    diff = [i for i, t in enumerate(toks) if t.startswith("D(")]
    if diff and toks.index("R(partition)") < diff[0]:  # before the edge: another chain
        return label
    rest = [t for t in toks if t != "R(partition)"]
    return "-".join([*rest[:-1], "R(partition)", rest[-1]])


def _transmission_token(p: NDArray, parts: list[tuple[int, float]]) -> NDArray[np.object_]:
    tok = np.full(p.shape[:-1], "T(concrete)", dtype=object)
    for axis, pos in parts:
        tok = np.where(_on(p[..., axis], pos), "T(partition)", tok)
    return tok


def classify_mechanisms(ds: RaytraceDataset, mechanisms: MechanismSet | None = None
                        ) -> Mechanisms:
    """The mechanism of every traced path (module docstring); needs ``ds.path_vertices_m``.
    ``mechanisms``: the slots the labels map to (default the 18).

    Raises
    ------
    ValueError
        The dataset has no ``path_vertices_m`` (traced before they were stored: re-trace it).
    """
    if ds.path_vertices_m is None:
        raise ValueError("the dataset has no path_vertices_m (traced by an older diffpos): "
                         "re-run 'diffpos raytrace' to classify paths into mechanisms")
    b = ds.scenario.building
    parts = [(0 if p.axis == "x" else 1, float(p.position_m)) for p in b.partitions]
    verts = ds.path_vertices_m.astype(np.float64)  # (N, M, K, D, 3)
    n, m, k, depth = verts.shape[:4]
    node_floor = np.broadcast_to(b.floor_index(ds.nodes_m[:, 2])[:, None, None], (n, m, k))
    zg = ground_z_m(ds)
    labels = np.full((n, m, k), "Tx", dtype=object)
    chain = ds.path_chain.astype(np.uint16)
    for d in range(min(depth, 4)):
        flag = (chain >> np.uint16(4 * d)) & np.uint16(0xF)
        p = verts[:, :, :, d, :]
        tok = np.full((n, m, k), "", dtype=object)
        tok = np.where(flag == SPECULAR, _reflection_token(p, node_floor, b, zg, parts), tok)
        tok = np.where(flag == DIFFRACTION, _diffraction_token(p, node_floor, b), tok)
        tok = np.where(flag == REFRACTION, _transmission_token(p, parts), tok)
        tok = np.where(flag == DIFFUSE, "S", tok)
        keep = (tok != "") & (tok != "T(partition)")
        labels = np.where(keep, labels + "-" + tok, labels)
    labels = np.where(ds.path_valid, labels + "-Rx", "")
    slot_of = {name: i for i, name in enumerate((mechanisms or mechanism_set()).labels)}
    uniq, inv = np.unique(labels.astype(str), return_inverse=True)
    codes = np.array([slot_of.get(_partition_last(u), OTHER) if u else NO_PATH for u in uniq])
    return Mechanisms(code=codes[inv.reshape(labels.shape)], label=labels)


def model_lengths(ds: RaytraceDataset, mechanisms: MechanismSet | None = None
                  ) -> tuple[NDArray, NDArray[np.bool_], NDArray[np.bool_]]:
    """The model's length (also where it does not exist) and existence of every slot of
    ``mechanisms`` (default the 18) per link ``(N, M, K)`` on the node's floor, and the
    existence with the window band widened by :data:`BAND_TIE_M`
    (:func:`diffpos.paths.model.graded_paths` ``loose``: rays entering on a band limit).

    The ground slots (``R(ground)``) are evaluated in the scene's frame, whose ground lies
    :func:`ground_z_m` (1 cm below the paper's anchor at ``z = 0``): the whole geometry is
    shifted up by ``-ground_z`` for them (the model's ground is ``z = 0``).
    """
    b = ds.scenario.building
    nodes = ds.nodes_m[:, None, :]
    anchors = ds.anchors_m[None, :, :]
    floor = b.floor_index(ds.nodes_m[:, 2])[:, None]
    mech = mechanisms or mechanism_set()
    ps = first_arrival_paths(nodes, anchors, b, floor=floor, mechanisms=mech)
    gp = graded_paths(nodes, anchors, b, relax_m=BAND_TIE_M, floor=floor, mechanisms=mech)
    length, valid, loose = gp.length_m.copy(), ps.valid.copy(), gp.loose.copy()
    zg = ground_z_m(ds)
    if zg != 0.0:
        up = np.array([0.0, 0.0, -zg])
        b_up = dataclasses.replace(b, first_floor_z_m=b.first_floor_z_m - zg)
        ground = [i for i, r in enumerate(mech.recipes) if r.ground]
        pg = first_arrival_paths(nodes + up, anchors + up, b_up, floor=floor, slots=ground,
                                 mechanisms=mech)
        gg = graded_paths(nodes + up, anchors + up, b_up, relax_m=BAND_TIE_M, floor=floor,
                          slots=ground, mechanisms=mech)
        length[..., ground] = gg.length_m
        valid[..., ground] = pg.valid
        loose[..., ground] = gg.loose
    return length, valid, loose


def mechanism_length_check(ds: RaytraceDataset, mech: Mechanisms | None = None,
                           mechanisms: MechanismSet | None = None
                           ) -> dict[str, dict[str, float]]:
    """Per mechanism: traced length vs the model's closed-form length on the node's floor.

    ``mechanisms``: the set the paths are classified into (default the 18); ``mech``, if
    given, must have been classified with it.

    Returns
    -------
    dict
        ``{label: {"paths", "model_exists" (fraction of these paths for which the model says
        the mechanism exists), "exists_on_band" (... or would with the band widened by
        :data:`BAND_TIE_M`), "max_abs_m", "p99_abs_m", "within_1mm" (fraction)}}`` for every
        slot with at least one traced path; the errors are over the paths the model has
        (``exists_on_band``; the length is computed there too).
    """
    mset = mechanisms or mechanism_set()
    mech = mech or classify_mechanisms(ds, mset)
    length, valid, loose = model_lengths(ds, mset)
    out: dict[str, dict[str, float]] = {}
    for s, name in enumerate(mset.labels):
        idx = np.argwhere(mech.code == s)
        if len(idx) == 0:
            continue
        n, m, k = idx.T
        err = np.abs(ds.path_length_m[n, m, k] - length[n, m, s])
        ok = loose[n, m, s]
        e = err[ok]
        out[name] = {"paths": float(len(idx)), "model_exists": float(valid[n, m, s].mean()),
                     "exists_on_band": float(ok.mean()),
                     "max_abs_m": float(e.max()) if e.size else float("nan"),
                     "p99_abs_m": float(np.percentile(e, 99)) if e.size else float("nan"),
                     "within_1mm": float(np.mean(e < 1e-3)) if e.size else float("nan")}
    return out
