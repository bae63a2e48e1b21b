"""Per-slot rays of the compiled SNR prediction (:mod:`diffpos.channel.snr_nb`, whose
docstring states the model and its differences to the numpy emulator): the direct ray, the
specular reflections and the UTD edge diffraction of one (anchor, node) pair, scalars only.

The fields are complex in the emulator; here a complex field is carried as its real and
imaginary parts (``re, im`` pairs) wherever it meets a *real* factor (a direction, a
spreading factor, a pattern amplitude): numba would promote the real factor to complex and
spend four products and two sums (or a complex division: three divisions and a branch) where
two products do. Every value is the complex arithmetic's bit for bit when finite (the
promoted product's extra terms are ``x * 0``: they change at most the sign of a zero, which
no later step can see: every field ends in ``|gain|^2`` sums of squares); a non-finite field
is an invalid slot either way (``math.isfinite`` of the magnitude). The genuinely complex
steps (Fresnel coefficients, ``Gamma * E``, the Faddeeva branch of the UTD term) are the
complex operations of numba (CPython's formulas), written out where their operands are
pairs.

The per-slot functions that take the ``prm`` / ``parts`` arrays (:func:`_direct`,
:func:`_specular`, :func:`_diffracted`, the UTD field, :func:`_partition_loss`,
:func:`_tx_field`) are inlined at numba IR level (``_INLINE``): an array passed to a compiled
call costs two atomic reference-count operations and the call itself, per slot; inlining
keeps every floating-point operation and its order (no fast-math), so the values are the
same bits. The scalar-only helpers (:func:`_reflect`, :func:`_fresnel`, the UTD terms) stay
calls: inlining them too measured ~3 % less CPU for twice the compile again.

numba keys the cache of the kernels in :mod:`diffpos.channel.snr_nb` on that file: they
compile these functions into themselves, so after editing this file (or
:mod:`diffpos.channel.transition_nb`) update its ``CALLEES_SHA256`` stamp (the value
tests/core/test_kernel_stamps.py names), which invalidates the stale cache.
"""

from __future__ import annotations

import cmath
import math

import numpy as np
from numba import njit

from diffpos.channel.transition_nb import (
    _EXP_J_3PI4,
    _EXP_J_PI4,
    _SQRT_PI,
    TRANSITION_ASYMPTOTIC_MIN,
    faddeeva,
    transition_asymptotic,
)
from diffpos.paths.model_nb import (
    SLOT_EDGE,
    SLOT_GROUND,
    SLOT_PLANE0,
    SLOT_PLANE1,
    fermat_point,
    in_floor_box,
    inside_plane,
    mirror,
)

#: numba keys this file's on-disk cache on this file only, not on the ``*_nb`` code its
#: kernels compile in: a digest of that code (tests/core/test_kernel_stamps.py names the new
#: value after a callee's edit; writing it here is what invalidates a warm cache).
CALLEES_SHA256 = "23889a5af4f29efa"

_RAD2DEG = 180.0 / math.pi
_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}
#: the per-slot functions inlined into the kernels (module docstring)
_INLINE = {**_OPTS, "inline": "always"}

# params (float64 vector) layout, filled by channel_params
_P_FIRST_Z, _P_FLOOR_H, _P_SILL, _P_WIN_H, _P_X0, _P_X1, _P_DEPTH, _P_N_FLOORS = range(8)
_P_WALL_DB, _P_SLAB_DB, _P_GLASS_DB = 8, 9, 10
_P_K, _P_LAM, _P_TX_HPBW, _P_TX_PEAK, _P_RX_HPBW, _P_RX_PEAK = 11, 12, 13, 14, 15, 16
_P_POWER0, _P_PGAIN, _P_N0 = 17, 18, 19
_P_E0 = 20  # three entries
N_PARAMS = 23


