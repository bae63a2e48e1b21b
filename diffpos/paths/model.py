"""First-arrival path model: every mechanism that can arrive first, its length and Jacobian.

One geometry implementation shared by the channel emulator (:mod:`diffpos.channel.emulator` calls
:func:`specular_path` and :func:`diffracted_path` for lengths, validity and interaction points
and only adds amplitudes) and by the mechanism-aware estimator (:func:`diffpos.estimators.mnls.solver`
calls :func:`first_arrival_paths`). Vectorised over any batch shape.

:func:`first_arrival_paths` (and :func:`graded_paths`, the unmasked variant with existence
graded by the entry height, for a tracker) run the compiled kernel
:mod:`diffpos.paths.model_nb`: one loop over (node, anchor, floor) rows and slots performing
the numpy reference's floating-point operations in the same order (the reference,
:func:`_first_arrival_paths_numpy` on :func:`specular_path` / :func:`diffracted_path`, stays
here; tests/core/test_paths_kernel.py holds the kernel to it: lengths <= 1e-12 relative,
existence exactly). Call :func:`diffpos.paths.model_nb.warm_paths` at service start: the
first call compiles (a few s CPU) or loads numba's on-disk cache (~0.4 s).
Cost per row, all 18 slots with Jacobians: ``benchmarks/bench_path_model.py``. Only lengths
(``want_jac=False`` of the kernel) saves < 10 %, so there is no separate public entry point
for it; a subset of slots (``slots=``) costs in proportion (the diffraction slots are ~2x the
specular ones).

Mechanisms (slot order = :data:`MECHANISMS` = ``diffpos.channel.emulator.MECHANISMS``)

====  ============================  ============================================================
slot  label                         geometry (node floor ``k``: floor plane ``z_f``, ceiling
                                    ``z_f + H``, window band ``[z_lo, z_hi]``, ``x0 < x < x1``)
====  ============================  ============================================================
0     ``Tx-Rx``                     straight line; *exists in the model only through the
                                    window opening of floor k* (see below)
1     ``Tx-R(ground)-Rx``           anchor imaged in ``z = 0``; ground point outside, entry in
                                    the window band
2-6   ``Tx-R(plane)-Rx``            node imaged in its floor / ceiling / back / side walls;
                                    the unfolded ray enters through the window band and the
                                    reflection point lies on the floor's inside surface
7-8   ``Tx-D(upper|lower)-Rx``      Fermat point on the upper / lower edge at its *physical*
                                    height ``z_hi`` / ``z_lo`` (not the paper's moving edge)
9-13  ``Tx-D(edge)-R(plane)-Rx``    Fermat point for the node imaged in the plane, then the
                                    reflection point on the inside surface
14-17 double bounces                ground+ceiling, ceiling+floor, floor+ceiling, ceiling+back
====  ============================  ============================================================

Higher-order families (:func:`diffpos.paths.mechanisms.mechanism_set`, order > 2) use the
same two builders: any entry (straight through the window, a ground bounce, a window-edge
diffraction, a ground bounce then the edge) followed by an image series between the floor and
ceiling slabs and at most one wall. Two kinds of them go beyond the facade's horizontal edges:

* **Vertical window edges** (``D(vertical x1)`` / ``D(vertical x2)``): the window band's edges
  at the facade ends ``x = x0`` / ``x1``, from the sill to the lintel of the node's floor (the
  side wall's edge); the same Fermat / Keller-cone point (:func:`diffpos.geometry.diffraction_point`
  on a segment of that orientation), valid strictly between sill and lintel. Anchors beyond
  the facade ends reach the rooms by them.
* **Partition reflections** (``"partition"`` in a recipe, ``mechanism_set(..., partitions=True)``):
  the node imaged in one of the building's interior partitions (:attr:`FloorFrame.partitions`)
  as well as in the slabs. A vertical mirror commutes with the horizontal ones, so the length
  does not depend on where the ray meets the partition among the slab reflections; the
  geometry decides it (:func:`_free_walk`: the partition's point on the unfolded ray, every
  point folded back by the mirrors met before it, on the floor's inside surface, the
  partition's strictly inside its span). Of the partitions, the shortest existing path is
  the family's.

Both were checked against Sionna RT's traced paths of the same interaction chain
(``benchmarks/bench_path_model.py --sionna``): within 0.02 mm on every traced path of the
added families (the traced scene's side walls run 5 cm past the facade, so there its vertical
edges lie at ``y = -0.05``; the check evaluates the closed form in that frame).

Existence (``valid``) is the emulator's, with strict inequalities at the window band and the
edge ends and a 1e-9 m tolerance on the inside surfaces. Two decisions:

* **Through-wall direct path excluded.** The straight line through concrete (slot 0 when it
  does not cross the window opening) loses ~90 dB in the wall (ITU concrete, 0.2 m, 28 GHz)
  plus ~136 dB per slab: at the study's ranges its SNR is < -40 dB, below the detection floor,
  so it is never a first arrival (measured: 0 of 70,400 links of the default study). The
  model's slot-0 existence is ``through the opening``; the emulator keeps the through-wall ray
  (with its loss) in its channel.
* **Corner diffraction dropped, identically in both.** When the unconstrained Fermat point
  lies beyond an edge end (``t* <= x0`` or ``>= x1``) the ray would diffract at the window
  corner (vertex diffraction), whose field decays one order faster (an extra ``1/sqrt(kr)``)
  than edge diffraction and which GTD/UTD in :mod:`diffpos.channel.gtd` does not model. Clamping the
  point to the corner (what D-NLS does) would give a length with no amplitude behind it; both
  the emulator and this model drop the path instead (``valid`` False), so they agree exactly,
  also for anchors beyond the facade ends.

Jacobians: ``d length / d node``. For an image-method path the length is ``|I(node) - S|``
with ``I`` a composition of plane mirrors, so the derivative is the unit vector of the
unfolded ray with the mirrored components' signs flipped. For a diffraction path the Fermat
point is stationary (envelope theorem): the derivative is the unit vector from the
diffraction point to the (imaged) node, again with mirrored signs flipped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.geometry import diffraction_point
from diffpos.paths.mechanisms import (
    DIFFRACTION_SLOTS,
    MECHANISMS,
    SPECULAR_SLOTS,
    MechanismSet,
    mechanism_set,
)
from diffpos.paths.model_nb import (
    DEFAULT_TABLE,
    building_planes,
    eval_paths_kernel,
    mechanism_table,
    partition_array,
)

__all__ = [
    "DIFFRACTION_SLOTS",
    "MECHANISMS",
    "SPECULAR_SLOTS",
    "FloorFrame",
    "GradedPaths",
    "PathSet",
    "diffracted_path",
    "first_arrival_paths",
    "graded_paths",
    "specular_path",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]



@dataclass(frozen=True)
class FloorFrame:
    """The planes of one floor hypothesis (arrays broadcast against the batch shape).

    Attributes
    ----------
    z_floor, z_ceil, win_lo, win_hi : ndarray [m]
        Floor and ceiling planes and the window band of the node's floor.
    x0, x1 : float [m]
        Window edge / side wall extent along x.
    depth_m : float [m]
        Back wall at ``y = depth_m``.
    partitions : tuple of (int, float, float, float)
        The interior partitions (every floor): ``(axis 0 | 1, position, span start, span
        end)`` [m], the plane ``x = position`` (axis 0) or ``y = position`` (axis 1) spanning
        the other horizontal coordinate; plane name ``"partition:j"``.
    """

    z_floor: FloatArray
    z_ceil: FloatArray
    win_lo: FloatArray
    win_hi: FloatArray
    x0: float
    x1: float
    depth_m: float
    partitions: tuple[tuple[int, float, float, float], ...] = ()

    @classmethod
    def from_building(cls, building, floor: ArrayLike) -> FloorFrame:
        """Planes of floor index ``floor`` (any shape) of a :class:`~diffpos.scenario.Building`."""
        k = np.asarray(floor)
        z_f = building.floor_z_m(k)
        lo, hi = building.window_z_m(k)
        x0, x1 = building.edge_x_m
        return cls(z_floor=z_f, z_ceil=z_f + building.floor_height_m, win_lo=lo, win_hi=hi,
                   x0=float(x0), x1=float(x1), depth_m=float(building.depth_m),
                   partitions=partition_rows(building))

    def plane(self, name: str) -> tuple[int, FloatArray | float]:
        """Axis and coordinate of an inside plane (or the ground)."""
        if name == "floor":
            return 2, self.z_floor
        if name == "ceiling":
            return 2, self.z_ceil
        if name == "back":
            return 1, self.depth_m
        if name == "side x1":
            return 0, self.x0
        if name == "side x2":
            return 0, self.x1
        if name == "ground":
            return 2, 0.0
        if name.startswith("partition:"):
            axis, pos, _, _ = self.partitions[int(name.split(":")[1])]
            return axis, pos
        raise ValueError(name)

    def edge_segment(self, edge: str, shape: tuple[int, ...]) -> tuple[FloatArray, FloatArray]:
        """Start and end ``(*shape, 3)`` of a window edge of the floor: ``"upper"`` /
        ``"lower"`` (``z = win_hi`` / ``win_lo`` from ``x0`` to ``x1``), ``"vertical x1"`` /
        ``"vertical x2"`` (``x = x0`` / ``x1`` from ``win_lo`` up to ``win_hi``), on the facade
        ``y = 0``."""
        zero = np.zeros(shape)
        if edge in ("upper", "lower"):
            z_e = np.broadcast_to(self.win_hi if edge == "upper" else self.win_lo, shape)
            return (np.stack([np.full(shape, self.x0), zero, z_e], axis=-1),
                    np.stack([np.full(shape, self.x1), zero, z_e], axis=-1))
        if edge in ("vertical x1", "vertical x2"):
            x_e = np.full(shape, self.x0 if edge == "vertical x1" else self.x1)
            return (np.stack([x_e, zero, np.broadcast_to(self.win_lo, shape)], axis=-1),
                    np.stack([x_e, zero, np.broadcast_to(self.win_hi, shape)], axis=-1))
        raise ValueError(f"unknown window edge {edge!r}")

    def in_window(self, z: FloatArray, x: FloatArray) -> BoolArray:
        """Strictly inside the window opening of the floor."""
        return (z > self.win_lo) & (z < self.win_hi) & (x > self.x0) & (x < self.x1)

    def in_floor_box(self, p: FloatArray, tol: float = 1e-9) -> BoolArray:
        """On or inside the floor's box (walls, floor, ceiling), within ``tol`` [m]."""
        return ((p[..., 0] >= self.x0 - tol) & (p[..., 0] <= self.x1 + tol)
                & (p[..., 1] >= -tol) & (p[..., 1] <= self.depth_m + tol)
                & (p[..., 2] >= self.z_floor - tol) & (p[..., 2] <= self.z_ceil + tol))


