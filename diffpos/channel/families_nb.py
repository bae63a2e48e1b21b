"""Compiled SNR of the higher-order families of the emulated channel: any row of a mechanism
table (:func:`diffpos.paths.model_nb.mechanism_table` of
:func:`diffpos.paths.mechanisms.mechanism_set`), for the slots the 18 of
:mod:`diffpos.channel.snr_nb` leave out.

The numpy reference is :func:`diffpos.channel.slots.family_slot` (via
:func:`diffpos.channel.emulator.emulate_channel` with ``radio.channel_max_order`` > 2); the
physics is the emulator's: the dipole's transverse field and the transmit pattern on
departure, Fresnel reflections (TE/TM split) of the field vector on the ground (ITU ground
material) and on every inside slab or wall (interior material), the UTD field of the window
edge (a dielectric sheet of the walls' material, Luebbers' coefficients: every family is of
order >= 3, where the horizontal edges are dielectric too) with spherical spreading (a ground bounce first: the image source's reflected field meets
the edge, the field being linear in the source's polarisation), glass on a specular entry,
every inside segment's partitions, Friis spreading over the unfolded length. The geometry is
:func:`diffpos.paths.model.specular_path` / :func:`diffpos.paths.model.diffracted_path`'s
(image method, Fermat point strictly inside the edge, reflection points on the floor's inside
surface, in order). tests/core/test_channel_families.py holds the kernel to the reference
(same ``-inf`` pattern, finite values within 1e-7 dB: the operations are not ordered as the
reference's, so agreement is to rounding, not bit for bit).

numba keys this file's cache on this file only: after editing a ``*_nb`` module it compiles in,
update ``CALLEES_SHA256`` (tests/core/test_kernel_stamps.py names the value).
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit, types

from diffpos.channel.rays_nb import (
    _P_DEPTH,
    _P_E0,
    _P_FIRST_Z,
    _P_FLOOR_H,
    _P_GLASS_DB,
    _P_K,
    _P_LAM,
    _P_N0,
    _P_N_FLOORS,
    _P_PGAIN,
    _P_POWER0,
    _P_RX_HPBW,
    _P_RX_PEAK,
    _P_SILL,
    _P_TX_HPBW,
    _P_TX_PEAK,
    _P_WIN_H,
    _P_X0,
    _P_X1,
    _floor_index,
    _norm_c,
    _partition_loss,
    _pattern_db,
    _reflect,
    _tx_field,
    _unit,
    _zenith_deg,
    utd_field_frame,
)
from diffpos.paths.model_nb import (
    COL_EDGE,
    COL_GROUND,
    COL_KIND,
    COL_NPLANES,
    COL_PLANES,
    axis_component,
    edge_axis,
    facade_entry,
    fermat_point,
    in_floor_box,
    inside_plane,
    mirror,
    row_planes,
    vertical_axis,
    walk_ok,
)

#: numba keys this file's on-disk cache on this file only, not on the ``*_nb`` code its
#: kernels compile in: a digest of that code (tests/core/test_kernel_stamps.py names the new
#: value after a callee's edit; writing it here is what invalidates a warm cache).
CALLEES_SHA256 = "13024189c1a90fce"

__all__ = ["FAMILY_SIGNATURE", "eval_family_snr", "family_snr_kernel", "warm_families"]

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}
_PARTITION_CODE = 5  # model_nb's code of the "partition" plane
_NO_PART = (0.0, 0.0, 0.0, 0.0)  # no partition (a family without one)
_f8_1d = types.float64[::1]
_f8_2d = types.float64[:, ::1]
_f8_3d = types.float64[:, :, ::1]
#: The one compiled signature of :func:`family_snr_kernel`.
FAMILY_SIGNATURE = types.void(
    _f8_3d, _f8_2d,  # anchors (N, M, 3), nodes (N, 3)
    _f8_1d, _f8_2d, types.complex128[::1],  # prm, parts (P, 5), eta (channel_params)
    types.int64[:, ::1], types.int64[::1],  # mechanism table (K, C), slots (S,)
    types.boolean[:, :, ::1],  # mask (N, M, S): the pairs' slots to evaluate
    _f8_3d, _f8_3d,  # out (N, M, S) [dB], out_len (N, M, S) [m]
)


@njit(**_OPTS)
def _plane_of(code, zf, zc, x0, x1, depth, part):
    """inside_plane, and the partition ``part`` for the code of ``"partition"``."""
    if code == _PARTITION_CODE:
        return int(part[0]), part[1]
    return inside_plane(code, zf, zc, x0, x1, depth)


@njit(**_OPTS)
def _reflect_at(e0, e1, e2, e3, e4, e5, loss, p0, p1, p2, q0, q1, q2, ax, eta, parts):
    """The field reflected at ``q`` coming from ``p`` and the partitions' loss of ``p -> q``."""
    k0, k1, k2, _ = _unit(q0 - p0, q1 - p1, q2 - p2)
    e0, e1, e2, e3, e4, e5 = _reflect(e0, e1, e2, e3, e4, e5, k0, k1, k2, ax, eta)
    return e0, e1, e2, e3, e4, e5, loss + _partition_loss(p0, p1, p2, q0, q1, q2, parts)


