"""The answer of M-NLS (:mod:`diffpos.estimators.mnls.solver`) at its modes: the Gauss-Newton
information with the mechanism-ambiguity variance (:func:`_information`), the Laplace floor
posterior (:func:`_posterior`), :class:`MnlsResult` and its assembly from the per-fix answers
(:func:`_result`: the a posteriori variance factor on the covariance, the residual test,
statuses and exclusion reasons).

``p`` is the estimator's flattened problem, ``t`` the link terms at the modes ``sel``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from diffpos.channel.detection import normal_cdf
from diffpos.estimators.gating import chi2_threshold
from diffpos.estimators.result import ExclusionReason, FixResult, FixStatus

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


#: Standard normal draws of the box mass's Monte Carlo (:func:`_box_log_mass`): fixed, so the
#: posterior is deterministic; antithetic pairs (``u`` and ``-u``).
_BOX_DRAWS = np.concatenate([(u := np.random.default_rng(29).standard_normal((4096, 3))), -u])
#: A mode whose product-of-marginals box mass is below ``exp(-BOX_NEAR_NATS)`` is near a face
#: (within about 3 standard deviations): its mass is the Monte Carlo of the joint Gaussian.
BOX_NEAR_NATS = 1e-3


def _box_log_mass(x: FloatArray, h: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
    """Log of the mass of the Laplace Gaussian ``N(x, h^-1)`` inside the floor's box ``[lo,
    hi]`` (x, lo, hi (..., 3), h (..., 3, 3)): the product over x, y, z of the marginals'
    in-box probabilities where it is within :data:`BOX_NEAR_NATS` of 1 (far from every face),
    else the share of the fixed draws :data:`_BOX_DRAWS` of the joint Gaussian inside the box
    (at an edge or corner of the box the product ignores the correlation; at least half a draw).
    0 where ``h`` is not invertible (the mass is then not known: the Laplace term as it was)."""
    shape = np.shape(x)[:-1]
    x = np.reshape(x, (-1, 3))
    lo = np.reshape(np.broadcast_to(lo, (*shape, 3)), (-1, 3))
    hi = np.reshape(np.broadcast_to(hi, (*shape, 3)), (-1, 3))
    h = np.reshape(h, (-1, 3, 3))
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        cov = np.linalg.inv(np.where(np.isfinite(h), h, 0.0))
        sd = np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1))
        out = np.sum(np.log(normal_cdf((hi - x) / sd) - normal_cdf((lo - x) / sd)), axis=-1)
    near = np.flatnonzero(np.isfinite(out) & (out < -BOX_NEAR_NATS))
    for k in range(0, near.size, 64):  # bounded memory: 64 x 8192 x 3 draws at a time
        rows = near[k:k + 64]
        w, v = np.linalg.eigh(cov[rows])
        root = v * np.sqrt(np.maximum(w, 0.0))[:, None, :]  # root @ root.T = cov
        pts = x[rows, None, :] + np.einsum("nij,sj->nsi", root, _BOX_DRAWS)
        inside = np.all((pts >= lo[rows, None, :]) & (pts <= hi[rows, None, :]), axis=-1)
        out[rows] = np.log(np.maximum(inside.mean(axis=-1), 0.5 / len(_BOX_DRAWS)))
    return np.reshape(np.where(np.isfinite(out), out, 0.0), shape)


def _posterior(cost: FloatArray, h: FloatArray, log_mass: FloatArray | None = None
               ) -> FloatArray:
    """Laplace floor posterior from (B, F) costs and (B, F, 3, 3) Hessians; ``log_mass``
    (B, F): the log of each mode's Laplace mass inside its floor's box
    (:func:`_box_log_mass`; None: the whole Gaussian)."""
    sign, logdet = np.linalg.slogdet(h)
    logdet = np.where(sign > 0, logdet, np.inf)
    lp = -cost - 0.5 * logdet
    if log_mass is not None:
        lp = lp + log_mass
    lp = np.where(np.isfinite(lp), lp, -np.inf)
    mx = np.max(lp, axis=-1, keepdims=True)
    w = np.exp(lp - np.where(np.isfinite(mx), mx, 0.0))
    s = w.sum(axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(s > 0, w / s, 1.0 / cost.shape[-1])


@dataclass(frozen=True)
class MnlsResult(FixResult):
    """:class:`FixResult` plus the mechanism-aware fields.

    Attributes
    ----------
    floor : ndarray of int, shape (B,)
        Most probable floor (-1 where no fix).
    floor_probability : ndarray, shape (B, F) [-]
        Posterior probability of every floor of the building.
    mechanism : ndarray of int, shape (B, M)
        Slot of :data:`diffpos.paths.mechanisms.MECHANISMS` explaining each link at the answer (-1
        where unused or missing).
    """

    floor: NDArray[np.int_] = field(default_factory=lambda: np.zeros(0, dtype=int))
    floor_probability: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))
    mechanism: NDArray[np.int_] = field(default_factory=lambda: np.zeros((0, 0), dtype=int))



def _result(out, bi, pfa: float) -> MnlsResult:
    bsz, m = bi.ranges_m.shape
    used = out["used"]
    n_used = used.sum(axis=-1)
    dof = n_used - 3
    thr = np.where(dof >= 1, chi2_threshold(np.maximum(dof, 1), pfa), np.nan)
    has = np.isfinite(out["position_m"][:, 0])
    # a posteriori variance factor: residuals larger than the model's sigmas (chi-square
    # statistic above its degrees of freedom) widen the covariance, never narrow it
    with np.errstate(invalid="ignore", divide="ignore"):
        vf = np.where(dof >= 1, np.maximum(out["stat"] / np.maximum(dof, 1), 1.0), 1.0)
    cov = out["covariance_m2"] * np.where(np.isfinite(vf), vf, 1.0)[:, None, None]
    finite_cov = np.all(np.isfinite(cov.reshape(bsz, -1)), axis=-1)
    status = np.full(bsz, int(FixStatus.OK))
    status[has & (dof < 1)] = FixStatus.OK_UNVERIFIED
    status[has & (dof >= 1) & ~(out["stat"] <= thr)] = FixStatus.GATING_FAILED
    status[has & ~finite_cov] = FixStatus.NOT_IDENTIFIABLE
    status[~has | (n_used < 3)] = FixStatus.TOO_FEW_ANCHORS
    status[bi.input_error != 0] = FixStatus.INVALID_INPUT
    reason = np.zeros((bsz, m), dtype=np.int_)
    reason[out["tail"]] = ExclusionReason.RAIM
    reason[~bi.present] = ExclusionReason.MISSING
    with np.errstate(invalid="ignore"):
        peb = np.sqrt(np.trace(cov, axis1=-2, axis2=-1))
    return MnlsResult(
        position_m=out["position_m"], covariance_m2=cov, peb_m=peb,
        z_bound_m=np.sqrt(cov[:, 2, 2]), iterations=np.zeros(bsz, dtype=np.int_),
        converged=has.copy(), status=status, residuals_m=out["residuals_m"], used=used,
        excluded=out["tail"].copy(), exclusion_reason=reason, test_statistic=out["stat"],
        test_threshold=thr, dof=np.maximum(dof, 0), cost=out["cost"],
        input_error=bi.input_error, method="mnls",
        covariance_model="first-arrival model, floor mixture", sigmas_given=bi.sigmas_given,
        floor=out["floor"], floor_probability=out["floor_probability"],
        mechanism=out["mechanism"],
    )
