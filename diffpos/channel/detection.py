"""The first-arrival detector's rule as a likelihood (the generative rule itself:
:func:`diffpos.channel.emulator.first_arrival`).

The detector reports the earliest path whose SNR is within ``fap_threshold_db`` of the
strongest. So a mechanism ``k`` is the reported first arrival only if every path ``j``
arriving before it was below that threshold ``T``: with the paths' SNRs predicted as
``S_j`` with a Gaussian spread ``sigma``, probability ``prod_j Phi((T - S_j) / sigma)``.
The tracker (:func:`diffpos.tracking.model.skip_cost`, compiled in
:func:`diffpos.tracking.snr_term_nb.snr_skip_kernel`) and M-NLS
(:class:`diffpos.estimators.mnls.rules.SnrRule`) both use :func:`skipped_cost`.

No scipy: ``scipy.special`` costs ~80 ms of imports in every fusion and replay process, and
these are a reference and an off-by-default option.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["normal_cdf", "skipped_cost"]

FloatArray = NDArray[np.float64]

_PHI = np.frompyfunc(lambda x: 0.5 * math.erfc(-x / math.sqrt(2.0)), 1, 1)


def normal_cdf(x: ArrayLike) -> FloatArray:
    """The standard normal CDF ``0.5 erfc(-x / sqrt 2)``, elementwise (``math.erfc``: NaN
    stays NaN, +-inf give 1 / 0)."""
    return np.asarray(_PHI(np.asarray(x, dtype=np.float64)), dtype=np.float64)


def skipped_cost(length: FloatArray, ok: NDArray[np.bool_], pred: FloatArray, thr: ArrayLike,
                 sigma_db: float, weight: float) -> FloatArray:
    """``-log(weight prod_j Phi((thr - pred_j) / sigma_db) + 1 - weight)`` [nats] of every
    slot ``k`` of ``length`` (..., K) [m], the product over the slots ``j`` with ``ok`` and a
    finite prediction ``pred`` (..., K) [dB] strictly shorter than ``k`` (``thr`` [dB]
    broadcastable to (..., 1)); 0 where ``ok`` is False or the length is not finite.

    ``weight`` mixes the rule with 1, so a model that predicts a path tens of dB too strong
    costs at most ``-log(1 - weight)``. ``O(K log K)`` per link: the slots sorted by length,
    the log probabilities summed over the strictly shorter ones (ties share the sum of the
    slots before their group)."""
    ok = ok & np.isfinite(length)
    with np.errstate(invalid="ignore", divide="ignore"):
        lphi = np.where(ok & np.isfinite(pred),
                        np.log(normal_cdf((np.asarray(thr) - pred) / sigma_db)), 0.0)
    key = np.where(ok, length, np.inf)
    order = np.argsort(key, axis=-1, kind="stable")
    ks = np.take_along_axis(key, order, axis=-1)
    cs = np.cumsum(np.take_along_axis(lphi, order, axis=-1), axis=-1)
    before = np.concatenate([np.zeros((*cs.shape[:-1], 1)), cs[..., :-1]], axis=-1)
    idx = np.broadcast_to(np.arange(ks.shape[-1]), ks.shape)
    new = np.concatenate([np.ones((*ks.shape[:-1], 1), bool), ks[..., 1:] != ks[..., :-1]],
                         axis=-1)
    first = np.maximum.accumulate(np.where(new, idx, 0), axis=-1)  # its tie group's start
    val = np.empty_like(before)
    np.put_along_axis(val, order, np.take_along_axis(before, first, axis=-1), axis=-1)
    add = -np.log(weight * np.exp(val) + (1.0 - weight))
    return np.where(ok, add, 0.0)
