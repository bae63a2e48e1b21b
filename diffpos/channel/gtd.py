"""The paper's window-edge diffraction: both window edges of the building model, their power
ratio (Theorem 3) and the Lemma 3 coefficients; the half-plane GTD (Keller) and UTD
(Kouyoumjian-Pathak) they are built on (ray-fixed frames, coefficients, transition function,
diffracted field, conventions) are in :mod:`diffpos.channel.gtd_halfplane` (import them from
there).

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
from numpy.typing import ArrayLike

from diffpos.channel.gtd_halfplane import (
    Coefficients,
    ComplexArray,
    EdgeFrame,
    FloatArray,
    Spreading,
    _prefactor,
    edge_frame,
    field_from_frame,
    wavenumber_rad_m,
)
from diffpos.geometry import window_edge_path

__all__ = [
    "Lemma3Coefficients",
    "elevation_angle_rad",
    "elevation_sweep_positions",
    "lemma3_coefficients",
    "power_ratio_approx",
    "power_ratio_exact",
    "window_edge_fields",
    "window_edge_frame",
]

# Building model (paper, Table of n0, t0, e): wall is y = 0, anchors at y < 0.
_UPPER_EDGE = (np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]))
_LOWER_EDGE = (np.array([-1.0, 0.0, 0.0]), np.array([0.0, 0.0, -1.0]))


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