@njit(**_OPTS)
def _walk(table, s, c0, c1, c2, m0, m1, m2, t_last, p0, p1, p2, ok, e0, e1, e2, e3, e4, e5,
          loss, zf, zc, x0, x1, depth, parts, eta_in, part, eta_p):
    """The inside reflections of row ``s`` on the unfolded ray ``c -> m`` after ``t_last``,
    coming from ``p``, in path order: each reflects the field and adds the partitions crossed
    on the way to it; a ``"partition"`` plane wherever the ray meets it among the others
    (paths.model._free_walk's geometry and tests). Returns (ok, field, loss, last point)."""
    has_p = False
    for j in range(table[s, COL_NPLANES]):
        has_p = has_p or table[s, COL_PLANES + j] == _PARTITION_CODE
    pax, ppos = int(part[0]), part[1]
    t_p = np.inf
    if has_p:
        t_p = ((ppos - axis_component(c0, c1, c2, pax))
               / axis_component(m0 - c0, m1 - c1, m2 - c2, pax))
        ok = ok and (t_p > t_last) and (t_p < 1)
    done = not has_p
    for j in range(table[s, COL_NPLANES] + 1):
        if j == table[s, COL_NPLANES]:
            t, ax, c = 2.0, 0, 0.0  # past the last plane: the partition, if still to come
        else:
            code = table[s, COL_PLANES + j]
            if code == _PARTITION_CODE:
                continue
            ax, c = inside_plane(code, zf, zc, x0, x1, depth)
            t = ((c - axis_component(c0, c1, c2, ax))
                 / axis_component(m0 - c0, m1 - c1, m2 - c2, ax))
            ok = ok and (t > t_last) and (t < 1)
        if not done and t_p < t:  # the partition first, in this frame
            q0, q1, q2 = c0 + t_p * (m0 - c0), c1 + t_p * (m1 - c1), c2 + t_p * (m2 - c2)
            if pax == 0:
                q0, other = ppos, q1
            else:
                q1, other = ppos, q0
            ok = ok and (other > part[2]) and (other < part[3])
            ok = ok and in_floor_box(q0, q1, q2, zf, zc, x0, x1, depth)
            e0, e1, e2, e3, e4, e5, loss = _reflect_at(e0, e1, e2, e3, e4, e5, loss, p0, p1, p2,
                                                       q0, q1, q2, pax, eta_p, parts)
            p0, p1, p2 = q0, q1, q2
            done = True
        if j == table[s, COL_NPLANES]:
            break
        r0, r1, r2 = c0 + t * (m0 - c0), c1 + t * (m1 - c1), c2 + t * (m2 - c2)
        if has_p and t_p < t:
            r0, r1, r2 = mirror(r0, r1, r2, pax, ppos)
        ok = ok and in_floor_box(r0, r1, r2, zf, zc, x0, x1, depth)
        e0, e1, e2, e3, e4, e5, loss = _reflect_at(e0, e1, e2, e3, e4, e5, loss, p0, p1, p2, r0,
                                                   r1, r2, ax, eta_in, parts)
        m0, m1, m2 = mirror(m0, m1, m2, ax, c)
        c0, c1, c2 = mirror(c0, c1, c2, ax, c)
        t_last = t
        p0, p1, p2 = r0, r1, r2
    return ok, e0, e1, e2, e3, e4, e5, loss, p0, p1, p2


