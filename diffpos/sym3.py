"""Closed-form algebra of batches of symmetric 3x3 matrices (numpy): cofactors and determinant
(:func:`sym3_cofactors`), the adjugate (:func:`sym3_adjugate`, the fast path of
:func:`diffpos.bounds.bounds_from_fim`) and the batched solve of the numpy Levenberg-Marquardt's
normal equations (:func:`solve3`). Shared by the bounds and the estimators, so neither imports
the other.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["solve3", "sym3_adjugate", "sym3_cofactors"]

FloatArray = NDArray[np.float64]


def sym3_cofactors(
    a: FloatArray, b: FloatArray, c: FloatArray, d: FloatArray, e: FloatArray, g: FloatArray
) -> tuple[FloatArray, ...]:
    """Cofactors and determinant of symmetric 3x3 matrices ``[[a, b, c], [b, d, e], [c, e, g]]``.

    Returns ``(c00, c01, c02, c11, c12, c22, det)`` (the adjugate is symmetric too).
    """
    c00 = d * g - e * e
    c01 = c * e - b * g
    c02 = b * e - c * d
    c11 = a * g - c * c
    c12 = b * c - a * e
    c22 = a * d - b * b
    return c00, c01, c02, c11, c12, c22, a * c00 + b * c01 + c * c02


def sym3_adjugate(f: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Adjugate, determinant and Frobenius norm of symmetric 3x3 matrices ``f`` (..., 3, 3) (closed
    form; :func:`diffpos.bounds.bounds_from_fim`'s fast path)."""
    a, d, g = f[..., 0, 0], f[..., 1, 1], f[..., 2, 2]
    b = 0.5 * (f[..., 0, 1] + f[..., 1, 0])
    c = 0.5 * (f[..., 0, 2] + f[..., 2, 0])
    e = 0.5 * (f[..., 1, 2] + f[..., 2, 1])
    c00, c01, c02, c11, c12, c22, det = sym3_cofactors(a, b, c, d, e, g)
    adj = np.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], axis=-1)
    fro = np.sqrt(a * a + d * d + g * g + 2.0 * (b * b + c * c + e * e))
    return adj.reshape(*adj.shape[:-1], 3, 3), det, fro


def solve3(a: FloatArray, b: FloatArray) -> FloatArray:
    """Batched solve of symmetric 3x3 systems ``a x = b`` (LAPACK or cofactors; the normal
    equations of :func:`diffpos.estimators.lm.levenberg_marquardt`).

    Parameters
    ----------
    a : ndarray, shape (N, 3, 3)
    b : ndarray, shape (N, 3)
    """
    if a.shape[0] <= 128:  # LAPACK is cheaper for a few systems, cofactors for many
        try:
            return np.linalg.solve(a, b[..., None])[..., 0]
        except np.linalg.LinAlgError:
            pass  # a singular system: the cofactor form gives inf/nan for that row only
    c00, c01, c02, c11, c12, c22, det = sym3_cofactors(
        a[:, 0, 0], a[:, 0, 1], a[:, 0, 2], a[:, 1, 1], a[:, 1, 2], a[:, 2, 2]
    )
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = 1.0 / det
        x0 = (c00 * b0 + c01 * b1 + c02 * b2) * inv_det
        x1 = (c01 * b0 + c11 * b1 + c12 * b2) * inv_det
        x2 = (c02 * b0 + c12 * b1 + c22 * b2) * inv_det
    return np.stack([x0, x1, x2], axis=-1)
