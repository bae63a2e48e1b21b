"""UTD diffraction by a wedge of finite conductivity: the window edge as Sionna RT 2.2 traces it.

The emulator's horizontal window edges (:mod:`diffpos.channel.gtd_halfplane`) are the
perfectly conducting half-plane of the paper (wedge ``n = 2``), or at channel order >= 3
Luebbers' dielectric sheet. Against Sionna RT (the live ray-traced channel) the lower edge's
deep-shadow field of the half-plane is too weak: traced minus predicted power of
``Tx-D(lower)-Rx`` a median +4.5 dB at 40-50 dB diffraction loss and +7.9 dB beyond 50 dB on
heldout-2 s0u, the upper edge -1.6 to -2.6 dB at 30-50 dB (``benchmarks/bench_wedge.py``;
docs/channel_mix.md "Session 30"). This module gives the general wedge and the reflection
weighting Sionna uses, so the emulator and the tracker can predict Sionna's field.

Kouyoumjian-Pathak wedge (exterior angle ``n pi``; ``n = 2`` a half-plane, ``n = 1.5`` a
right-angled corner), with ``phi'``, ``phi`` the incident and diffracted directions measured
from the 0-face (the face the source sees) through the exterior, ``beta0`` the Keller-cone
angle and ``L`` the distance parameter (:func:`diffpos.channel.gtd_halfplane.distance_parameter_m`)::

    f  = -exp(-j pi/4) / (2 n sqrt(2 pi k) sin beta0)
    d1 = f cot((pi + (phi - phi')) / 2n) F(k L a+(phi - phi'))
    d2 = f cot((pi - (phi - phi')) / 2n) F(k L a-(phi - phi'))
    d3 = f cot((pi + (phi + phi')) / 2n) F(k L a+(phi + phi'))
    d4 = f cot((pi - (phi + phi')) / 2n) F(k L a-(phi + phi'))
    a+-(b) = 2 cos^2((2 pi n N+- - b) / 2),  N+- the integer nearest to (b +- pi) / (2 pi n)

``F`` is :func:`diffpos.channel.gtd_halfplane.transition_function`; each ``cot F`` product is
finite on its shadow or reflection boundary (limit ``sgn(sin psi) n sqrt(2 k L) exp(j pi/4)``
times ``cos psi``, as Sionna's ``cot_times_f_utd``). The perfect conductor:
``D_{s,h} = d1 + d2 -/+ (d3 + d4)`` (for ``n = 2`` exactly the half-plane's
``utd_coefficients``; tests/core/test_channel_wedge.py).

Faces of finite conductivity, two weightings (``form``):

* ``"luebbers"`` (Luebbers 1984; the emulator's dielectric sheet): the reflection terms carry
  their face's Fresnel coefficient, ``D = d1 + d2 + R_0 d4 + R_n d3`` (``R`` the TE
  coefficient for the soft, TM for the hard coefficient; a conductor ``-1`` / ``+1``).
* ``"sionna"`` (Sionna RT 2.2, ``RadioMaterial._diffraction_matrix``): each face's Fresnel
  matrix weights an incident *and* a reflection term, ``R_0 (d1 - d4) + R_n (d2 - d3)``, a
  2x2 matrix per face: the face's ``diag(r_te, r_tm)`` rotated from the face's TE/TM basis
  of the incident ray to the edge-fixed basis of its shadow boundary's direction (Hashimoto
  et al.), those components then used unchanged as the diffracted ray's (``wedge_field``).
  Where the ray is oblique to the edge (an anchor off to the side of the window) the
  rotations mix the face's TE and TM coefficients into the field along the edge; that, not
  the wedge angle, is what makes Sionna's lower-edge deep-shadow field 4-8 dB stronger than
  the conductor's (``benchmarks/bench_wedge.py``: ``wedge_field`` with this form reproduces
  Sionna's traced ``Tx-D(lower|upper)-Rx`` gains to < 0.01 dB in every loss band).
  :func:`wedge_coefficients` gives its scalar 2-D reading (ray normal to the edge):
  ``D_s = -[R_0 (d1 - d4) + R_n (d2 - d3)]`` (TE), ``D_h = R_0 (d1 + d4) + R_n (d2 + d3)``
  (TM; both signs chosen so the conductor gives the coefficients above).

Sionna's face coefficients (both forms here): ``R_0`` the ITU-R P.2040 single-layer slab
reflection coefficients (eq. 43; the wall's thickness) at the incident ray's angle on the
0-face, ``cos = |s' . n_0|``; ``R_n`` the same on the n-face, except ``R_n = -1`` (both
polarisations) where the exterior angle exceeds ``pi + phi'`` (the n-face is not lit; always
for a half-plane). Everything is numpy, vectorised by broadcasting; angles [rad], lengths [m],
frequency [Hz], coefficients [sqrt(m)] like :func:`~diffpos.channel.gtd_halfplane.utd_coefficients`.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.channel.gtd_halfplane import (
    EdgeFrame,
    distance_parameter_m,
    spreading_factor,
    transition_function,
    wavenumber_rad_m,
)

__all__ = ["EdgeModel", "WedgeForm", "slab_reflection", "wedge_coefficients", "wedge_field"]

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]
WedgeForm = Literal["sionna", "luebbers"]
#: The tracker's / channel's window-edge models: today's half-plane, or the wedge below.
EdgeModel = Literal["halfplane", "wedge"]

_EXP_MJ_PI4 = np.exp(-0.25j * np.pi)
_EXP_J_PI4 = np.exp(0.25j * np.pi)


def slab_reflection(cos_theta: ArrayLike, eta: complex, thickness_m: float,
                    wavelength_m: float) -> tuple[ComplexArray, ComplexArray]:
    """TE and TM reflection coefficients of a single-layer slab in vacuum (ITU-R P.2040-4 eq. 43,
    as Sionna RT's ``itu_coefficients_single_layer_slab``).

    Parameters
    ----------
    cos_theta : array_like [-]
        Cosine of the incidence angle from the slab's normal, in [0, 1].
    eta : complex [-]
        Relative permittivity ``eta' - j sigma / (omega eps0)`` of the slab.
    thickness_m, wavelength_m : float [m]

    Returns
    -------
    r_te, r_tm : ndarray of complex [-]
        ``R (1 - exp(-2jq)) / (1 - R^2 exp(-2jq))``, ``q = 2 pi d / lambda sqrt(eta - sin^2)``,
        ``R`` the half-space Fresnel coefficient. A thick lossy slab (concrete, 0.2 m at
        28 GHz) is the half-space to < 1e-6.
    """
    c = np.clip(np.asarray(cos_theta, dtype=np.float64), 0.0, 1.0)
    root = np.sqrt(complex(eta) - (1.0 - c * c) + 0j)
    if np.any(root.imag > 0):  # principal branch with Im <= 0 (a lossy medium), as Sionna
        root = np.where(root.imag > 0, -root, root)
    with np.errstate(invalid="ignore", divide="ignore"):
        r_te = (c - root) / (c + root)
        r_tm = (eta * c - root) / (eta * c + root)
    q = 2.0 * np.pi * thickness_m / wavelength_m * root
    e2 = np.exp(-2j * q)
    return (r_te * (1 - e2) / (1 - r_te**2 * e2), r_tm * (1 - e2) / (1 - r_tm**2 * e2))


def _a_pm(beta: FloatArray, n: float) -> tuple[FloatArray, FloatArray]:
    """``a+(beta)``, ``a-(beta)`` of the wedge ``n`` (module docstring)."""
    ext = n * np.pi
    n_p = np.round((beta + np.pi) / (2.0 * ext))
    n_m = np.round((beta - np.pi) / (2.0 * ext))
    return 2.0 * np.cos(ext * n_p - 0.5 * beta) ** 2, 2.0 * np.cos(ext * n_m - 0.5 * beta) ** 2


def _cot_f(psi: FloatArray, x: FloatArray, n: float, kl: FloatArray) -> ComplexArray:
    """``cot(psi) F(x)``, finite where ``sin psi`` and ``x`` vanish together (a boundary)."""
    s, c = np.sin(psi), np.cos(psi)
    f = transition_function(np.maximum(x, 0.0))
    pole = (np.abs(s) <= 1e-7) & (x <= 1e-7)
    lim = np.where(s >= 0, 1.0, -1.0) * n * np.sqrt(2.0 * kl) * _EXP_J_PI4
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(pole, c * lim, c / np.where(pole, 1.0, s) * f)


def wedge_coefficients(
    phi_rad: ArrayLike,
    phi_in_rad: ArrayLike,
    beta0_rad: ArrayLike,
    distance_param_m: ArrayLike,
    *,
    frequency_hz: float,
    n: float = 2.0,
    face0: tuple[ArrayLike, ArrayLike] | None = None,
    facen: tuple[ArrayLike, ArrayLike] | None = None,
    form: WedgeForm = "sionna",
) -> tuple[ComplexArray, ComplexArray]:
    """Soft and hard UTD coefficients of a wedge of exterior angle ``n pi`` (module docstring).

    Parameters
    ----------
    phi_rad, phi_in_rad : array_like [rad]
        ``phi`` in ``[0, n pi]`` and ``phi'`` in ``[0, n pi]``, from the 0-face.
    beta0_rad : array_like [rad]
        Keller-cone angle (``sin beta0 > 0``).
    distance_param_m : array_like [m]
        ``L`` (``s s' sin^2 beta0 / (s + s')`` for spherical incidence).
    frequency_hz : float [Hz]
    n : float
        Exterior angle over pi, in [1, 2] (2: a half-plane).
    face0, facen : (r_te, r_tm) of array_like complex, optional
        Reflection coefficients of the 0-face and the n-face; None: a perfect conductor
        (``-1``, ``+1``).
    form : {"sionna", "luebbers"}
        How the faces' coefficients weight the four terms (module docstring).

    Returns
    -------
    d_soft, d_hard : ndarray of complex [sqrt(m)]
        The perfect conductor of ``n = 2`` equals
        :func:`diffpos.channel.gtd_halfplane.utd_coefficients`.
    """
    if not 1.0 <= n <= 2.0:
        raise ValueError(f"n must be in [1, 2], got {n!r}")
    if form not in ("sionna", "luebbers"):
        raise ValueError(f"form must be 'sionna' or 'luebbers', got {form!r}")
    phi = np.asarray(phi_rad, dtype=np.float64)
    phi_in = np.asarray(phi_in_rad, dtype=np.float64)
    k = float(wavenumber_rad_m(frequency_hz))
    kl = k * np.asarray(distance_param_m, dtype=np.float64)
    with np.errstate(divide="ignore"):
        f = -_EXP_MJ_PI4 / (2.0 * n * np.sqrt(2.0 * np.pi * k)
                            * np.sin(np.asarray(beta0_rad, dtype=np.float64)))
    dif, tot = phi - phi_in, phi + phi_in
    a1, a2 = _a_pm(dif, n)
    a3, a4 = _a_pm(tot, n)
    d1 = f * _cot_f((np.pi + dif) / (2 * n), kl * a1, n, kl)
    d2 = f * _cot_f((np.pi - dif) / (2 * n), kl * a2, n, kl)
    d3 = f * _cot_f((np.pi + tot) / (2 * n), kl * a3, n, kl)
    d4 = f * _cot_f((np.pi - tot) / (2 * n), kl * a4, n, kl)
    r0s, r0h = (-1.0, 1.0) if face0 is None else face0
    rns, rnh = (-1.0, 1.0) if facen is None else facen
    if form == "luebbers":
        return d1 + d2 + r0s * d4 + rns * d3, d1 + d2 + r0h * d4 + rnh * d3
    return (-(r0s * (d1 - d4) + rns * (d2 - d3)), r0h * (d1 + d4) + rnh * (d2 + d3))


def _dot(a: NDArray, b: NDArray) -> NDArray:
    return np.einsum("...i,...i->...", a, b)


def _cross(a: NDArray, b: NDArray) -> NDArray:
    """``np.cross`` over the last axis (length 3) without its axis bookkeeping (the same
    products and differences)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack(np.broadcast_arrays(a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0),
                    axis=-1)


