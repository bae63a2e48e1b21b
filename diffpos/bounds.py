"""Fisher information, position error bound (PEB), z-axis bound and identifiability.

The range measurements are ``r_j = p_j(alpha) + n_j`` with independent ``n_j ~ N(0, sigma_j^2)``.
The paper writes the FIM in delay units, ``J_alpha = c^2 J^T J_tau J`` with
``J_tau = diag(8 pi^2 B^2 SNR_j)`` (eq. 15); since ``sigma_j = c / sqrt(8 pi^2 B^2 SNR_j)`` this is
the same matrix as the range-domain form used here, ``J_alpha = J^T diag(1 / sigma_j^2) J``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .geometry import los_path, window_edge_path

__all__ = [
    "Bounds",
    "Identifiability",
    "bounds_from_fim",
    "fisher_information",
    "identifiability",
    "position_error_bound",
]

FloatArray = NDArray[np.float64]

#: Condition number of the sqrt-FIM (ratio of largest to smallest singular value of the
#: whitened Jacobian) above which a geometry is reported as ill-conditioned.
DEFAULT_MAX_CONDITION = 1e6


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
        Ranging standard deviations.
    mask : array_like of bool, shape (..., M), optional
        Measurements to include (default all).

    Returns
    -------
    ndarray, shape (..., 3, 3) [1/m^2]
    """
    jac = np.asarray(jacobian, dtype=np.float64)
    w = 1.0 / np.square(np.asarray(sigmas_m, dtype=np.float64))
    if mask is not None:
        w = np.where(np.asarray(mask, dtype=bool), w, 0.0)
    return np.einsum("...mi,...m,...mj->...ij", jac, w, jac)