@njit(**_OPTS)
def _zenith_deg(d0, d1, d2):
    """channel._zenith_deg: zenith angle of a (not necessarily unit) vector [deg]."""
    n = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    u2 = d2 / n
    if u2 < -1.0:
        u2 = -1.0
    elif u2 > 1.0:
        u2 = 1.0
    return math.acos(u2) * _RAD2DEG


@njit(**_OPTS)
def _pattern_db(zen, hpbw, peak):
    """channel._pattern_db; ``hpbw`` NaN = isotropic (0 dB)."""
    if math.isnan(hpbw):
        return 0.0
    r = (zen - peak) / hpbw
    return -min(12.0 * (r * r), 30.0)


@njit(**_OPTS)
def _floor_index(z, first_z, floor_h, n_floors):
    """Building.floor_index as a float (NaN for a NaN height)."""
    k = np.floor((z - first_z) / floor_h)
    if k < -1.0:
        k = -1.0
    elif k > n_floors:
        k = n_floors
    return k


@njit(**_INLINE)
def _partition_loss(p0, p1, p2, q0, q1, q2, parts):
    """channel._Ctx.partition_loss_db of the segment p -> q [dB]."""
    loss = 0.0
    for i in range(parts.shape[0]):
        axis = int(parts[i, 0])
        pos = parts[i, 1]
        if axis == 0:
            a, bq, po, qo = p0 - pos, q0 - pos, p1, q1
        else:
            a, bq, po, qo = p1 - pos, q1 - pos, p0, q0
        db = 0.0
        if a * bq < 0:
            t = a / (a - bq)
            o = po + t * (qo - po)
            if o > parts[i, 2] and o < parts[i, 3]:
                db = parts[i, 4]
        loss = loss + db
    return loss


@njit(**_INLINE)
def _tx_field(u0, u1, u2, prm):
    """channel._Ctx.tx_field: the dipole's transverse field (real: the polarisation vector
    is real) and the pattern gain [dB] (applied in dB by the caller: every later step is
    linear in the field)."""
    g_db = 0.0
    if not math.isnan(prm[_P_TX_HPBW]):
        g_db = _pattern_db(_zenith_deg(u0, u1, u2), prm[_P_TX_HPBW], prm[_P_TX_PEAK])
    e0, e1, e2 = prm[_P_E0], prm[_P_E0 + 1], prm[_P_E0 + 2]
    ed = e0 * u0 + e1 * u1 + e2 * u2
    return e0 - ed * u0, e1 - ed * u1, e2 - ed * u2, g_db


@njit(**_OPTS)
def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(**_OPTS)
def _unit(v0, v1, v2):
    """Unit vector and norm (one division: the field's directions, never an existence
    test, so the 1-ulp difference to numpy's three divisions is immaterial)."""
    n = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    inv = 1.0 / n
    return v0 * inv, v1 * inv, v2 * inv, n


@njit(**_OPTS)
def _reflect(r0, i0, r1, i1, r2, i2, k0, k1, k2, axis, eta):
    """channel._reflect_field: the complex field ``(r0 + j i0, r1 + j i1, r2 + j i2)`` of a
    ray along the unit vector k reflected off the plane normal to ``axis`` (Fresnel TE/TM
    split), as six floats in the same order."""
    m0 = 1.0 if axis == 0 else 0.0
    m1 = 1.0 if axis == 1 else 0.0
    m2 = 1.0 if axis == 2 else 0.0
    if axis == 0:
        cos_t, o0, o1, o2 = abs(k0), -k0, k1, k2
    elif axis == 1:
        cos_t, o0, o1, o2 = abs(k1), k0, -k1, k2
    else:
        cos_t, o0, o1, o2 = abs(k2), k0, k1, -k2
    c0, c1, c2 = _cross(k0, k1, k2, m0, m1, m2)
    s0, s1, s2, sn = _unit(c0, c1, c2)
    if not sn > 1e-12:  # normal incidence: any transverse direction works as s
        s0 = 1.0 if (axis + 1) % 3 == 0 else 0.0
        s1 = 1.0 if (axis + 1) % 3 == 1 else 0.0
        s2 = 1.0 if (axis + 1) % 3 == 2 else 0.0
    pi0, pi1, pi2 = _cross(s0, s1, s2, k0, k1, k2)
    po0, po1, po2 = _cross(s0, s1, s2, o0, o1, o2)
    gs, gp = _fresnel(cos_t, eta)
    esr, esi = (r0 * s0 + r1 * s1) + r2 * s2, (i0 * s0 + i1 * s1) + i2 * s2
    epr, epi = (r0 * pi0 + r1 * pi1) + r2 * pi2, (i0 * pi0 + i1 * pi1) + i2 * pi2
    ar, ai = _cmul(gs.real, gs.imag, esr, esi)
    br, bi = _cmul(gp.real, gp.imag, epr, epi)
    return (ar * s0 + br * po0, ai * s0 + bi * po0, ar * s1 + br * po1, ai * s1 + bi * po1,
            ar * s2 + br * po2, ai * s2 + bi * po2)