def partition_rows(building) -> tuple[tuple[int, float, float, float], ...]:
    """``(axis 0 | 1, position, span start, span end)`` [m] of every interior partition of a
    :class:`~diffpos.scenario.Building` (:attr:`FloorFrame.partitions`)."""
    return tuple((0 if p.axis == "x" else 1, float(p.position_m), float(min(p.span_m)),
                  float(max(p.span_m))) for p in building.partitions)


def _mirror(p: FloatArray, axis: int, c: FloatArray | float) -> FloatArray:
    q = p.copy()
    q[..., axis] = 2.0 * c - p[..., axis]
    return q


@dataclass(frozen=True)
class _Geom:
    """Length, validity, Jacobian and interaction points of one mechanism."""

    length_m: FloatArray
    valid: BoolArray
    jacobian: FloatArray
    points: list  # interaction points in path order (entry/diffraction point, reflections)
    ground_point: FloatArray | None = None
    deviation_cos: FloatArray | None = None  # diffraction: cos(incident, diffracted ray)
    outside_m: FloatArray | None = None  # diffraction: anchor -> diffraction point [m]
    # a partition family: the recipe's plane index of every reflection point, in path order,
    # and the partition (FloorFrame.partitions index) of the path
    order: NDArray[np.int_] | None = None
    partition: NDArray[np.int_] | None = None