def _unit(v: NDArray) -> NDArray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.sqrt(_dot(v, v))[..., None]


def _rotator(k: NDArray, a: NDArray, b: NDArray) -> NDArray:
    """2x2 change of a Jones vector's basis ``(a, k x a)`` -> ``(b, k x b)`` (Sionna's
    ``jones_matrix_rotator``), shape (..., 2, 2)."""
    c = _dot(a, b)
    s = _dot(k, _cross(a, b))
    return np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], -2)


def _face_matrix(ki: NDArray, edge: NDArray, normal: NDArray, r_te: NDArray, r_tm: NDArray
                 ) -> NDArray:
    """A face's Fresnel matrix from the incident edge-fixed basis ``(phi', ki x phi')`` to its
    shadow boundary's ``(phi_sb, k_sb x phi_sb)`` (Sionna RT 2.2, after Hashimoto et al.):
    rotate to the face's TE/TM basis, weight by ``diag(r_te, r_tm)``, rotate to the reflected
    ray's edge-fixed basis. Shape (..., 2, 2), complex."""
    phi_in = _unit(_cross(ki, edge))
    k_sb = _unit(ki - 2.0 * _dot(ki, normal)[..., None] * normal)
    phi_sb = -_unit(_cross(k_sb, edge))
    te = _cross(ki, normal)
    degenerate = _dot(te, te) < 1e-12  # normal incidence: any transverse vector
    ref = np.where((np.abs(ki[..., :1]) < 0.9), [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    te = _unit(np.where(degenerate[..., None], ref - _dot(ref, ki)[..., None] * ki, te))
    diag = np.zeros((*np.shape(r_te), 2, 2), dtype=np.complex128)
    diag[..., 0, 0], diag[..., 1, 1] = r_te, r_tm
    return _rotator(k_sb, te, phi_sb) @ diag @ _rotator(ki, phi_in, te)


def _sionna_matrix(frame: EdgeFrame, d: tuple, n: float, permittivity: complex,
                   thickness_m: float, wavelength_m: float) -> NDArray:
    """Sionna RT 2.2's diffraction matrix ``R_0 (d1 - d4) + R_n (d2 - d3)`` from the incident
    basis ``(phi', s' x phi')`` to ``(phi, s x phi)`` with ``phi' = (s' x e)/|.|`` and
    ``phi = -(s x e)/|.|`` (its ``_diffraction_matrix`` without the world-frame rotations)."""
    ki, e, n0 = frame.s_in, frame.edge, frame.n0  # n0 x e = t0 (the 0-face), as Sionna's
    ang = n * np.pi
    nn = -(np.cos(ang) * n0 - np.sin(ang) * frame.t0)
    r0 = slab_reflection(np.abs(_dot(ki, n0)), permittivity, thickness_m, wavelength_m)
    rn = slab_reflection(np.abs(_dot(ki, nn)), permittivity, thickness_m, wavelength_m)
    m0 = _face_matrix(ki, e, n0, *r0)
    mn = _face_matrix(ki, e, nn, *rn)
    dark = (n * np.pi > np.pi + frame.psi_in_rad)[..., None, None]
    mn = np.where(dark, -np.eye(2), mn)
    d1, d2, d3, d4 = d
    return m0 * (d1 - d4)[..., None, None] + mn * (d2 - d3)[..., None, None]


def _terms(frame: EdgeFrame, k: float, n: float) -> tuple:
    """``d1..d4`` of the module docstring at a frame (spherical-wave distance parameter)."""
    kl = k * distance_parameter_m(frame.s_in_m, frame.s_out_m, frame.sin_gamma0)
    with np.errstate(divide="ignore"):
        f = -_EXP_MJ_PI4 / (2.0 * n * np.sqrt(2.0 * np.pi * k) * frame.sin_gamma0)
    dif = frame.psi_rad - frame.psi_in_rad
    tot = frame.psi_rad + frame.psi_in_rad
    a1, a2 = _a_pm(dif, n)
    a3, a4 = _a_pm(tot, n)
    return (f * _cot_f((np.pi + dif) / (2 * n), kl * a1, n, kl),
            f * _cot_f((np.pi - dif) / (2 * n), kl * a2, n, kl),
            f * _cot_f((np.pi + tot) / (2 * n), kl * a3, n, kl),
            f * _cot_f((np.pi - tot) / (2 * n), kl * a4, n, kl))


def wedge_field(
    frame: EdgeFrame,
    e0: ArrayLike,
    *,
    frequency_hz: float,
    n: float = 2.0,
    permittivity: complex | None = None,
    thickness_m: float = 0.0,
    form: WedgeForm = "sionna",
) -> ComplexArray:
    """Diffracted field of an isotropic point source at a wedge edge [V/m for E0 at 1 m].

    ``frame`` is the half-plane's :func:`diffpos.channel.gtd_halfplane.edge_frame` (``t0``
    along the 0-face, ``n0`` towards the source): ``phi' = psi'`` and ``phi = psi`` there.
    The n-face lies at ``phi = n pi``; its outward normal is ``sin(n pi) t0 - cos(n pi) n0``.

    ``permittivity`` None: a perfect conductor, ``E^d = [-D_s E^i_beta0' beta0 - D_h E^i_phi'
    phi] A(s', s) exp(-j k s)`` with :func:`wedge_coefficients` (with ``n = 2`` exactly
    :func:`diffpos.channel.gtd_halfplane.field_from_frame`, UTD, spherical spreading).
    Else both faces of that material and thickness: ``form="luebbers"`` the same expression
    with Luebbers' coefficients; ``form="sionna"`` Sionna RT 2.2's full 2x2 matrix (each
    face's Fresnel matrix rotated between its TE/TM basis and the edge-fixed bases of the
    incident ray and of its shadow boundary; module docstring), which mixes the faces' TE
    and TM coefficients where the ray is oblique to the edge. Same spreading ``A(s', s) =
    sqrt(s' / (s (s + s')))`` in every case.
    """
    k = float(wavenumber_rad_m(frequency_hz))
    e0c = np.asarray(e0, dtype=np.complex128)
    incident = np.exp(-1j * k * frame.s_in_m) / frame.s_in_m
    amp = spreading_factor(frame.s_in_m, frame.s_out_m) * np.exp(-1j * k * frame.s_out_m)
    if permittivity is not None and form == "sionna":
        e = frame.edge
        p_in = _unit(_cross(frame.s_in, e))
        p_out = -_unit(_cross(frame.s_out, e))
        a = np.stack([_dot(e0c, p_in), _dot(e0c, _cross(frame.s_in, p_in))], -1)
        m = _sionna_matrix(frame, _terms(frame, k, n), n, permittivity, thickness_m,
                           2.0 * np.pi / k)
        out = np.einsum("...ij,...j->...i", m, a) * (incident * amp)[..., None]
        return out[..., :1] * p_out + out[..., 1:] * _cross(frame.s_out, p_out)
    face0 = facen = None
    if permittivity is not None:
        lam = 2.0 * np.pi / k
        face0 = slab_reflection(np.abs(_dot(frame.s_in, frame.n0)), permittivity,
                                thickness_m, lam)
        ang = n * np.pi
        nn = -(np.cos(ang) * frame.n0 - np.sin(ang) * frame.t0)
        rn = slab_reflection(np.abs(_dot(frame.s_in, nn)), permittivity, thickness_m, lam)
        dark = n * np.pi > np.pi + frame.psi_in_rad
        facen = (np.where(dark, -1.0, rn[0]), np.where(dark, -1.0, rn[1]))
    big_l = distance_parameter_m(frame.s_in_m, frame.s_out_m, frame.sin_gamma0)
    d_s, d_h = wedge_coefficients(frame.psi_rad, frame.psi_in_rad, frame.gamma0_rad, big_l,
                                  frequency_hz=frequency_hz, n=n, face0=face0, facen=facen,
                                  form=form)
    ei_beta = _dot(e0c, frame.beta0_in) * incident
    ei_phi = _dot(e0c, frame.phi_in) * incident
    return ((-d_s * ei_beta * amp)[..., None] * frame.beta0_out
            + (-d_h * ei_phi * amp)[..., None] * frame.phi_out)