@njit(**_OPTS)
def _fresnel(cos_t, eta):
    """slots.fresnel_coefficients: the half-space's TE and TM reflection coefficients."""
    c = min(max(cos_t, 0.0), 1.0)
    root = cmath.sqrt(eta - (1.0 - c * c) + 0j)
    return (c - root) / (c + root), (eta * c - root) / (eta * c + root)


@njit(**_OPTS)
def _cmul(a, b, c, d):
    """``(a + j b) (c + j d)`` with numba's (CPython's) operations: ``(ac - bd, ad + bc)``."""
    return a * c - b * d, a * d + b * c


@njit(**_OPTS)
def _norm_c(r0, i0, r1, i1, r2, i2):
    """channel._field_norm of a complex 3-vector given as six floats (the real part of
    ``sum f conj(f)``: ``r r - i (-i)`` is ``r r + i i`` exactly)."""
    return math.sqrt(((r0 * r0 + i0 * i0) + (r1 * r1 + i1 * i1)) + (r2 * r2 + i2 * i2))


@njit(**_OPTS)
def _ray_gain(amp, length, lam):
    """|channel._Ctx.ray_gain| without its loss factor (applied in dB by the caller) and
    phase: ``amp lambda / (4 pi d)``."""
    return amp * (lam / (4 * math.pi * length))


@njit(**_INLINE)
def _direct(a0, a1, a2, n0, n1, n2, k_node, lo, hi, prm, parts):
    """channel._direct: |gain| and arrival direction of the straight ray (through the window
    opening, another floor's window band, or the wall and slabs, with their losses)."""
    d0, d1, d2 = n0 - a0, n1 - a1, n2 - a2
    u0, u1, u2, length = _unit(d0, d1, d2)
    t = -a1 / d1
    zc = a2 + t * d2
    xc = a0 + t * d0
    x0, x1 = prm[_P_X0], prm[_P_X1]
    through = (zc > lo) and (zc < hi) and (xc > x0) and (xc < x1)
    k_cross = _floor_index(zc, prm[_P_FIRST_Z], prm[_P_FLOOR_H], prm[_P_N_FLOORS])
    n_slabs = abs(k_node - k_cross)
    zlo_c = (prm[_P_FIRST_Z] + k_cross * prm[_P_FLOOR_H]) + prm[_P_SILL]
    zhi_c = zlo_c + prm[_P_WIN_H]
    other = ((k_cross >= 0) and (k_cross < prm[_P_N_FLOORS]) and (zc > zlo_c) and (zc < zhi_c)
             and (xc > x0) and (xc < x1))
    loss = (prm[_P_GLASS_DB] if (through or other) else prm[_P_WALL_DB]) + n_slabs * prm[_P_SLAB_DB]
    loss = loss + _partition_loss(a0 + t * d0, a1 + t * d1, a2 + t * d2, n0, n1, n2, parts)
    e0, e1, e2, g_db = _tx_field(u0, u1, u2, prm)
    amp = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
    return _ray_gain(amp, length, prm[_P_LAM]), loss - g_db, -u0, -u1, -u2, length


