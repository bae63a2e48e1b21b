"""Compiled first-arrival path model: :func:`diffpos.paths.model.first_arrival_paths` in one loop.

The kernel evaluates, for ``P`` rows (node, anchor, floor planes) and ``S`` slots of
:data:`diffpos.paths.mechanisms.MECHANISMS`, exactly the floating-point operations of the numpy reference
(:func:`diffpos.paths.model._first_arrival_paths_numpy`, built on :func:`diffpos.paths.model.specular_path`
and :func:`diffpos.paths.model.diffracted_path`) in the same order, so lengths and Jacobians agree to
rounding (tests/core/test_paths_kernel.py: <= 1e-12 relative) and existence agrees exactly,
also on the window-band boundaries and the edge ends. ``error_model="numpy"``: a division by
zero gives inf/NaN as in numpy (and the same existence verdicts), never an exception.

One compiled signature (:data:`SIGNATURE`, C-contiguous float64 inputs, writable outputs);
:func:`warm_paths` compiles it, or loads it from numba's on-disk cache (``cache=True``).
Callers run it at service start so the first fix does not pay the compile.

Two modes (arguments of the same signature):

* ``raw=False``: the :class:`~diffpos.paths.model.PathSet` values (length NaN and Jacobian 0 where
  the mechanism does not exist).
* ``raw=True``: lengths and Jacobians also where the mechanism does not exist, and ``valid``
  *without* the window-band height test of the entry point (returned separately as
  ``entry_z``), so a caller can grade existence with a widened / narrowed band (the tracker's
  ``loose`` / ``sure``).

``want_jac=False`` skips the Jacobian, deviation and outside-length outputs (left untouched).

Other compiled kernels (a compiled estimator or tracker step) call the per-row pieces directly
from numba code: :func:`row_planes` (a floor's planes), :func:`edge_axis` (once per building)
and :func:`slot_path` (one slot of one row, scalars in and out, no allocation).

The helpers stay separate compiled functions (calls from the loop): inlining them at numba IR
level (``inline="always"``) measured ~20 % less CPU per row but about twice the first compile
(4.7 vs 2.5 s CPU, shared 2-core machine), a bad trade while the path model is < 10 % of an
M-NLS fix. Except :func:`fermat_point` (small, on every diffraction slot of the tracker's
``all_paths_kernel`` and the SNR kernels): inline, no measurable change of the compile.
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit, types

__all__ = [
    "COL_EDGE",
    "COL_GROUND",
    "COL_KIND",
    "COL_NPLANES",
    "COL_PLANES",
    "DEFAULT_TABLE",
    "N_SLOTS",
    "SIGNATURE",
    "SLOT_EDGE",
    "SLOT_GROUND",
    "SLOT_KIND",
    "SLOT_PLANE0",
    "SLOT_PLANE1",
    "axis_component",
    "building_planes",
    "edge_axis",
    "eval_paths_kernel",
    "facade_entry",
    "family_path",
    "family_path_parts",
    "fermat_point",
    "in_floor_box",
    "inside_plane",
    "mechanism_table",
    "mirror",
    "partition_array",
    "paths_kernel",
    "row_planes",
    "slot_path",
    "vertical_axis",
    "walk_ok",
    "warm_paths",
]

#: Mechanism tables: one row per slot, columns :data:`COL_KIND` (0 direct, 1 specular, 2
#: diffraction), :data:`COL_GROUND` (1: a ground bounce outside first), :data:`COL_EDGE` (0
#: upper, 1 lower window edge, 2 / 3 the vertical edge at x0 / x1, -1 none),
#: :data:`COL_NPLANES` and from :data:`COL_PLANES` on the
#: inside planes in path order (0 floor, 1 ceiling, 2 back, 3 side x1, 4 side x2, -1 padding).
#: :func:`mechanism_table` builds one from ``diffpos.paths.mechanisms`` recipes;
#: :data:`DEFAULT_TABLE` is the compiled twin of ``diffpos.paths.mechanisms.RECIPES`` (a literal:
#: numba freezes a global array into the code it compiles, so it must change with this file;
#: a test checks it equals ``mechanism_table(RECIPES)``).
COL_KIND, COL_GROUND, COL_EDGE, COL_NPLANES, COL_PLANES = 0, 1, 2, 3, 4
DEFAULT_TABLE = np.array([
    [0, 0, -1, 0, -1, -1], [1, 1, -1, 0, -1, -1], [1, 0, -1, 1, 0, -1], [1, 0, -1, 1, 1, -1],
    [1, 0, -1, 1, 2, -1], [1, 0, -1, 1, 3, -1], [1, 0, -1, 1, 4, -1], [2, 0, 0, 0, -1, -1],
    [2, 0, 1, 0, -1, -1], [2, 0, 0, 1, 0, -1], [2, 0, 0, 1, 1, -1], [2, 0, 1, 1, 0, -1],
    [2, 0, 1, 1, 1, -1], [2, 0, 0, 1, 2, -1], [1, 1, -1, 1, 1, -1], [1, 0, -1, 2, 1, 0],
    [1, 0, -1, 2, 0, 1], [1, 0, -1, 2, 1, 2]], dtype=np.int64)
#: The default table's columns as the channel's compiled code reads them
#: (:mod:`diffpos.channel.rays_nb`, :mod:`diffpos.channel.snr_nb`), as are :func:`inside_plane`,
#: :func:`in_floor_box` and :func:`mirror`; ``SLOT_PLANE0`` / ``SLOT_PLANE1``: the first two
#: planes (every default slot has at most two).
SLOT_KIND = np.ascontiguousarray(DEFAULT_TABLE[:, COL_KIND])
SLOT_GROUND = np.ascontiguousarray(DEFAULT_TABLE[:, COL_GROUND])
SLOT_PLANE0 = np.ascontiguousarray(DEFAULT_TABLE[:, COL_PLANES])
SLOT_PLANE1 = np.ascontiguousarray(DEFAULT_TABLE[:, COL_PLANES + 1])
SLOT_EDGE = np.ascontiguousarray(DEFAULT_TABLE[:, COL_EDGE])
N_SLOTS = 18
_PLANE_CODE = {"floor": 0, "ceiling": 1, "back": 2, "side x1": 3, "side x2": 4, "partition": 5}
_PARTITION = 5
_NO_PARTS = np.zeros((0, 4))  # eval_paths_kernel's default: no partitions
_EDGE_CODE = {"upper": 0, "lower": 1, "vertical x1": 2, "vertical x2": 3}
_KIND_CODE = {"direct": 0, "spec": 1, "diff": 2}
_TOL = 1e-9  # in_floor_box tolerance [m] (FloorFrame.in_floor_box)

_f8_2d = types.float64[:, ::1]
_f8_1d = types.float64[::1]
#: The one compiled signature of :func:`paths_kernel`.
SIGNATURE = types.void(
    _f8_2d, _f8_2d,  # nodes (P, 3), anchors (P, 3)
    _f8_1d,  # floor index of every row (P,), as float64
    types.float64, types.float64, types.float64, types.float64,  # first floor z, H, sill, w
    types.float64, types.float64, types.float64,  # x0, x1, depth
    _f8_2d,  # partitions (Q, 4): partition_array
    types.int64[:, ::1], types.int64[::1],  # mechanism table (K, C), slots (S,) (rows of it)
    types.boolean, types.boolean,  # raw, want_jac
    _f8_2d, types.boolean[:, ::1], types.float64[:, :, ::1],  # length, valid, jac
    _f8_2d, _f8_2d, _f8_2d,  # deviation_cos, outside_m, entry_z
)
_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}


@njit(**_OPTS)
def inside_plane(code, zf, zc, x0, x1, depth):
    """(axis, coordinate) of an inside plane (FloorFrame.plane)."""
    if code == 0:
        return 2, zf
    if code == 1:
        return 2, zc
    if code == 2:
        return 1, depth
    if code == 3:
        return 0, x0
    return 0, x1


@njit(**_OPTS)
def in_floor_box(r0, r1, r2, zf, zc, x0, x1, depth):
    """FloorFrame.in_floor_box with its 1e-9 m tolerance."""
    return ((r0 >= x0 - _TOL) and (r0 <= x1 + _TOL) and (r1 >= -_TOL)
            and (r1 <= depth + _TOL) and (r2 >= zf - _TOL) and (r2 <= zc + _TOL))


@njit(**_OPTS)
def axis_component(v0, v1, v2, axis):
    """The ``axis`` component (0 x, 1 y, 2 z) of (v0, v1, v2)."""
    if axis == 0:
        return v0
    if axis == 1:
        return v1
    return v2


@njit(**_OPTS)
def mirror(v0, v1, v2, axis, c):
    """Mirror (v0, v1, v2) in the plane ``v[axis] = c`` (paths._mirror)."""
    if axis == 0:
        return 2.0 * c - v0, v1, v2
    if axis == 1:
        return v0, 2.0 * c - v1, v2
    return v0, v1, 2.0 * c - v2


@njit(**_OPTS)
def _direct(a0, a1, a2, n0, n1, n2, x0, x1):
    """Slot 0: length, Jacobian, facade crossing (paths.direct_opening): x test in ``ok``."""
    d0, d1, d2 = n0 - a0, n1 - a1, n2 - a2
    length = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    t = -a1 / d1
    zc = a2 + t * d2
    xc = a0 + t * d0
    ok = (xc > x0) and (xc < x1)
    return length, ok, zc, d0, d1, d2, 1.0, 1.0, 1.0


@njit(**_OPTS)
def _specular(a0, a1, a2, n0, n1, n2, ground, table, s, zf, zc, x0, x1, depth, pax, ppos, plo,
              phi):
    """paths.specular_path for the planes of row ``s`` of ``table``: length, ok (without the
    entry's band test), entry z, unfolded ray ``d`` and the mirror signs (Jacobian
    ``d / length * sign``). ``pax, ppos, plo, phi``: the partition a ``"partition"`` plane
    (code 5) stands for (:func:`partition_array`'s row)."""
    s0, s1, s2 = a0, a1, a2
    if ground:
        s2 = 2.0 * 0.0 - a2
    i0, i1, i2 = n0, n1, n2
    g0 = g1 = g2 = 1.0
    n_pl = table[s, COL_NPLANES]
    for j in range(n_pl - 1, -1, -1):  # image: last plane first
        ax, c = _plane(table[s, COL_PLANES + j], zf, zc, x0, x1, depth, pax, ppos)
        i0, i1, i2 = mirror(i0, i1, i2, ax, c)
        if ax == 0:
            g0 = -g0
        elif ax == 1:
            g1 = -g1
        else:
            g2 = -g2
    d0, d1, d2, length, t_f, _, ok = facade_entry(s0, s1, s2, i0, i1, i2, ground)
    e0 = s0 + t_f * d0
    ez = s2 + t_f * d2
    ok = ok and (e0 > x0) and (e0 < x1)
    if _has_partition(table, s):
        ok = ok and _free_ok(s0, s1, s2, i0, i1, i2, t_f, table, s, zf, zc, x0, x1, depth, pax,
                             ppos, plo, phi)
    else:
        ok = ok and _reflections_ok(s0, s1, s2, i0, i1, i2, t_f, table, s, zf, zc, x0, x1,
                                    depth)
    ok = ok and math.isfinite(length)
    return length, ok, ez, d0, d1, d2, g0, g1, g2


@njit(**_OPTS)
def facade_entry(s0, s1, s2, i0, i1, i2, ground):
    """The unfolded ray ``s -> i`` (source, node imaged in every plane): its vector ``d``, its
    length, the parameter ``t_f`` at which it crosses the facade plane (y = 0), that of the
    ground bounce ``t_g`` (0 without ``ground``), and whether it bounces on the ground first
    (``0 < t_g < t_f``, with ``ground``) and then enters the facade (``t_g < t_f < 1``)."""
    d0, d1, d2 = i0 - s0, i1 - s1, i2 - s2
    length = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    t_f = (0.0 - s1) / d1
    t_prev = 0.0
    ok = True
    if ground:
        t_g = (0.0 - s2) / d2
        ok = (t_g > 0) and (t_g < t_f)
        t_prev = t_g
    ok = ok and (t_f > t_prev) and (t_f < 1)
    return d0, d1, d2, length, t_f, t_prev, ok


@njit(**_OPTS)
def walk_ok(c0, c1, c2, m0, m1, m2, t_start, table, s, zf, zc, x0, x1, depth, pax, ppos, plo,
            phi):
    """The reflections of row ``s`` on the unfolded ray ``c -> m`` (source, node imaged in
    every plane) exist, after ``t_start`` (paths.specular_path / diffracted_path's tests;
    ``pax, ppos, plo, phi``: the partition a ``"partition"`` plane stands for): a geometry-only
    test for callers that compute more per path (the emulator's fields)."""
    if _has_partition(table, s):
        return _free_ok(c0, c1, c2, m0, m1, m2, t_start, table, s, zf, zc, x0, x1, depth, pax,
                        ppos, plo, phi)
    return _reflections_ok(c0, c1, c2, m0, m1, m2, t_start, table, s, zf, zc, x0, x1, depth)


@njit(**_OPTS)
def _plane(code, zf, zc, x0, x1, depth, pax, ppos):
    """:func:`inside_plane`, and the partition ``(pax, ppos)`` for code 5."""
    if code == _PARTITION:
        return pax, ppos
    return inside_plane(code, zf, zc, x0, x1, depth)


@njit(**_OPTS)
def _has_partition(table, s):
    """Row ``s`` of ``table`` has a ``"partition"`` plane."""
    for j in range(table[s, COL_NPLANES]):
        if table[s, COL_PLANES + j] == _PARTITION:
            return True
    return False


@njit(**_OPTS)
def _free_ok(c0, c1, c2, m0, m1, m2, t_start, table, s, zf, zc, x0, x1, depth, pax, ppos, plo,
             phi):
    """paths._free_walk: the slab reflections of row ``s`` in path order after ``t_start`` on
    the unfolded ray ``c -> m``, the partition ``(pax, ppos)`` wherever the ray meets it after
    ``t_start``; every point folded back by the mirrors met before it on the floor's inside
    surface, the partition's strictly inside its span ``(plo, phi)``."""
    d0, d1, d2 = m0 - c0, m1 - c1, m2 - c2
    t_p = (ppos - axis_component(c0, c1, c2, pax)) / axis_component(d0, d1, d2, pax)
    ok = (t_p > t_start) and (t_p < 1)
    q0, q1, q2 = c0 + t_p * d0, c1 + t_p * d1, c2 + t_p * d2
    t_last = t_start
    for j in range(table[s, COL_NPLANES]):
        code = table[s, COL_PLANES + j]
        if code == _PARTITION:
            continue
        ax, c = inside_plane(code, zf, zc, x0, x1, depth)
        dd0, dd1, dd2 = m0 - c0, m1 - c1, m2 - c2
        t = (c - axis_component(c0, c1, c2, ax)) / axis_component(dd0, dd1, dd2, ax)
        ok = ok and (t > t_last) and (t < 1)
        r0, r1, r2 = c0 + t * dd0, c1 + t * dd1, c2 + t * dd2
        if t_p < t:
            r0, r1, r2 = mirror(r0, r1, r2, pax, ppos)
        ok = ok and in_floor_box(r0, r1, r2, zf, zc, x0, x1, depth)
        if t < t_p:
            q0, q1, q2 = mirror(q0, q1, q2, ax, c)
        m0, m1, m2 = mirror(m0, m1, m2, ax, c)
        c0, c1, c2 = mirror(c0, c1, c2, ax, c)
        t_last = t
    if pax == 0:
        q0 = ppos
        other = q1
    else:
        q1 = ppos
        other = q0
    return ok and (other > plo) and (other < phi) and in_floor_box(q0, q1, q2, zf, zc, x0, x1,
                                                                    depth)


@njit(**_OPTS)
def _reflections_ok(c0, c1, c2, m0, m1, m2, t_last, table, s, zf, zc, x0, x1, depth):
    """The reflection points of the unfolded ray ``c -> m`` (source, image through every plane
    of row ``s``) lie on the floor's inside surface, in path order after ``t_last``."""
    ok = True
    for j in range(table[s, COL_NPLANES]):
        ax, c = inside_plane(table[s, COL_PLANES + j], zf, zc, x0, x1, depth)
        dd0, dd1, dd2 = m0 - c0, m1 - c1, m2 - c2
        t = (c - axis_component(c0, c1, c2, ax)) / axis_component(dd0, dd1, dd2, ax)
        ok = ok and (t > t_last) and (t < 1)
        ok = ok and in_floor_box(c0 + t * dd0, c1 + t * dd1, c2 + t * dd2, zf, zc, x0, x1, depth)
        m0, m1, m2 = mirror(m0, m1, m2, ax, c)
        c0, c1, c2 = mirror(c0, c1, c2, ax, c)
        t_last = t
    return ok


@njit(**_OPTS, inline="always")
def fermat_point(s0, s1, s2, o0, o1, o2, x0, z_e, edge):
    """geometry.diffraction_point on the edge from ``(x0, 0, z_e)`` along ``edge`` (length,
    unit vector) between ``s`` and ``o`` (the source and the node or its image): the point
    (clamped to the edge) and whether the unclamped point lies strictly inside it."""
    edge_len, ee0, ee1, ee2 = edge
    ds0, ds1, ds2 = s0 - x0, s1 - 0.0, s2 - z_e
    dq0, dq1, dq2 = o0 - x0, o1 - 0.0, o2 - z_e
    s_t = ds0 * ee0 + ds1 * ee1 + ds2 * ee2
    o_t = dq0 * ee0 + dq1 * ee1 + dq2 * ee2
    w0, w1, w2 = ds0 - s_t * ee0, ds1 - s_t * ee1, ds2 - s_t * ee2
    r_s = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    w0, w1, w2 = dq0 - o_t * ee0, dq1 - o_t * ee1, dq2 - o_t * ee2
    r_o = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    denom = r_s + r_o
    scale = abs(s_t) + abs(o_t) + r_s + r_o + edge_len
    if denom <= 1e-12 * scale:
        t_star = 0.5 * (s_t + o_t)
    else:
        t_star = (s_t * r_o + o_t * r_s) / denom
    t = t_star
    if t < 0.0:
        t = 0.0
    elif t > edge_len:
        t = edge_len
    return x0 + t * ee0, 0.0 + t * ee1, z_e + t * ee2, (t_star > 0.0) and (t_star < edge_len)


@njit(**_OPTS)
def _diffracted(a0, a1, a2, n0, n1, n2, x_e, z_e, table, s, zf, zc, x0, x1, depth, edge, pax,
                ppos, plo, phi):
    """paths.diffracted_path (geometry.diffraction_point on the edge from ``(x_e, 0, z_e)``)
    with the ground bounce and the planes of row ``s`` of ``table``: length, ok, Jacobian,
    deviation cosine, anchor (ground image) -> diffraction point length. ``edge``: length and
    unit vector of the edge (:func:`edge_axis` for the horizontal edges, the same for every
    row; :func:`vertical_axis` for the vertical ones)."""
    ground = table[s, COL_GROUND] == 1
    if ground:
        a2 = 2.0 * 0.0 - a2
    o0, o1, o2 = n0, n1, n2
    g0 = g1 = g2 = 1.0
    for j in range(table[s, COL_NPLANES] - 1, -1, -1):  # image: last plane first
        ax, c = _plane(table[s, COL_PLANES + j], zf, zc, x0, x1, depth, pax, ppos)
        o0, o1, o2 = mirror(o0, o1, o2, ax, c)
        if ax == 0:
            g0 = -g0
        elif ax == 1:
            g1 = -g1
        else:
            g2 = -g2
    q0, q1, q2, ok = fermat_point(a0, a1, a2, o0, o1, o2, x_e, z_e, edge)
    v0, v1, v2 = a0 - q0, a1 - q1, a2 - q2
    u0, u1, u2 = o0 - q0, o1 - q1, o2 - q2
    d_in = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)  # = |Q - A| below, bit for bit (squares)
    nu = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    length = d_in + nu
    if ground:  # the ground point between the anchor's image and the edge (outside, y < 0)
        t_g = (0.0 - a2) / (q2 - a2)
        ok = ok and (t_g > 0) and (t_g < 1)
    # reflection points between the edge and the node, on the inside surface
    if _has_partition(table, s):
        ok = ok and _free_ok(q0, q1, q2, o0, o1, o2, 0.0, table, s, zf, zc, x0, x1, depth, pax,
                             ppos, plo, phi)
    else:
        ok = ok and _reflections_ok(q0, q1, q2, o0, o1, o2, 0.0, table, s, zf, zc, x0, x1,
                                    depth)
    u0, u1, u2 = u0 / nu, u1 / nu, u2 / nu
    v0, v1, v2 = q0 - a0, q1 - a1, q2 - a2
    v0, v1, v2 = v0 / d_in, v1 / d_in, v2 / d_in
    ok = ok and math.isfinite(length)
    dev = v0 * u0 + v1 * u1 + v2 * u2
    return length, ok, u0 * g0, u1 * g1, u2 * g2, dev, d_in