def _slab_walk(src: FloatArray, img: FloatArray, t_start: float | FloatArray, axes_coords,
               frame: FloorFrame, valid: NDArray[np.bool_], shape: tuple[int, ...] | None = None
               ) -> tuple[NDArray[np.bool_], list[FloatArray]]:
    """The reflection points of the ray ``src`` -> ``img`` (the image across ``axes_coords``,
    first plane first) after ``t_start``: each after the previous one and on the floor's inside
    surface (``valid`` narrowed by that). ``shape``: the planes' coordinates are broadcast to
    it before mirroring."""
    pts = []
    cur_src, cur_img, t_last = src, img, t_start
    for axis, coord in axes_coords:
        dd = cur_img - cur_src
        t = (coord - cur_src[..., axis]) / dd[..., axis]
        valid = valid & (t > t_last) & (t < 1)
        rp = cur_src + t[..., None] * dd
        valid = valid & frame.in_floor_box(rp)
        pts.append(rp)
        c = coord if shape is None else np.broadcast_to(coord, shape)
        cur_img = _mirror(cur_img, axis, c)
        cur_src = _mirror(cur_src, axis, c)
        t_last = t
    return valid, pts


def specular_path(anchor: FloatArray, node: FloatArray, frame: FloorFrame,
                  planes: tuple[str, ...] | list[str], *, ground: bool = False) -> _Geom:
    """Anchor [-> ground] -> window opening -> inside planes... -> node, by the image method.

    ``anchor`` and ``node`` are ``(..., 3)`` arrays of the same shape. The node is imaged
    across the inside planes (last plane first); the ray from the (ground-imaged) anchor to the
    image must cross the facade inside the window band after the ground point and before every
    reflection point, and every reflection point must lie on the floor's inside surface.
    ``points`` are the entry point, then the reflection points, then the node.
    """
    shape = anchor.shape[:-1]
    if "partition" in planes:
        return _best_partition(frame, tuple(planes), shape, lambda pl: specular_path(
            anchor, node, frame, pl, ground=ground))
    a, n = anchor, node
    src = _mirror(a, 2, 0.0) if ground else a
    img = n
    axes_coords = [frame.plane(p) for p in planes]
    sign = np.ones(3)
    for axis, coord in reversed(axes_coords):
        img = _mirror(img, axis, coord)
        sign[axis] = -sign[axis]
    d = img - src
    length = np.sqrt(np.einsum("...i,...i->...", d, d))
    valid = np.ones(shape, dtype=bool)
    g_pt = None
    with np.errstate(invalid="ignore", divide="ignore"):
        t_f = (0.0 - src[..., 1]) / d[..., 1]
        t_prev = np.zeros(shape)
        if ground:
            t_g = (0.0 - src[..., 2]) / d[..., 2]
            valid &= (t_g > 0) & (t_g < t_f)
            t_prev = t_g
            g_pt = src + t_g[..., None] * d
        valid &= (t_f > t_prev) & (t_f < 1)
        entry = src + t_f[..., None] * d
        valid &= frame.in_window(entry[..., 2], entry[..., 0])
        pts = [entry]
        order = None
        if any(p.startswith("partition:") for p in planes):
            ok, rps, order = _free_walk(src, img, t_f, planes, frame)
            valid &= ok
            pts += rps
        else:
            valid, rps = _slab_walk(src, img, t_f, axes_coords, frame, valid)
            pts += rps
        pts.append(n)
        jac = d / length[..., None] * sign
    valid &= np.isfinite(length)
    return _Geom(length_m=length, valid=valid, jacobian=jac, points=pts, ground_point=g_pt,
                 order=order)