@njit(**_OPTS)
def _specular_points(s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth):
    """The geometry of :func:`_specular` (paths.specular_path, <= 2 planes): (valid, length,
    the ground bounce point, the window entry point, the inside bounce points r1, r2; NaN
    where the slot has none)."""
    ground = SLOT_GROUND[s] == 1
    pl0, pl1 = SLOT_PLANE0[s], SLOT_PLANE1[s]
    n_pl = 0 if pl0 < 0 else (1 if pl1 < 0 else 2)
    src0, src1, src2 = a0, a1, a2
    if ground:
        src2 = 2.0 * 0.0 - a2
    i0, i1, i2 = n0, n1, n2
    for j in range(n_pl - 1, -1, -1):  # image: last plane first
        ax, c = inside_plane(pl0 if j == 0 else pl1, zf, zc, x0, x1, depth)
        i0, i1, i2 = mirror(i0, i1, i2, ax, c)
    d0, d1, d2 = i0 - src0, i1 - src1, i2 - src2
    length = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    nan = np.nan
    t_f = (0.0 - src1) / d1
    ok = True
    t_prev = 0.0
    g0 = g1 = g2 = nan
    if ground:
        t_g = (0.0 - src2) / d2
        ok = (t_g > 0) and (t_g < t_f)
        t_prev = t_g
        g0, g1, g2 = src0 + t_g * d0, src1 + t_g * d1, src2 + t_g * d2
    ok = ok and (t_f > t_prev) and (t_f < 1)
    en0, en1, en2 = src0 + t_f * d0, src1 + t_f * d1, src2 + t_f * d2
    ok = ok and (en2 > lo) and (en2 < hi) and (en0 > x0) and (en0 < x1)
    r10 = r11 = r12 = r20 = r21 = r22 = nan
    c0, c1, c2 = src0, src1, src2
    m0, m1, m2 = i0, i1, i2
    t_last = t_f
    for j in range(n_pl):
        ax, c = inside_plane(pl0 if j == 0 else pl1, zf, zc, x0, x1, depth)
        dd0, dd1, dd2 = m0 - c0, m1 - c1, m2 - c2
        if ax == 0:
            t = (c - c0) / dd0
        elif ax == 1:
            t = (c - c1) / dd1
        else:
            t = (c - c2) / dd2
        ok = ok and (t > t_last) and (t < 1)
        q0, q1, q2 = c0 + t * dd0, c1 + t * dd1, c2 + t * dd2
        ok = ok and in_floor_box(q0, q1, q2, zf, zc, x0, x1, depth)
        if j == 0:
            r10, r11, r12 = q0, q1, q2
        else:
            r20, r21, r22 = q0, q1, q2
        m0, m1, m2 = mirror(m0, m1, m2, ax, c)
        c0, c1, c2 = mirror(c0, c1, c2, ax, c)
        t_last = t
    ok = ok and math.isfinite(length)
    return ok, length, g0, g1, g2, en0, en1, en2, r10, r11, r12, r20, r21, r22


