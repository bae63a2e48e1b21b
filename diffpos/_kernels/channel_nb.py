"""Compiled SNR prediction: the SNR of every slot of :func:`diffpos.channel.pair_snr_db`.

One loop over (node, anchor) pairs and the 18 slots of ``diffpos.channel.MECHANISMS``,
scalars only, no allocation in the loop. Every slot is the numpy emulator's computation
(``diffpos.channel._slots``: geometry of ``diffpos.paths``, transmit dipole and antenna
pattern, Fresnel reflections with the TE/TM split, the UTD field of ``diffpos.gtd`` with
spherical spreading, partition / wall / slab / glass losses, receive pattern, link budget)
with the same floating-point operations in the same order, except:

* **Global phases are dropped.** Only ``|gain|`` enters the SNR. The numpy emulator multiplies
  every field by phase factors common to all its components (``exp(-j k d)`` of the ray, the
  incident ``exp(-j k s')`` and diffracted ``exp(-j k s)`` of the UTD field, the
  ``-exp(-j pi/4)`` of the UTD prefactor); a common phase survives the (linear) reflections
  unchanged and cancels in the magnitude, so the kernel leaves them out (``|gain|`` changes by
  rounding only, ~1e-16 relative).
* **Gains and losses in dB.** The transmit pattern and the wall / slab / glass / partition
  losses scale the field linearly, so the kernel adds them to ``20 log10 |gain|`` instead of
  multiplying the field by ``10 ** (dB / 20)`` (rounding only).
* **Angles without trigonometry.** The UTD coefficients need ``cos((psi -/+ psi') / 2)`` and
  ``sin gamma0`` only; they are formed from the unit vectors (half-angle vectors of ``psi``
  and ``psi'``, :func:`_half_angle`) instead of ``atan2`` / ``mod`` / ``cos`` / ``sin`` of the
  angles (a few ulp; the sign of ``cos(b/2)``, which decides the side of a shadow boundary,
  can differ from numpy's only within a few ulp of the boundary itself).
* **Transition function.** ``F(X)`` through the Faddeeva function ``w`` (Weideman's
  rational approximation and asymptotic series, compiled): :mod:`.transition_nb`.

The resulting SNRs agree with the numpy emulator to 3.4e-12 dB (max over 12,000 random links x
3 radios x 4 buildings, tests/core/test_channel_kernel.py; tolerance 1e-9 dB) with the same
``-inf`` pattern.

Cost (``benchmarks/bench_channel.py --snr-only``): ~2.2 us CPU per link (18 slots), 6x less
than numpy on large batches and ~400x less on one-node calls (numpy's per-call overhead);
about 80 % of it in the 7 diffraction slots (the UTD field). First call: ~5.5 s CPU to
compile, ~0.2 s to load numba's on-disk cache.

Existence (``valid``) is the emulator's: the geometry of ``diffpos.paths`` (specular paths
entering through the window band, Fermat point strictly inside the edge, reflection points on
the floor's inside surface within 1e-9 m), the through-wall direct ray always valid, and the
slot dropped where its length or field is not finite. The per-row pieces of
:mod:`diffpos._kernels.paths_nb` are reused (plane codes and slot recipes, ``row_planes``,
``edge_axis``, ``_plane``, ``_mirror``, ``_in_box``); the path functions themselves are
re-stated here because the amplitudes need their interaction points (entry, ground and
reflection points, the diffraction point), which ``slot_path`` does not return.

Inputs are plain arrays prepared once in Python (:func:`channel_params`): the building's
planes and losses, the partitions as a ``(P, 5)`` array ``(axis, position, span lo, span hi,
loss dB)``, the radio (wavenumber, wavelength, patterns, link-budget constants, polarisation)
and the two complex permittivities (ground, interior). One compiled signature
(:data:`SIGNATURE`), ``cache=True``; :func:`warm_channel` compiles it or loads numba's on-disk
cache (call it at service start).

:func:`channel_snr_masked_kernel` is the same loop over a per-pair slot mask ``need``
(:data:`MASKED_SIGNATURE`): the slots needed are evaluated by the same statements, so they
are bit-identical to the unmasked kernel's; the others are not evaluated and hold NaN (the tracker re-scores a pair's "hole" slots at a shifted height,
``diffpos.tracking_snr.snr_cost_near``: mostly specular slots near a window-band edge, and
not the 7 diffraction slots that are ~80 % of a full prediction).

:func:`snr_cost_kernel` is the tracker's SNR cost of the predicted slots (Gaussian about the
prediction plus the detector's threshold), the numpy reference's operations in one pass.
"""