@njit(**_OPTS)
def edge_axis(x0, x1):
    """Length and unit vector of the edge ``(x0, 0, z) -> (x1, 0, z)`` as
    geometry.diffraction_point computes them (``z - z = 0`` for every finite z)."""
    w0, w1, w2 = x1 - x0, 0.0 - 0.0, 0.0
    edge_len = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    return edge_len, w0 / edge_len, w1 / edge_len, w2 / edge_len


@njit(**_OPTS)
def vertical_axis(lo, hi):
    """Length and unit vector of a vertical window edge ``(x, 0, lo) -> (x, 0, hi)`` as
    geometry.diffraction_point computes them."""
    w0, w1, w2 = 0.0, 0.0 - 0.0, hi - lo
    edge_len = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    return edge_len, w0 / edge_len, w1 / edge_len, w2 / edge_len


@njit(**_OPTS, inline="always")
def row_planes(floor, first_z, floor_h, sill, win_h):
    """``(z_floor, z_ceil, win_lo, win_hi)`` of floor index ``floor`` (float), with the
    operations of ``Building.floor_z_m`` / ``window_z_m``."""
    zf = first_z + floor * floor_h
    lo = zf + sill
    return zf, zf + floor_h, lo, lo + win_h


@njit(**_OPTS, inline="always")
def family_path(table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth, edge, raw,
                want_jac):
    """Row ``s`` of the mechanism ``table`` (module docstring) for one (anchor, node, floor)
    row, for other compiled kernels, without partitions (a partition family does not exist:
    :func:`family_path_parts` has them).

    ``zf, zc, lo, hi``: :func:`row_planes`; ``edge``: :func:`edge_axis`. Returns ``(length,
    valid, j0, j1, j2, deviation_cos, outside_m, entry_z)`` with the conventions of
    :func:`paths_kernel` (``raw``: unmasked, ``valid`` without the entry's band test; the
    Jacobian is 0 where masked or ``want_jac`` is False; NaN deviation / outside / entry where
    they do not apply).
    """
    if _has_partition(table, s):
        nan = np.nan
        return nan, False, 0.0, 0.0, 0.0, nan, nan, nan
    return _family_one(table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth, edge,
                       raw, want_jac, 0, 0.0, 0.0, 0.0)