@njit(**_INLINE)
def _specular(s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, prm, parts, eta_g, eta_in):
    """channel._reflections for slot ``s`` (geometry: :func:`_specular_points`):
    (|gain|, arrival vector, length, valid)."""
    x0, x1, depth = prm[_P_X0], prm[_P_X1], prm[_P_DEPTH]
    ok, length, g0, g1, g2, en0, en1, en2, r10, r11, r12, r20, r21, r22 = _specular_points(
        s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth)
    nan = np.nan
    if not ok:
        return 0.0, 0.0, nan, nan, nan, length, False
    ground = SLOT_GROUND[s] == 1
    pl0, pl1 = SLOT_PLANE0[s], SLOT_PLANE1[s]
    n_pl = 0 if pl0 < 0 else (1 if pl1 < 0 else 2)
    # field: departure, ground bounce, then inside bounces (channel._reflections)
    if ground:
        u0, u1, u2, _ = _unit(g0 - a0, g1 - a1, g2 - a2)
    else:
        u0, u1, u2, _ = _unit(en0 - a0, en1 - a1, en2 - a2)
    f0, f1, f2, g_db = _tx_field(u0, u1, u2, prm)
    e0, e1, e2, e3, e4, e5 = f0, 0.0, f1, 0.0, f2, 0.0  # (re, im) of every component
    loss = prm[_P_GLASS_DB]
    if ground:
        e0, e1, e2, e3, e4, e5 = _reflect(e0, e1, e2, e3, e4, e5, u0, u1, u2, 2, eta_g)
        k0, k1, k2, _ = _unit(en0 - g0, en1 - g1, en2 - g2)
    else:
        k0, k1, k2 = u0, u1, u2
    # points in path order: entry, r1, (r2), node
    p0, p1, p2 = en0, en1, en2  # pts[j]
    for j in range(n_pl):
        ax, _c = inside_plane(pl0 if j == 0 else pl1, zf, zc, x0, x1, depth)
        e0, e1, e2, e3, e4, e5 = _reflect(e0, e1, e2, e3, e4, e5, k0, k1, k2, ax, eta_in)
        if j == 0:
            q0, q1, q2 = r10, r11, r12
        else:
            q0, q1, q2 = r20, r21, r22
        loss = loss + _partition_loss(p0, p1, p2, q0, q1, q2, parts)
        if j + 1 < n_pl:
            nx0, nx1, nx2 = r20, r21, r22
        else:
            nx0, nx1, nx2 = n0, n1, n2
        k0, k1, k2, _ = _unit(nx0 - q0, nx1 - q1, nx2 - q2)
        p0, p1, p2 = q0, q1, q2
    loss = loss + _partition_loss(p0, p1, p2, n0, n1, n2, parts)
    amp = _norm_c(e0, e1, e2, e3, e4, e5)
    if not math.isfinite(amp):
        return 0.0, 0.0, nan, nan, nan, length, False
    return (_ray_gain(amp, length, prm[_P_LAM]), loss - g_db, p0 - n0, p1 - n1, p2 - n2,
            length, True)


@njit(**_OPTS)
def _half_angle(x, y):
    """``(cos(a/2), sin(a/2))`` of ``a = atan2(y, x) mod 2 pi`` in ``[0, 2 pi)`` for a unit
    vector ``(x, y)`` (so ``a/2`` in ``[0, pi)``, ``sin(a/2) >= 0``): the component that is
    >= 1/sqrt(2) from ``sqrt((1 +- x) / 2)``, the other from ``sin a = 2 sin(a/2) cos(a/2)``,
    each to a few ulp (no cancellation). ``y = -0.0`` counts as ``a = 0`` (numpy's mod)."""
    if x >= 0.0:
        c = math.sqrt(0.5 * (1.0 + x))
        if y < 0.0:
            c = -c
        return c, y / (2.0 * c)
    s = math.sqrt(0.5 * (1.0 - x))
    return y / (2.0 * s), s


@njit(**_OPTS)
def _utd_term_ri(c, kl):
    """:func:`diffpos.channel.transition_nb._utd_term` as ``(re, im)``: in the asymptotic
    branch ``sgn F / |c|`` part by part (numba's complex product with ``sgn`` and division by
    ``|c|`` give these values: their extra terms are ``x * 0``), else the complex
    expression itself (:func:`_utd_term_root` of ``sqrt(2 kl)``)."""
    return _utd_term_root(c, math.sqrt(2.0 * kl))