from __future__ import annotations

import cmath
import math
import time

import numpy as np
from numba import njit, types

from ..constants import SPEED_OF_LIGHT_M_S
from ..linkbudget import noise_floor_dbm
from .paths_nb import (
    _EDGE,
    _GROUND,
    _KIND,
    _PLANE0,
    _PLANE1,
    N_SLOTS,
    _in_box,
    _mirror,
    _plane,
    edge_axis,
    row_planes,
)
from .pool import SNR_MIN_PAIRS, run_rows
from .transition_nb import (
    ASYMPTOTIC_MIN_ABS,
    TRANSITION_ASYMPTOTIC_MIN,
    WEIDEMAN_N,
    _utd_term,
    faddeeva,
    faddeeva_kernel,
    transition,
    transition_asymptotic,
    weideman_coefficients,
)

__all__ = ["ASYMPTOTIC_MIN_ABS", "COST_SIGNATURE", "MASKED_SIGNATURE", "SIGNATURE",
           "TRANSITION_ASYMPTOTIC_MIN", "WEIDEMAN_N", "channel_params", "channel_snr_kernel",
           "channel_snr_masked_kernel", "eval_snr_kernel", "eval_snr_masked_kernel", "faddeeva", "faddeeva_kernel",
           "snr_cost_kernel", "transition", "transition_asymptotic", "warm_channel",
           "weideman_coefficients"]

_RAD2DEG = 180.0 / math.pi
_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}

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


@njit(**_OPTS)
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


@njit(**_OPTS)
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
def _reflect(f0, f1, f2, k0, k1, k2, axis, eta):
    """channel._reflect_field: the complex field (f0, f1, f2) of a ray along the unit vector
    k reflected off the plane normal to ``axis`` (Fresnel TE/TM split)."""
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
    # fresnel_coefficients
    c = min(max(cos_t, 0.0), 1.0)
    root = cmath.sqrt(eta - (1.0 - c * c) + 0j)
    gs = (c - root) / (c + root)
    gp = (eta * c - root) / (eta * c + root)
    es = f0 * s0 + f1 * s1 + f2 * s2
    ep = f0 * pi0 + f1 * pi1 + f2 * pi2
    a = gs * es
    b = gp * ep
    return a * s0 + b * po0, a * s1 + b * po1, a * s2 + b * po2


@njit(**_OPTS)
def _norm_c(f0, f1, f2):
    """channel._field_norm of a complex 3-vector."""
    return math.sqrt((f0 * f0.conjugate() + f1 * f1.conjugate() + f2 * f2.conjugate()).real)


@njit(**_OPTS)
def _ray_gain(amp, length, lam):
    """|channel._Ctx.ray_gain| without its loss factor (applied in dB by the caller) and
    phase: ``amp lambda / (4 pi d)``."""
    return amp * (lam / (4 * math.pi * length))


