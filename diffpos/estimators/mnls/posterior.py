"""Floor posterior and information of the M-NLS modes (:mod:`diffpos.estimators.mnls.solver`).

``p`` is the estimator's flattened problem, ``t`` the link terms at the modes ``sel``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def _information(p, sel, t) -> tuple[FloatArray, FloatArray]:
    """Gauss-Newton Hessian with the mechanism-ambiguity variance, and per-link variance."""
    sig = p.sig[sel]
    e_all = p.r[sel][..., None] - t["length"]
    near = t["cand"] & (np.abs(e_all) < 3 * sig[..., None])
    chosen = np.take_along_axis(t["length"], t["slot"][..., None], axis=-1)
    dl = np.where(near, np.abs(t["length"] - chosen), 0.0)
    var = sig**2 + (0.5 * np.nanmax(np.where(near, dl, 0.0), axis=-1)) ** 2
    used = p.mask[sel] & ~t["tail"] & ~t["none"]
    ws = np.where(used, 1.0 / var, 0.0)
    h = np.einsum("nm,nmi,nmj->nij", ws, t["jac"], t["jac"])
    # the uniform-over-the-floor prior: z as in the cost, x and y (W^2/12, D^2/12) only here,
    # to keep directions no link constrains finite (negligible next to any range)
    h[:, 2, 2] += 1.0 / p.prior_var
    box = (p.hi - p.lo)[sel]
    h[:, 0, 0] += 12.0 / box[:, 0] ** 2
    h[:, 1, 1] += 12.0 / box[:, 1] ** 2
    return h, var


def _posterior(cost: FloatArray, h: FloatArray) -> FloatArray:
    """Laplace floor posterior from (B, F) costs and (B, F, 3, 3) Hessians."""
    sign, logdet = np.linalg.slogdet(h)
    logdet = np.where(sign > 0, logdet, np.inf)
    lp = -cost - 0.5 * logdet
    lp = np.where(np.isfinite(lp), lp, -np.inf)
    mx = np.max(lp, axis=-1, keepdims=True)
    w = np.exp(lp - np.where(np.isfinite(mx), mx, 0.0))
    s = w.sum(axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(s > 0, w / s, 1.0 / cost.shape[-1])