def diffracted_path(anchor: FloatArray, node: FloatArray, frame: FloorFrame, edge: str,
                    then: str | tuple[str, ...] | list[str] | None = None, *,
                    ground: bool = False) -> _Geom:
    """Anchor [-> ground] -> Fermat point on a window edge [-> inside planes...] -> node.

    The edge is the physical one (:meth:`FloorFrame.edge_segment`): ``"upper"`` / ``"lower"``,
    ``z = win_hi`` or ``win_lo`` of the floor from ``x0`` to ``x1``, or ``"vertical x1"`` /
    ``"vertical x2"``, ``x = x0`` / ``x1`` from ``win_lo`` to ``win_hi`` (the same Fermat /
    Keller-cone point on a segment of another orientation); the path is valid only where the
    Fermat point lies strictly inside the edge (corner diffraction dropped: module docstring). ``then``: one inside plane or a sequence of them in
    path order; the node is imaged across them (last plane first), the Fermat point is that of
    the image, and every reflection point of the unfolded ray from the edge must lie on the
    floor's inside surface, in order. ``ground``: the anchor is imaged in ``z = 0`` first and the
    ground point must lie between the anchor and the edge. ``points`` are the diffraction point,
    then the reflection points, then the node (``ground_point`` apart); ``outside_m`` is the
    length anchor [-> ground] -> diffraction point.
    """
    shape = np.broadcast_shapes(anchor.shape, node.shape)[:-1]
    a = np.broadcast_to(anchor, (*shape, 3))
    n = np.broadcast_to(node, (*shape, 3))
    planes = () if then is None else ((then,) if isinstance(then, str) else tuple(then))
    if "partition" in planes:
        return _best_partition(frame, planes, shape, lambda pl: diffracted_path(
            a, n, frame, edge, pl, ground=ground))
    src = _mirror(np.array(a), 2, 0.0) if ground else a
    p0, p1 = frame.edge_segment(edge, shape)
    obs = n
    sign = np.ones(3)
    axes_coords = [frame.plane(p) for p in planes]
    for axis, coord in reversed(axes_coords):
        obs = _mirror(np.array(obs), axis, np.broadcast_to(coord, shape))
        sign[axis] = -sign[axis]
    dp = diffraction_point(src, obs, p0, p1)
    q = dp.point_m
    valid = dp.on_edge.copy()
    pts = [q]
    d = obs - q
    g_pt = None
    with np.errstate(invalid="ignore", divide="ignore"):
        if ground:
            t_g = (0.0 - src[..., 2]) / (q[..., 2] - src[..., 2])
            valid &= (t_g > 0) & (t_g < 1)
            g_pt = src + t_g[..., None] * (q - src)
            g_pt[..., 2] = 0.0
        order = None
        if any(p.startswith("partition:") for p in planes):
            ok, rps, order = _free_walk(q, obs, 0.0, planes, frame)
            valid &= ok
            pts += rps
        else:
            valid, rps = _slab_walk(q, obs, 0.0, axes_coords, frame, valid, shape)
            pts += rps
        u_out = d / np.sqrt(np.einsum("...i,...i->...", d, d))[..., None]
        u_in = q - src
        d_in = np.sqrt(np.einsum("...i,...i->...", u_in, u_in))
        u_in = u_in / d_in[..., None]
        jac = u_out * sign
    pts.append(n)
    return _Geom(length_m=dp.length_m, valid=valid & np.isfinite(dp.length_m), jacobian=jac,
                 points=pts, ground_point=g_pt,
                 deviation_cos=np.einsum("...i,...i->...", u_in, u_out), outside_m=d_in,
                 order=order)


