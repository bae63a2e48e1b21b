"""Edge-diffraction geometry: the Fermat point on an edge and the building path model.

Everything here is vectorised with numpy broadcasting over arrays of shape ``(..., 3)``.

The key fact used throughout is that for a straight line with unit direction ``e`` the
path length through a point at abscissa ``t`` on the line,

    f(t) = sqrt((t - s_t)^2 + r_s^2) + sqrt((t - o_t)^2 + r_o^2),

(``s_t, o_t`` the abscissae of the source and observer projected on the line, ``r_s, r_o`` their
distances to it) is a sum of two convex functions of ``t``. Unfolding the observer about the
line into the half-plane opposite the source makes the optimal path a straight segment, so
the global minimiser and the minimum are, in closed form,

    t* = (s_t r_o + o_t r_s) / (r_s + r_o),      f(t*) = sqrt((o_t - s_t)^2 + (r_s + r_o)^2).

Because ``f`` is convex, the minimiser over a finite edge ``[t_0, t_1]`` is ``clip(t*, t_0, t_1)``:
exact, branch-free and with no spurious root.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "DiffractionPoint",
    "EdgePath",
    "diffraction_point",
    "lemma1_roots",
    "los_path",
    "window_edge_path",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class DiffractionPoint:
    """Fermat (Keller-cone) point of a finite straight edge.

    Attributes
    ----------
    point_m : ndarray, shape (..., 3) [m]
        The point Q on the edge minimising ``|S - Q| + |Q - O|``.
    length_m : ndarray, shape (...) [m]
        The minimal path length ``|S - Q| + |Q - O|``.
    on_edge : ndarray of bool, shape (...)
        True where Q lies strictly inside the edge (edge diffraction, the law of diffraction
        holds); False where the unconstrained Fermat point lies beyond an end and Q was clamped
        to that end (corner diffraction, which the paper ignores).
    edge_param : ndarray, shape (...) [-]
        Position of Q along the edge, 0 at ``edge_start_m`` and 1 at ``edge_end_m``. With
        ``X_2 = edge_start`` and ``X_1 = edge_end`` this is the paper's ``lambda`` (Lemma 1,
        ``Q = X_2 + lambda (X_1 - X_2)``).
    """

    point_m: FloatArray
    length_m: FloatArray
    on_edge: BoolArray
    edge_param: FloatArray


def _full(v: FloatArray, shape: tuple[int, ...]) -> FloatArray:
    """``v`` as a writable array of exactly ``shape`` (copies only when broadcasting)."""
    v = np.asarray(v, dtype=np.float64)
    return v if v.shape == shape else np.broadcast_to(v, shape).copy()


def _norm(v: FloatArray) -> FloatArray:
    return np.sqrt(np.einsum("...i,...i->...", v, v))


def diffraction_point(
    source_m: ArrayLike,
    observer_m: ArrayLike,
    edge_start_m: ArrayLike,
    edge_end_m: ArrayLike,
) -> DiffractionPoint:
    """Diffraction point and path length for a straight finite edge in any orientation.

    Generalises the paper's Lemma 1 (horizontal edge in the plane ``y = 0``) to an arbitrary
    edge ``[edge_start_m, edge_end_m]``. The paper obtains the point from the law of diffraction
    ``s' . e = s . e`` after squaring, which gives the quadratic ``a lambda^2 + b lambda + c = 0``
    of its eq. (4). Squaring also admits ``s' . e = -(s . e)``, so one of the two roots is
    spurious (an external division point where the path is not stationary); which one depends
    on the geometry (see :func:`lemma1_roots`). Here the point is instead computed from the
    unfolding closed form (module docstring), which is the unique global minimiser of the
    Fermat path length and coincides with the correct root of Lemma 1 whenever that root lies
    on the edge.

    Parameters
    ----------
    source_m, observer_m : array_like, shape (..., 3) [m]
        Source S (e.g. the anchor) and observer O (the node).
    edge_start_m, edge_end_m : array_like, shape (..., 3) [m]
        End points of the edge; must differ. All four arguments broadcast against each other.

    Returns
    -------
    DiffractionPoint

    Notes
    -----
    If both S and O lie on the edge line (``r_s + r_o = 0``) every point between them is a
    minimiser; the midpoint of their projections (clamped to the edge) is returned.
    """
    s = np.asarray(source_m, dtype=np.float64)
    o = np.asarray(observer_m, dtype=np.float64)
    p0 = np.asarray(edge_start_m, dtype=np.float64)
    p1 = np.asarray(edge_end_m, dtype=np.float64)
    axis = p1 - p0
    edge_len = _norm(axis)
    if np.any(edge_len == 0.0):
        raise ValueError("edge_start_m and edge_end_m must differ (zero-length edge)")
    e = axis / edge_len[..., None]
    ds = s - p0
    do = o - p0
    s_t = np.einsum("...i,...i->...", ds, e)
    o_t = np.einsum("...i,...i->...", do, e)
    r_s = _norm(ds - s_t[..., None] * e)
    r_o = _norm(do - o_t[..., None] * e)
    denom = r_s + r_o
    # Both points on the edge line (up to rounding): every point between them is optimal.
    scale = np.abs(s_t) + np.abs(o_t) + r_s + r_o + edge_len
    degenerate = denom <= 1e-12 * scale
    with np.errstate(invalid="ignore", divide="ignore"):
        t_star = np.where(degenerate, 0.5 * (s_t + o_t), (s_t * r_o + o_t * r_s) / denom)
    t = np.clip(t_star, 0.0, edge_len)
    on_edge = (t_star > 0.0) & (t_star < edge_len)
    q = p0 + t[..., None] * e
    length = _norm(s - q) + _norm(o - q)
    return DiffractionPoint(point_m=q, length_m=length, on_edge=on_edge, edge_param=t / edge_len)


def lemma1_roots(
    source_m: ArrayLike,
    observer_m: ArrayLike,
    edge_x_m: tuple[float, float],
    edge_z_m: float,
) -> FloatArray:
    """Both roots ``lambda`` of the paper's Lemma 1 quadratic (eq. 4), as printed.

    The edge runs from ``X_1 = (x_1, 0, z_e)`` to ``X_2 = (x_2, 0, z_e)`` and the diffraction
    point is ``Q = lambda X_1 + (1 - lambda) X_2``. This is a *reference implementation of the
    paper's formula*, kept to document and test its spurious root; use
    :func:`diffraction_point` for the actual point.

    Returns
    -------
    ndarray, shape (..., 2)
        The two roots (``-b - sqrt(disc)``, ``-b + sqrt(disc)``) / ``2a``; NaN where complex.
        Where ``a == 0`` (equal distances of S and O to the edge line) the single root ``-c/b``
        is returned twice.
    """
    s = np.asarray(source_m, dtype=np.float64)
    o = np.asarray(observer_m, dtype=np.float64)
    x1, x2 = edge_x_m
    xa, ya, za = s[..., 0], s[..., 1], s[..., 2]
    xn, yn, zn = o[..., 0], o[..., 1], o[..., 2]
    ze = edge_z_m
    d = x1 - x2
    a = d**2 * ((yn**2 - ya**2) + (zn**2 - za**2) + 2 * ze * (za - zn))
    b = 2 * d * ((x2 - xa) * ((ze - zn) ** 2 + yn**2) - (x2 - xn) * ((ze - za) ** 2 + ya**2))
    c = (x2 - xa) ** 2 * ((ze - zn) ** 2 + yn**2) - (x2 - xn) ** 2 * ((ze - za) ** 2 + ya**2)
    with np.errstate(invalid="ignore", divide="ignore"):
        disc = np.sqrt(b**2 - 4 * a * c)
        r1 = np.where(a != 0, (-b - disc) / (2 * a), -c / b)
        r2 = np.where(a != 0, (-b + disc) / (2 * a), -c / b)
    return np.stack([r1, r2], axis=-1)


@dataclass(frozen=True)
class EdgePath:
    """Diffraction path over a horizontal window edge (paper, Corollary 1).

    Attributes
    ----------
    length_m : ndarray, shape (...) [m]
        Path length anchor -> edge point -> node (OPL + IPL).
    jacobian : ndarray, shape (..., 3) [m/m]
        Derivative of ``length_m`` with respect to the node position ``(x_n, y_n, z_n)``, the
        edge moving with the node as the model prescribes. NaN where the inside path length is
        zero (node on the edge line, ``y_n = 0`` and ``Delta = w/2``): the length is not
        differentiable there.
    on_edge : ndarray of bool, shape (...)
        False where the edge extent clamped the point (corner diffraction).
    outside_m, inside_m : ndarray, shape (...) [m]
        Outside path length |anchor - Q| (OPL) and inside path length |Q - node| (IPL).
    point_x_m, point_z_m : ndarray, shape (...) [m]
        Coordinates of the diffraction point Q = (point_x_m, 0, point_z_m).
    """

    length_m: FloatArray
    jacobian: FloatArray
    on_edge: BoolArray
    outside_m: FloatArray
    inside_m: FloatArray
    point_x_m: FloatArray
    point_z_m: FloatArray

    @property
    def point_m(self) -> FloatArray:
        """The diffraction point Q, shape (..., 3) [m] (built on demand)."""
        qx, qz = np.broadcast_arrays(self.point_x_m, self.point_z_m)
        return np.stack([qx, np.zeros_like(qx), qz], axis=-1)


def edge_height_offset_m(
    window_height_m: float | ArrayLike,
    delta_m: float | ArrayLike = 0.0,
    edge: Literal["upper", "lower"] = "upper",
) -> FloatArray:
    """Height of the diffracting edge above the node, ``z_e - z_n`` [m].

    With the paper's Case-2 offset ``z_n = z_e^u - 0.5 w + Delta`` (eq. 20) the upper edge is at
    ``z_n + 0.5 w - Delta`` and the lower edge, ``w`` below it, at ``z_n - 0.5 w - Delta``.
    ``Delta = 0`` is Assumption 1 (node at the window's mid-height, Case-1).
    """
    w = np.asarray(window_height_m, dtype=np.float64)
    d = np.asarray(delta_m, dtype=np.float64)
    if edge == "upper":
        return 0.5 * w - d
    if edge == "lower":
        return -0.5 * w - d
    raise ValueError(f"edge must be 'upper' or 'lower', got {edge!r}")


def window_edge_path(
    anchor_m: ArrayLike,
    node_m: ArrayLike,
    *,
    window_height_m: float | ArrayLike,
    delta_m: float | ArrayLike = 0.0,
    edge: Literal["upper", "lower"] = "upper",
    edge_x_m: tuple[float, float] | None = None,
) -> EdgePath:
    """Diffraction path length over the window edge on the node's floor, with Jacobian.

    The edge is the line ``y = 0, z = z_n + h`` parallel to ``x`` (``h`` from
    :func:`edge_height_offset_m`), limited to ``edge_x_m = (x_1, x_2)`` if given (default:
    unbounded). For the paper's upper edge and ``Delta = 0`` this is exactly eq. (6)
    (Corollary 1); the lower edge and Case-2 offset follow from the same construction.

    The Jacobian is analytic. Because Q minimises the length, the envelope theorem gives
    ``dp/dalpha = dp/dalpha |_(q_x fixed)`` both when Q is interior (stationary) and when it is
    clamped to an end (Q constant), so no derivative of the quadratic's root (the paper's
    eq. 24) is needed:

        dp/dx_n = (x_n - q_x) / IPL,   dp/dy_n = y_n / IPL,   dp/dz_n = (z_e - z_a) / OPL.

    Parameters
    ----------
    anchor_m, node_m : array_like, shape (..., 3) [m]
        Anchor and node positions in building coordinates; they broadcast (use
        ``nodes[:, None, :]`` and ``anchors[None, :, :]`` for all node x anchor pairs).
    window_height_m : float or array_like [m]
        Window height ``w``.
    delta_m : float or array_like [m]
        Case-2 vertical offset ``Delta`` (0 for Case-1).
    edge : {"upper", "lower"}
        Which window edge.
    edge_x_m : (float, float), optional
        Extent ``(x_1, x_2)`` of the window edge along x [m].
    """
    a = np.asarray(anchor_m, dtype=np.float64)
    n = np.asarray(node_m, dtype=np.float64)
    h = edge_height_offset_m(window_height_m, delta_m, edge)
    xa, ya, za = a[..., 0], a[..., 1], a[..., 2]
    xn, yn, zn = n[..., 0], n[..., 1], n[..., 2]
    shape = np.broadcast_shapes(xa.shape, xn.shape, h.shape)
    # Unfolded closed form (module docstring): with r_s, r_o the distances of anchor and node to
    # the edge line and L the straight unfolded length, similar triangles give
    # OPL = L r_s / (r_s + r_o), IPL = L r_o / (r_s + r_o): two square roots per pair.
    dz = zn + h - za  # z_e - z_a
    r_s = np.sqrt(ya * ya + dz * dz)
    r_o = np.sqrt(yn * yn + h * h)
    tot = r_s + r_o
    dx = xn - xa
    length = np.sqrt(dx * dx + tot * tot)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac_s = r_s / tot
        opl = length * frac_s
        ipl = length - opl
        qx = xa + dx * frac_s
    jac = np.empty((*shape, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        np.divide(dx, length, out=jac[..., 0])
        np.divide(yn, ipl, out=jac[..., 1])
        np.divide(dz, opl, out=jac[..., 2])
    length, qx, opl, ipl = (_full(v, shape) for v in (length, qx, opl, ipl))
    on_edge = np.ones(shape, dtype=bool)

    # Pairs needing the general (two-distance) formula: clamped to an end of a finite edge, or
    # degenerate (anchor and node both on the edge line, tot == 0).
    fix = ~(tot > 0.0)
    if edge_x_m is not None:
        x_lo, x_hi = min(edge_x_m), max(edge_x_m)
        outside = (qx <= x_lo) | (qx >= x_hi)
        on_edge = ~outside
        fix = fix | outside
    if np.any(fix):
        b = [np.broadcast_to(v, shape)[fix] for v in (xa, xn, yn, dz, r_s, r_o)]
        xa_f, xn_f, yn_f, dz_f, rs_f, ro_f = b
        q = np.where(rs_f + ro_f > 0.0, qx[fix], 0.5 * (xa_f + xn_f))
        if edge_x_m is not None:
            q = np.clip(q, x_lo, x_hi)
        o = np.sqrt((q - xa_f) ** 2 + rs_f**2)
        i = np.sqrt((xn_f - q) ** 2 + ro_f**2)
        qx[fix], opl[fix], ipl[fix], length[fix] = q, o, i, o + i
        with np.errstate(invalid="ignore", divide="ignore"):
            jac[fix] = np.stack([(xn_f - q) / i, yn_f / i, dz_f / o], axis=-1)
    return EdgePath(
        length_m=length,
        jacobian=jac,
        on_edge=on_edge,
        outside_m=opl,
        inside_m=ipl,
        point_x_m=qx,
        point_z_m=_full(zn + h, shape),
    )


def los_path(anchor_m: ArrayLike, node_m: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Straight-line (LoS) distance and its Jacobian with respect to the node.

    Returns
    -------
    length_m : ndarray, shape (...) [m]
    jacobian : ndarray, shape (..., 3) [m/m]
        Unit vector from anchor to node.
    """
    d = np.asarray(node_m, dtype=np.float64) - np.asarray(anchor_m, dtype=np.float64)
    r = _norm(d)
    with np.errstate(invalid="ignore", divide="ignore"):
        return r, d / r[..., None]