@njit(**_OPTS)
def _images(table, s, a0, a1, a2, n0, n1, n2, zf, zc, prm, part):
    """Row ``s``'s images: whether it starts with a ground bounce, the anchor's image in the
    ground (the anchor without one) and the node's image in the row's planes, last first."""
    x0, x1, depth = prm[_P_X0], prm[_P_X1], prm[_P_DEPTH]
    ground = table[s, COL_GROUND] == 1
    i0, i1, i2 = n0, n1, n2
    for j in range(table[s, COL_NPLANES] - 1, -1, -1):
        ax, c = _plane_of(table[s, COL_PLANES + j], zf, zc, x0, x1, depth, part)
        i0, i1, i2 = mirror(i0, i1, i2, ax, c)
    return ground, a0, a1, (-a2 if ground else a2), i0, i1, i2


@njit(**_OPTS)
def _spec_family(table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, prm, parts, eta_g, eta_in,
                 part, eta_p):
    """slots._reflections for table row ``s`` (any number of planes): (|gain|, loss [dB] incl.
    the pattern, arrival vector, ok). ``part``: the partition ``(axis, position, span start,
    span end)`` a ``"partition"`` plane stands for, ``eta_p`` its permittivity."""
    x0, x1, depth = prm[_P_X0], prm[_P_X1], prm[_P_DEPTH]
    ground, s0, s1, s2, i0, i1, i2 = _images(table, s, a0, a1, a2, n0, n1, n2, zf, zc, prm,
                                             part)
    d0, d1, d2, length, t_f, t_g, ok = facade_entry(s0, s1, s2, i0, i1, i2, ground)
    g0, g1, g2 = s0 + t_g * d0, s1 + t_g * d1, s2 + t_g * d2  # the ground point (with ground)
    p0, p1, p2 = s0 + t_f * d0, s1 + t_f * d1, s2 + t_f * d2  # entry
    ok = ok and (p2 > lo) and (p2 < hi) and (p0 > x0) and (p0 < x1)
    ok = ok and walk_ok(s0, s1, s2, i0, i1, i2, t_f, table, s, zf, zc, x0, x1, depth,
                        int(part[0]), part[1], part[2], part[3])  # before any field
    if not (ok and math.isfinite(length)):
        return 0.0, 0.0, 0.0, 0.0, 0.0, length, False
    if ground:
        u0, u1, u2, _ = _unit(g0 - a0, g1 - a1, g2 - a2)
    else:
        u0, u1, u2, _ = _unit(p0 - a0, p1 - a1, p2 - a2)
    f0, f1, f2, g_db = _tx_field(u0, u1, u2, prm)
    e0, e1, e2, e3, e4, e5 = f0, 0.0, f1, 0.0, f2, 0.0
    if ground:
        e0, e1, e2, e3, e4, e5 = _reflect(e0, e1, e2, e3, e4, e5, u0, u1, u2, 2, eta_g)
    ok, e0, e1, e2, e3, e4, e5, loss, p0, p1, p2 = _walk(
        table, s, s0, s1, s2, i0, i1, i2, t_f, p0, p1, p2, ok, e0, e1, e2, e3, e4, e5,
        prm[_P_GLASS_DB], zf, zc, x0, x1, depth, parts, eta_in, part, eta_p)
    loss = loss + _partition_loss(p0, p1, p2, n0, n1, n2, parts)
    amp = _norm_c(e0, e1, e2, e3, e4, e5)
    ok = ok and math.isfinite(amp)
    gain = amp * (prm[_P_LAM] / (4 * math.pi * length))
    return gain, loss - g_db, p0 - n0, p1 - n1, p2 - n2, length, ok