@njit(**_OPTS)
def _utd_term_root(c, root):
    """:func:`_utd_term_ri` of ``root = sqrt(2 kl)``: a field's two UTD terms share their
    ``kl``, so :func:`utd_field_frame` takes the square root once (the same value)."""
    sgn = 1.0 if c >= 0.0 else -1.0
    t = root * abs(c)
    if t * t >= TRANSITION_ASYMPTOTIC_MIN:
        f = transition_asymptotic(t * t)
        ac = abs(c)
        return (sgn * f.real) / ac, (sgn * f.imag) / ac
    w = sgn * _SQRT_PI * root * _EXP_J_PI4 * faddeeva(_EXP_J_3PI4 * root * abs(c))
    return w.real, w.imag


@njit(**_INLINE)
def _utd_field(a0, a1, a2, o0, o1, o2, q0, q1, q2, s_in_m, s_out_m, upper, prm, sq2pik,
               eta_face):
    """gtd.diffracted_field (UTD, spherical spreading) of the window edge at Q for the
    source at the anchor and the observer O, without its common phase factors, as six floats
    (re, im of x, y, z). ``s_in_m`` = ``|Q - A|``, ``s_out_m`` = ``|O - Q|`` and ``sq2pik`` =
    ``sqrt(2 pi k)`` are the caller's (the same operations: computed once). The source's
    polarisation is the radio's. ``eta_face``: the sheet (the facade wall above / below the
    window; :func:`utd_field_frame`'s: 0 a perfect conductor, else its permittivity)."""
    if upper:  # e = +x, t0 = +z
        e0, e1, e2, t0, t1, t2 = 1.0, 0.0, 0.0, 0.0, 0.0, 1.0
    else:  # e = -x, t0 = -z
        e0, e1, e2, t0, t1, t2 = -1.0, 0.0, 0.0, 0.0, 0.0, -1.0
    return utd_field_frame(a0, a1, a2, o0, o1, o2, q0, q1, q2, s_in_m, s_out_m, e0, e1, e2,
                           t0, t1, t2, prm, sq2pik, prm[_P_E0], prm[_P_E0 + 1], prm[_P_E0 + 2],
                           eta_face)