@njit(**_OPTS)
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
def _specular(s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, prm, parts, eta_g, eta_in):
    """channel._reflections for slot ``s`` (geometry: paths.specular_path, <= 2 planes):
    (|gain|, arrival vector, length, valid)."""
    x0, x1, depth = prm[_P_X0], prm[_P_X1], prm[_P_DEPTH]
    ground = _GROUND[s] == 1
    pl0, pl1 = _PLANE0[s], _PLANE1[s]
    n_pl = 0 if pl0 < 0 else (1 if pl1 < 0 else 2)
    src0, src1, src2 = a0, a1, a2
    if ground:
        src2 = 2.0 * 0.0 - a2
    i0, i1, i2 = n0, n1, n2
    for j in range(n_pl - 1, -1, -1):  # image: last plane first
        ax, c = _plane(pl0 if j == 0 else pl1, zf, zc, x0, x1, depth)
        i0, i1, i2 = _mirror(i0, i1, i2, ax, c)
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
        ax, c = _plane(pl0 if j == 0 else pl1, zf, zc, x0, x1, depth)
        dd0, dd1, dd2 = m0 - c0, m1 - c1, m2 - c2
        if ax == 0:
            t = (c - c0) / dd0
        elif ax == 1:
            t = (c - c1) / dd1
        else:
            t = (c - c2) / dd2
        ok = ok and (t > t_last) and (t < 1)
        q0, q1, q2 = c0 + t * dd0, c1 + t * dd1, c2 + t * dd2
        ok = ok and _in_box(q0, q1, q2, zf, zc, x0, x1, depth)
        if j == 0:
            r10, r11, r12 = q0, q1, q2
        else:
            r20, r21, r22 = q0, q1, q2
        m0, m1, m2 = _mirror(m0, m1, m2, ax, c)
        c0, c1, c2 = _mirror(c0, c1, c2, ax, c)
        t_last = t
    ok = ok and math.isfinite(length)
    if not ok:
        return 0.0, 0.0, nan, nan, nan, length, False
    # field: departure, ground bounce, then inside bounces (channel._reflections)
    if ground:
        u0, u1, u2, _ = _unit(g0 - a0, g1 - a1, g2 - a2)
    else:
        u0, u1, u2, _ = _unit(en0 - a0, en1 - a1, en2 - a2)
    f0, f1, f2, g_db = _tx_field(u0, u1, u2, prm)
    e0, e1, e2 = f0 + 0j, f1 + 0j, f2 + 0j
    loss = prm[_P_GLASS_DB]
    if ground:
        e0, e1, e2 = _reflect(e0, e1, e2, u0, u1, u2, 2, eta_g)
        k0, k1, k2, _ = _unit(en0 - g0, en1 - g1, en2 - g2)
    else:
        k0, k1, k2 = u0, u1, u2
    # points in path order: entry, r1, (r2), node
    p0, p1, p2 = en0, en1, en2  # pts[j]
    for j in range(n_pl):
        ax, _c = _plane(pl0 if j == 0 else pl1, zf, zc, x0, x1, depth)
        e0, e1, e2 = _reflect(e0, e1, e2, k0, k1, k2, ax, eta_in)
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
    amp = _norm_c(e0, e1, e2)
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
def _utd_field(a0, a1, a2, o0, o1, o2, q0, q1, q2, upper, prm):
    """gtd.diffracted_field (UTD, spherical spreading) of the window edge at Q for the
    source at the anchor and the observer O, without its common phase factors."""
    if upper:  # e = +x, t0 = +z
        e0, e1, e2, t0, t1, t2 = 1.0, 0.0, 0.0, 0.0, 0.0, 1.0
    else:  # e = -x, t0 = -z
        e0, e1, e2, t0, t1, t2 = -1.0, 0.0, 0.0, 0.0, 0.0, -1.0
    nn0, nn1, nn2 = _cross(e0, e1, e2, t0, t1, t2)
    di0, di1, di2 = q0 - a0, q1 - a1, q2 - a2
    do0, do1, do2 = o0 - q0, o1 - q1, o2 - q2
    si0, si1, si2, s_in_m = _unit(di0, di1, di2)
    so0, so1, so2, s_out_m = _unit(do0, do1, do2)
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
    pre = 1.0 / (2.0 * math.sqrt(2.0 * math.pi * k) * sin_gamma0)  # |prefactor|
    kl = k * big_l
    t_minus = _utd_term(hc * hc_in + hs * hs_in, kl)  # cos((psi - psi') / 2)
    t_plus = _utd_term(hc * hc_in - hs * hs_in, kl)  # cos((psi + psi') / 2)
    d_s = pre * (t_minus - t_plus)
    d_h = pre * (t_minus + t_plus)
    ex, ey, ez = prm[_P_E0], prm[_P_E0 + 1], prm[_P_E0 + 2]
    ei_beta = (ex * bi0 + ey * bi1 + ez * bi2) / s_in_m
    ei_phi = (ex * pi0 + ey * pi1 + ez * pi2) / s_in_m
    amp = math.sqrt(s_in_m / (s_out_m * (s_out_m + s_in_m)))
    cb = -d_s * ei_beta * amp
    cp = -d_h * ei_phi * amp
    return cb * bo0 + cp * po0, cb * bo1 + cp * po1, cb * bo2 + cp * po2