@njit(**_OPTS)
def _diff_family(table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, prm, parts, eta_g, eta_in,
                 edge, sq2pik, part, eta_p, eta_wall):
    """slots._diffracted_family for table row ``s``: (|gain|, loss [dB] incl. the pattern,
    arrival vector, length, ok); ``part``, ``eta_p``: :func:`_spec_family`'s; ``eta_wall``:
    the walls' permittivity (every window edge's dielectric sheet: the side wall at a vertical
    edge, the facade wall at a horizontal one)."""
    x0, x1, depth = prm[_P_X0], prm[_P_X1], prm[_P_DEPTH]
    code = table[s, COL_EDGE]
    ground, s0, s1, s2, o0, o1, o2 = _images(table, s, a0, a1, a2, n0, n1, n2, zf, zc, prm,
                                             part)
    # the edge (slots._edge_frame): tangent e, half-plane face t0
    # every edge's half-plane a dielectric sheet of the walls' material (the families are
    # orders >= 3: slots.family_slot)
    if code == 0:  # upper: the facade wall above the window
        q0, q1, q2, ok = fermat_point(s0, s1, s2, o0, o1, o2, x0, hi, edge)
        ed0, ed2, tf1, tf2 = 1.0, 0.0, 0.0, 1.0
    elif code == 1:  # lower: the facade wall below it
        q0, q1, q2, ok = fermat_point(s0, s1, s2, o0, o1, o2, x0, lo, edge)
        ed0, ed2, tf1, tf2 = -1.0, 0.0, 0.0, -1.0
    else:  # vertical at x0 / x1: the side wall, into the building
        q0, q1, q2, ok = fermat_point(s0, s1, s2, o0, o1, o2, x0 if code == 2 else x1, lo,
                                 vertical_axis(lo, hi))
        ed0, ed2, tf1, tf2 = 0.0, (1.0 if code == 2 else -1.0), 1.0, 0.0
    sheet = eta_wall
    s_in = math.sqrt((s0 - q0) ** 2 + (s1 - q1) ** 2 + (s2 - q2) ** 2)
    s_out = math.sqrt((o0 - q0) ** 2 + (o1 - q1) ** 2 + (o2 - q2) ** 2)
    length = s_in + s_out
    t_g = 0.0
    if ground:
        t_g = (0.0 - s2) / (q2 - s2)
        ok = ok and (t_g > 0) and (t_g < 1)
    ok = ok and walk_ok(q0, q1, q2, o0, o1, o2, 0.0, table, s, zf, zc, x0, x1, depth,
                        int(part[0]), part[1], part[2], part[3])  # before the UTD
    if not (ok and math.isfinite(length)):
        return 0.0, 0.0, 0.0, 0.0, 0.0, length, False
    # the source's field: the radio's polarisation (pattern towards the edge), or the
    # dipole's field reflected on the ground (pattern towards the ground point)
    if ground:
        g0, g1 = s0 + t_g * (q0 - s0), s1 + t_g * (q1 - s1)
        u0, u1, u2, _ = _unit(g0 - a0, g1 - a1, 0.0 - a2)
        f0, f1, f2, g_db = _tx_field(u0, u1, u2, prm)
        e0, e1, e2, e3, e4, e5 = _reflect(f0, 0.0, f1, 0.0, f2, 0.0, u0, u1, u2, 2, eta_g)
    else:
        g_db = 0.0
        if not math.isnan(prm[_P_TX_HPBW]):
            g_db = _pattern_db(_zenith_deg(q0 - a0, q1 - a1, q2 - a2), prm[_P_TX_HPBW],
                               prm[_P_TX_PEAK])
        e0, e1, e2, e3, e4, e5 = prm[_P_E0], 0.0, prm[_P_E0 + 1], 0.0, prm[_P_E0 + 2], 0.0
    r = utd_field_frame(s0, s1, s2, o0, o1, o2, q0, q1, q2, s_in, s_out, ed0, 0.0, ed2, 0.0,
                        tf1, tf2, prm, sq2pik, e0, e2, e4, sheet)
    im = utd_field_frame(s0, s1, s2, o0, o1, o2, q0, q1, q2, s_in, s_out, ed0, 0.0, ed2, 0.0,
                         tf1, tf2, prm, sq2pik, e1, e3, e5, sheet)
    # field = UTD(Re e) + j UTD(Im e), each a (re, im) triple
    f0, f1 = r[0] - im[1], r[1] + im[0]
    f2, f3 = r[2] - im[3], r[3] + im[2]
    f4, f5 = r[4] - im[5], r[5] + im[4]
    ok, f0, f1, f2, f3, f4, f5, loss, p0, p1, p2 = _walk(
        table, s, q0, q1, q2, o0, o1, o2, 0.0, q0, q1, q2, ok, f0, f1, f2, f3, f4, f5, 0.0, zf,
        zc, x0, x1, depth, parts, eta_in, part, eta_p)
    loss = loss + _partition_loss(p0, p1, p2, n0, n1, n2, parts)
    c1_ = prm[_P_LAM] / (4 * math.pi)
    amp = _norm_c(f0 * c1_, f1 * c1_, f2 * c1_, f3 * c1_, f4 * c1_, f5 * c1_)
    ok = ok and math.isfinite(amp)
    return amp, loss - g_db, p0 - n0, p1 - n1, p2 - n2, length, ok


