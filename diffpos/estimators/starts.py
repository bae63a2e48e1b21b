"""The multi-start points of the iterative estimators (D-NLS, IPPA): one start per floor
height, at the anchors' mean ``x`` and a fixed depth inside the wall (:func:`grid_starts`), and
the validated start heights (:func:`check_z_starts`, default :data:`DEFAULT_Z_STARTS_M`). D-NLS
adds the LoS LLS position as one more start (:mod:`diffpos.estimators.dnls.fit`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["DEFAULT_Z_STARTS_M", "check_z_starts", "grid_starts"]

FloatArray = NDArray[np.float64]

#: Default start heights [m]: one per 3 m floor from the ground to 30 m.
DEFAULT_Z_STARTS_M = tuple(float(z) for z in np.arange(0.0, 30.0 + 1e-9, 3.0))


def check_z_starts(z_starts_m: ArrayLike | None) -> FloatArray:
    """The start heights (default :data:`DEFAULT_Z_STARTS_M`), validated, shape (S,) [m]."""
    zs = np.asarray(DEFAULT_Z_STARTS_M if z_starts_m is None else z_starts_m, float)
    if zs.ndim != 1 or zs.size == 0 or not np.all(np.isfinite(zs)):
        raise ValueError("z_starts_m must be a non-empty 1-D array of finite heights [m]")
    return zs


def grid_starts(
    anchors_m: FloatArray, mask: NDArray[np.bool_], z_starts: FloatArray, y_start: float
) -> FloatArray:
    """Multi-start points ``(B, S, 3)``: x = mean anchor x, y = ``y_start``, z from the grid."""
    cnt = np.maximum(mask.sum(axis=-1), 1)
    xm = np.where(mask, anchors_m[..., 0], 0.0).sum(axis=-1) / cnt
    b, s = xm.shape[0], z_starts.size
    st = np.empty((b, s, 3))
    st[..., 0] = xm[:, None]
    st[..., 1] = y_start
    st[..., 2] = z_starts[None, :]
    return st
