"""Compiled bookkeeping of the tracker's SNR cache (:func:`diffpos.tracking.model._snr_cost_cached`):
which cached links are reused, which slots are predicted, and the cache's update. Pure data
movement and comparisons (no arithmetic on the values but the float32 rounding numpy's
assignment does), so the results are numpy's bit for bit; replaced the numpy version's
(N, H, M, K) boolean temporaries and fancy-index gathers and scatters (~2 % of the tracker's
CPU on the 16 x 200 soak). The distances to the cached point and anchors stay numpy's
(``np.sum``'s order of summation).

:func:`cache_plan_kernel` (before the prediction): a cached link whose existence of a cached
diffraction slot differs from the one at the point (``strict``) restarts its hypothesis
(``near`` cleared); ``hit`` = reused links; ``mask`` = the slots to predict.
:func:`cache_store_kernel` (after it): the reused links' cached slots written into the
predictions (-inf where not needed), the hypotheses that moved cleared, the fresh links'
anchors and predictions stored.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["cache_plan_kernel", "cache_store_kernel", "warm_snr_cache"]

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}


@njit(**_OPTS)
def cache_plan_kernel(near, kept, known, old, strict, need, cached, is_cached, hit, mask):
    """``near`` (N, H) bool, updated; ``kept`` (N, H, Mc) bool (anchor within its margin);
    ``known`` (N, M) bool (SNR measured); ``old`` (N, H, C, S) float32 the cached
    predictions (C >= Mc); ``strict``, ``need`` (N, H, M, K) bool; ``cached`` (S,) int64 the
    cached slots; ``is_cached`` (K,) bool. Writes ``hit`` (N, H, M) and ``mask`` (N, H, M, K).
    """
    n_n, n_h, n_mc = kept.shape
    n_m, n_k = need.shape[2], need.shape[3]
    n_s = cached.shape[0]
    for n in range(n_n):
        for h in range(n_h):
            nr = near[n, h]
            for m in range(n_mc):
                if kept[n, h, m]:
                    for j in range(1, n_s):
                        if math.isfinite(old[n, h, m, j]) != strict[n, h, m, cached[j]]:
                            nr = False
                            break
            near[n, h] = nr
            for m in range(n_m):
                ht = m < n_mc and nr and kept[n, h, m] and known[n, m]
                hit[n, h, m] = ht
                for k in range(n_k):
                    mask[n, h, m, k] = need[n, h, m, k] and not (ht and is_cached[k])


@njit(**_OPTS)
def cache_store_kernel(near, hit, known, need, cached, anc, pred, c_anchor, c_pred):
    """``pred`` (N, H, M, K) float64: the reused links' cached slots from ``c_pred`` (N, H, C,
    S) float32 (-inf where not ``need``); then the cache: the hypotheses not ``near`` cleared
    (NaN), every fresh link (``known`` (N, M) and not ``hit``, among the first C) stores its
    anchor (``anc`` (N, M, 3) float64 -> ``c_anchor`` (N, H, C, 3) float32) and its cached
    slots' predictions."""
    n_n, n_h, n_m = hit.shape
    n_c, n_s = c_pred.shape[2], c_pred.shape[3]
    n_mc = n_m if n_m < n_c else n_c
    for n in range(n_n):
        for h in range(n_h):
            for m in range(n_m):
                if hit[n, h, m]:
                    for j in range(n_s):
                        k = cached[j]
                        pred[n, h, m, k] = (np.float64(c_pred[n, h, m, j]) if need[n, h, m, k]
                                            else -np.inf)
            if not near[n, h]:
                for c in range(n_c):
                    for i in range(3):
                        c_anchor[n, h, c, i] = np.nan
                    for j in range(n_s):
                        c_pred[n, h, c, j] = np.nan
            for m in range(n_mc):
                if known[n, m] and not hit[n, h, m]:
                    for i in range(3):
                        c_anchor[n, h, m, i] = np.float32(anc[n, m, i])
                    for j in range(n_s):
                        c_pred[n, h, m, j] = np.float32(pred[n, h, m, cached[j]])


def warm_snr_cache() -> None:
    """Compile (or load from numba's cache) both kernels on tiny inputs of the tracker's
    types (called by :func:`diffpos.tracking.tracker.warm_tracking`)."""
    k, s = 18, 8
    b2, b3, b4 = (np.ones((1, 1), np.bool_), np.ones((1, 1, 1), np.bool_),
                  np.ones((1, 1, 1, k), np.bool_))
    c_pred = np.full((1, 1, 1, s), np.nan, np.float32)
    cached = np.arange(s, dtype=np.int64)
    hit, mask = np.empty((1, 1, 1), np.bool_), np.empty((1, 1, 1, k), np.bool_)
    cache_plan_kernel(b2.copy(), b3, b2, c_pred, b4, b4, cached, np.ones(k, np.bool_), hit,
                      mask)
    cache_store_kernel(b2, hit, b2, b4, cached, np.zeros((1, 1, 3)), np.zeros((1, 1, 1, k)),
                       np.full((1, 1, 1, 3), np.nan, np.float32), c_pred)