@njit(**_OPTS)
def _family(table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, prm, parts, eta, edge, sq2pik):
    """Row ``s`` for one pair: (|gain|, loss, arrival vector, length, ok); a partition family
    on every partition, the shortest existing path (slots.family_slot)."""
    kind = table[s, COL_KIND]
    has_p = False
    for j in range(table[s, COL_NPLANES]):
        has_p = has_p or table[s, COL_PLANES + j] == _PARTITION_CODE
    n_try = parts.shape[0] if has_p else 1
    best = (0.0, 0.0, 0.0, 0.0, 0.0, np.nan, False)
    for p in range(n_try):
        part = (parts[p, 0], parts[p, 1], parts[p, 2], parts[p, 3]) if has_p else _NO_PART
        eta_p = eta[2 + p] if has_p else eta[1]
        if kind == 1:
            res = _spec_family(table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, prm, parts,
                               eta[0], eta[1], part, eta_p)
        elif kind == 2:
            res = _diff_family(table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, prm, parts,
                               eta[0], eta[1], edge, sq2pik, part, eta_p,
                               eta[2 + parts.shape[0]])
        else:
            break
        if res[6] and res[0] != 0.0 and (not best[6] or res[5] < best[5]):
            best = res
    return best


@njit(**_OPTS)
def family_snr_kernel(anchors, nodes, prm, parts, eta, table, slots, mask, out, out_len):
    """SNR [dB] of the table rows ``slots`` for every pair: ``anchors`` (N, M, 3), ``nodes``
    (N, 3) -> ``out`` (N, M, S), ``-inf`` where the path does not exist (the numpy emulator's
    :func:`diffpos.channel.slots.family_slot` plus its link budget), and the path length
    ``out_len`` [m] (NaN where it does not exist). Direct rows are not served (the 18 of
    :mod:`diffpos.channel.snr_nb` hold the direct path): ``-inf``. Only where ``mask``
    (N, M, S) is True: elsewhere ``-inf`` and NaN, not evaluated (the rest bit for bit)."""
    first_z, floor_h, sill, win_h = prm[_P_FIRST_Z], prm[_P_FLOOR_H], prm[_P_SILL], prm[_P_WIN_H]
    edge = edge_axis(prm[_P_X0], prm[_P_X1])
    c0, pgain, n0_dbm = prm[_P_POWER0], prm[_P_PGAIN], prm[_P_N0]
    rx_hpbw, rx_peak = prm[_P_RX_HPBW], prm[_P_RX_PEAK]
    sq2pik = math.sqrt(2.0 * math.pi * prm[_P_K])
    ninf = -np.inf
    for i in range(nodes.shape[0]):
        n0, n1, n2 = nodes[i, 0], nodes[i, 1], nodes[i, 2]
        k_node = _floor_index(n2, first_z, floor_h, prm[_P_N_FLOORS])
        zf, zc, lo, hi = row_planes(k_node, first_z, floor_h, sill, win_h)
        for j in range(anchors.shape[1]):
            a0, a1, a2 = anchors[i, j, 0], anchors[i, j, 1], anchors[i, j, 2]
            for k in range(slots.shape[0]):
                if not mask[i, j, k]:
                    out[i, j, k] = ninf
                    out_len[i, j, k] = np.nan
                    continue
                s = slots[k]
                g, att, v0, v1, v2, length, ok = _family(
                    table, s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, prm, parts, eta, edge,
                    sq2pik)
                if not ok or g == 0.0:
                    out[i, j, k] = ninf
                    out_len[i, j, k] = np.nan
                    continue
                out_len[i, j, k] = length
                rx_db = 0.0
                if not math.isnan(rx_hpbw):
                    rx_db = _pattern_db(_zenith_deg(v0, v1, v2), rx_hpbw, rx_peak)
                out[i, j, k] = (c0 + rx_db + (20 * math.log10(g) - att)) + pgain - n0_dbm


