"""Compiled SNR term of the tracker's measurement update
(:func:`diffpos.tracking.model.snr_term`): everything of
:func:`diffpos.tracking.model.snr_cost_near` (with its :class:`~diffpos.tracking.model.SnrCache`)
and :func:`~diffpos.tracking.model.cap_snr_cost` but the two SNR predictions themselves, in
three passes instead of ~60 numpy calls with their (N, H, M, K) temporaries, gathers and
scatters.

* :func:`snr_plan_kernel` (before the prediction at the hypotheses): the distances to the
  cached point and anchors, the cache's plan (:func:`diffpos.tracking.snr_nb.cache_plan_kernel`:
  which links are reused, which slots to predict), the point of every hypothesis (the cached
  one where reused), and the pairs to predict packed as (P, 1, 3) anchors, (P, 3) points and
  (P, 1, K) slot masks, one per link with a known SNR in (node, hypothesis, anchor) order.
* :func:`snr_score_kernel` (after it): the predictions unpacked (-inf where not predicted),
  the reused links' cached slots and the cache's update
  (:func:`diffpos.tracking.snr_nb.cache_store_kernel`), every slot's cost and every link's
  detector threshold (:func:`diffpos.channel.snr_nb.snr_cost_kernel`), the "holes" (a slot
  that exists within the margin but carries no power at the point) and their two shifted
  points packed for the second prediction.
* :func:`snr_hole_kernel` (after that): the holes' costs against the hypothesis' own
  threshold (``HOLE_THRESHOLD_AT_PRIOR``), the better of the two heights written into the
  costs, then the cap.
* :func:`snr_skip_kernel` (``TrackerConfig.first_arrival_prior`` > 0): the detector's
  skipped paths, every candidate's cost raised by its earlier candidates' probability of
  having been below the threshold (:func:`diffpos.tracking.model.skip_cost` is the numpy
  reference, equal to 1e-12).

The arithmetic is the numpy version's, operation for operation (the distances
``sqrt((d0^2 + d1^2) + d2^2)`` as numpy's sum over three, the shifted heights clipped as
``np.clip``, ``np.minimum``'s NaN), so the costs, thresholds and the cache are numpy's bit
for bit (tests/core/test_snr_term.py).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from diffpos.channel.snr_nb import snr_cost_kernel
from diffpos.tracking.model_nb import candidate_slots
from diffpos.tracking.snr_nb import cache_plan_kernel, cache_store_kernel

__all__ = ["snr_hole_kernel", "snr_plan_kernel", "snr_score_kernel", "snr_skip_kernel",
           "warm_snr_term"]

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}
#: numba keys this file's on-disk cache on this file only, not on the ``*_nb`` code its
#: kernels compile in: a digest of that code (tests/core/test_kernel_stamps.py names the new
#: value after a callee's edit; writing it here is what invalidates a warm cache).
CALLEES_SHA256 = "1ee2ebe1bfb93b03"


@njit(**_OPTS)
def _dist(a0, a1, a2, b0, b1, b2):
    """``np.sqrt(np.sum((a - b) ** 2, axis=-1))`` of one pair of 3-vectors."""
    d0, d1, d2 = a0 - b0, a1 - b1, a2 - b2
    return math.sqrt((d0 * d0 + d1 * d1) + d2 * d2)


@njit(**_OPTS)
def snr_plan_kernel(pos, anchors, snr, need, strict, use_cache, c_node, c_anchor, c_pred,
                    reuse_node, reuse_anchor, cached, is_cached, near, hit, mask, at,
                    p_anc, p_node, p_need):
    """The cache's plan and the pairs to predict.

    ``pos`` (N, H, 3) the hypotheses, ``anchors`` (N, M, 3), ``snr`` (N, M) measured [dB]
    (NaN: unknown), ``need``/``strict`` (N, H, M, K) bool; with ``use_cache`` the cache
    ``c_node`` (N, H, 3), ``c_anchor`` (N, H, C, 3) float32, ``c_pred`` (N, H, C, S) float32
    and its margins ``reuse_node``/``reuse_anchor`` [m] (without: ignored, nothing reused);
    ``cached`` (S,) int64, ``is_cached`` (K,) bool. Writes ``near`` (N, H), ``hit`` (N, H, M),
    ``mask`` (N, H, M, K) (the slots to predict), ``at`` (N, H, 3) (where the hypothesis is
    predicted) and the packed pairs ``p_anc`` (>= P, 1, 3), ``p_node`` (>= P, 3), ``p_need``
    (>= P, 1, K); returns P."""
    n_n, n_h, n_m, n_k = need.shape
    known = np.empty((n_n, n_m), dtype=np.bool_)
    for n in range(n_n):
        for m in range(n_m):
            known[n, m] = math.isfinite(snr[n, m])
    if use_cache:
        n_mc = min(n_m, c_pred.shape[2])
        kept = np.empty((n_n, n_h, n_mc), dtype=np.bool_)
        for n in range(n_n):
            for h in range(n_h):
                near[n, h] = _dist(pos[n, h, 0], pos[n, h, 1], pos[n, h, 2], c_node[n, h, 0],
                                   c_node[n, h, 1], c_node[n, h, 2]) <= reuse_node
                for m in range(n_mc):
                    kept[n, h, m] = _dist(anchors[n, m, 0], anchors[n, m, 1], anchors[n, m, 2],
                                          np.float64(c_anchor[n, h, m, 0]),
                                          np.float64(c_anchor[n, h, m, 1]),
                                          np.float64(c_anchor[n, h, m, 2])) <= reuse_anchor
        cache_plan_kernel(near, kept, known, c_pred, strict, need, cached, is_cached, hit,
                          mask)
    else:
        for n in range(n_n):
            for h in range(n_h):
                near[n, h] = False
                for m in range(n_m):
                    hit[n, h, m] = False
                    for k in range(n_k):
                        mask[n, h, m, k] = need[n, h, m, k]
    p = 0
    for n in range(n_n):
        for h in range(n_h):
            src = c_node[n, h] if near[n, h] else pos[n, h]
            for i in range(3):
                at[n, h, i] = src[i]
            for m in range(n_m):
                if not known[n, m]:
                    continue
                for i in range(3):
                    p_anc[p, 0, i] = anchors[n, m, i]
                    p_node[p, i] = at[n, h, i]
                for k in range(n_k):
                    p_need[p, 0, k] = mask[n, h, m, k]
                p += 1
    return p


@njit(**_OPTS)
def snr_score_kernel(p_pred, snr, need, mask, trust, loose, near, hit, use_cache, cached,
                     anchors, c_anchor, c_pred, sigma_db, fap_db, det_db, pos, relax, floor,
                     first_z, floor_h, pred, cost, thr, hole_idx, h_anc, h_node, h_need,
                     h_meas, h_thr):
    """The predictions ``p_pred`` (P, 1, K) of :func:`snr_plan_kernel`'s pairs unpacked into
    ``pred`` (N, H, M, K) (-inf where not in ``mask`` or the SNR is unknown), the reused
    links' cached slots and the cache's update (with ``use_cache``), the costs ``cost`` (N, H,
    M, K) and thresholds ``thr`` (N, H, M) (``snr_cost_kernel`` with ``trust``), then the
    holes (``~isfinite(cost) & loose``): every link with one is packed twice (its point
    ``pos`` moved down, then up by ``relax`` (N, H), clipped 0.01 m inside its floor
    ``floor`` (N, H) float64 of ``first_z``/``floor_h``) into ``hole_idx`` (>= Q, 3) (n, h, m),
    ``h_anc`` (>= 2Q, 1, 3), ``h_node`` (>= 2Q, 3), ``h_need`` (>= 2Q, 1, K) (the hole
    slots), ``h_meas``, ``h_thr`` (>= 2Q,); the rows Q.. are the upward points. Returns Q."""
    n_n, n_h, n_m, n_k = need.shape
    p = 0
    for n in range(n_n):
        for h in range(n_h):
            for m in range(n_m):
                ok = math.isfinite(snr[n, m])
                for k in range(n_k):
                    pred[n, h, m, k] = p_pred[p, 0, k] if (ok and mask[n, h, m, k]) else -np.inf
                if ok:
                    p += 1
    known = np.empty((n_n, n_m), dtype=np.bool_)
    for n in range(n_n):
        for m in range(n_m):
            known[n, m] = math.isfinite(snr[n, m])
    if use_cache:
        cache_store_kernel(near, hit, known, need, cached, anchors, pred, c_anchor, c_pred)
    meas = np.empty(n_n * n_h * n_m)
    i = 0
    for n in range(n_n):
        for _ in range(n_h):
            for m in range(n_m):
                meas[i] = snr[n, m]
                i += 1
    snr_cost_kernel(pred.reshape(-1, n_k), meas, trust.reshape(-1, n_k), sigma_db, fap_db,
                    det_db, False, thr.reshape(-1), cost.reshape(-1, n_k))
    q = 0
    for n in range(n_n):
        for h in range(n_h):
            for m in range(n_m):
                any_hole = False
                for k in range(n_k):
                    if loose[n, h, m, k] and not math.isfinite(cost[n, h, m, k]):
                        any_hole = True
                        break
                if any_hole:
                    hole_idx[q, 0] = n
                    hole_idx[q, 1] = h
                    hole_idx[q, 2] = m
                    q += 1
    zf_off = 0.01
    for j in range(q):
        n, h, m = hole_idx[j, 0], hole_idx[j, 1], hole_idx[j, 2]
        zf = first_z + floor[n, h] * floor_h
        lo = zf + zf_off
        hi = (zf + floor_h) - zf_off
        dz = relax[n, h]
        for side in range(2):
            r = j + side * q
            for i in range(3):
                h_anc[r, 0, i] = anchors[n, m, i]
                h_node[r, i] = pos[n, h, i]
            z = pos[n, h, 2] + (-dz if side == 0 else dz)
            c = z if z > lo else lo  # np.clip: min(max(z, lo), hi), NaN kept
            if math.isnan(z):
                c = z
            c = c if c < hi else hi
            if math.isnan(z):
                c = z
            h_node[r, 2] = c
            for k in range(n_k):
                h_need[r, 0, k] = loose[n, h, m, k] and not math.isfinite(cost[n, h, m, k])
            h_meas[r] = snr[n, m]
            h_thr[r] = thr[n, h, m]
    return q


@njit(**_OPTS)
def snr_hole_kernel(h_pred, h_need, h_meas, h_thr, hole_idx, q, sigma_db, fap_db, det_db,
                    cap, cost, h_cost):
    """The holes' costs: ``h_pred`` (2Q, 1, K) the predictions at the shifted points (NaN
    where not needed) scored against the hypothesis' threshold ``h_thr`` (``snr_cost_kernel``
    with the threshold given, the slots not needed -inf: +inf), the lower of the two heights
    (``np.minimum``: NaN wins) written into ``cost`` (N, H, M, K) at the hole slots; then
    every finite cost above ``cap`` capped (``cap > 0``; an infinite one stays). ``h_cost``
    (>= 2Q, K) work."""
    n_k = cost.shape[3]
    nq = 2 * q
    hp = np.empty((nq, n_k))
    for r in range(nq):
        for k in range(n_k):
            hp[r, k] = h_pred[r, 0, k] if h_need[r, 0, k] else -np.inf
    snr_cost_kernel(hp, h_meas[:nq], h_need[:nq, 0], sigma_db, fap_db, det_db, True,
                    h_thr[:nq], h_cost[:nq])
    for j in range(q):
        n, h, m = hole_idx[j, 0], hole_idx[j, 1], hole_idx[j, 2]
        for k in range(n_k):
            if h_need[j, 0, k]:
                a, b = h_cost[j, k], h_cost[j + q, k]
                cost[n, h, m, k] = a if (math.isnan(a) or a < b) else b
                if math.isnan(b):
                    cost[n, h, m, k] = b if not math.isnan(a) else a
    if cap > 0:
        c4 = cost.reshape(-1)
        for i in range(c4.shape[0]):
            v = c4[i]
            if v > cap and math.isfinite(v):
                c4[i] = cap


@njit(**_OPTS)
def snr_skip_kernel(length, loose, sure, is_diff, pred, thr, snr, fap_db, sigma_db, weight,
                    cost):
    """The skipped paths' term added to ``cost`` (N, H, M, K) in place (numpy reference:
    :func:`diffpos.tracking.model.skip_cost`). For every link with a known SNR ``snr`` (N, M)
    and every candidate slot ``k`` (:func:`diffpos.tracking.links.candidates` of ``length``,
    ``loose``, ``sure``, ``is_diff``; a finite cost), ``-log(w prod_j Phi((T - pred_j) /
    sigma_db) + 1 - w)`` over the candidates ``j`` strictly shorter with a finite prediction
    ``pred`` (N, H, M, K) [dB], ``T = fmax(thr, snr - fap_db)`` (``thr`` (N, H, M) the
    predicted detector threshold [dB]), ``w = weight``.

    Per link only the factors a product can read and that are not 1 are formed
    (:func:`_skip_factors`) and multiplied in slot order: every product has the bits of the
    product over all ``j`` (``x * 1.0 == x``; docs/replay_speed.md, session 27)."""
    n_n, n_h, n_m, n_k = cost.shape
    valid = np.empty(n_k, dtype=np.bool_)
    fac = np.empty(n_k)  # the factors, in slot order ...
    at = np.empty(n_k, dtype=np.int64)  # ... and their slots
    for n in range(n_n):
        for m in range(n_m):
            s = snr[n, m]
            if not math.isfinite(s):
                continue
            for h in range(n_h):
                ln, c = length[n, h, m], cost[n, h, m]
                candidate_slots(ln, sure[n, h, m], loose[n, h, m], is_diff, valid)
                t = thr[n, h, m]
                t2 = s - fap_db
                if math.isnan(t) or t2 > t:
                    t = t2
                nj = _skip_factors(ln, c, sure[n, h, m], pred[n, h, m], t, sigma_db, valid,
                                   fac, at)
                for k in range(n_k):
                    if not (valid[k] and math.isfinite(c[k])):
                        continue
                    prod = 1.0
                    for i in range(nj):
                        if ln[at[i]] < ln[k]:
                            prod *= fac[i]
                    c[k] -= math.log(weight * prod + (1.0 - weight))


@njit(**_OPTS, inline="always")
def _skip_factors(ln, c, sure, pj, t, sigma_db, valid, fac, at):
    """:func:`snr_skip_kernel`'s factors of one link: ``valid`` (K,) narrowed in place to the
    candidates with a finite cost or not sure; each candidate ``j`` with a finite prediction
    ``pj[j]`` and shorter than the longest scored candidate (valid, finite cost: no product
    reads the others) gets ``Phi((t - pj) / sigma_db)``, written with its slot to ``fac``,
    ``at`` (slot order) unless it is 1. Returns how many."""
    n_k = ln.shape[0]
    longest = -np.inf  # (a NaN length is never longer, nor shorter than anything)
    for j in range(n_k):
        valid[j] = valid[j] and (math.isfinite(c[j]) or not sure[j])
        if valid[j] and math.isfinite(c[j]) and ln[j] > longest:
            longest = ln[j]
    r2 = math.sqrt(2.0)
    nj = 0
    for j in range(n_k):
        if valid[j] and math.isfinite(pj[j]) and ln[j] < longest:
            f = 0.5 * math.erfc(-((t - pj[j]) / sigma_db) / r2)
            if f != 1.0:
                fac[nj] = f
                at[nj] = j
                nj += 1
    return nj


def warm_snr_term() -> None:
    """Compile (or load from numba's cache) the four kernels on tiny inputs of the tracker's
    types (called by :func:`diffpos.tracking.tracker.warm_tracking`)."""
    k, s = 18, 8
    f4 = np.float32
    b2 = np.zeros((1, 1), np.bool_)
    b3 = np.zeros((1, 1, 1), np.bool_)
    b4 = np.ones((1, 1, 1, k), np.bool_)
    pos, anc, snr = np.ones((1, 1, 3)), np.ones((1, 1, 3)), np.ones((1, 1))
    c_node = np.full((1, 1, 3), np.nan)
    c_anc = np.full((1, 1, 1, 3), np.nan, f4)
    c_pred = np.full((1, 1, 1, s), np.nan, f4)
    cached, is_cached = np.arange(s, dtype=np.int64), np.zeros(k, np.bool_)
    mask, at = b4.copy(), np.empty((1, 1, 3))
    p_anc, p_node, p_need = np.empty((1, 1, 3)), np.empty((1, 3)), np.empty((1, 1, k), np.bool_)
    snr_plan_kernel(pos, anc, snr, b4, b4, True, c_node, c_anc, c_pred, 0.1, 0.1, cached,
                    is_cached, b2, b3, mask, at, p_anc, p_node, p_need)
    cost, thr = np.empty((1, 1, 1, k)), np.empty((1, 1, 1))
    hole_idx = np.empty((1, 3), np.int64)
    h_anc, h_node, h_need = np.empty((2, 1, 3)), np.empty((2, 3)), np.empty((2, 1, k), np.bool_)
    h_meas, h_thr = np.empty(2), np.empty(2)
    q = snr_score_kernel(np.zeros((1, 1, k)), snr, b4, mask, b4, b4, b2, b3, True, cached,
                         anc, c_anc, c_pred, 6.0, 15.0, 0.0, pos, np.zeros((1, 1)),
                         np.zeros((1, 1)), 0.0, 3.0, np.empty((1, 1, 1, k)), cost, thr,
                         hole_idx, h_anc, h_node, h_need, h_meas, h_thr)
    snr_hole_kernel(np.zeros((2, 1, k)), h_need, h_meas, h_thr, hole_idx, q, 6.0, 15.0, 0.0,
                    4.5, cost, np.empty((2, k)))
    snr_skip_kernel(np.zeros((1, 1, 1, k)), b4, b4, np.zeros(k, np.bool_),
                    np.zeros((1, 1, 1, k)), thr, snr, 15.0, 6.0, 0.9, cost)