@njit(**_INLINE)
def utd_field_frame(a0, a1, a2, o0, o1, o2, q0, q1, q2, s_in_m, s_out_m, e0, e1, e2, t0, t1,
                    t2, prm, sq2pik, ex, ey, ez, eta_face):
    """:func:`utd_field_e` on the half-plane of edge tangent ``e`` and face direction ``t0``
    (``diffpos.channel.gtd_halfplane.diffracted_field``'s ``edge_dir`` / ``face_dir``; the
    vertical window edges' half-plane is the side wall, the horizontal ones' the facade wall
    above / below the window). ``eta_face`` 0: a perfectly
    conducting sheet (Kouyoumjian-Pathak); else the relative permittivity of a dielectric
    sheet (``gtd_halfplane.utd_coefficients``' ``lit_face_reflection``: Luebbers' reflection
    terms, the Fresnel coefficients of the lit face and -1 for the unlit one)."""
    nn0, nn1, nn2 = _cross(e0, e1, e2, t0, t1, t2)
    di0, di1, di2 = q0 - a0, q1 - a1, q2 - a2
    do0, do1, do2 = o0 - q0, o1 - q1, o2 - q2
    inv = 1.0 / s_in_m  # _unit's operations
    si0, si1, si2 = di0 * inv, di1 * inv, di2 * inv
    inv = 1.0 / s_out_m
    so0, so1, so2 = do0 * inv, do1 * inv, do2 * inv
    if ((a0 - q0) * nn0 + (a1 - q1) * nn1 + (a2 - q2) * nn2) < 0.0:  # n0 faces the source
        nn0, nn1, nn2, e0, e1, e2 = -nn0, -nn1, -nn2, -e0, -e1, -e2
    ci0, ci1, ci2 = _cross(e0, e1, e2, si0, si1, si2)
    co0, co1, co2 = _cross(e0, e1, e2, so0, so1, so2)
    pi0, pi1, pi2, sin_g = _unit(ci0, ci1, ci2)
    pi0, pi1, pi2 = -pi0, -pi1, -pi2
    bi0, bi1, bi2 = _cross(pi0, pi1, pi2, si0, si1, si2)
    po0, po1, po2, _ = _unit(co0, co1, co2)
    bo0, bo1, bo2 = _cross(po0, po1, po2, so0, so1, so2)
    de = si0 * e0 + si1 * e1 + si2 * e2
    st0, st1, st2, _ = _unit(si0 - de * e0, si1 - de * e1, si2 - de * e2)
    # psi' = atan2(y', x') mod 2 pi and psi = atan2(y, x) mod 2 pi (EdgeFrame) enter only as
    # cos((psi -/+ psi') / 2): from their half-angle vectors, without atan2 and cos
    hc_in, hs_in = _half_angle(-(st0 * t0 + st1 * t1 + st2 * t2),
                               -(st0 * nn0 + st1 * nn1 + st2 * nn2))
    de = so0 * e0 + so1 * e1 + so2 * e2
    st0, st1, st2, _ = _unit(so0 - de * e0, so1 - de * e1, so2 - de * e2)
    hc, hs = _half_angle(st0 * t0 + st1 * t1 + st2 * t2, st0 * nn0 + st1 * nn1 + st2 * nn2)
    # sin(gamma0) with gamma0 = atan2(sin_g, |s' . e|) (EdgeFrame), without atan2 and sin
    cos_g = abs(si0 * e0 + si1 * e1 + si2 * e2)
    sin_gamma0 = sin_g / math.sqrt(sin_g * sin_g + cos_g * cos_g)
    k = prm[_P_K]
    # utd_coefficients with L = s s' sin^2 gamma0 / (s + s') (distance_parameter_m)
    big_l = s_out_m * s_in_m * sin_g ** 2 / (s_out_m + s_in_m)
    pre = 1.0 / (2.0 * sq2pik * sin_gamma0)  # |prefactor|
    root = math.sqrt(2.0 * (k * big_l))  # _utd_term_ri's, once for both terms
    mr, mi = _utd_term_root(hc * hc_in + hs * hs_in, root)  # cos((psi - psi') / 2)
    pr, pi_ = _utd_term_root(hc * hc_in - hs * hs_in, root)  # cos((psi + psi') / 2)
    if eta_face == 0j:  # perfectly conducting: the reflection terms' weights are -1 / +1
        dsr, dsi = pre * (mr - pr), pre * (mi - pi_)
        dhr, dhi = pre * (mr + pr), pre * (mi + pi_)
    else:  # dielectric: w = ((1 + sin((psi + psi')/2)) R0 - (1 - sin(...))) / 2
        sp = hs * hc_in + hc * hs_in
        gs, gp = _fresnel(abs(si0 * nn0 + si1 * nn1 + si2 * nn2), eta_face)
        wsr, wsi = 0.5 * ((1.0 + sp) * gs.real - (1.0 - sp)), 0.5 * (1.0 + sp) * gs.imag
        whr, whi = 0.5 * ((1.0 + sp) * gp.real - (1.0 - sp)), 0.5 * (1.0 + sp) * gp.imag
        ar, ai = _cmul(wsr, wsi, pr, pi_)
        dsr, dsi = pre * (mr + ar), pre * (mi + ai)
        ar, ai = _cmul(whr, whi, pr, pi_)
        dhr, dhi = pre * (mr + ar), pre * (mi + ai)
    ei_beta = (ex * bi0 + ey * bi1 + ez * bi2) / s_in_m
    ei_phi = (ex * pi0 + ey * pi1 + ez * pi2) / s_in_m
    amp = math.sqrt(s_in_m / (s_out_m * (s_out_m + s_in_m)))
    cbr, cbi = -dsr * ei_beta * amp, -dsi * ei_beta * amp
    cpr, cpi = -dhr * ei_phi * amp, -dhi * ei_phi * amp
    return (cbr * bo0 + cpr * po0, cbi * bo0 + cpi * po0, cbr * bo1 + cpr * po1,
            cbi * bo1 + cpi * po1, cbr * bo2 + cpr * po2, cbi * bo2 + cpi * po2)