@njit(**_OPTS)
def family_path_parts(table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth, edge,
                      raw, want_jac, parts):
    """:func:`family_path` with the building's partitions ``parts`` (:func:`partition_array`):
    a row with a ``"partition"`` plane is evaluated on every partition and the shortest
    existing path returned (``raw``: existing without the entry's band test; none existing:
    the first partition's raw values, or NaN / invalid without partitions)."""
    if not _has_partition(table, s):
        return _family_one(table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth,
                           edge, raw, want_jac, 0, 0.0, 0.0, 0.0)
    nan = np.nan
    best = (nan, False, 0.0, 0.0, 0.0, nan, nan, nan)
    for p in range(parts.shape[0]):
        res = _family_one(table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth,
                          edge, raw, want_jac, int(parts[p, 0]), parts[p, 1], parts[p, 2],
                          parts[p, 3])
        if p == 0 or (res[1] and (not best[1] or res[0] < best[0])):
            best = res
    return best


@njit(**_OPTS, inline="always")
def _family_one(table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth, edge, raw,
                want_jac, pax, ppos, plo, phi):
    """:func:`family_path` of one partition ``(pax, ppos, plo, phi)`` (ignored by a row
    without a ``"partition"`` plane)."""
    nan = np.nan
    kind = table[s, COL_KIND]
    dv = nan
    om = nan
    if kind == 2:
        code = table[s, COL_EDGE]
        if code < 2:  # horizontal: upper / lower
            z_e = hi if code == 0 else lo
            ln, ok, j0, j1, j2, dv, om = _diffracted(a0, a1, a2, n0, n1, n2, x0, z_e, table,
                                                     s, zf, zc, x0, x1, depth, edge, pax,
                                                     ppos, plo, phi)
        else:  # vertical x1 / x2: from the sill up
            x_e = x0 if code == 2 else x1
            ln, ok, j0, j1, j2, dv, om = _diffracted(a0, a1, a2, n0, n1, n2, x_e, lo, table,
                                                     s, zf, zc, x0, x1, depth,
                                                     vertical_axis(lo, hi), pax, ppos, plo,
                                                     phi)
        ez = nan
    else:
        if kind == 0:
            ln, ok, ez, d0, d1, d2, g0, g1, g2 = _direct(a0, a1, a2, n0, n1, n2, x0, x1)
        else:
            ln, ok, ez, d0, d1, d2, g0, g1, g2 = _specular(
                a0, a1, a2, n0, n1, n2, table[s, COL_GROUND] == 1, table, s, zf, zc, x0, x1,
                depth, pax, ppos, plo, phi)
        if not raw:
            ok = ok and (ez > lo) and (ez < hi)
        j0 = j1 = j2 = 0.0
        if want_jac and (ok or raw):  # the reference's d / length * sign
            j0, j1, j2 = d0 / ln * g0, d1 / ln * g1, d2 / ln * g2
    if not (ok or raw):
        ln = nan
        j0 = j1 = j2 = 0.0
    return ln, ok, j0, j1, j2, dv, om, ez


