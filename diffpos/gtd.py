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

Building model and Theorem 3
----------------------------
The front wall is the plane ``y = 0`` with the anchor at ``y < 0`` and the node inside at
``y > 0`` (paper's Table of ``e, n0, t0``): the upper window edge has ``n0 = -y, t0 = +z,
e = +x`` (the wall above the window), the lower edge ``n0 = -y, t0 = -z, e = -x`` (the wall
below it). :func:`window_edge_fields` gives both fields, :func:`power_ratio_exact` their power
ratio and :func:`power_ratio_approx` the closed form ``(1 + cos theta) / (1 - cos theta)``.

Issues found in the paper (checked independently; tests pin them down)
----------------------------------------------------------------------
* Table of edge coordinate vectors, lower edge: ``phi'`` should read
  ``(-(z_e - z_a) y - y_a z)/sqrt(...)`` (the printed ``+(z_e - z_a) y`` is not orthogonal to
  ``s'``), and ``beta0`` should have z-component ``-(0.5 w)(x_n - q_x)`` (printed ``+``; again
  not orthogonal to ``s``). The upper-edge entries are right. Neither error matters for the
  x-polarised power ratio with ``x_n = q_x``.
* Lemma 3 table: the hard coefficients have the wrong sign. With ``psi = 3 pi / 2``,
  ``cos(psi/2) = -sqrt(2)/2`` (the appendix takes the positive root of the half-angle identity),
  so ``D_h^l = A (-2 sqrt(1 + cos th)/cos th)`` and ``D_h^u = A (2 sqrt(1 - cos th)/cos th)``.
  The soft coefficients (the ones Theorem 3 uses) are right. See :func:`lemma3_coefficients`.
* Corollary 2 drops the minus signs of ``-D_s, -D_h`` (a global sign, harmless for powers).
* The Lemma 3 coefficients diverge like ``1/cos theta`` as ``theta -> 90 deg``: there the node
  (``psi ~ 3 pi/2``) sits on the incident shadow boundary ``psi = pi + psi'`` of both edges and
  the Keller form is invalid; the UTD form stays finite. The ratio in Theorem 3 stays finite
  because the factors cancel.
* Kouyoumjian-Pathak's large-argument series for ``F`` prints ``75/(16 X^4)``; the correct
  coefficient is ``105/16`` (``F ~ sum_n (2n-1)!! (j/(2X))^n``). Not used here (see
  :func:`transition_function`), only in the tests.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import wofz

from .constants import SPEED_OF_LIGHT_M_S
from .geometry import window_edge_path

__all__ = [
    "EdgeFrame",
    "Lemma3Coefficients",
    "diffracted_field",
    "distance_parameter_m",
    "edge_frame",
    "elevation_angle_rad",
    "elevation_sweep_positions",
    "field_from_frame",
    "keller_coefficients",
    "lemma3_coefficients",
    "power_ratio_approx",
    "power_ratio_exact",
    "spreading_factor",
    "transition_function",
    "utd_coefficients",
    "wavenumber_rad_m",
    "window_edge_fields",
    "window_edge_frame",
]

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]
Coefficients = Literal["utd", "gtd", "keller"]
Spreading = Literal["spherical", "paper"]

_EXP_MJ_PI4 = np.exp(-0.25j * np.pi)
_EXP_J_PI4 = np.exp(0.25j * np.pi)
_EXP_J_3PI4 = np.exp(0.75j * np.pi)