def _free_walk(src: FloatArray, img: FloatArray, t_start: float | FloatArray,
               planes: tuple[str, ...] | list[str], frame: FloorFrame
               ) -> tuple[BoolArray, list, NDArray[np.int_]]:
    """The reflection points of the unfolded ray ``src -> img`` (``img``: the node imaged in
    every plane) for slab planes in path order plus one ``"partition:j"`` plane anywhere: the
    slab reflections follow one another after ``t_start``; the partition's parameter is that
    of its own plane on the unfolded ray (the vertical mirror commutes with the horizontal
    ones), after ``t_start``. Every point is folded back by the mirrors met before it and must
    lie on the floor's inside surface, the partition's strictly inside its span. Returns
    (valid, the points in path order, the recipe's plane index of each)."""
    fi = next(i for i, p in enumerate(planes) if p.startswith("partition:"))
    pax, ppos, plo, phi = frame.partitions[int(planes[fi].split(":")[1])]
    shape = src.shape[:-1]
    npl = len(planes)
    valid = np.ones(shape, dtype=bool)
    ts = np.empty((*shape, npl))
    pts = np.empty((*shape, npl, 3))
    d = img - src
    t_p = (ppos - src[..., pax]) / d[..., pax]
    valid &= (t_p > t_start) & (t_p < 1)
    pp = src + t_p[..., None] * d
    cur_src, cur_img, t_last = src, img, t_start
    for i, p in enumerate(planes):
        if i == fi:
            continue
        axis, coord = frame.plane(p)
        dd = cur_img - cur_src
        t = (coord - cur_src[..., axis]) / dd[..., axis]
        valid &= (t > t_last) & (t < 1)
        rp = cur_src + t[..., None] * dd
        rp[..., pax] = np.where(t_p < t, 2.0 * ppos - rp[..., pax], rp[..., pax])
        valid &= frame.in_floor_box(rp)
        pp[..., axis] = np.where(t < t_p, 2.0 * coord - pp[..., axis], pp[..., axis])
        ts[..., i], pts[..., i, :] = t, rp
        cur_img = _mirror(cur_img, axis, coord)
        cur_src = _mirror(cur_src, axis, coord)
        t_last = t
    pp[..., pax] = ppos
    other = pp[..., 1 - pax]
    valid &= (other > plo) & (other < phi) & frame.in_floor_box(pp)
    ts[..., fi], pts[..., fi, :] = t_p, pp
    order = np.argsort(np.where(np.isfinite(ts), ts, np.inf), axis=-1, kind="stable")
    pts = np.take_along_axis(pts, order[..., None], axis=-2)
    return valid, [pts[..., j, :] for j in range(npl)], order


