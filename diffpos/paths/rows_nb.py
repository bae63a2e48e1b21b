"""Every mechanism of :data:`diffpos.paths.model_nb.DEFAULT_TABLE` for one (anchor, node, floor)
row at once: :func:`default_slots_row`, for compiled kernels that evaluate all 18 slots of a
row (the tracker's ``all_paths_kernel``).

Its values are those of ``slot_path(k, ..., raw=True, want_jac=True)`` for every ``k``, bit
for bit (length, existence without the entry's band test, Jacobian, entry height): each slot
is the same floating-point operations in the same order (the node's images ``2 c - v`` plane
by plane, last plane first; the unfolded ray, the facade crossing, the reflection walk; the
Fermat point of geometry.diffraction_point; the Jacobian ``d / length * sign``). What it
leaves out is work whose result the row does not return or the default table does not need:

* the slot recipes are read from small per-kind tables made once from ``DEFAULT_TABLE`` (no
  per-slot kind dispatch, partition scan or plane-code look-up through the whole table);
* the diffraction slots' deviation cosine and anchor-side length (``slot_path``'s
  ``deviation_cos`` / ``outside_m``, three divisions each) are not computed;
* the default table's diffraction slots are on the horizontal edges without a ground
  bounce (checked at import), so those branches are gone.

tests/core/test_paths_rows.py holds it to ``slot_path`` bit for bit (random rows on other
buildings, anchors above the windows and beyond the facade ends, nodes on every floor and
outside the band, degenerate rows); on the tracker's inputs of the 30 s ``large`` replay it
costs ~0.6 of the per-slot loop (docs/performance.md, "The paths of a row at once").
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from diffpos.paths.model_nb import (
    COL_EDGE,
    COL_GROUND,
    COL_NPLANES,
    COL_PLANES,
    DEFAULT_TABLE,
    SLOT_KIND,
    in_floor_box,
    inside_plane,
    mirror,
)

#: numba keys this file's on-disk cache on this file only, not on the ``*_nb`` code its
#: kernels compile in: a digest of that code (tests/core/test_kernel_stamps.py names the new
#: value after a callee's edit; writing it here is what invalidates a warm cache).
CALLEES_SHA256 = "2df3ef4ee9e18242"

__all__ = ["default_slots_row"]

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}

# the default table by kind: the direct slot, the specular slots (ground bounce, number of
# inside planes, their codes in path order) and the diffraction slots (upper edge, plane)
_DIRECT = np.flatnonzero(SLOT_KIND == 0)
_SPEC_K = np.flatnonzero(SLOT_KIND == 1).astype(np.int64)
_SPEC_GROUND = np.ascontiguousarray(DEFAULT_TABLE[_SPEC_K, COL_GROUND])
_SPEC_NPL = np.ascontiguousarray(DEFAULT_TABLE[_SPEC_K, COL_NPLANES])
_SPEC_P1 = np.ascontiguousarray(DEFAULT_TABLE[_SPEC_K, COL_PLANES])
_SPEC_P2 = np.ascontiguousarray(DEFAULT_TABLE[_SPEC_K, COL_PLANES + 1])
_DIFF_K = np.flatnonzero(SLOT_KIND == 2).astype(np.int64)
_DIFF_UP = np.ascontiguousarray((DEFAULT_TABLE[_DIFF_K, COL_EDGE] == 0).astype(np.int64))
_DIFF_P = np.ascontiguousarray(DEFAULT_TABLE[_DIFF_K, COL_PLANES])
if not (list(_DIRECT) == [0] and np.all(_SPEC_NPL <= 2)
        and np.all(DEFAULT_TABLE[_DIFF_K, COL_EDGE] < 2)
        and np.all(DEFAULT_TABLE[_DIFF_K, COL_GROUND] == 0)
        and np.all(DEFAULT_TABLE[_DIFF_K, COL_NPLANES] <= 1)
        and np.all(DEFAULT_TABLE[:, COL_PLANES:] < 5)):
    raise ValueError("paths.rows_nb: DEFAULT_TABLE has a recipe default_slots_row does not "
                     "cover (direct slot 0 only; <= 2 planes; diffraction on a horizontal "
                     "edge, no ground bounce, <= 1 plane; no partition): extend it")


@njit(**_OPTS)
def _hit(c0, c1, c2, m0, m1, m2, ax, c, t_last, zf, zc, x0, x1, depth):
    """One reflection of the walk on the unfolded ray ``c -> m`` (model_nb._reflections_ok's
    body): its ray parameter and whether it exists after ``t_last``."""
    dd0, dd1, dd2 = m0 - c0, m1 - c1, m2 - c2
    if ax == 0:
        t = (c - c0) / dd0
    elif ax == 1:
        t = (c - c1) / dd1
    else:
        t = (c - c2) / dd2
    ok = (t > t_last) and (t < 1)
    ok = ok and in_floor_box(c0 + t * dd0, c1 + t * dd1, c2 + t * dd2, zf, zc, x0, x1, depth)
    return ok, t


@njit(**_OPTS, inline="always")
def _flip(g0, g1, g2, ax):
    """The mirror signs after a mirror in a plane normal to ``ax``."""
    if ax == 0:
        return -g0, g1, g2
    if ax == 1:
        return g0, -g1, g2
    return g0, g1, -g2


@njit(**_OPTS, inline="always")
def _specular(a0, a1, a2, n0, n1, n2, ground, n_pl, p1, p2, zf, zc, x0, x1, depth):
    """model_nb._specular of a default slot (planes ``p1``, ``p2`` in path order, ``n_pl`` of
    them): length, ok (without the band test), entry z, Jacobian."""
    ax1, c1 = inside_plane(p1, zf, zc, x0, x1, depth)
    ax2, c2 = inside_plane(p2, zf, zc, x0, x1, depth)
    i0, i1, i2 = n0, n1, n2
    g0 = g1 = g2 = 1.0
    if n_pl == 2:  # image: last plane first
        i0, i1, i2 = mirror(i0, i1, i2, ax2, c2)
        g0, g1, g2 = _flip(g0, g1, g2, ax2)
    if n_pl >= 1:
        i0, i1, i2 = mirror(i0, i1, i2, ax1, c1)
        g0, g1, g2 = _flip(g0, g1, g2, ax1)
    s0, s1, s2 = a0, a1, a2
    if ground:
        s2 = 2.0 * 0.0 - a2
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
    e0 = s0 + t_f * d0
    ez = s2 + t_f * d2
    ok = ok and (e0 > x0) and (e0 < x1)
    if ok and n_pl >= 1:  # the reflection walk (model_nb: skipped by ``and`` as here)
        ok, t = _hit(s0, s1, s2, i0, i1, i2, ax1, c1, t_f, zf, zc, x0, x1, depth)
        if ok and n_pl == 2:
            m0, m1, m2 = mirror(i0, i1, i2, ax1, c1)
            q0, q1, q2 = mirror(s0, s1, s2, ax1, c1)
            ok, _ = _hit(q0, q1, q2, m0, m1, m2, ax2, c2, t, zf, zc, x0, x1, depth)
    ok = ok and math.isfinite(length)
    return length, ok, ez, d0 / length * g0, d1 / length * g1, d2 / length * g2


@njit(**_OPTS, inline="always")
def _diffracted(a0, a1, a2, n0, n1, n2, z_e, plane, zf, zc, x0, x1, depth, edge):
    """model_nb._diffracted of a default slot (the horizontal edge at ``z_e`` from ``x0``,
    no ground bounce, the inside plane ``plane`` after the edge or none if < 0): length, ok,
    Jacobian."""
    ax, c = inside_plane(plane, zf, zc, x0, x1, depth)
    o0, o1, o2 = n0, n1, n2
    g0 = g1 = g2 = 1.0
    if plane >= 0:
        o0, o1, o2 = mirror(o0, o1, o2, ax, c)
        g0, g1, g2 = _flip(g0, g1, g2, ax)
    x_e = x0
    edge_len, e0, e1, e2 = edge
    ds0, ds1, ds2 = a0 - x_e, a1 - 0.0, a2 - z_e
    do0, do1, do2 = o0 - x_e, o1 - 0.0, o2 - z_e
    s_t = ds0 * e0 + ds1 * e1 + ds2 * e2
    o_t = do0 * e0 + do1 * e1 + do2 * e2
    p0, p1, p2 = ds0 - s_t * e0, ds1 - s_t * e1, ds2 - s_t * e2
    r_s = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
    p0, p1, p2 = do0 - o_t * e0, do1 - o_t * e1, do2 - o_t * e2
    r_o = math.sqrt(p0 * p0 + p1 * p1 + p2 * p2)
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
    ok = (t_star > 0.0) and (t_star < edge_len)
    q0, q1, q2 = x_e + t * e0, 0.0 + t * e1, z_e + t * e2
    v0, v1, v2 = a0 - q0, a1 - q1, a2 - q2
    u0, u1, u2 = o0 - q0, o1 - q1, o2 - q2
    d_in = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    nu = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    length = d_in + nu
    if ok and plane >= 0:
        ok, _ = _hit(q0, q1, q2, o0, o1, o2, ax, c, 0.0, zf, zc, x0, x1, depth)
    ok = ok and math.isfinite(length)
    return length, ok, (u0 / nu) * g0, (u1 / nu) * g1, (u2 / nu) * g2


@njit(**_OPTS)
def default_slots_row(a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth, edge, length,
                      valid, jac, entry_z):
    """Every slot of ``DEFAULT_TABLE`` for the anchor ``a``, the node ``n`` and the floor's
    planes ``zf, zc, lo, hi`` (``model_nb.row_planes``; ``edge``: ``model_nb.edge_axis``):
    writes ``length`` (18,), ``valid`` (18,) bool (raw: without the entry's band test),
    ``jac`` (18, 3) and ``entry_z`` (18,) (NaN for the diffraction slots): ``slot_path(k,
    ..., raw=True, want_jac=True)``'s values for every ``k``, bit for bit."""
    d0, d1, d2 = n0 - a0, n1 - a1, n2 - a2  # model_nb._direct
    ln = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    t = -a1 / d1
    zcr = a2 + t * d2
    xc = a0 + t * d0
    length[0] = ln
    valid[0] = (xc > x0) and (xc < x1)
    entry_z[0] = zcr
    jac[0, 0], jac[0, 1], jac[0, 2] = d0 / ln * 1.0, d1 / ln * 1.0, d2 / ln * 1.0
    for q in range(_SPEC_K.shape[0]):
        k = _SPEC_K[q]
        ln, ok, ez, j0, j1, j2 = _specular(a0, a1, a2, n0, n1, n2, _SPEC_GROUND[q] == 1,
                                           _SPEC_NPL[q], _SPEC_P1[q], _SPEC_P2[q], zf, zc, x0,
                                           x1, depth)
        length[k] = ln
        valid[k] = ok
        entry_z[k] = ez
        jac[k, 0], jac[k, 1], jac[k, 2] = j0, j1, j2
    for q in range(_DIFF_K.shape[0]):
        k = _DIFF_K[q]
        ln, ok, j0, j1, j2 = _diffracted(a0, a1, a2, n0, n1, n2, hi if _DIFF_UP[q] == 1 else lo,
                                         _DIFF_P[q], zf, zc, x0, x1, depth, edge)
        length[k] = ln
        valid[k] = ok
        entry_z[k] = np.nan
        jac[k, 0], jac[k, 1], jac[k, 2] = j0, j1, j2

