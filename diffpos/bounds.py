"""Fisher information, position error bound (PEB), z-axis bound and identifiability.

The range measurements are ``r_j = p_j(alpha) + n_j`` with independent ``n_j ~ N(0, sigma_j^2)``.
The paper writes the FIM in delay units, ``J_alpha = c^2 J^T J_tau J`` with
``J_tau = diag(8 pi^2 B^2 SNR_j)`` (eq. 15); since ``sigma_j = c / sqrt(8 pi^2 B^2 SNR_j)`` this is
the same matrix as the range-domain form used here, ``J_alpha = J^T diag(1 / sigma_j^2) J``
(rows of ``J`` are ``dp_j / dalpha``, the transpose of the paper's eq. 16).

Bounds (paper, Results section): ``PEB = sqrt(tr J_alpha^-1)`` and the z bound
``sqrt([J_alpha^-1]_33)``. ``J_alpha`` is invertible iff ``rank(J) = 3`` (Theorem 2); the
paper's counter-example (Corollary 3 discussion) has every anchor at ``x_a = 0`` and the node
at ``x_n = 0``: then every diffraction point has ``q_x = 0``, ``dp_j/dx_n = 0`` for all ``j`` and
the x coordinate carries no information. :func:`identifiability` reports such cases (and
near-singular ones) with the direction that is missing.

Shapes: everything is batched over leading dimensions ``(...)``; e.g. ``N`` nodes and ``M``
anchors give a Jacobian ``(N, M, 3)``, FIMs ``(N, 3, 3)`` and bounds ``(N,)``. A link can be
switched off with ``mask`` or, equivalently, with ``sigma = inf``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.geometry import los_path, window_edge_path
from diffpos.sym3 import sym3_adjugate

__all__ = [
    "DEFAULT_MAX_CONDITION",
    "Bounds",
    "Identifiability",
    "bounds_from_fim",
    "fisher_information",
    "identifiability",
    "path_jacobian",
    "position_error_bound",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Condition number of the whitened Jacobian ``diag(1/sigma) J`` (ratio of its largest to its
#: smallest singular value, i.e. ``sqrt(cond(J_alpha))``) above which a geometry is reported as
#: ill-conditioned / not identifiable. At 1e6 the weakest direction is a million times less
#: well determined than the best one; the FIM's own condition number is then 1e12.
DEFAULT_MAX_CONDITION = 1e6

_AXES = ("x", "y", "z")


def _weights(sigmas_m: ArrayLike, mask: ArrayLike | None) -> FloatArray:
    """``1 / sigma^2`` with masked-out links (and ``sigma = inf``) at weight 0."""
    sig = np.asarray(sigmas_m, dtype=np.float64)
    if np.any(np.isnan(sig)) or np.any(sig <= 0.0):
        raise ValueError(
            "sigmas_m must be > 0 (use inf or the mask to drop a link); "
            f"got min {np.nanmin(sig) if sig.size else sig!r} and {int(np.isnan(sig).sum())} NaN"
        )
    w = 1.0 / (sig * sig)
    if mask is not None:
        w = np.where(np.asarray(mask, dtype=bool), w, 0.0)
    return w


def fisher_information(
    jacobian: ArrayLike,
    sigmas_m: ArrayLike,
    mask: ArrayLike | None = None,
) -> FloatArray:
    """FIM of the node position from ranges with the given Jacobian and noise.

    Parameters
    ----------
    jacobian : array_like, shape (..., M, 3) [m/m]
        Rows ``dp_j / dalpha`` (the transpose of the paper's ``J``, eq. 16).
    sigmas_m : array_like, shape (..., M) [m]
        Ranging standard deviations; broadcast against ``jacobian[..., 0]``. ``inf`` drops a link.
    mask : array_like of bool, shape (..., M), optional
        Measurements to include (default all).

    Returns
    -------
    ndarray, shape (..., 3, 3) [1/m^2]
        ``sum_j w_j g_j g_j^T`` with ``w_j = 1/sigma_j^2`` and ``g_j`` the j-th Jacobian row.

    Raises
    ------
    ValueError
        If the Jacobian's last axis is not 3 or a sigma is NaN or not positive.
    """
    jac = np.asarray(jacobian, dtype=np.float64)
    if jac.ndim < 2 or jac.shape[-1] != 3:
        raise ValueError(f"jacobian must have shape (..., M, 3), got {jac.shape}")
    w = _weights(sigmas_m, mask)
    try:
        wj = jac * w[..., None]
    except ValueError:
        raise ValueError(
            f"sigmas_m shape {np.shape(sigmas_m)} does not broadcast with the links "
            f"{jac.shape[:-1]} of the Jacobian (expected (..., M))"
        ) from None
    # (..., 3, M) @ (..., M, 3): one batched matmul, much faster than a 3-operand einsum.
    return np.matmul(np.swapaxes(wj, -1, -2), jac)


def path_jacobian(
    anchors_m: ArrayLike,
    node_m: ArrayLike,
    *,
    model: Literal["diffraction", "los"] = "diffraction",
    window_height_m: float | ArrayLike | None = None,
    delta_m: float | ArrayLike = 0.0,
    edge: Literal["upper", "lower"] = "upper",
    edge_x_m: tuple[float, float] | None = None,
) -> FloatArray:
    """Jacobian rows ``dp_j/dalpha`` of every anchor-node pair for a path model.

    Parameters
    ----------
    anchors_m : array_like, shape (..., M, 3) [m]
    node_m : array_like, shape (..., 3) [m]
        Broadcast against the leading dimensions of ``anchors_m``.
    model : {"diffraction", "los"}
        Window-edge diffraction path (paper Corollary 1, :func:`diffpos.geometry.window_edge_path`)
        or the straight line (LoS).
    window_height_m : float [m]
        Window height ``w`` (required for the diffraction model).
    delta_m, edge, edge_x_m
        Passed to :func:`diffpos.geometry.window_edge_path`.

    Returns
    -------
    ndarray, shape (..., M, 3) [m/m]
    """
    anchors = np.asarray(anchors_m, dtype=np.float64)
    node = np.asarray(node_m, dtype=np.float64)
    if anchors.ndim < 2 or anchors.shape[-1] != 3:
        raise ValueError(f"anchors_m must have shape (..., M, 3), got {anchors.shape}")
    if node.ndim < 1 or node.shape[-1] != 3:
        raise ValueError(f"node_m must have shape (..., 3), got {node.shape}")
    node = node[..., None, :]
    if model == "diffraction":
        if window_height_m is None:
            raise ValueError("window_height_m is required for the diffraction model")
        return window_edge_path(
            anchors,
            node,
            window_height_m=window_height_m,
            delta_m=delta_m,
            edge=edge,
            edge_x_m=edge_x_m,
        ).jacobian
    if model == "los":
        return los_path(anchors, node)[1]
    raise ValueError(f"model must be 'diffraction' or 'los', got {model!r}")


@dataclass(frozen=True)
class Identifiability:
    """Whether the 3D position is identifiable (paper Theorem 2 / Corollary 3).

    Attributes
    ----------
    identifiable : ndarray of bool, shape (...)
        ``rank(J) == 3`` and the condition number is below the threshold.
    rank : ndarray of int, shape (...)
        Numerical rank of the whitened Jacobian (tolerance as ``numpy.linalg.matrix_rank``).
    condition : ndarray, shape (...) [-]
        Ratio of the largest to the smallest singular value of the whitened Jacobian
        (``inf`` when rank deficient).
    weakest_direction : ndarray, shape (..., 3) [-]
        Unit vector of the least-informed direction (right singular vector of the smallest
        singular value), sign fixed so that its largest component is positive; e.g. ``+x`` for
        the paper's example of all anchors and the node at ``x = 0``.
    weakest_sigma_m : ndarray, shape (...) [m]
        Bound along ``weakest_direction``, ``1 / s_min`` (``inf`` when rank deficient).
    max_condition : float
        The threshold used.

    Notes
    -----
    :attr:`message` (one string per geometry, flattened order) and :meth:`summary` are built
    on demand, so checking many thousands of geometries stays vectorised.
    """

    identifiable: BoolArray
    rank: NDArray[np.int_]
    condition: FloatArray
    weakest_direction: FloatArray
    weakest_sigma_m: FloatArray
    max_condition: float = DEFAULT_MAX_CONDITION

    @property
    def message(self) -> list[str]:
        """Human-readable verdict per geometry (flattened order)."""
        return [
            _verdict(bool(ok), int(r), float(c), v, float(s), self.max_condition)
            for ok, r, c, v, s in zip(
                np.ravel(self.identifiable),
                np.ravel(self.rank),
                np.ravel(self.condition),
                np.reshape(self.weakest_direction, (-1, 3)),
                np.ravel(self.weakest_sigma_m),
                strict=True,
            )
        ]

    def summary(self) -> str:
        """One line: how many geometries are identifiable, and the first failure's reason."""
        ok = np.ravel(self.identifiable)
        n_bad = int(ok.size - np.count_nonzero(ok))
        if n_bad == 0:
            return f"all {ok.size} geometries identifiable"
        i = int(np.flatnonzero(~ok)[0])
        first = _verdict(
            False,
            int(np.ravel(self.rank)[i]),
            float(np.ravel(self.condition)[i]),
            np.reshape(self.weakest_direction, (-1, 3))[i],
            float(np.ravel(self.weakest_sigma_m)[i]),
            self.max_condition,
        )
        return f"{n_bad} of {ok.size} geometries not identifiable; first (index {i}): {first}"


def _verdict(ok: bool, rank: int, cond: float, v: FloatArray, sigma: float, max_cond: float) -> str:
    direction = "[" + ", ".join(f"{x:+.2f}" for x in v) + "]"
    axis = _AXES[int(np.argmax(np.abs(v)))]
    if ok:
        return f"identifiable (condition {cond:.3g})"
    if rank < 3:
        return (
            f"not identifiable: rank {rank} < 3, the ranges carry no information about {axis} "
            f"(null direction {direction}); move or add an anchor to break the symmetry"
        )
    return (
        f"ill-conditioned: condition {cond:.3g} >= {max_cond:.3g}, the bound along {direction} "
        f"(mostly {axis}) is {sigma:.3g} m"
    )


def identifiability(
    jacobian: ArrayLike,
    sigmas_m: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    max_condition: float = DEFAULT_MAX_CONDITION,
) -> Identifiability:
    """Rank and conditioning of the whitened Jacobian ``diag(1/sigma) J``.

    ``J_alpha = (W J)^T (W J)`` is invertible iff ``rank(J) = 3`` (Theorem 2); the singular
    values of ``W J`` are the square roots of the FIM's eigenvalues, so the condition number
    reported here is ``sqrt(cond(J_alpha))``.

    Parameters
    ----------
    jacobian : array_like, shape (..., M, 3) [m/m]
    sigmas_m : array_like, shape (..., M) [m]
    mask : array_like of bool, shape (..., M), optional
    max_condition : float
        Threshold on the condition number (default :data:`DEFAULT_MAX_CONDITION`).

    Returns
    -------
    Identifiability

    Examples
    --------
    The paper's example: all anchors and the node at ``x = 0``.

    >>> import numpy as np
    >>> from diffpos.bounds import identifiability, path_jacobian
    >>> anchors = np.array([[0.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0]])
    >>> jac = path_jacobian(anchors, [0.0, 5.0, 7.5], window_height_m=1.5)
    >>> res = identifiability(jac, np.full(3, 0.01))
    >>> bool(res.identifiable), int(res.rank)
    (False, 2)
    >>> res.message[0].split(",")[0]
    'not identifiable: rank 2 < 3'
    """
    jac = np.asarray(jacobian, dtype=np.float64)
    if jac.ndim < 2 or jac.shape[-1] != 3:
        raise ValueError(f"jacobian must have shape (..., M, 3), got {jac.shape}")
    w = np.sqrt(_weights(sigmas_m, mask))
    wj = jac * w[..., None]
    m = wj.shape[-2]
    if m < 3:  # pad with zero rows so the SVD always exposes a 3-D right singular basis
        wj = np.concatenate([wj, np.zeros((*wj.shape[:-2], 3 - m, 3))], axis=-2)
    _, sv, vt = np.linalg.svd(wj, full_matrices=False)
    smax = sv[..., 0]
    tol = smax * max(m, 3) * np.finfo(np.float64).eps
    rank = np.sum(sv > tol[..., None], axis=-1)
    smin = sv[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.where(rank == 3, smax / smin, np.inf)
        weakest_sigma = np.where(rank == 3, 1.0 / smin, np.inf)
    ok = (rank == 3) & (cond < max_condition)
    weakest = vt[..., 2, :]
    # fix the sign: largest-magnitude component positive
    big = np.take_along_axis(weakest, np.argmax(np.abs(weakest), axis=-1)[..., None], axis=-1)
    weakest = weakest * np.where(big < 0.0, -1.0, 1.0)
    return Identifiability(
        identifiable=ok,
        rank=rank,
        condition=cond,
        weakest_direction=weakest,
        weakest_sigma_m=weakest_sigma,
        max_condition=float(max_condition),
    )


@dataclass(frozen=True)
class Bounds:
    """Position error bound, z-axis bound and the CRLB matrix.

    Attributes
    ----------
    peb_m : ndarray, shape (...) [m]
        ``sqrt(tr(J_alpha^-1))``; ``inf`` where not identifiable.
    z_bound_m : ndarray, shape (...) [m]
        ``sqrt([J_alpha^-1]_33)``; ``inf`` where not identifiable.
    crlb_m2 : ndarray, shape (..., 3, 3) [m^2]
        ``J_alpha^-1`` (all ``inf`` where not identifiable).
    identifiable : ndarray of bool, shape (...)
        False where ``J_alpha`` is singular or its condition number exceeds
        ``max_condition**2`` (see :func:`identifiability` for a readable reason).
    fim : ndarray, shape (..., 3, 3) [1/m^2]
        The Fisher information matrix ``J_alpha`` itself.
    """

    peb_m: FloatArray
    z_bound_m: FloatArray
    crlb_m2: FloatArray
    identifiable: BoolArray
    fim: FloatArray | None = None

    @property
    def axis_bounds_m(self) -> FloatArray:
        """Per-axis bounds ``sqrt(diag(J_alpha^-1))``, shape (..., 3) [m] (x, y, z)."""
        return np.sqrt(np.diagonal(self.crlb_m2, axis1=-2, axis2=-1))


def bounds_from_fim(fim: ArrayLike, *, max_condition: float = DEFAULT_MAX_CONDITION) -> Bounds:
    """PEB, z bound and CRLB matrix from FIMs of shape ``(..., 3, 3)``.

    Parameters
    ----------
    fim : array_like, shape (..., 3, 3) [1/m^2]
        Symmetric positive semi-definite Fisher information matrices.
    max_condition : float
        A FIM counts as invertible when ``lambda_min > lambda_max / max_condition**2``
        (the same criterion as :func:`identifiability` on the whitened Jacobian).

    Returns
    -------
    Bounds

    Notes
    -----
    Fast path: where ``det F > tau ||F||_F^3`` with ``tau = max(max_condition**-2, 1e-6)``,
    ``lambda_min >= det / lambda_max^2 >= tau lambda_max``, so the FIM is certainly invertible
    within the threshold (condition number at most ``1/tau``) and is inverted in closed form
    (adjugate / determinant; relative error below about ``1e-13 cond``, i.e. 1e-7 at worst).
    The rest (condition number possibly above 1e6: near-singular or badly conditioned, rare in
    practice) goes through ``eigvalsh`` for the exact criterion and LAPACK ``inv``. Rounding in
    the determinant (about ``10 eps ||F||^3``) is far below ``tau ||F||^3``, so it never
    decides anything.
    """
    f = np.asarray(fim, dtype=np.float64)
    if f.ndim < 2 or f.shape[-2:] != (3, 3):
        raise ValueError(f"fim must have shape (..., 3, 3), got {f.shape}")
    batch = f.shape[:-2]
    flat = f.reshape(-1, 3, 3)
    adj, det, fro = sym3_adjugate(flat)
    tau = max(float(max_condition) ** -2, 1e-6)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ok = det > tau * fro**3
        inv = adj / det[:, None, None]
    slow = np.flatnonzero(~ok)
    if slow.size:
        fs = flat[slow]
        eig = np.linalg.eigvalsh(fs)
        emax = eig[:, -1]
        ok_s = (emax > 0.0) & (eig[:, 0] > emax / float(max_condition) ** 2)
        inv_s = np.linalg.inv(np.where(ok_s[:, None, None], fs, np.eye(3)))
        inv[slow] = np.where(ok_s[:, None, None], inv_s, np.inf)
        ok[slow] = ok_s
    inv = inv.reshape(*batch, 3, 3)
    ok = ok.reshape(batch)
    peb = np.sqrt(np.trace(inv, axis1=-2, axis2=-1))
    zb = np.sqrt(inv[..., 2, 2])
    return Bounds(peb_m=peb, z_bound_m=zb, crlb_m2=inv, identifiable=ok, fim=f)


def position_error_bound(
    anchors_m: ArrayLike,
    node_m: ArrayLike,
    sigmas_m: ArrayLike,
    window_height_m: float,
    delta_m: float = 0.0,
    *,
    model: Literal["diffraction", "los"] = "diffraction",
    edge: Literal["upper", "lower"] = "upper",
    edge_x_m: tuple[float, float] | None = None,
    mask: ArrayLike | None = None,
    max_condition: float = DEFAULT_MAX_CONDITION,
) -> Bounds:
    """PEB and z-axis bound of nodes for the diffraction path model (or LoS, to compare).

    Parameters
    ----------
    anchors_m : array_like, shape (..., M, 3) [m]
        Anchor positions (building coordinates).
    node_m : array_like, shape (..., 3) [m]
        Node positions; broadcast against the leading dimensions of ``anchors_m``. E.g.
        anchors ``(M, 3)`` and nodes ``(N, 3)`` give bounds of shape ``(N,)``.
    sigmas_m : array_like, shape (..., M) [m]
        Ranging standard deviations (e.g. :func:`diffpos.channel.linkbudget.ranging_crlb_m` at each
        link's SNR); ``(M,)`` or ``(N, M)``. ``inf`` drops a link.
    window_height_m : float [m]
        Window height ``w``.
    delta_m : float [m]
        Case-2 offset used in the model (0: Assumption 1).
    model : {"diffraction", "los"}
        Path model of the FIM: the window-edge diffraction path (paper eq. 6) or a straight line.
    edge : {"upper", "lower"}
        Diffracting edge (the paper's FIM uses the dominant upper edge).
    edge_x_m : (float, float), optional
        Extent of the window edge along x [m] (default unbounded).
    mask : array_like of bool, shape (..., M), optional
        Links to include.
    max_condition : float
        See :func:`bounds_from_fim`.

    Returns
    -------
    Bounds
        ``peb_m`` and ``z_bound_m`` of shape ``(...)``; ``inf`` where the geometry is not
        identifiable (see :func:`identifiability` for the reason).
    """
    jac = path_jacobian(
        anchors_m,
        node_m,
        model=model,
        window_height_m=window_height_m,
        delta_m=delta_m,
        edge=edge,
        edge_x_m=edge_x_m,
    )
    fim = fisher_information(jac, sigmas_m, mask)
    return bounds_from_fim(fim, max_condition=max_condition)