@njit(**_OPTS)
def _diffracted(s, a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, prm, parts, eta_in, edge):
    """channel._diffracted for slot ``s`` (geometry: paths.diffracted_path):
    (|gain|, arrival vector, length, valid)."""
    x0, x1, depth = prm[_P_X0], prm[_P_X1], prm[_P_DEPTH]
    nan = np.nan
    upper = _EDGE[s] == 0
    z_e = hi if upper else lo
    then = _PLANE0[s]
    o0, o1, o2 = n0, n1, n2
    ax = 0
    c = 0.0
    if then >= 0:
        ax, c = _plane(then, zf, zc, x0, x1, depth)
        o0, o1, o2 = _mirror(n0, n1, n2, ax, c)
    # geometry.diffraction_point with p0 = (x0, 0, z_e), p1 = (x1, 0, z_e)
    edge_len, ee0, ee1, ee2 = edge
    ds0, ds1, ds2 = a0 - x0, a1 - 0.0, a2 - z_e
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
    t = min(max(t_star, 0.0), edge_len)
    ok = (t_star > 0.0) and (t_star < edge_len)
    q0, q1, q2 = x0 + t * ee0, 0.0 + t * ee1, z_e + t * ee2
    v0, v1, v2 = a0 - q0, a1 - q1, a2 - q2
    u0, u1, u2 = o0 - q0, o1 - q1, o2 - q2
    length = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2) + math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
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
        ok = ok and _in_box(rp0, rp1, rp2, zf, zc, x0, x1, depth)
    ok = ok and math.isfinite(length)
    if not ok:
        return 0.0, 0.0, nan, nan, nan, length, False
    f0, f1, f2 = _utd_field(a0, a1, a2, o0, o1, o2, q0, q1, q2, upper, prm)
    g_db = 0.0  # the pattern on departure, applied in dB (every later step is linear)
    if not math.isnan(prm[_P_TX_HPBW]):
        g_db = _pattern_db(_zenith_deg(q0 - a0, q1 - a1, q2 - a2), prm[_P_TX_HPBW],
                           prm[_P_TX_PEAK])
    if then < 0:
        loss = 0.0 + _partition_loss(q0, q1, q2, n0, n1, n2, parts)
        l0, l1, l2 = q0, q1, q2
    else:
        k0, k1, k2, _ = _unit(u0, u1, u2)
        f0, f1, f2 = _reflect(f0, f1, f2, k0, k1, k2, ax, eta_in)
        loss = (0.0 + _partition_loss(q0, q1, q2, rp0, rp1, rp2, parts)
                + _partition_loss(rp0, rp1, rp2, n0, n1, n2, parts))
        l0, l1, l2 = rp0, rp1, rp2
    c1 = prm[_P_LAM] / (4 * math.pi)
    amp = _norm_c(f0 * c1, f1 * c1, f2 * c1)
    if not math.isfinite(amp):
        return 0.0, 0.0, nan, nan, nan, length, False
    return amp, loss - g_db, l0 - n0, l1 - n1, l2 - n2, length, True