@njit(**_OPTS, inline="always")
def slot_path(s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth, edge, raw, want_jac):
    """Slot ``s`` of :data:`DEFAULT_TABLE` (the 18 mechanisms): :func:`family_path`."""
    return family_path(DEFAULT_TABLE, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth,
                       edge, raw, want_jac)


@njit(**_OPTS)
def paths_kernel(nodes, anchors, floor, first_z, floor_h, sill, win_h, x0, x1, depth, parts,
                 table, slots, raw, want_jac, length, valid, jac, dev, outm, entry_z):
    """Every requested slot (row of the mechanism ``table``) for every row (module
    docstring); writes the output arrays.

    The planes of row ``p`` are those of ``Building.floor_z_m`` / ``window_z_m`` with the same
    operations (:func:`row_planes`); each slot is :func:`family_path`.
    """
    edge = edge_axis(x0, x1)
    for p in range(nodes.shape[0]):
        a0, a1, a2 = anchors[p, 0], anchors[p, 1], anchors[p, 2]
        n0, n1, n2 = nodes[p, 0], nodes[p, 1], nodes[p, 2]
        zf, zc, lo, hi = row_planes(floor[p], first_z, floor_h, sill, win_h)
        for j in range(slots.shape[0]):
            ln, ok, j0, j1, j2, dv, om, ez = family_path_parts(
                table, slots[j], a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth, edge,
                raw, want_jac, parts)
            entry_z[p, j] = ez
            valid[p, j] = ok
            length[p, j] = ln
            if want_jac:
                jac[p, j, 0] = j0
                jac[p, j, 1] = j1
                jac[p, j, 2] = j2
                dev[p, j] = dv
                outm[p, j] = om