def _best_partition(frame: FloorFrame, planes: tuple[str, ...], shape: tuple[int, ...],
                    path_of) -> _Geom:
    """``path_of(planes)`` on every partition (``"partition"`` -> ``"partition:j"``), per
    element the shortest existing one (the first partition's where none exists)."""
    geoms = [path_of(tuple(f"partition:{j}" if p == "partition" else p for p in planes))
             for j in range(len(frame.partitions))]
    if not geoms:
        nan = np.full(shape, np.nan)
        return _Geom(length_m=nan, valid=np.zeros(shape, dtype=bool),
                     jacobian=np.zeros((*shape, 3)), points=[], deviation_cos=nan,
                     outside_m=nan)
    key = np.stack([np.where(g.valid, g.length_m, np.inf) for g in geoms])
    pick = np.argmin(key, axis=0)

    def sel(vals):
        if vals[0] is None:
            return None
        v = np.stack(vals)
        idx = pick.reshape((1, *shape, *([1] * (v.ndim - 1 - len(shape)))))
        return np.take_along_axis(v, np.broadcast_to(idx, (1, *v.shape[1:])), axis=0)[0]

    return _Geom(length_m=sel([g.length_m for g in geoms]), valid=sel([g.valid for g in geoms]),
                 jacobian=sel([g.jacobian for g in geoms]),
                 points=[sel([g.points[k] for g in geoms]) for k in range(len(geoms[0].points))],
                 ground_point=sel([g.ground_point for g in geoms]),
                 deviation_cos=sel([g.deviation_cos for g in geoms]),
                 outside_m=sel([g.outside_m for g in geoms]),
                 order=sel([g.order for g in geoms]), partition=pick)