@njit(**_OPTS)
def channel_snr_kernel(anchors, nodes, prm, parts, eta, out):
    """SNR of every slot: ``anchors`` (N, M, 3), ``nodes`` (N, 3) -> ``out`` (N, M, 18) [dB],
    ``-inf`` where the slot is not valid (``diffpos.channel.pair_snr_db``).

    ``prm``: :func:`channel_params`' float vector; ``parts``: (P, 5) partitions; ``eta``:
    complex (2,) permittivities of the ground and the interior surfaces.
    """
    first_z, floor_h, sill, win_h = prm[_P_FIRST_Z], prm[_P_FLOOR_H], prm[_P_SILL], prm[_P_WIN_H]
    edge = edge_axis(prm[_P_X0], prm[_P_X1])
    eta_g, eta_in = eta[0], eta[1]
    c0, pgain, n0_dbm = prm[_P_POWER0], prm[_P_PGAIN], prm[_P_N0]
    rx_hpbw, rx_peak = prm[_P_RX_HPBW], prm[_P_RX_PEAK]
    ninf = -np.inf
    for i in range(nodes.shape[0]):
        n0, n1, n2 = nodes[i, 0], nodes[i, 1], nodes[i, 2]
        k_node = _floor_index(n2, first_z, floor_h, prm[_P_N_FLOORS])
        zf, zc, lo, hi = row_planes(k_node, first_z, floor_h, sill, win_h)
        for j in range(anchors.shape[1]):
            a0, a1, a2 = anchors[i, j, 0], anchors[i, j, 1], anchors[i, j, 2]
            for s in range(N_SLOTS):
                kind = _KIND[s]
                if kind == 0:
                    g, att, v0, v1, v2, length = _direct(a0, a1, a2, n0, n1, n2, k_node, lo,
                                                         hi, prm, parts)
                    ok = math.isfinite(length)
                elif kind == 1:
                    g, att, v0, v1, v2, length, ok = _specular(s, a0, a1, a2, n0, n1, n2, zf, zc,
                                                          lo, hi, prm, parts, eta_g, eta_in)
                else:
                    g, att, v0, v1, v2, length, ok = _diffracted(s, a0, a1, a2, n0, n1, n2, zf,
                                                            zc, lo, hi, prm, parts, eta_in,
                                                            edge)
                if not ok:
                    out[i, j, s] = ninf
                    continue
                rx_db = 0.0
                if not math.isnan(rx_hpbw):
                    rx_db = _pattern_db(_zenith_deg(v0, v1, v2), rx_hpbw, rx_peak)
                if g == 0.0:
                    out[i, j, s] = ninf
                    continue
                power = c0 + rx_db + (20 * math.log10(g) - att)
                out[i, j, s] = power + pgain - n0_dbm


@njit(**_OPTS)
def channel_snr_masked_kernel(anchors, nodes, prm, parts, eta, need, out):
    """:func:`channel_snr_kernel` of the needed slots only: ``need`` (N, M, 18) bool; a slot
    not needed is not evaluated and its ``out`` is NaN (a value no caller uses). The loop body
    is :func:`channel_snr_kernel`'s, statement for statement (a shared per-slot function cost
    the unmasked kernel 20 % CPU: kept apart), so every needed slot is its value bit for bit
    (-inf where not valid)."""
    first_z, floor_h, sill, win_h = prm[_P_FIRST_Z], prm[_P_FLOOR_H], prm[_P_SILL], prm[_P_WIN_H]
    edge = edge_axis(prm[_P_X0], prm[_P_X1])
    eta_g, eta_in = eta[0], eta[1]
    c0, pgain, n0_dbm = prm[_P_POWER0], prm[_P_PGAIN], prm[_P_N0]
    rx_hpbw, rx_peak = prm[_P_RX_HPBW], prm[_P_RX_PEAK]
    ninf = -np.inf
    for i in range(nodes.shape[0]):
        n0, n1, n2 = nodes[i, 0], nodes[i, 1], nodes[i, 2]
        k_node = _floor_index(n2, first_z, floor_h, prm[_P_N_FLOORS])
        zf, zc, lo, hi = row_planes(k_node, first_z, floor_h, sill, win_h)
        for j in range(anchors.shape[1]):
            a0, a1, a2 = anchors[i, j, 0], anchors[i, j, 1], anchors[i, j, 2]
            for s in range(N_SLOTS):
                if not need[i, j, s]:
                    out[i, j, s] = np.nan
                    continue
                kind = _KIND[s]
                if kind == 0:
                    g, att, v0, v1, v2, length = _direct(a0, a1, a2, n0, n1, n2, k_node, lo,
                                                         hi, prm, parts)
                    ok = math.isfinite(length)
                elif kind == 1:
                    g, att, v0, v1, v2, length, ok = _specular(s, a0, a1, a2, n0, n1, n2, zf, zc,
                                                          lo, hi, prm, parts, eta_g, eta_in)
                else:
                    g, att, v0, v1, v2, length, ok = _diffracted(s, a0, a1, a2, n0, n1, n2, zf,
                                                            zc, lo, hi, prm, parts, eta_in,
                                                            edge)
                if not ok:
                    out[i, j, s] = ninf
                    continue
                rx_db = 0.0
                if not math.isnan(rx_hpbw):
                    rx_db = _pattern_db(_zenith_deg(v0, v1, v2), rx_hpbw, rx_peak)
                if g == 0.0:
                    out[i, j, s] = ninf
                    continue
                power = c0 + rx_db + (20 * math.log10(g) - att)
                out[i, j, s] = power + pgain - n0_dbm