_state: dict[str, object] = {}


def warm_paths() -> float:
    """Compile :func:`paths_kernel` for :data:`SIGNATURE`, or load it from numba's cache.

    Idempotent; returns the seconds it took (0 once warm). Call it at service start.
    """
    if "entry" in _state:
        return 0.0
    t0 = time.perf_counter()
    paths_kernel.compile(SIGNATURE.args)
    _state["entry"] = paths_kernel
    return time.perf_counter() - t0


def eval_paths_kernel(nodes: np.ndarray, anchors: np.ndarray, floor: np.ndarray,
                      building_planes: tuple[float, ...], slots: np.ndarray, *,
                      raw: bool = False, want_jac: bool = True,
                      table: np.ndarray | None = None,
                      parts: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Allocate the outputs and run the kernel on flat rows.

    ``nodes``, ``anchors``: C-contiguous writable float64 ``(P, 3)``; ``floor``: float64
    ``(P,)`` floor index per row; ``building_planes``: :func:`building_planes` of the building;
    ``slots`` int64 ``(S,)``: rows of ``table`` (a C-contiguous int64 mechanism table,
    :func:`mechanism_table`; default :data:`DEFAULT_TABLE`, the 18 mechanisms). Returns
    ``(length (P, S), valid (P, S), jac (P, S, 3), deviation_cos, outside_m, entry_z)``; with
    ``want_jac=False`` the last three float outputs except ``entry_z`` are uninitialised.
    """
    warm_paths()
    p, s = nodes.shape[0], slots.shape[0]
    length = np.empty((p, s))
    valid = np.empty((p, s), dtype=np.bool_)
    jac = np.empty((p, s, 3) if want_jac else (0, 0, 3))
    dev = np.empty((p, s) if want_jac else (0, 0))
    outm = np.empty((p, s) if want_jac else (0, 0))
    entry_z = np.empty((p, s))
    tab = DEFAULT_TABLE if table is None else table
    prt = _NO_PARTS if parts is None else parts
    paths_kernel(nodes, anchors, floor, *building_planes, prt, tab, slots, bool(raw),
                 bool(want_jac), length, valid, jac, dev, outm, entry_z)
    return length, valid, jac, dev, outm, entry_z


def building_planes(building) -> tuple[float, ...]:
    """The building's scalars the kernel needs, in argument order: first floor z, floor
    height, sill height, window height, edge x0, x1, depth [m]."""
    x0, x1 = building.edge_x_m
    return (float(building.first_floor_z_m), float(building.floor_height_m),
            float(building.sill_height_m), float(building.window_height_m), float(x0),
            float(x1), float(building.depth_m))


def partition_array(building) -> np.ndarray:
    """The building's interior partitions as the kernels take them: float64 ``(Q, 4)``, rows
    ``(axis 0 | 1, position, span start, span end)`` [m] (``diffpos.paths.model.partition_rows``'s
    numbers; axis 0: the plane ``x = position``)."""
    rows = [(0.0 if p.axis == "x" else 1.0, float(p.position_m), float(min(p.span_m)),
             float(max(p.span_m))) for p in building.partitions]
    return np.ascontiguousarray(np.array(rows, dtype=np.float64).reshape(-1, 4))


def mechanism_table(recipes) -> np.ndarray:
    """The compiled mechanism table (module docstring) of ``diffpos.paths.mechanisms`` recipes
    (``MechanismSet.recipes``): int64 ``(K, COL_PLANES + max planes)``, at least 2 plane
    columns."""
    width = max(2, *(len(r.planes) for r in recipes))
    tab = np.full((len(recipes), COL_PLANES + width), -1, dtype=np.int64)
    for i, r in enumerate(recipes):
        tab[i, COL_KIND] = _KIND_CODE[r.kind]
        tab[i, COL_GROUND] = int(r.ground)
        tab[i, COL_EDGE] = -1 if r.edge is None else _EDGE_CODE[r.edge]
        tab[i, COL_NPLANES] = len(r.planes)
        tab[i, COL_PLANES:COL_PLANES + len(r.planes)] = [_PLANE_CODE[p] for p in r.planes]
    return tab
