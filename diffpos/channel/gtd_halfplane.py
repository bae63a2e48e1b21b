"""Edge diffraction by a perfectly conducting half-plane: GTD (Keller) and UTD (Kouyoumjian-Pathak).

Everything is vectorised with numpy broadcasting over arrays of shape ``(..., 3)``.

Geometry and conventions (paper, Section II-C, Definitions 1-2)
----------------------------------------------------------------
A half-plane (thin perfectly conducting sheet) has a straight edge with unit tangent ``e`` and
a unit vector ``t0`` lying in the sheet, perpendicular to the edge and pointing away from the
edge into the sheet ("face direction"). The paper's third vector ``n0`` is the normal of the
sheet *towards the source*, and ``t0 = n0 x e``; for an orthonormal triple this is the same as
``n0 = e x t0``. A caller gives ``e`` and ``t0`` only; :func:`edge_frame` computes
``n0 = e x t0`` and, where the source lies on the other side (``(S - Q) . n0 < 0``), flips
``n0 -> -n0`` and ``e -> -e`` together (``t0`` is kept, so ``t0 = n0 x e`` still holds). The
flip changes no physical output: the dyads ``beta0 beta0'`` and ``phi phi'`` and ``sin gamma0``
are invariant under ``e -> -e``; only the angles ``psi, psi'`` need ``n0`` on the source side.

Ray-fixed unit vectors (incident ray ``s'`` from the source S to the edge point Q, diffracted
ray ``s`` from Q to the observer O)::

    phi'  = -(e x s') / |e x s'|,    beta0' = phi' x s',
    phi   =  (e x s)  / |e x s|,     beta0  = phi  x s.

(Kouyoumjian-Pathak write ``beta0' = s' x phi'`` and ``beta0 = s x phi``; both signs flip, so
the dyadic ``-D_s beta0 beta0' - D_h phi phi'`` is the same.) The projections on the plane
normal to the edge are ``s_t' = (s' - (s'.e) e)/|...|`` and ``s_t = (s - (s.e) e)/|...|`` and the
angles, measured from the face ``t0`` towards ``n0``, are (paper's eq. for psi', psi)::

    psi' = pi - [pi - arccos(-s_t' . t0)] sgn(-s_t' . n0)     in [0, pi] (n0 faces the source)
    psi  = pi - [pi - arccos( s_t  . t0)] sgn( s_t  . n0)     in [0, 2 pi]

They are computed here with ``arctan2`` (same values, accurate near grazing). One quirk of the
printed rule: ``sgn(0) = 0`` gives ``psi = pi`` for an observer exactly on the face plane, where
the geometric angle is 0 or 2 pi; ``arctan2`` returns 0 there. The incident shadow boundary
(ISB) is ``psi = pi + psi'`` and the reflection shadow boundary (RSB) ``psi = pi - psi'``.

Diffraction coefficients
------------------------
With ``k`` the wavenumber and ``gamma0`` the Keller-cone half angle (``cos gamma0 = |s'.e| =
|s.e|``, Definition 1)::

    D_{s,h} = -exp(-j pi/4) / (2 sqrt(2 pi k) sin gamma0) * [T(psi - psi') -/+ T(psi + psi')]

Keller (GTD): ``T(b) = 1 / cos(b/2)`` (the paper's eq.), singular at the shadow boundaries.
UTD (Kouyoumjian & Pathak 1974, half-plane ``n = 2``): ``T(b) = F(k L a(b)) / cos(b/2)`` with
``a(b) = 2 cos^2(b/2)`` (for ``n = 2``, ``a+ = a-`` whatever the integers ``N+-``, so the four
cotangent terms of the wedge collapse into the two secant terms above) and the transition
function :func:`transition_function`. ``F(X) -> 1`` away from the boundaries, so UTD -> Keller
there (relative difference ~ ``1/(2X)``). At a boundary ``F(X)/cos(b/2)`` stays finite:
``F(X) ~ sqrt(pi X) exp(j pi/4)`` gives ``T -> sgn(cos(b/2)) sqrt(2 pi k L) exp(j pi/4)``. The
diffracted field alone therefore *jumps* across a shadow boundary, by exactly the
geometrical-optics (GO) field it switches on/off, so that GO + diffracted is continuous
(``tests/test_gtd.py`` checks this). On the boundary itself (``cos(b/2) = 0``) the lit-side
value is returned.

Diffracted field (paper eqs. for E^d and E^i)
---------------------------------------------
An isotropic point source with polarisation vector ``E0`` (field ``E0`` at 1 m) gives at Q the
incident components ``E^i_{beta0'} = (E0 . beta0') exp(-j k s')/s'`` and
``E^i_{phi'} = (E0 . phi') exp(-j k s')/s'``, and at O::

    E^d = [-D_s E^i_{beta0'} beta0 - D_h E^i_{phi'} phi] A(s', s) exp(-j k s).

``spreading="spherical"`` (default, UTD for spherical-wave incidence on a straight edge, caustic
distance ``rho = s'``): ``A = sqrt(s' / (s (s + s')))`` and ``L = s s' sin^2 gamma0 / (s + s')``.
``spreading="paper"``: the paper's eq. for E^d, ``A = 1/sqrt(s)`` (the plane-wave spreading
factor, caustic at infinity) and, for consistency, ``L = s sin^2 gamma0``. The paper multiplies
this plane-wave factor by the spherical incident amplitude ``1/s'`` (its Corollary 2:
``exp(-jk(s'+s)) / (s' sqrt(s))``). Relative to the spherical form its amplitude is larger by
``sqrt((s + s')/s')``: it agrees only for ``s << s'``; for ``s = s'`` it is 3 dB too strong.
The power ratio of Theorem 3 is barely affected (the upper and lower paths have nearly the
same ``s, s'``).

Dielectric sheet (``face_permittivity``; the emulator's vertical window edges)
------------------------------------------------------------------------------
A wall is concrete, not a perfect conductor. Splitting the half-plane's secant terms back into
the wedge's four cotangent terms (``n = 2``: ``cot((pi -+ b)/4) = (1 +- sin(b/2)) / cos(b/2)``)
gives ``T(b+) = D3 + D4`` with ``D4 = (1 + sin(b+/2))/2 T(b+)`` (the lit face's reflection
boundary ``psi = pi - psi'``) and ``D3 = (1 - sin(b+/2))/2 T(b+)`` (the other face's).
Luebbers' finite-conductivity UTD (IEEE Trans. AP-32, 1984) weights each reflection term with
its face's Fresnel coefficient instead of the conductor's ``-1`` (soft) / ``+1`` (hard)::

    D_{s,h} = prefactor [T(b-) + w_{s,h} T(b+)],
    w = ((1 + sin(b+/2)) R0 + (1 - sin(b+/2)) Rn) / 2

with ``R0`` the lit face's TE (soft) / TM (hard) coefficient at the incident ray's angle
(``cos = |s' . n0|``). The other face of a sheet lit from the ``n0`` side receives no incident
field, so it has no reflection boundary and no angle of its own: ``Rn`` takes the grazing
limit of any finite permittivity, ``-1`` for both polarisations (the TM coefficient of a
dielectric tends to -1 at grazing incidence where a conductor's is +1). With ``R0 = -1`` the
soft coefficient is Kouyoumjian-Pathak's; the hard one is not: a perfect conductor doubles
the hard field along its shadowed face (``D3 + D4`` add), a dielectric one does not. This is
the ray tracer's choice too (Sionna RT 2.2 ``RadioMaterial._diffraction_matrix``: ``Rn = -I``
for a face the incident wave does not see), whose hard field of a concrete side-wall edge is
up to 18 dB weaker than the conductor's deep in the shadow (docs/channel_mix.md).

The paper's window edges, their power ratio (Theorem 3) and Lemma 3 are in
:mod:`diffpos.channel.gtd`, built on this module.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.constants import SPEED_OF_LIGHT_M_S

__all__ = [
    "EdgeFrame",
    "diffracted_field",
    "distance_parameter_m",
    "edge_frame",
    "field_from_frame",
    "keller_coefficients",
    "spreading_factor",
    "transition_function",
    "utd_coefficients",
    "wavenumber_rad_m",
]

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]
Coefficients = Literal["utd", "gtd", "keller"]
Spreading = Literal["spherical", "paper"]

_EXP_MJ_PI4 = np.exp(-0.25j * np.pi)
_EXP_J_PI4 = np.exp(0.25j * np.pi)
_EXP_J_3PI4 = np.exp(0.75j * np.pi)


def _dot(a: NDArray, b: NDArray) -> NDArray:
    return np.einsum("...i,...i->...", a, b)


def _norm(v: FloatArray) -> FloatArray:
    return np.sqrt(_dot(v, v))


def _unit(v: FloatArray) -> FloatArray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / _norm(v)[..., None]


def wavenumber_rad_m(frequency_hz: float | ArrayLike) -> FloatArray:
    """Free-space wavenumber ``k = 2 pi f / c`` [rad/m]."""
    f = np.asarray(frequency_hz, dtype=np.float64)
    if np.any(~np.isfinite(f)) or np.any(f <= 0.0):
        raise ValueError(f"frequency_hz must be positive and finite, got {frequency_hz!r}")
    return 2.0 * np.pi * f / SPEED_OF_LIGHT_M_S


@dataclass(frozen=True)
class EdgeFrame:
    """Ray-fixed and edge-fixed unit vectors and angles of one diffraction (paper, Sec. II-C).

    All vectors are unit vectors, shape ``(..., 3)``; angles and lengths have shape ``(...)``.

    Attributes
    ----------
    s_in : ndarray, shape (..., 3) [-]
        Incident ray direction ``s'`` (source -> Q).
    s_out : ndarray, shape (..., 3) [-]
        Diffracted ray direction ``s`` (Q -> observer).
    edge : ndarray, shape (..., 3) [-]
        Edge tangent ``e``, flipped where needed so that ``n0`` faces the source.
    n0 : ndarray, shape (..., 3) [-]
        Normal of the half-plane towards the source.
    t0 : ndarray, shape (..., 3) [-]
        In the half-plane, perpendicular to the edge, pointing away from it (``t0 = n0 x e``).
    st_in, st_out : ndarray, shape (..., 3) [-]
        ``s_t'`` and ``s_t``: ``s'`` and ``s`` projected on the plane normal to the edge.
    phi_in, beta0_in : ndarray, shape (..., 3) [-]
        ``phi' = -(e x s')/|e x s'|`` and ``beta0' = phi' x s'``.
    phi_out, beta0_out : ndarray, shape (..., 3) [-]
        ``phi = (e x s)/|e x s|`` and ``beta0 = phi x s``.
    psi_in_rad : ndarray, shape (...) [rad]
        ``psi'`` in ``[0, pi]``, angle of the source direction from the face ``t0``.
    psi_rad : ndarray, shape (...) [rad]
        ``psi`` in ``[0, 2 pi)``, angle of the observer direction from the face ``t0``.
    gamma0_rad : ndarray, shape (...) [rad]
        Keller-cone half angle in ``[0, pi/2]``: ``cos gamma0 = |s' . e|`` (Definition 1).
    sin_gamma0 : ndarray, shape (...) [-]
        ``sin gamma0 = |e x s'|`` (computed directly, accurate near grazing).
    s_in_m : ndarray, shape (...) [m]
        ``|S - Q|`` (the paper's ``|s'|``, OPL in the building model).
    s_out_m : ndarray, shape (...) [m]
        ``|O - Q|`` (the paper's ``|s|``, IPL in the building model).
    """

    s_in: FloatArray
    s_out: FloatArray
    edge: FloatArray
    n0: FloatArray
    t0: FloatArray
    st_in: FloatArray
    st_out: FloatArray
    phi_in: FloatArray
    beta0_in: FloatArray
    phi_out: FloatArray
    beta0_out: FloatArray
    psi_in_rad: FloatArray
    psi_rad: FloatArray
    gamma0_rad: FloatArray
    sin_gamma0: FloatArray
    s_in_m: FloatArray
    s_out_m: FloatArray


def edge_frame(
    source_m: ArrayLike,
    observer_m: ArrayLike,
    point_m: ArrayLike,
    edge_dir: ArrayLike,
    face_dir: ArrayLike,
) -> EdgeFrame:
    """Unit vectors and angles of the diffraction S -> Q -> O at a half-plane edge.

    Parameters
    ----------
    source_m, observer_m : array_like, shape (..., 3) [m]
        Source S and observer O.
    point_m : array_like, shape (..., 3) [m]
        Diffraction point Q on the edge (e.g. from :func:`diffpos.geometry.diffraction_point`;
        it is used as given, the law of diffraction is not enforced here).
    edge_dir : array_like, shape (..., 3) [-]
        Edge tangent ``e`` (normalised here; either sense).
    face_dir : array_like, shape (..., 3) [-]
        ``t0``: lies in the half-plane, points away from the edge into the sheet. Its component
        along ``e`` is removed and it is normalised.

    Returns
    -------
    EdgeFrame
        With ``n0 = e x t0`` flipped (together with ``e``) to face the source; see the module
        docstring. Degenerate rays (S or O on the edge line, ``sin gamma0 = 0``) give NaN.
    """
    s = np.asarray(source_m, dtype=np.float64)
    o = np.asarray(observer_m, dtype=np.float64)
    q = np.asarray(point_m, dtype=np.float64)
    e = np.asarray(edge_dir, dtype=np.float64)
    t = np.asarray(face_dir, dtype=np.float64)
    for name, arr in (
        ("source_m", s),
        ("observer_m", o),
        ("point_m", q),
        ("edge_dir", e),
        ("face_dir", t),
    ):
        if arr.shape[-1:] != (3,):
            raise ValueError(f"{name} must have shape (..., 3), got {arr.shape}")
    shape = np.broadcast_shapes(s.shape, o.shape, q.shape, e.shape, t.shape)
    s, o, q, e, t = (np.broadcast_to(v, shape) for v in (s, o, q, e, t))
    e_len = _norm(e)
    if np.any(~(e_len > 0.0)):
        raise ValueError("edge_dir must be a non-zero finite vector")
    e = e / e_len[..., None]
    t = t - _dot(t, e)[..., None] * e
    t_len = _norm(t)
    if np.any(~(t_len > 1e-12)):
        raise ValueError("face_dir must be non-zero and not parallel to edge_dir")
    t = t / t_len[..., None]
    n = np.cross(e, t)

    d_in = q - s
    d_out = o - q
    s_in_m = _norm(d_in)
    s_out_m = _norm(d_out)
    s_in = _unit(d_in)
    s_out = _unit(d_out)

    # n0 must face the source: flip n0 and e together (t0 = n0 x e is preserved).
    flip = _dot(s - q, n) < 0.0
    sign = np.where(flip, -1.0, 1.0)[..., None]
    n = n * sign
    e = e * sign

    cross_in = np.cross(e, s_in)
    cross_out = np.cross(e, s_out)
    sin_g = _norm(cross_in)
    phi_in = -_unit(cross_in)
    beta0_in = np.cross(phi_in, s_in)
    phi_out = _unit(cross_out)
    beta0_out = np.cross(phi_out, s_out)

    st_in = _unit(s_in - _dot(s_in, e)[..., None] * e)
    st_out = _unit(s_out - _dot(s_out, e)[..., None] * e)
    psi_in = np.mod(np.arctan2(-_dot(st_in, n), -_dot(st_in, t)), 2.0 * np.pi)
    psi = np.mod(np.arctan2(_dot(st_out, n), _dot(st_out, t)), 2.0 * np.pi)
    gamma0 = np.arctan2(sin_g, np.abs(_dot(s_in, e)))
    return EdgeFrame(
        s_in=s_in,
        s_out=s_out,
        edge=e,
        n0=n,
        t0=t,
        st_in=st_in,
        st_out=st_out,
        phi_in=phi_in,
        beta0_in=beta0_in,
        phi_out=phi_out,
        beta0_out=beta0_out,
        psi_in_rad=psi_in,
        psi_rad=psi,
        gamma0_rad=gamma0,
        sin_gamma0=sin_g,
        s_in_m=s_in_m,
        s_out_m=s_out_m,
    )


def transition_function(x: ArrayLike) -> ComplexArray:
    """UTD transition function ``F(X) = 2j sqrt(X) exp(jX) int_{sqrt X}^inf exp(-j tau^2) dtau``.

    Evaluated through the Faddeeva function ``w`` (``scipy.special.wofz``)::

        int_u^inf exp(-j tau^2) dtau = (sqrt(pi)/2) exp(-j pi/4) erfc(exp(j pi/4) u),
        erfc(z) = exp(-z^2) w(j z)   =>   F(X) = sqrt(pi X) exp(j pi/4) w(exp(j 3 pi/4) sqrt X).

    The factor ``exp(jX)`` cancels analytically against ``exp(-z^2) = exp(-jX)``, so unlike the
    textbook form with ``scipy.special.fresnel`` (``0.5 - C``, ``0.5 - S`` and a separate
    ``exp(jX)``, which lose relative accuracy and phase for large X) no branch between a
    small-X series, the Fresnel integrals and the large-X asymptotic series is needed: the
    argument of ``w`` lies in the upper half-plane where ``w`` is bounded and smooth. Limits:
    ``F(0) = 0``, ``F(X) ~ sqrt(pi X) exp(j pi/4)`` for ``X -> 0``, ``F(X) -> 1 + j/(2X)`` for
    ``X -> inf`` (the tests check both and compare with ``scipy.integrate.quad`` and with the
    Fresnel-integral form).

    Parameters
    ----------
    x : array_like, shape (...) [-]
        ``X >= 0`` (``X = k L a``).

    Returns
    -------
    ndarray of complex, shape (...)
    """
    from scipy.special import wofz  # only here: a module-level import costs every process

    xa = np.asarray(x, dtype=np.float64)
    if np.any(xa < 0.0):
        raise ValueError("transition_function: X must be >= 0 (X = k L a)")
    r = np.sqrt(xa)
    return np.sqrt(np.pi) * r * _EXP_J_PI4 * wofz(_EXP_J_3PI4 * r)


def _utd_term(beta: FloatArray, kl: FloatArray) -> ComplexArray:
    """``F(k L a(b)) / cos(b/2)`` with ``a(b) = 2 cos^2(b/2)``, finite at ``cos(b/2) = 0``."""
    from scipy.special import wofz  # only here: a module-level import costs every process

    c = np.cos(0.5 * beta)
    sgn = np.where(c >= 0.0, 1.0, -1.0)
    root = np.sqrt(2.0 * kl)
    return sgn * np.sqrt(np.pi) * root * _EXP_J_PI4 * wofz(_EXP_J_3PI4 * root * np.abs(c))


def _prefactor(k: FloatArray, sin_gamma0: FloatArray) -> ComplexArray:
    with np.errstate(divide="ignore"):
        return -_EXP_MJ_PI4 / (2.0 * np.sqrt(2.0 * np.pi * k) * sin_gamma0)


def keller_coefficients(
    psi_rad: ArrayLike,
    psi_in_rad: ArrayLike,
    gamma0_rad: ArrayLike,
    *,
    frequency_hz: float | ArrayLike,
) -> tuple[ComplexArray, ComplexArray]:
    """Keller (GTD) soft and hard diffraction coefficients of a half-plane (paper's eq.).

    ``D_{s,h} = -exp(-j pi/4)/(2 sqrt(2 pi k) sin gamma0) [1/cos((psi-psi')/2) -/+ 1/cos((psi+psi')/2)]``

    Parameters
    ----------
    psi_rad, psi_in_rad : array_like, shape (...) [rad]
        ``psi`` and ``psi'`` as in :class:`EdgeFrame`.
    gamma0_rad : array_like, shape (...) [rad]
        Keller-cone half angle.
    frequency_hz : float or array_like [Hz]

    Returns
    -------
    d_soft, d_hard : ndarray of complex, shape (...) [sqrt(m)]
        Infinite (or huge) on the shadow boundaries ``psi = pi -/+ psi'``.
    """
    psi = np.asarray(psi_rad, dtype=np.float64)
    psi_in = np.asarray(psi_in_rad, dtype=np.float64)
    pre = _prefactor(
        wavenumber_rad_m(frequency_hz), np.sin(np.asarray(gamma0_rad, dtype=np.float64))
    )
    with np.errstate(divide="ignore"):
        t_minus = 1.0 / np.cos(0.5 * (psi - psi_in))
        t_plus = 1.0 / np.cos(0.5 * (psi + psi_in))
    return pre * (t_minus - t_plus), pre * (t_minus + t_plus)


def utd_coefficients(
    psi_rad: ArrayLike,
    psi_in_rad: ArrayLike,
    gamma0_rad: ArrayLike,
    distance_param_m: ArrayLike,
    *,
    frequency_hz: float | ArrayLike,
    lit_face_reflection: tuple[ArrayLike, ArrayLike] | None = None,
) -> tuple[ComplexArray, ComplexArray]:
    """UTD (Kouyoumjian-Pathak 1974) soft and hard coefficients of a half-plane (wedge ``n = 2``).

    ``D_{s,h} = -exp(-j pi/4)/(2 sqrt(2 pi k) sin gamma0) [F(kL a(b-))/cos(b-/2) -/+ F(kL a(b+))/cos(b+/2)]``
    with ``b-+ = psi -/+ psi'``, ``a(b) = 2 cos^2(b/2)`` and ``F`` from
    :func:`transition_function`. Same sign convention as :func:`keller_coefficients`, to which
    it tends for ``k L a -> inf``.

    Parameters
    ----------
    psi_rad, psi_in_rad, gamma0_rad : array_like, shape (...) [rad]
        As in :func:`keller_coefficients`.
    distance_param_m : array_like, shape (...) [m]
        Distance parameter ``L`` (see :func:`distance_parameter_m`).
    frequency_hz : float or array_like [Hz]
    lit_face_reflection : (array_like, array_like) of complex, optional
        A dielectric sheet instead of a perfectly conducting one: the Fresnel reflection
        coefficients (TE for the soft, TM for the hard coefficient) of the lit face (the
        ``n0`` side, facing the source) at the incident ray's angle. See the module docstring
        ("Dielectric sheet"). Default: the perfect conductor (``-1`` soft, ``+1`` hard).

    Returns
    -------
    d_soft, d_hard : ndarray of complex, shape (...) [sqrt(m)]
        Finite everywhere (``sin gamma0 > 0``); each jumps across a shadow boundary by the
        amount that keeps GO + diffracted continuous.
    """
    psi = np.asarray(psi_rad, dtype=np.float64)
    psi_in = np.asarray(psi_in_rad, dtype=np.float64)
    big_l = np.asarray(distance_param_m, dtype=np.float64)
    if np.any(big_l < 0.0):
        raise ValueError("distance_param_m must be >= 0")
    k = wavenumber_rad_m(frequency_hz)
    pre = _prefactor(k, np.sin(np.asarray(gamma0_rad, dtype=np.float64)))
    kl = k * big_l
    t_minus = _utd_term(psi - psi_in, kl)
    t_plus = _utd_term(psi + psi_in, kl)
    if lit_face_reflection is None:
        return pre * (t_minus - t_plus), pre * (t_minus + t_plus)
    sp = np.sin(0.5 * (psi + psi_in))
    r_s, r_h = (np.asarray(r, dtype=np.complex128) for r in lit_face_reflection)
    w_s = 0.5 * ((1.0 + sp) * r_s - (1.0 - sp))
    w_h = 0.5 * ((1.0 + sp) * r_h - (1.0 - sp))
    return pre * (t_minus + w_s * t_plus), pre * (t_minus + w_h * t_plus)


def _check_spreading(spreading: str) -> None:
    if spreading not in ("spherical", "paper"):
        raise ValueError(f"spreading must be 'spherical' or 'paper', got {spreading!r}")


def distance_parameter_m(
    s_in_m: ArrayLike,
    s_out_m: ArrayLike,
    sin_gamma0: ArrayLike,
    *,
    spreading: Spreading = "spherical",
) -> FloatArray:
    """UTD distance parameter ``L`` [m].

    ``"spherical"``: ``L = s s' sin^2 gamma0 / (s + s')`` (spherical-wave incidence);
    ``"paper"``: ``L = s sin^2 gamma0`` (plane-wave incidence, matching ``A = 1/sqrt(s)``).
    """
    _check_spreading(spreading)
    sp = np.asarray(s_in_m, dtype=np.float64)
    so = np.asarray(s_out_m, dtype=np.float64)
    sg2 = np.asarray(sin_gamma0, dtype=np.float64) ** 2
    if spreading == "spherical":
        return so * sp * sg2 / (so + sp)
    return so * sg2


def spreading_factor(
    s_in_m: ArrayLike,
    s_out_m: ArrayLike,
    *,
    spreading: Spreading = "spherical",
) -> FloatArray:
    """Spatial attenuation ``A(s', s)`` of the diffracted ray [1/sqrt(m)].

    ``"spherical"``: ``sqrt(s' / (s (s + s')))`` (caustic distance ``rho = s'``);
    ``"paper"``: ``1/sqrt(s)`` (the paper's eq. for E^d).
    """
    _check_spreading(spreading)
    sp = np.asarray(s_in_m, dtype=np.float64)
    so = np.asarray(s_out_m, dtype=np.float64)
    if spreading == "spherical":
        return np.sqrt(sp / (so * (so + sp)))
    return 1.0 / np.sqrt(so)


def _coefficients_for(
    frame: EdgeFrame, k_hz: float | ArrayLike, coefficients: str, spreading: str,
    face_permittivity: complex | None = None,
) -> tuple[ComplexArray, ComplexArray]:
    key = str(coefficients).lower()
    if key == "utd":
        big_l = distance_parameter_m(
            frame.s_in_m, frame.s_out_m, frame.sin_gamma0, spreading=spreading
        )  # type: ignore[arg-type]
        lit = None
        if face_permittivity is not None:
            lit = _fresnel(np.abs(_dot(frame.s_in, frame.n0)), complex(face_permittivity))
        return utd_coefficients(
            frame.psi_rad, frame.psi_in_rad, frame.gamma0_rad, big_l, frequency_hz=k_hz,
            lit_face_reflection=lit,
        )
    if face_permittivity is not None:
        raise ValueError("face_permittivity needs coefficients='utd'")
    if key in ("gtd", "keller"):
        return keller_coefficients(
            frame.psi_rad, frame.psi_in_rad, frame.gamma0_rad, frequency_hz=k_hz
        )
    raise ValueError(f"coefficients must be 'utd', 'gtd' or 'keller', got {coefficients!r}")


def field_from_frame(
    frame: EdgeFrame,
    e0: ArrayLike,
    *,
    frequency_hz: float | ArrayLike,
    coefficients: Coefficients = "utd",
    spreading: Spreading = "spherical",
    face_permittivity: complex | None = None,
) -> ComplexArray:
    """Diffracted field at the observer of an :class:`EdgeFrame` (see :func:`diffracted_field`)."""
    _check_spreading(spreading)
    k = wavenumber_rad_m(frequency_hz)
    d_s, d_h = _coefficients_for(frame, frequency_hz, coefficients, spreading,
                                 face_permittivity)
    e0c = np.asarray(e0, dtype=np.complex128)
    if e0c.shape[-1:] != (3,):
        raise ValueError(f"e0 must have shape (..., 3), got {e0c.shape}")
    incident = np.exp(-1j * k * frame.s_in_m) / frame.s_in_m
    ei_beta = _dot(e0c, frame.beta0_in) * incident
    ei_phi = _dot(e0c, frame.phi_in) * incident
    amp = spreading_factor(frame.s_in_m, frame.s_out_m, spreading=spreading) * np.exp(
        -1j * k * frame.s_out_m
    )
    return (-d_s * ei_beta * amp)[..., None] * frame.beta0_out + (-d_h * ei_phi * amp)[
        ..., None
    ] * frame.phi_out


def diffracted_field(
    source_m: ArrayLike,
    observer_m: ArrayLike,
    point_m: ArrayLike,
    edge_dir: ArrayLike,
    face_dir: ArrayLike,
    e0: ArrayLike,
    *,
    frequency_hz: float | ArrayLike,
    coefficients: Coefficients = "utd",
    spreading: Spreading = "spherical",
    face_permittivity: complex | None = None,
) -> ComplexArray:
    """Edge-diffracted electric field of an isotropic point source at a half-plane.

    ``E^d = [-D_s E^i_{beta0'} beta0 - D_h E^i_{phi'} phi] A(s', s) exp(-j k s)`` with
    ``E^i_{beta0'} = (E0 . beta0') exp(-j k s')/s'`` and ``E^i_{phi'} = (E0 . phi') exp(-j k s')/s'``
    (paper, Definition 2 and the eqs. after it; conventions in the module docstring).

    Parameters
    ----------
    source_m, observer_m : array_like, shape (..., 3) [m]
        Source S and observer O.
    point_m : array_like, shape (..., 3) [m]
        Diffraction point Q on the edge (the Fermat point; used as given).
    edge_dir : array_like, shape (..., 3) [-]
        Edge tangent ``e`` (either sense).
    face_dir : array_like, shape (..., 3) [-]
        ``t0``: in the half-plane, perpendicular to the edge, pointing away from the edge into
        the sheet. ``n0 = e x t0`` is flipped towards the source where needed.
    e0 : array_like, shape (..., 3), real or complex [V/m at 1 m]
        Transmit polarisation vector: the incident field is ``E0 exp(-jkr)/r`` projected on the
        plane normal to the ray.
    frequency_hz : float or array_like [Hz]
    coefficients : {"utd", "gtd", "keller"}
        UTD (default, finite at shadow boundaries) or Keller's GTD ("gtd" = "keller").
    spreading : {"spherical", "paper"}
        ``A = sqrt(s'/(s(s+s')))`` (default) or the paper's ``1/sqrt(s)``; also selects ``L``.
    face_permittivity : complex, optional
        Relative permittivity of a dielectric sheet (a concrete wall; UTD only, see the module
        docstring, "Dielectric sheet"); default a perfect conductor.

    Returns
    -------
    ndarray of complex, shape (..., 3) [V/m]
        The diffracted field at O for a source of unit amplitude at 1 m (times ``E0``).
    """
    frame = edge_frame(source_m, observer_m, point_m, edge_dir, face_dir)
    return field_from_frame(
        frame, e0, frequency_hz=frequency_hz, coefficients=coefficients, spreading=spreading,
        face_permittivity=face_permittivity,
    )


def _fresnel(cos_theta: FloatArray, eta: complex) -> tuple[ComplexArray, ComplexArray]:
    """Half-space TE and TM reflection coefficients (``diffpos.channel.slots``'
    ``fresnel_coefficients``; that module builds on this one)."""
    c = np.clip(cos_theta, 0.0, 1.0)
    root = np.sqrt(eta - (1.0 - c * c) + 0j)
    with np.errstate(invalid="ignore", divide="ignore"):
        return (c - root) / (c + root), (eta * c - root) / (eta * c + root)