@njit(**_OPTS)
def snr_cost_kernel(pred, meas, trust, sigma_db, fap_db, det_db, given_thr, thr, out):
    """The tracker's SNR cost of every slot (``diffpos.tracking_snr._snr_cost_of``, its
    numpy reference: the same operations in the same order, NaN propagated as numpy's ``max``
    does, so bit-identical): ``pred`` (P, K) predicted SNRs [dB], ``meas`` (P,) measured
    [dB], ``trust`` (P, K) bool (the slots whose maximum sets the detector's threshold) ->
    ``out`` (P, K): ``((meas - pred) / sigma)^2 / 2`` plus the same of the shortfall below
    ``thr - sigma``, ``thr = max(max_trust pred - fap_db, det_db)`` the detector's threshold;
    +inf where ``pred`` is not finite, 0 where ``meas`` is not. ``thr`` (P,): written (NaN
    where ``meas`` is not finite), or with ``given_thr`` read (``trust`` unused)."""
    n_k = pred.shape[1]
    for i in range(pred.shape[0]):
        mi = meas[i]
        if not math.isfinite(mi):
            for k in range(n_k):
                out[i, k] = 0.0
            if not given_thr:
                thr[i] = np.nan
            continue
        if given_thr:
            th = thr[i]
        else:
            top = -np.inf
            for k in range(n_k):
                if trust[i, k]:
                    v = pred[i, k]
                    if math.isnan(v):
                        top = np.nan
                        break
                    if v > top:
                        top = v
            th = top - fap_db
            if not th >= det_db:  # np.maximum: NaN propagates
                th = det_db if not math.isnan(th) else th
            thr[i] = th
        short = (th - sigma_db) - mi
        if not short >= 0.0:
            short = 0.0 if not math.isnan(short) else short
        q = short / sigma_db
        extra = 0.5 * (q * q)
        for k in range(n_k):
            v = pred[i, k]
            if not math.isfinite(v):
                out[i, k] = np.inf
                continue
            r = (mi - v) / sigma_db
            out[i, k] = 0.5 * (r * r) + extra


_c16_1d = types.complex128[::1]
#: The one compiled signature of :func:`channel_snr_kernel`.
SIGNATURE = types.void(types.float64[:, :, ::1], types.float64[:, ::1], types.float64[::1],
                       types.float64[:, ::1], _c16_1d, types.float64[:, :, ::1])
#: The compiled signature of :func:`channel_snr_masked_kernel` (``need`` before ``out``).
MASKED_SIGNATURE = types.void(types.float64[:, :, ::1], types.float64[:, ::1],
                              types.float64[::1], types.float64[:, ::1], _c16_1d,
                              types.boolean[:, :, ::1], types.float64[:, :, ::1])
#: The compiled signature of :func:`snr_cost_kernel`.
COST_SIGNATURE = types.void(types.float64[:, ::1], types.float64[::1], types.boolean[:, ::1],
                            types.float64, types.float64, types.float64, types.boolean,
                            types.float64[::1], types.float64[:, ::1])
_state: dict[str, object] = {}


