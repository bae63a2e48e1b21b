"""Compiled set-up of the tracker's measurement update
(:func:`diffpos.tracking.model.measurement_update`): every input of its passes that depends on
the prior only, in one pass per hypothesis instead of ~40 numpy calls.

:func:`update_fixed_kernel` writes the prior clamped into its floor's box
(:func:`~diffpos.tracking.state.clamp_to_floor`) and the nodes it moved, every hypothesis'
existence margin (:func:`~diffpos.tracking.model.existence_margin`, or the fixed one at
initialisation), the prior's information matrix and log-determinant (``iekf_nb``'s LU, as
:func:`~diffpos.tracking.iekf_nb.prior_info_kernel`), the floor box and the height prior of
the IEKF (``model._box``, ``model._height_prior``). :func:`clamp_kernel` is
:func:`~diffpos.tracking.state.clamp_to_floor` of the posterior. The numpy functions stay the
reference; the operations are theirs in their order (``np.clip``'s and ``np.maximum``'s NaN
rules included), so the values are bit for bit (tests/core/test_update_fixed.py).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from diffpos.tracking.iekf_nb import _D, _lu, _lu_inv, _lu_logdet

__all__ = ["clamp_kernel", "update_fixed_kernel", "warm_update"]

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}
#: numba keys this file's on-disk cache on this file only, not on the ``*_nb`` code its
#: kernels compile in: a digest of that code (tests/core/test_kernel_stamps.py names the new
#: value after a callee's edit; writing it here is what invalidates a warm cache).
CALLEES_SHA256 = "e98bb3e233128f21"


@njit(**_OPTS)
def _clip(v, lo, hi):
    """``np.clip`` of one float: ``min(max(v, lo), hi)``, NaN kept."""
    if math.isnan(v):
        return v
    c = v if v > lo else lo
    return c if c < hi else hi


@njit(**_OPTS)
def _bounds(fl, box):
    """The floor box of floor ``fl`` (float): ``box`` = (x0 + m, x1 - m, m, depth - m,
    first_z, floor_h, margin) -> (z lo, z hi) as ``Building.floor_z_m`` and ``model._box``."""
    zf = box[4] + fl * box[5]
    return zf + box[6], (zf + box[5]) - box[6]


@njit(**_OPTS)
def clamp_kernel(x, floor, box, out):
    """``state.clamp_to_floor``: ``out`` (N, H, D) = ``x`` with its first three coordinates
    clipped into the box of ``floor`` (N, H) float64; ``box`` as :func:`_bounds`."""
    n_n, n_h, n_d = x.shape
    for n in range(n_n):
        for h in range(n_h):
            z_lo, z_hi = _bounds(floor[n, h], box)
            out[n, h, 0] = _clip(x[n, h, 0], box[0], box[1])
            out[n, h, 1] = _clip(x[n, h, 1], box[2], box[3])
            out[n, h, 2] = _clip(x[n, h, 2], z_lo, z_hi)
            for i in range(3, n_d):
                out[n, h, i] = x[n, h, i]


@njit(**_OPTS)
def update_fixed_kernel(x, p, floor, level, has_level, box, margins, height, xc, moved,
                        relax, y, logdet_y, lo, hi, z_nom, wh, h_const):
    """The prior-only inputs of one measurement update.

    ``x`` (N, H, 6), ``p`` (N, H, 6, 6) the prior, ``floor`` (N, H) float64, ``level`` (N, H)
    bool (the vertical modes; ignored unless ``has_level``), ``box`` as :func:`_bounds`,
    ``margins`` = (exist_margin_m, ENTRY_SIGMAS), ``height`` = (nominal height above the
    floor, 1 / sigma_h^2, the level and the stairs mode's log-normalisers ``w_lvl +
    ll_gauss``, ``w_any + ll_any`` (``model._height_prior``: with ``has_level`` the weights
    are 0), sigma_h). Writes ``xc`` (N, H, 3) the
    clamped prior, ``moved`` (N,) bool (a hypothesis of the node clamped or not finite),
    ``relax`` (N, H) (with ``has_level`` the hypothesis' own margin, else the fixed one),
    ``y`` (N, H, 6, 6), ``logdet_y`` (N, H), ``lo``/``hi`` (N, H, 3), ``z_nom``, ``wh``,
    ``h_const`` (N, H)."""
    n_n, n_h = floor.shape
    lu = np.empty((_D, _D))
    piv = np.empty(_D, dtype=np.int64)
    col = np.empty(_D)
    for n in range(n_n):
        mv = False
        for h in range(n_h):
            fl = floor[n, h]
            z_lo, z_hi = _bounds(fl, box)
            lo[n, h, 0], lo[n, h, 1], lo[n, h, 2] = box[0], box[2], z_lo
            hi[n, h, 0], hi[n, h, 1], hi[n, h, 2] = box[1], box[3], z_hi
            c0 = _clip(x[n, h, 0], box[0], box[1])
            c1 = _clip(x[n, h, 1], box[2], box[3])
            c2 = _clip(x[n, h, 2], z_lo, z_hi)
            xc[n, h, 0], xc[n, h, 1], xc[n, h, 2] = c0, c1, c2
            mv = mv or not (c0 == x[n, h, 0] and c1 == x[n, h, 1] and c2 == x[n, h, 2])
            if has_level:
                v = p[n, h, 2, 2]
                v = v if (v > 0.0 or math.isnan(v)) else 0.0  # np.maximum(v, 0)
                r = margins[1] * math.sqrt(v)
                relax[n, h] = r if (r > margins[0] or math.isnan(r)) else margins[0]
            else:
                relax[n, h] = margins[0]
            zn = (box[4] + fl * box[5]) + height[0]
            z_nom[n, h] = zn
            if has_level:
                lv = level[n, h]
            else:  # the max-mixture's mode, chosen at the prior
                q = (x[n, h, 2] - zn) / height[4]
                lv = (height[2] - 0.5 * (q * q)) > height[3]
            wh[n, h] = height[1] if lv else 0.0
            h_const[n, h] = height[2] if lv else height[3]
            _lu(p[n, h], lu, piv)
            _lu_inv(lu, piv, y[n, h], col)
            _lu(y[n, h], lu, piv)
            logdet_y[n, h] = _lu_logdet(lu)
        moved[n] = mv


def warm_update() -> None:
    """Compile (or load from numba's cache) both kernels on tiny inputs of the tracker's
    types."""
    x, p = np.ones((1, 1, 6)), np.broadcast_to(np.eye(6), (1, 1, 6, 6)).copy()
    fl, box = np.zeros((1, 1)), np.array([0.05, 9.95, 0.05, 9.95, 0.0, 3.0, 0.05])
    clamp_kernel(x, fl, box, np.empty((1, 1, 6)))
    e = np.empty
    update_fixed_kernel(x, p, fl, np.ones((1, 1), np.bool_), True, box, np.array([0.2, 2.0]),
                        np.ones(5), e((1, 1, 3)), e(1, np.bool_), e((1, 1)), e((1, 1, 6, 6)),
                        e((1, 1)), e((1, 1, 3)), e((1, 1, 3)), e((1, 1)), e((1, 1)), e((1, 1)))