@dataclass(frozen=True)
class Identifiability:
    """Whether the 3D position is identifiable (paper Theorem 2 / Corollary 3).

    Attributes
    ----------
    identifiable : ndarray of bool, shape (...)
        ``rank(J) == 3`` and the condition number is below the threshold.
    rank : ndarray of int, shape (...)
        Numerical rank of the whitened Jacobian.
    condition : ndarray, shape (...)
        Ratio of the largest to the smallest singular value of the whitened Jacobian
        (``inf`` when rank deficient).
    weakest_direction : ndarray, shape (..., 3)
        Unit vector of the least-informed direction (right singular vector of the smallest
        singular value); e.g. ``+-x`` for the paper's example of all anchors and the node at
        ``x = 0``.
    message : list of str
        Human-readable verdict per geometry (flattened order).
    """

    identifiable: NDArray[np.bool_]
    rank: NDArray[np.int_]
    condition: FloatArray
    weakest_direction: FloatArray
    message: list[str]


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
    """
    jac = np.asarray(jacobian, dtype=np.float64)
    sig = np.asarray(sigmas_m, dtype=np.float64)
    w = 1.0 / sig
    if mask is not None:
        w = np.where(np.asarray(mask, dtype=bool), w, 0.0)
    wj = jac * w[..., None]
    _, sv, vt = np.linalg.svd(wj, full_matrices=False)
    # sv: (..., k) with k = min(M, 3); pad to 3 for M < 3.
    if sv.shape[-1] < 3:
        pad = 3 - sv.shape[-1]
        sv = np.concatenate([sv, np.zeros((*sv.shape[:-1], pad))], axis=-1)
    smax = sv[..., 0]
    tol = np.maximum(smax, np.finfo(float).tiny) * max(jac.shape[-2], 3) * np.finfo(float).eps
    rank = np.sum(sv > tol[..., None], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.where(rank == 3, smax / sv[..., 2], np.inf)
    ok = (rank == 3) & (cond < max_condition)
    if vt.shape[-2] == 3:
        weakest = vt[..., 2, :]
    else:  # fewer than 3 measurements: the null space is not in vt; use the cross product
        full_v = np.linalg.svd(
            np.concatenate([wj, np.zeros((*wj.shape[:-2], 3 - wj.shape[-2], 3))], axis=-2)
        )[2]
        weakest = full_v[..., 2, :]
    names = np.array(["x", "y", "z"])
    msgs: list[str] = []
    for r, c, ok_i, v in zip(
        np.ravel(rank), np.ravel(cond), np.ravel(ok), weakest.reshape(-1, 3), strict=True
    ):
        if ok_i:
            msgs.append(f"identifiable (condition {c:.3g})")
            continue
        axis = names[int(np.argmax(np.abs(v)))]
        direction = "[" + ", ".join(f"{x:+.2f}" for x in v) + "]"
        if r < 3:
            msgs.append(
                f"not identifiable: rank {int(r)} < 3, no information along {direction} "
                f"(mostly {axis}); add an anchor that breaks the symmetry"
            )
        else:
            msgs.append(
                f"ill-conditioned: condition {c:.3g} >= {max_condition:.3g}, weakest direction "
                f"{direction} (mostly {axis})"
            )
    return Identifiability(
        identifiable=ok,
        rank=rank,
        condition=cond,
        weakest_direction=weakest,
        message=msgs,
    )


@dataclass(frozen=True)
class Bounds:
    """Position error bound and z-axis bound.

    Attributes
    ----------
    peb_m : ndarray, shape (...) [m]
        ``sqrt(tr(J_alpha^-1))``; ``inf`` where not identifiable.
    z_bound_m : ndarray, shape (...) [m]
        ``sqrt([J_alpha^-1]_33)``; ``inf`` where not identifiable.
    crlb_m2 : ndarray, shape (..., 3, 3) [m^2]
        ``J_alpha^-1`` (``inf`` where not identifiable).
    identifiable : ndarray of bool, shape (...)
    """

    peb_m: FloatArray
    z_bound_m: FloatArray
    crlb_m2: FloatArray
    identifiable: NDArray[np.bool_]


def bounds_from_fim(fim: ArrayLike, *, max_condition: float = DEFAULT_MAX_CONDITION) -> Bounds:
    """PEB, z bound and CRLB matrix from FIMs of shape ``(..., 3, 3)``."""
    f = np.asarray(fim, dtype=np.float64)
    eig = np.linalg.eigvalsh(f)
    emax = np.maximum(eig[..., -1], np.finfo(float).tiny)
    ok = eig[..., 0] > emax / max_condition**2
    safe = np.where(ok[..., None, None], f, np.eye(3))
    inv = np.linalg.inv(safe)
    inv = np.where(ok[..., None, None], inv, np.inf)
    peb = np.sqrt(np.trace(inv, axis1=-2, axis2=-1))
    zb = np.sqrt(inv[..., 2, 2])
    return Bounds(peb_m=peb, z_bound_m=zb, crlb_m2=inv, identifiable=ok)


def position_error_bound(
    anchors_m: ArrayLike,
    node_m: ArrayLike,
    sigmas_m: ArrayLike,
    window_height_m: float,
    delta_m: float = 0.0,
    *,
    model: Literal["diffraction", "los"] = "diffraction",
    edge_x_m: tuple[float, float] | None = None,
    max_condition: float = DEFAULT_MAX_CONDITION,
) -> Bounds:
    """PEB and z-axis bound of a node for the diffraction path model (or LoS, to compare).

    Parameters
    ----------
    anchors_m : array_like, shape (..., M, 3) [m]
        Anchor positions (building coordinates).
    node_m : array_like, shape (..., 3) [m]
        Node positions; broadcast against the leading dimensions of ``anchors_m``.
    sigmas_m : array_like, shape (..., M) [m]
        Ranging standard deviations (e.g. the ranging CRLB at each link's SNR).
    window_height_m : float [m]
        Window height ``w``.
    delta_m : float [m]
        Case-2 offset used in the model.
    model : {"diffraction", "los"}
        Path model of the FIM: the upper-edge diffraction path (paper eq. 6) or a straight line.

    Returns
    -------
    Bounds
        ``peb_m`` and ``z_bound_m`` of shape ``(...)``; ``inf`` where the geometry is not
        identifiable (see :func:`identifiability` for the reason).
    """
    anchors = np.asarray(anchors_m, dtype=np.float64)
    node = np.asarray(node_m, dtype=np.float64)[..., None, :]
    if model == "diffraction":
        jac = window_edge_path(
            anchors, node, window_height_m=window_height_m, delta_m=delta_m, edge_x_m=edge_x_m
        ).jacobian
    elif model == "los":
        jac = los_path(anchors, node)[1]
    else:
        raise ValueError(f"model must be 'diffraction' or 'los', got {model!r}")
    fim = fisher_information(jac, sigmas_m)
    return bounds_from_fim(fim, max_condition=max_condition)