@njit(**_INLINE)
def _diffracted(s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, prm, parts, eta_in, edge, sq2pik,
                eta_edge):
    """channel._diffracted for slot ``s`` (geometry: paths.diffracted_path):
    (|gain|, arrival vector, length, valid). ``sq2pik``: ``math.sqrt(2.0 * math.pi * k)``
    (the kernel's, once per call); ``eta_edge``: the window edge's sheet (0: a perfect
    conductor, the channel at order 2; else the facade wall's permittivity)."""
    x0, x1, depth = prm[_P_X0], prm[_P_X1], prm[_P_DEPTH]
    nan = np.nan
    upper = SLOT_EDGE[s] == 0
    z_e = hi if upper else lo
    then = SLOT_PLANE0[s]
    o0, o1, o2 = n0, n1, n2
    ax = 0
    c = 0.0
    if then >= 0:
        ax, c = inside_plane(then, zf, zc, x0, x1, depth)
        o0, o1, o2 = mirror(n0, n1, n2, ax, c)
    q0, q1, q2, ok = fermat_point(a0, a1, a2, o0, o1, o2, x0, z_e, edge)
    v0, v1, v2 = a0 - q0, a1 - q1, a2 - q2
    u0, u1, u2 = o0 - q0, o1 - q1, o2 - q2
    s_in_m = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)  # = |Q - A| bit for bit (squares)
    s_out_m = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    length = s_in_m + s_out_m
    rp0 = rp1 = rp2 = nan
    if then >= 0:  # reflection point between the edge and the node, on the inside surface
        if ax == 0:
            tr = (c - q0) / u0
        elif ax == 1:
            tr = (c - q1) / u1
        else:
            tr = (c - q2) / u2
        ok = ok and (tr > 0) and (tr < 1)
        rp0, rp1, rp2 = q0 + tr * u0, q1 + tr * u1, q2 + tr * u2
        ok = ok and in_floor_box(rp0, rp1, rp2, zf, zc, x0, x1, depth)
    ok = ok and math.isfinite(length)
    if not ok:
        return 0.0, 0.0, nan, nan, nan, length, False
    f0, f1, f2, f3, f4, f5 = _utd_field(a0, a1, a2, o0, o1, o2, q0, q1, q2, s_in_m, s_out_m,
                                        upper, prm, sq2pik, eta_edge)
    g_db = 0.0  # the pattern on departure, applied in dB (every later step is linear)
    if not math.isnan(prm[_P_TX_HPBW]):
        g_db = _pattern_db(_zenith_deg(q0 - a0, q1 - a1, q2 - a2), prm[_P_TX_HPBW],
                           prm[_P_TX_PEAK])
    if then < 0:
        loss = 0.0 + _partition_loss(q0, q1, q2, n0, n1, n2, parts)
        l0, l1, l2 = q0, q1, q2
    else:
        k0, k1, k2, _ = _unit(u0, u1, u2)
        f0, f1, f2, f3, f4, f5 = _reflect(f0, f1, f2, f3, f4, f5, k0, k1, k2, ax, eta_in)
        loss = (0.0 + _partition_loss(q0, q1, q2, rp0, rp1, rp2, parts)
                + _partition_loss(rp0, rp1, rp2, n0, n1, n2, parts))
        l0, l1, l2 = rp0, rp1, rp2
    c1 = prm[_P_LAM] / (4 * math.pi)
    amp = _norm_c(f0 * c1, f1 * c1, f2 * c1, f3 * c1, f4 * c1, f5 * c1)
    if not math.isfinite(amp):
        return 0.0, 0.0, nan, nan, nan, length, False
    return amp, loss - g_db, l0 - n0, l1 - n1, l2 - n2, length, True