def direct_opening(anchor: FloatArray, node: FloatArray, frame: FloorFrame
                   ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Facade crossing ``(x_c, z_c)`` of the straight line and whether it is in the window.

    Returns ``(x_c, z_c, through_window)`` (anchor at ``y < 0``, node at ``y > 0``).
    """
    d = node - anchor
    with np.errstate(invalid="ignore", divide="ignore"):
        t = -anchor[..., 1] / d[..., 1]
    zc = anchor[..., 2] + t * d[..., 2]
    xc = anchor[..., 0] + t * d[..., 0]
    return xc, zc, frame.in_window(zc, xc)


@dataclass(frozen=True)
class PathSet:
    """Every first-arrival mechanism of node x anchor pairs.

    Attributes
    ----------
    length_m : ndarray, shape (..., K) [m]
        Path length of every slot of :data:`MECHANISMS` (NaN where it does not exist).
    valid : ndarray of bool, shape (..., K)
        The mechanism exists geometrically for this node, floor and anchor (slot 0: the
        straight line passes through the floor's window opening).
    jacobian : ndarray, shape (..., K, 3) [m/m]
        ``d length_m / d node`` (0 where not valid).
    floor : ndarray of int, shape (...)
        The floor hypothesis the paths were computed for.
    deviation_cos : ndarray, shape (..., K) [-]
        For diffraction slots, the cosine of the angle between the incident ray and the
        diffracted ray (towards the node or its image): 1 on the shadow boundary, smaller deeper
        in the shadow, where the UTD field is weaker; NaN for the other slots.
    outside_m : ndarray, shape (..., K) [m]
        For diffraction slots, the length anchor -> diffraction point; NaN otherwise.
    """

    length_m: FloatArray
    valid: BoolArray
    jacobian: FloatArray
    floor: NDArray[np.int_]
    deviation_cos: FloatArray | None = None
    outside_m: FloatArray | None = None

    @property
    def earliest_slot(self) -> NDArray[np.int_]:
        """Slot of the shortest existing mechanism (-1 where none exists)."""
        lm = np.where(self.valid, self.length_m, np.inf)
        s = np.argmin(lm, axis=-1)
        return np.where(np.any(self.valid, axis=-1), s, -1)


def first_arrival_paths(nodes_m: ArrayLike, anchors_m: ArrayLike, building, *,
                        floor: ArrayLike | None = None, slots: ArrayLike | None = None,
                        mechanisms: MechanismSet | None = None) -> PathSet:
    """Lengths, existence and Jacobians of the first-arrival mechanisms (module docstring).

    Computed by the compiled kernel :func:`diffpos.paths.model_nb.paths_kernel` (one loop
    over node-anchor pairs and slots); :func:`_first_arrival_paths_numpy` is the numpy
    reference it is tested against (same results to rounding, same existence).

    Parameters
    ----------
    nodes_m : array_like, shape (..., 3) [m]
        Node position hypotheses.
    anchors_m : array_like, shape (..., 3) [m]
        Anchor positions (outside, ``y < 0``); broadcast against ``nodes_m``.
    building : diffpos.scenario.Building
    floor : array_like of int, optional
        Floor hypothesis per node (broadcast against the batch shape); default
        ``building.floor_index(z)``. The node need not lie between that floor's planes (an
        estimator iterate may stray); existence is evaluated with the given floor's planes.
    slots : array_like of int, optional
        Subset of slots to compute (default all, in :data:`MECHANISMS` order); the output's
        last axes follow this order.
    mechanisms : diffpos.paths.mechanisms.MechanismSet, optional
        The mechanisms the slots index (default the 18 of :data:`MECHANISMS`;
        :func:`diffpos.paths.mechanisms.mechanism_set` adds higher-order families after them).

    Returns
    -------
    PathSet
    """
    rows = _kernel_rows(nodes_m, anchors_m, building, floor, slots, mechanisms)
    length, valid, jac, dev, outm, _ = eval_paths_kernel(*rows.args, table=rows.table,
                                                          parts=rows.parts)
    sh = (*rows.shape, rows.slots.shape[0])
    return PathSet(length_m=length.reshape(sh), valid=valid.reshape(sh),
                   jacobian=jac.reshape((*sh, 3)), floor=rows.floor,
                   deviation_cos=dev.reshape(sh), outside_m=outm.reshape(sh))


@dataclass(frozen=True)
class GradedPaths:
    """Raw geometry of every mechanism with graded existence, shapes (..., K) / (..., K, 3).

    For an iterate that may cross an existence boundary of its chosen mechanism (a tracker):

    Attributes
    ----------
    length_m : ndarray [m]
        Path length also where the mechanism does not exist.
    jacobian : ndarray [m/m]
        ``d length_m / d node``, also where the mechanism does not exist.
    strict : ndarray of bool
        Existence as in :func:`first_arrival_paths` (``PathSet.valid``).
    loose, sure : ndarray of bool
        Existence with the window band widened / narrowed by ``relax_m`` at the entry point
        of the specular slots (incl. the direct one); the diffraction slots: ``strict``.
    entry_z_m : ndarray [m]
        Height of the facade entry point of the specular slots (NaN for diffraction).
    """

    length_m: FloatArray
    jacobian: FloatArray
    strict: BoolArray
    loose: BoolArray
    sure: BoolArray
    entry_z_m: FloatArray


def graded_paths(nodes_m: ArrayLike, anchors_m: ArrayLike, building, *, relax_m: float,
                 floor: ArrayLike | None = None, slots: ArrayLike | None = None,
                 mechanisms: MechanismSet | None = None) -> GradedPaths:
    """:func:`first_arrival_paths` without the masking, with existence graded by ``relax_m``.

    Same arguments as :func:`first_arrival_paths` plus ``relax_m`` [m] (>= 0), the uncertainty
    of the entry point's height: ``loose`` holds where the entry lies strictly inside the band
    widened by ``relax_m`` (``z > win_lo - relax_m``), ``sure`` where its margin to both band
    limits exceeds ``relax_m`` (``min(z - win_lo, win_hi - z) > relax_m``), ``strict`` where the
    margin is > 0; every other condition of the mechanism applies unchanged. One kernel pass
    (``raw=True``); the band tests are a few vectorised comparisons.
    """
    if not relax_m >= 0.0:
        raise ValueError(f"relax_m must be >= 0 [m]; got {relax_m!r}")
    rows = _kernel_rows(nodes_m, anchors_m, building, floor, slots, mechanisms)
    length, ok, jac, _, _, z_in = eval_paths_kernel(*rows.args, raw=True, table=rows.table,
                                                  parts=rows.parts)
    lo, hi = (v[:, None] for v in building.window_z_m(rows.args[2]))
    spec = SPECULAR_SLOTS if mechanisms is None else mechanisms.specular
    band = np.isin(rows.slots, spec)
    with np.errstate(invalid="ignore"):
        margin = np.minimum(z_in - lo, hi - z_in)
        loose = ok & np.where(band, (z_in > lo - relax_m) & (z_in < hi + relax_m), True)
        strict = loose & np.where(band, margin > 0, True)
        sure = loose & np.where(band, margin > relax_m, True)
    sh = (*rows.shape, rows.slots.shape[0])
    return GradedPaths(length_m=length.reshape(sh), jacobian=jac.reshape((*sh, 3)),
                       strict=strict.reshape(sh), loose=loose.reshape(sh),
                       sure=sure.reshape(sh), entry_z_m=z_in.reshape(sh))


@dataclass(frozen=True)
class _Rows:
    """Flat kernel inputs of one call (internal)."""

    shape: tuple[int, ...]
    floor: NDArray[np.int_]
    slots: NDArray[np.int64]
    args: tuple
    table: NDArray[np.int64]
    parts: NDArray[np.float64]


#: Compiled tables of the mechanism sets in use.
_TABLES: dict[MechanismSet, NDArray[np.int64]] = {}


def _table(mechanisms: MechanismSet | None) -> NDArray[np.int64]:
    if mechanisms is None:
        return DEFAULT_TABLE
    tab = _TABLES.get(mechanisms)
    if tab is None:
        tab = _TABLES[mechanisms] = mechanism_table(mechanisms.recipes)
    return tab


def _slot_array(slots: ArrayLike | None, k: int = len(MECHANISMS)) -> NDArray[np.int64]:
    if slots is None:
        return np.arange(k, dtype=np.int64)
    sel = np.array([int(s) for s in np.ravel(slots)], dtype=np.int64)
    if np.any((sel < -k) | (sel >= k)):
        raise IndexError(f"slots must lie in [0, {k}) (the mechanisms); got {sel.tolist()}")
    return sel % k


def _kernel_rows(nodes_m: ArrayLike, anchors_m: ArrayLike, building,
                 floor: ArrayLike | None, slots: ArrayLike | None,
                 mechanisms: MechanismSet | None = None) -> _Rows:
    """Broadcast nodes, anchors and floors to flat C-contiguous rows for the kernel."""
    table = _table(mechanisms)
    sel = _slot_array(slots, table.shape[0])
    diff = DIFFRACTION_SLOTS if mechanisms is None else mechanisms.diffraction
    n = np.asarray(nodes_m, dtype=np.float64)
    a = np.asarray(anchors_m, dtype=np.float64)
    shape = np.broadcast_shapes(n.shape, a.shape)[:-1]
    rows_n = np.empty((*shape, 3))  # fresh C-contiguous writable copies: the one signature
    rows_n[...] = n
    rows_a = np.empty((*shape, 3))
    rows_a[...] = a
    k = building.floor_index(rows_n[..., 2]) if floor is None else np.asarray(floor)
    k = np.broadcast_to(k, shape)
    k_f = np.empty(shape)
    k_f[...] = k
    planes = building_planes(building)
    if planes[4] == planes[5] and np.any(np.isin(sel, diff)):
        raise ValueError("the window edge has zero length (edge_x_m equal)")
    args = (rows_n.reshape(-1, 3), rows_a.reshape(-1, 3), k_f.reshape(-1), planes, sel)
    return _Rows(shape=shape, floor=np.asarray(k), slots=sel, args=args, table=table,
                 parts=partition_array(building))


def _first_arrival_paths_numpy(nodes_m: ArrayLike, anchors_m: ArrayLike, building, *,
                               floor: ArrayLike | None = None,
                               slots: ArrayLike | None = None,
                               mechanisms: MechanismSet | None = None) -> PathSet:
    """The numpy reference of :func:`first_arrival_paths` (same arguments and results), built on
    :func:`specular_path` and :func:`diffracted_path`; the tests hold the kernel to it.
    """
    n = np.asarray(nodes_m, dtype=np.float64)
    a = np.asarray(anchors_m, dtype=np.float64)
    shape = np.broadcast_shapes(n.shape, a.shape)[:-1]
    n = np.broadcast_to(n, (*shape, 3)).copy()
    a = np.broadcast_to(a, (*shape, 3)).copy()
    k = building.floor_index(n[..., 2]) if floor is None else np.asarray(floor)
    k = np.broadcast_to(k, shape)
    frame = FloorFrame.from_building(building, k)
    recipes = (mechanisms or mechanism_set()).recipes
    sel = range(len(recipes)) if slots is None else [int(s) for s in np.ravel(slots)]
    lens, vals, jacs, devs, outs = [], [], [], [], []
    for s in sel:
        rec = recipes[s]
        dev = np.full(shape, np.nan)
        out = np.full(shape, np.nan)
        if rec.kind == "direct":
            d = n - a
            length = np.sqrt(np.einsum("...i,...i->...", d, d))
            valid = direct_opening(a, n, frame)[2]
            with np.errstate(invalid="ignore", divide="ignore"):
                jac = d / length[..., None]
        elif rec.kind == "spec":
            g = specular_path(a, n, frame, rec.planes, ground=rec.ground)
            length, valid, jac = g.length_m, g.valid, g.jacobian
        else:
            g = diffracted_path(a, n, frame, rec.edge, rec.planes, ground=rec.ground)
            length, valid, jac, dev = g.length_m, g.valid, g.jacobian, g.deviation_cos
            out = g.outside_m
        devs.append(dev)
        outs.append(out)
        lens.append(length)
        vals.append(valid)
        jacs.append(jac)
    valid = np.stack(vals, axis=-1)
    length = np.where(valid, np.stack(lens, axis=-1), np.nan)
    jac = np.where(valid[..., None], np.stack(jacs, axis=-2), 0.0)
    return PathSet(length_m=length, valid=valid, jacobian=jac, floor=np.asarray(k),
                   deviation_cos=np.stack(devs, axis=-1), outside_m=np.stack(outs, axis=-1))
