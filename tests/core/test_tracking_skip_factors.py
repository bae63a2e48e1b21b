"""The compiled skipped-path term (:func:`diffpos.tracking.snr_term_nb.snr_skip_kernel`) forms
only the factors a product can read that are not 1 (session 27, docs/replay_speed.md): its
costs are those of the product over every earlier candidate, bit for bit. The reference here
is that product as the kernel computed it before (every slot's factor, 1 where the slot is no
candidate or has no finite prediction, multiplied in slot order), on random links where many
factors are exactly 1 (predictions far below the threshold, or an infinite threshold) and
some lengths tie or are NaN."""

from __future__ import annotations

import math

import numpy as np

from diffpos.paths.mechanisms import DIFFRACTION_SLOTS, MECHANISMS
from diffpos.tracking.links import PathEval, candidates
from diffpos.tracking.snr_term_nb import snr_skip_kernel

IS_DIFFRACTION = np.isin(np.arange(len(MECHANISMS)), DIFFRACTION_SLOTS)


def _reference(pe: PathEval, pred, thr, snr, fap, sigma, w, cost):
    """The full product per candidate (the kernel's arithmetic, every factor), in place."""
    valid_all = candidates(pe) & (np.isfinite(cost) | ~pe.sure)
    n_n, n_h, n_m, n_k = cost.shape
    for n in range(n_n):
        for m in range(n_m):
            if not math.isfinite(snr[n, m]):
                continue
            for h in range(n_h):
                ln, c, valid = pe.length[n, h, m], cost[n, h, m], valid_all[n, h, m]
                t = thr[n, h, m]
                if math.isnan(t) or snr[n, m] - fap > t:
                    t = snr[n, m] - fap
                phi = [0.5 * math.erfc(-((t - pred[n, h, m, j]) / sigma) / math.sqrt(2.0))
                       if valid[j] and math.isfinite(pred[n, h, m, j]) else 1.0
                       for j in range(n_k)]
                for k in range(n_k):
                    if valid[k] and math.isfinite(c[k]):
                        prod = 1.0
                        for j in range(n_k):
                            if ln[j] < ln[k]:
                                prod *= phi[j]
                        c[k] -= math.log(w * prod + (1.0 - w))


def test_the_compact_product_is_the_full_one_bit_for_bit():
    rng = np.random.default_rng(27)
    n, h, m, k = 6, 4, 5, len(IS_DIFFRACTION)
    shape = (n, h, m, k)
    changed = 0
    for _ in range(6):
        length = rng.uniform(10.0, 30.0, shape)
        length[..., 3] = length[..., 2]  # ties
        length[rng.random(shape) < 0.02] = np.nan
        loose = rng.random(shape) < 0.7
        sure = loose & (rng.random(shape) < 0.5)
        pe = PathEval(length=length, jac=np.zeros((*shape, 3)), strict=sure, loose=loose,
                      sure=sure)
        pred = np.where(rng.random(shape) < 0.2, -np.inf, rng.uniform(-60.0, 40.0, shape))
        thr = rng.uniform(0.0, 30.0, (n, h, m))
        thr[rng.random((n, h, m)) < 0.2] = np.inf  # every factor exactly 1
        thr[rng.random((n, h, m)) < 0.1] = np.nan
        snr = np.where(rng.random((n, m)) < 0.2, np.nan, rng.uniform(-10.0, 45.0, (n, m)))
        cost = np.where(rng.random(shape) < 0.3, np.inf, rng.uniform(0.0, 5.0, shape))
        ref, got = cost.copy(), cost.copy()
        _reference(pe, pred, thr, snr, 15.0, 6.0, 0.8, ref)
        snr_skip_kernel(length, loose, sure, IS_DIFFRACTION, pred, thr, snr, 15.0, 6.0, 0.8,
                        got)
        assert ref.tobytes() == got.tobytes()
        changed += int(np.sum(np.isfinite(ref) & (ref != cost)))
    assert changed > 100  # the term was exercised