# Building model (paper, Table of n0, t0, e): wall is y = 0, anchors at y < 0.
_UPPER_EDGE = (np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
_LOWER_EDGE = (np.array([-1.0, 0.0, 0.0]), np.array([0.0, 0.0, -1.0]))


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
    xa = np.asarray(x, dtype=np.float64)
    if np.any(xa < 0.0):
        raise ValueError("transition_function: X must be >= 0 (X = k L a)")
    r = np.sqrt(xa)
    return np.sqrt(np.pi) * r * _EXP_J_PI4 * wofz(_EXP_J_3PI4 * r)


def _utd_term(beta: FloatArray, kl: FloatArray) -> ComplexArray:
    """``F(k L a(b)) / cos(b/2)`` with ``a(b) = 2 cos^2(b/2)``, finite at ``cos(b/2) = 0``."""
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
    return pre * (t_minus - t_plus), pre * (t_minus + t_plus)


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
    frame: EdgeFrame, k_hz: float | ArrayLike, coefficients: str, spreading: str
) -> tuple[ComplexArray, ComplexArray]:
    key = str(coefficients).lower()
    if key == "utd":
        big_l = distance_parameter_m(
            frame.s_in_m, frame.s_out_m, frame.sin_gamma0, spreading=spreading
        )  # type: ignore[arg-type]
        return utd_coefficients(
            frame.psi_rad, frame.psi_in_rad, frame.gamma0_rad, big_l, frequency_hz=k_hz
        )
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
) -> ComplexArray:
    """Diffracted field at the observer of an :class:`EdgeFrame` (see :func:`diffracted_field`)."""
    _check_spreading(spreading)
    k = wavenumber_rad_m(frequency_hz)
    d_s, d_h = _coefficients_for(frame, frequency_hz, coefficients, spreading)
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

    Returns
    -------
    ndarray of complex, shape (..., 3) [V/m]
        The diffracted field at O for a source of unit amplitude at 1 m (times ``E0``).
    """
    frame = edge_frame(source_m, observer_m, point_m, edge_dir, face_dir)
    return field_from_frame(
        frame, e0, frequency_hz=frequency_hz, coefficients=coefficients, spreading=spreading
    )


def _check_building_sides(anchor: FloatArray, node: FloatArray) -> None:
    if np.any(~(anchor[..., 1] < 0.0)):
        raise ValueError("anchor_m: every anchor must be outside the wall (y < 0)")
    if np.any(~(node[..., 1] > 0.0)):
        raise ValueError("node_m: every node must be inside the building (y > 0)")


def window_edge_frame(
    anchor_m: ArrayLike,
    node_m: ArrayLike,
    *,
    window_height_m: float | ArrayLike,
    edge: Literal["upper", "lower"],
    delta_m: float | ArrayLike = 0.0,
    edge_x_m: tuple[float, float] | None = None,
) -> EdgeFrame:
    """:class:`EdgeFrame` of the upper or lower window edge on the node's floor.

    The edge point comes from :func:`diffpos.geometry.window_edge_path` (Corollary 1, Case-2
    offset ``delta_m``); the edge vectors follow the paper's Table (upper: ``e = +x, t0 = +z``;
    lower: ``e = -x, t0 = -z``; ``n0 = -y`` for both).

    Parameters
    ----------
    anchor_m : array_like, shape (..., 3) [m]
        Anchors, outside (``y < 0``).
    node_m : array_like, shape (..., 3) [m]
        Nodes, inside (``y > 0``).
    window_height_m : float or array_like [m]
    edge : {"upper", "lower"}
    delta_m : float or array_like [m]
        Case-2 vertical offset (0: node at window mid-height).
    edge_x_m : (float, float), optional
        Extent of the edge along x [m].
    """
    a = np.asarray(anchor_m, dtype=np.float64)
    n = np.asarray(node_m, dtype=np.float64)
    _check_building_sides(a, n)
    if edge == "upper":
        e_dir, t_dir = _UPPER_EDGE
    elif edge == "lower":
        e_dir, t_dir = _LOWER_EDGE
    else:
        raise ValueError(f"edge must be 'upper' or 'lower', got {edge!r}")
    path = window_edge_path(
        a, n, window_height_m=window_height_m, delta_m=delta_m, edge=edge, edge_x_m=edge_x_m
    )
    return edge_frame(a, n, path.point_m, e_dir, t_dir)


def window_edge_fields(
    anchor_m: ArrayLike,
    node_m: ArrayLike,
    *,
    window_height_m: float | ArrayLike,
    delta_m: float | ArrayLike = 0.0,
    e0: ArrayLike = (1.0, 0.0, 0.0),
    frequency_hz: float | ArrayLike = 28e9,
    edge_x_m: tuple[float, float] | None = None,
    coefficients: Coefficients = "utd",
    spreading: Spreading = "spherical",
) -> tuple[ComplexArray, ComplexArray]:
    """Diffracted fields of the upper and lower window edges at the node (Corollary 2).

    Parameters
    ----------
    anchor_m : array_like, shape (..., 3) [m]
        Anchor (source) positions, ``y < 0``.
    node_m : array_like, shape (..., 3) [m]
        Node (observer) positions, ``y > 0``; broadcast against ``anchor_m``.
    window_height_m : float or array_like [m]
        Window height ``w``.
    delta_m : float or array_like [m]
        Case-2 vertical offset of the node below the window centre (paper's ``Delta``).
    e0 : array_like, shape (..., 3) [V/m at 1 m]
        Transmit polarisation; default x (parallel to the edges, Theorem 3).
    frequency_hz : float [Hz]
    edge_x_m : (float, float), optional
        Extent of the window edges along x [m]; default unbounded.
    coefficients, spreading
        As in :func:`diffracted_field`.

    Returns
    -------
    e_upper, e_lower : ndarray of complex, shape (..., 3) [V/m]
    """
    kw = {"window_height_m": window_height_m, "delta_m": delta_m, "edge_x_m": edge_x_m}
    fu = window_edge_frame(anchor_m, node_m, edge="upper", **kw)
    fl = window_edge_frame(anchor_m, node_m, edge="lower", **kw)
    opts = {"frequency_hz": frequency_hz, "coefficients": coefficients, "spreading": spreading}
    return field_from_frame(fu, e0, **opts), field_from_frame(fl, e0, **opts)


def power_ratio_exact(
    anchor_m: ArrayLike,
    node_m: ArrayLike,
    *,
    window_height_m: float | ArrayLike,
    e0: ArrayLike = (1.0, 0.0, 0.0),
    delta_m: float | ArrayLike = 0.0,
    frequency_hz: float | ArrayLike = 28e9,
    edge_x_m: tuple[float, float] | None = None,
    coefficients: Coefficients = "utd",
    spreading: Spreading = "spherical",
) -> FloatArray:
    """Power ratio ``P^u / P^l = |E^u|^2 / |E^l|^2`` of the two window-edge diffraction MPCs.

    Evaluated from the full field model at the real positions (no Assumption 2): the
    "exact" curves of the paper's power-ratio figure. Arguments as in
    :func:`window_edge_fields`.

    Returns
    -------
    ndarray, shape (...) [-]
        Linear power ratio (``10 log10`` for dB).
    """
    eu, el = window_edge_fields(
        anchor_m,
        node_m,
        window_height_m=window_height_m,
        delta_m=delta_m,
        e0=e0,
        frequency_hz=frequency_hz,
        edge_x_m=edge_x_m,
        coefficients=coefficients,
        spreading=spreading,
    )
    pu = np.sum(np.abs(eu) ** 2, axis=-1)
    pl = np.sum(np.abs(el) ** 2, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return pu / pl


def power_ratio_approx(theta_rad: ArrayLike) -> FloatArray:
    """Theorem 3: ``P^u / P^l ~ (1 + cos theta) / (1 - cos theta)`` (x-polarised transmit).

    Parameters
    ----------
    theta_rad : array_like, shape (...) [rad]
        Elevation angle of the anchor seen from the window (:func:`elevation_angle_rad`).

    Returns
    -------
    ndarray, shape (...) [-]
        Linear ratio; ``inf`` at ``theta = 0``, 1 at ``theta = pi/2``. It exceeds 5 dB for
        ``cos theta > (10^0.5 - 1)/(10^0.5 + 1) = 0.5195``, i.e. ``theta < 58.70 deg``.
    """
    c = np.cos(np.asarray(theta_rad, dtype=np.float64))
    with np.errstate(divide="ignore"):
        return (1.0 + c) / (1.0 - c)


def elevation_angle_rad(anchor_m: ArrayLike, edge_z_m: ArrayLike) -> FloatArray:
    """Elevation angle ``theta`` of Assumption 2 [rad].

    ``theta = arccos((z_e - z_a) / sqrt(y_a^2 + (z_e - z_a)^2))``, computed as
    ``arctan2(|y_a|, z_e - z_a)``: ``pi/2`` with the anchor at the edge height, ``-> 0`` for
    floors far above the anchor, ``> pi/2`` for floors below it.

    Parameters
    ----------
    anchor_m : array_like, shape (..., 3) [m]
    edge_z_m : array_like, shape (...) [m]
        Height of the edge (or window centre) the angle refers to.
    """
    a = np.asarray(anchor_m, dtype=np.float64)
    dz = np.asarray(edge_z_m, dtype=np.float64) - a[..., 2]
    return np.arctan2(np.abs(a[..., 1]), dz)


def elevation_sweep_positions(
    theta_rad: ArrayLike,
    depth_m: ArrayLike,
    *,
    anchor_distance_m: float,
    anchor_height_m: float = 1.0,
    delta_m: float = 0.0,
    x_m: float = 0.0,
) -> tuple[FloatArray, FloatArray]:
    """Anchor and node positions that sweep the elevation angle ``theta`` (power-ratio figure).

    The anchor is fixed at ``(x, -anchor_distance_m, anchor_height_m)``; the node's floor is
    moved vertically so that the window centre is at ``z_c = z_a + d cot theta``, i.e. seen from
    the anchor at elevation ``theta`` (:func:`elevation_angle_rad` of ``z_c``; ``theta = 90 deg``
    puts the window centre at the anchor height, small ``theta`` is a high floor). The node is at
    depth ``y_n = depth_m`` behind the wall, at ``z_n = z_c + delta_m`` (Case-2 offset; 0 puts
    it at the window mid-height) and the same ``x`` as the anchor.

    Parameters
    ----------
    theta_rad : array_like, shape (...) [rad]
        In ``(0, pi)``.
    depth_m : array_like, shape (...) [m]
        Node depth ``y_n > 0``; broadcasts against ``theta_rad``.
    anchor_distance_m : float [m]
        ``|y_a| > 0``.
    anchor_height_m, delta_m, x_m : float [m]

    Returns
    -------
    anchor_m, node_m : ndarray, shape (..., 3) [m]
    """
    th = np.asarray(theta_rad, dtype=np.float64)
    depth = np.asarray(depth_m, dtype=np.float64)
    if np.any(~((th > 0.0) & (th < np.pi))):
        raise ValueError("theta_rad must lie strictly between 0 and pi")
    if np.any(~(depth > 0.0)):
        raise ValueError("depth_m must be > 0 (node inside the building)")
    if not anchor_distance_m > 0.0:
        raise ValueError("anchor_distance_m must be > 0")
    th, depth = np.broadcast_arrays(th, depth)
    z_c = anchor_height_m + anchor_distance_m / np.tan(th)
    ones = np.ones_like(th)
    anchor = np.stack([x_m * ones, -anchor_distance_m * ones, anchor_height_m * ones], axis=-1)
    node = np.stack([x_m * ones, depth, z_c + delta_m], axis=-1)
    return anchor, node


@dataclass(frozen=True)
class Lemma3Coefficients:
    """Approximate Keller coefficients of the two window edges (paper's Lemma 3 table).

    All values are complex, shape ``(...)`` [sqrt(m)], and include the common factor
    ``A = -exp(-j pi/4) / (2 sqrt(2 pi k) sin gamma0)``.
    """

    soft_lower: ComplexArray
    soft_upper: ComplexArray
    hard_lower: ComplexArray
    hard_upper: ComplexArray


def lemma3_coefficients(
    theta_rad: ArrayLike,
    *,
    frequency_hz: float | ArrayLike = 28e9,
    sin_gamma0: ArrayLike = 1.0,
    as_printed: bool = False,
) -> Lemma3Coefficients:
    """Keller coefficients at ``psi = 3 pi/2``, ``psi'^l = theta``, ``psi'^u = pi - theta``.

    Closed forms (derived here independently from the Keller eq. with ``a = psi/2 = 3 pi/4``,
    ``b = psi'/2``: ``1/cos(a-b) -/+ 1/cos(a+b) = {-2 sin a sin b, 2 cos a cos b} /
    (cos^2 a cos^2 b - sin^2 a sin^2 b)``, with ``sin a = sqrt(2)/2``, ``cos a = -sqrt(2)/2``)::

        D_s^l = A (-2 sqrt(1 - cos th) / cos th)     D_s^u = A ( 2 sqrt(1 + cos th) / cos th)
        D_h^l = A (-2 sqrt(1 + cos th) / cos th)     D_h^u = A ( 2 sqrt(1 - cos th) / cos th)

    The soft ones agree with the paper's table; the paper prints the hard ones with the
    opposite sign (``as_printed=True`` reproduces that), because its appendix uses
    ``cos(psi/2) = +sqrt((1 + cos psi)/2)`` while ``cos(3 pi/4) < 0``. All four diverge as
    ``theta -> pi/2`` (node on the incident shadow boundary; Keller invalid there).

    Parameters
    ----------
    theta_rad : array_like, shape (...) [rad]
    frequency_hz : float [Hz]
    sin_gamma0 : array_like [-]
        ``sin gamma0`` (1 for an anchor and node in the same x-plane).
    as_printed : bool
        Return the paper's printed signs instead of the corrected ones.
    """
    th = np.asarray(theta_rad, dtype=np.float64)
    c = np.cos(th)
    pre = _prefactor(wavenumber_rad_m(frequency_hz), np.asarray(sin_gamma0, dtype=np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        soft_l = pre * (-2.0 * np.sqrt(1.0 - c) / c)
        soft_u = pre * (2.0 * np.sqrt(1.0 + c) / c)
        hard_l = pre * (-2.0 * np.sqrt(1.0 + c) / c)
        hard_u = pre * (2.0 * np.sqrt(1.0 - c) / c)
    if as_printed:
        hard_l, hard_u = -hard_l, -hard_u
    return Lemma3Coefficients(
        soft_lower=soft_l, soft_upper=soft_u, hard_lower=hard_l, hard_upper=hard_u
    )