_state: dict[str, object] = {}


def warm_families() -> float:
    """Compile :func:`family_snr_kernel` for :data:`FAMILY_SIGNATURE` or load it from numba's
    cache; idempotent; the seconds it took (0 once warm). The anchors' channel warm-up
    (:func:`diffpos.emulation.warm_up_channel`, a first :func:`diffpos.channel.emulator.pair_first_arrival`)
    reaches it when ``radio.channel_max_order`` > 2."""
    if "entry" in _state:
        return 0.0
    t0 = time.perf_counter()
    family_snr_kernel.compile(FAMILY_SIGNATURE.args)
    _state["entry"] = family_snr_kernel
    return time.perf_counter() - t0


def eval_family_snr(anchors: np.ndarray, nodes: np.ndarray,
                    params: tuple[np.ndarray, np.ndarray, np.ndarray], table: np.ndarray,
                    slots: np.ndarray, mask: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Run :func:`family_snr_kernel`: ``anchors`` (N, M, 3), ``nodes`` (N, 3) C-contiguous
    float64, ``params`` of :func:`diffpos.channel.snr_nb.channel_params`, the mechanism
    ``table`` and the rows ``slots`` of it; returns the SNR [dB] and the length [m], (N, M, S)
    each. ``mask`` (N, M, S) bool: only those (``-inf`` / NaN elsewhere); None: every one."""
    warm_families()
    shape = (nodes.shape[0], anchors.shape[1], slots.shape[0])
    out = np.empty(shape)
    out_len = np.empty_like(out)
    mask = (np.ones(shape, np.bool_) if mask is None
            else np.require(np.broadcast_to(mask, shape), np.bool_, ("C", "W")))
    family_snr_kernel(anchors, nodes, *params, np.ascontiguousarray(table, dtype=np.int64),
                      np.ascontiguousarray(slots, dtype=np.int64), mask, out, out_len)
    return out, out_len