def warm_channel() -> float:
    """Compile :func:`channel_snr_kernel` for :data:`SIGNATURE`,
    :func:`channel_snr_masked_kernel` for :data:`MASKED_SIGNATURE` and :func:`snr_cost_kernel`
    for :data:`COST_SIGNATURE`, or load them from numba's cache. Idempotent; returns the seconds it took (0 once warm). Call it at service start."""
    if "entry" in _state:
        return 0.0
    t0 = time.perf_counter()
    channel_snr_kernel.compile(SIGNATURE.args)
    channel_snr_masked_kernel.compile(MASKED_SIGNATURE.args)
    snr_cost_kernel.compile(COST_SIGNATURE.args)
    _state["entry"] = channel_snr_kernel
    return time.perf_counter() - t0


def channel_params(building, radio, materials) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernel's constants: ``(prm, parts, eta)`` (module docstring) of a building and radio.

    ``materials``: ``(eta_ground, eta_in, wall_db, slab_db, glass_db, parts)`` as the numpy
    emulator computes them (``diffpos.channel._materials``), so both use the same numbers.
    """
    eta_g, eta_in, wall_db, slab_db, glass_db, plist = materials
    x0, x1 = building.edge_x_m
    nan = float("nan")
    k = 2.0 * math.pi * radio.frequency_hz / SPEED_OF_LIGHT_M_S  # gtd.wavenumber_rad_m
    prm = np.empty(N_PARAMS)
    prm[:_P_E0] = (
        float(building.first_floor_z_m), float(building.floor_height_m),
        float(building.sill_height_m), float(building.window_height_m), float(x0), float(x1),
        float(building.depth_m), float(building.n_floors),
        float(wall_db), float(slab_db), float(glass_db), float(k), float(radio.wavelength_m),
        nan if radio.tx_hpbw_deg is None else float(radio.tx_hpbw_deg), float(radio.tx_peak_deg),
        nan if radio.rx_hpbw_deg is None else float(radio.rx_hpbw_deg), float(radio.rx_peak_deg),
        radio.tx_power_dbm + radio.tx_gain_dbi + radio.rx_gain_dbi,
        float(radio.processing_gain_db),
        float(noise_floor_dbm(radio.bandwidth_hz, temperature_k=radio.noise_temperature_k,
                              noise_figure_db=radio.noise_figure_db)),
    )
    prm[_P_E0:] = np.asarray(radio.polarization, dtype=np.float64)
    parts = np.array([[float(axis), float(pos), float(lo), float(hi), float(db)]
                      for axis, pos, (lo, hi), db in plist], dtype=np.float64).reshape(-1, 5)
    eta = np.array([eta_g, eta_in], dtype=np.complex128)
    return prm, np.ascontiguousarray(parts), eta


def eval_snr_kernel(anchors: np.ndarray, nodes: np.ndarray,
                    params: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """Run the kernel: ``anchors`` (N, M, 3), ``nodes`` (N, 3) C-contiguous float64,
    ``params`` from :func:`channel_params`; returns (N, M, 18) [dB]."""
    warm_channel()
    out = np.empty((nodes.shape[0], anchors.shape[1], N_SLOTS))
    prm, parts, eta = params

    def rows(lo: int, hi: int) -> None:  # the node rows [lo, hi): slices keep the signature
        channel_snr_kernel(anchors[lo:hi], nodes[lo:hi], prm, parts, eta, out[lo:hi])

    run_rows(rows, nodes.shape[0], min_rows=-(-SNR_MIN_PAIRS // max(anchors.shape[1], 1)))
    return out


def eval_snr_masked_kernel(anchors: np.ndarray, nodes: np.ndarray,
                           params: tuple[np.ndarray, np.ndarray, np.ndarray],
                           need: np.ndarray) -> np.ndarray:
    """:func:`eval_snr_kernel` of the slots ``need`` (N, M, 18) C-contiguous bool only
    (:func:`channel_snr_masked_kernel`: NaN elsewhere)."""
    warm_channel()
    out = np.empty((nodes.shape[0], anchors.shape[1], N_SLOTS))
    channel_snr_masked_kernel(anchors, nodes, *params, need, out)
    return out
