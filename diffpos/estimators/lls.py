"""LLS: the linearised LoS time-of-arrival least squares baseline (batched).

Assuming every range is a straight line, ``r_j^2 = |a_j - x|^2``. Subtracting the equation of
a reference anchor ``k`` removes ``|x|^2``:

    2 (a_j - a_k)^T x = |a_j|^2 - |a_k|^2 - r_j^2 + r_k^2,     j != k,

a linear system ``A x = b`` with ``|S| - 1`` rows (``reference="first"``: ``k`` is the first
used anchor, as in the paper's baseline), or one row per anchor pair (``"all_pairs"``). It is
solved by a batched SVD. When ``A`` is rank deficient or its condition number exceeds
``max_condition`` (e.g. 3 anchors, or all anchors in one plane such as a line of UAVs at the
same height and stand-off) the fix is reported ``NOT_IDENTIFIABLE`` with a NaN position
instead of the silent minimum-norm (pseudo-inverse) answer.

The covariance reported is the inverse FIM of the **LoS** range model at the estimate
(``covariance_model="LoS FIM"``): the bound LLS would face if its LoS assumption held.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from diffpos.bounds import bounds_from_fim, fisher_information
from diffpos.estimators.result import ExclusionReason, FixResult, FixStatus, prepare_batch
from diffpos.geometry import los_path

__all__ = ["lls", "lls_positions"]


def lls_positions(
    a: np.ndarray,
    r: np.ndarray,
    use: np.ndarray,
    *,
    reference: str = "first",
    max_condition: float = 1e8,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Core of :func:`lls` on prepared arrays: positions ``(B, 3)`` (NaN where not solvable),
    condition numbers ``(B,)`` and the solvable flags ``(B,)``."""
    b, m = r.shape
    q = np.einsum("bmi,bmi->bm", a, a) - r * r  # |a_j|^2 - r_j^2
    if reference == "first":
        k = np.argmax(use, axis=-1)  # first used anchor
        ak = a[np.arange(b), k]
        qk = q[np.arange(b), k]
        rows = use.copy()
        rows[np.arange(b), k] = False
        amat = 2.0 * (a - ak[:, None, :])
        bvec = q - qk[:, None]
    else:
        i, j = np.triu_indices(m, k=1)
        rows = use[:, i] & use[:, j]
        amat = 2.0 * (a[:, j] - a[:, i])
        bvec = q[:, j] - q[:, i]
    amat = np.where(rows[..., None], amat, 0.0)
    bvec = np.where(rows, bvec, 0.0)
    x = np.full((b, 3), np.nan)
    if amat.shape[1] < 3:
        return x, np.full(b, np.inf), np.zeros(b, dtype=bool)
    u, sv, vt = np.linalg.svd(amat, full_matrices=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.where(sv[:, 2] > 0, sv[:, 0] / sv[:, 2], np.inf)
    solvable = (use.sum(axis=-1) >= 3) & np.isfinite(cond) & (cond < max_condition)
    if np.any(solvable):
        ub = np.einsum("bmi,bm->bi", u[solvable], bvec[solvable])
        x[solvable] = np.einsum("bij,bi->bj", vt[solvable], ub / sv[solvable])
    return x, cond, solvable


def lls(
    anchors_m: ArrayLike,
    ranges_m: ArrayLike,
    sigmas_m: ArrayLike | None = None,
    *,
    mask: ArrayLike | None = None,
    reference: str = "first",
    max_condition: float = 1e8,
) -> FixResult:
    """Batched linear least-squares ToA fixes assuming LoS.

    Parameters
    ----------
    anchors_m : array_like, shape (B, M, 3) or (M, 3) [m]
    ranges_m : array_like, shape (B, M) or (M,) [m]
    sigmas_m : array_like, shape (B, M), scalar or None [m]
        Only used for the reported LoS-FIM covariance (1 m if None). The linear system is
        unweighted, like the paper's baseline.
    mask : array_like of bool, shape (B, M), optional
    reference : {"first", "all_pairs"}
        Difference against the first used anchor, or over all pairs of used anchors.
    max_condition : float [-]
        Largest accepted condition number of ``A``.

    Returns
    -------
    FixResult
        ``method="lls"``; ``iterations`` 0, ``converged`` True where solved; status
        ``OK_UNVERIFIED`` (LLS does not test its residuals), ``NOT_IDENTIFIABLE`` or
        ``TOO_FEW_ANCHORS``.
    """
    if reference not in ("first", "all_pairs"):
        raise ValueError(f"reference must be 'first' or 'all_pairs', got {reference!r}")
    pb = prepare_batch(anchors_m, ranges_m, sigmas_m, mask)
    a, r, s, use = pb.anchors_m, pb.ranges_m, pb.sigmas_m, pb.mask
    b, m = r.shape
    x, cond, solvable = lls_positions(a, r, use, reference=reference, max_condition=max_condition)
    n_used = use.sum(axis=-1)
    dist, jac = los_path(a, np.where(np.isfinite(x), x, 0.0)[:, None, :])
    res = np.where(use & solvable[:, None], r - dist, np.nan)
    fim = fisher_information(np.nan_to_num(jac), s, use & solvable[:, None])
    bnd = bounds_from_fim(fim)
    cov = np.where(solvable[:, None, None], bnd.crlb_m2, np.nan)
    status = np.full(b, int(FixStatus.OK_UNVERIFIED), dtype=np.int_)
    status[~solvable] = FixStatus.NOT_IDENTIFIABLE
    status[n_used < 3] = FixStatus.TOO_FEW_ANCHORS
    status[pb.input_error != 0] = FixStatus.INVALID_INPUT
    reason = np.where(pb.present, ExclusionReason.NONE, ExclusionReason.MISSING).astype(np.int_)
    sw = use / s
    t_stat = np.where(solvable & pb.sigmas_given, np.nansum((res * sw) ** 2, axis=-1), np.nan)
    return FixResult(
        position_m=x,
        covariance_m2=cov,
        peb_m=np.sqrt(np.trace(cov, axis1=-2, axis2=-1)),
        z_bound_m=np.sqrt(cov[:, 2, 2]),
        iterations=np.zeros(b, dtype=np.int_),
        converged=solvable.copy(),
        status=status,
        residuals_m=res,
        used=use.copy(),
        excluded=np.zeros((b, m), dtype=bool),
        exclusion_reason=reason,
        test_statistic=t_stat,
        test_threshold=np.full(b, np.nan),
        dof=np.maximum(n_used - 3, 0),
        cost=np.where(solvable, 0.5 * np.nansum((res * sw) ** 2, axis=-1), np.nan),
        input_error=pb.input_error,
        method="lls",
        covariance_model="LoS FIM",
        sigmas_given=pb.sigmas_given,
        condition=cond,
    )
