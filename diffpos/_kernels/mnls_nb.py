"""Compiled M-NLS link terms: :func:`diffpos.estimators.mnls._link_terms_numpy` in one loop.

For every hypothesis row and link, the candidate mechanisms (existence, never later than the
shortest specular path or a path predicted surely detected, same-edge dominance, the
knife-edge SNR bound, an optional restriction), the max-mixture cost of every candidate
(Gaussian core or one-sided exponential tail, plus the SNR cost), the chosen slot and its
residual, Jacobian and IRLS weight: the same operations as the numpy reference, which stays
in :mod:`diffpos.estimators.mnls` and is what the tests compare against
(tests/core/test_mnls.py: equal slots and flags, values to rounding).

One compiled signature (:data:`SIGNATURE`, C-contiguous inputs); ``cache=True``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, types

__all__ = ["SIGNATURE", "link_terms_kernel"]

_f8_1d = types.float64[::1]
_f8_2d = types.float64[:, ::1]
_f8_3d = types.float64[:, :, ::1]
_f8_4d = types.float64[:, :, :, ::1]
_b1_1d = types.boolean[::1]
_b1_2d = types.boolean[:, ::1]
_b1_3d = types.boolean[:, :, ::1]
_i8_2d = types.int64[:, ::1]

#: The one compiled signature of :func:`link_terms_kernel`.
SIGNATURE = types.void(
    _f8_3d, _b1_3d, _f8_4d, _f8_3d, _f8_3d,  # length, valid, jacobian, deviation_cos, outside
    _f8_2d, _f8_2d, _b1_2d, _f8_2d, _f8_2d,  # r, sig, mask, tail_a, excess_db  (N, M)
    types.float64, types.float64, types.float64,  # lam, wavelength, snr margin [dB]
    _f8_3d, _b1_3d, _b1_3d,  # snr_cost, strong, allowed (N, M, K) or (0, 0, 0)
    _b1_1d, _b1_1d, _i8_2d,  # specular slots, diffraction slots, same-edge pairs (P, 2)
    # outputs: cost (N, M), res, w (N, M), slot (N, M), tail, none (N, M), cand (N, M, K),
    # jac (N, M, 3)
    _f8_2d, _f8_2d, _f8_2d, _i8_2d, _b1_2d, _b1_2d, _b1_3d, _f8_3d,
)


@njit(SIGNATURE, cache=True, error_model="numpy")
def link_terms_kernel(length, valid, jac_all, dev, outm, r, sig, mask, tail_a, excess, lam,
                      wavelength, margin_db, snr_cost, strong, allowed, spec, diff, same_edge,
                      cost_out, res_out, w_out, slot_out, tail_out, none_out, cand, jac_out):
    n, m, k = length.shape
    has_snr = snr_cost.shape[0] > 0
    has_strong = strong.shape[0] > 0
    has_allowed = allowed.shape[0] > 0
    gauss = np.empty(k)
    tail = np.empty(k)
    for i in range(n):
        for j in range(m):
            l_spec = math.inf
            for s in range(k):
                if valid[i, j, s] and length[i, j, s] < l_spec:
                    if spec[s] or (has_strong and strong[i, j, s]):
                        l_spec = length[i, j, s]
            for s in range(k):
                cand[i, j, s] = valid[i, j, s] and length[i, j, s] <= l_spec
            for p in range(same_edge.shape[0]):
                b, a = same_edge[p, 0], same_edge[p, 1]
                if valid[i, j, a] and dev[i, j, a] >= dev[i, j, b]:
                    cand[i, j, b] = False
            for s in range(k):
                if diff[s] and cand[i, j, s]:
                    d1 = outm[i, j, s]
                    d2 = length[i, j, s] - d1
                    theta = math.acos(min(max(dev[i, j, s], -1.0), 1.0))
                    nu = theta * math.sqrt(2 * d1 * d2 / (wavelength * length[i, j, s]))
                    jl = 0.0
                    if nu > -0.78:
                        jl = 6.9 + 20 * math.log10(math.sqrt((nu - 0.1) ** 2 + 1) + nu - 0.1)
                    if excess[i, j] < jl - margin_db:
                        cand[i, j, s] = False
                if has_allowed and not allowed[i, j, s]:
                    cand[i, j, s] = False
            best = math.inf
            slot = 0
            for s in range(k):
                e = r[i, j] - length[i, j, s]
                z = e / sig[i, j]
                gauss[s] = 0.5 * z * z
                tail[s] = tail_a[i, j] + e / lam if e > 0 else math.inf
                c = min(gauss[s], tail[s])
                if has_snr:
                    c += snr_cost[i, j, s]
                if not cand[i, j, s]:
                    c = math.inf
                if c < best:
                    best = c
                    slot = s
            none = not (best < math.inf)
            is_tail = tail[slot] < gauss[slot]
            e = 0.0 if none else r[i, j] - length[i, j, slot]
            w = 1.0
            if is_tail:
                w = sig[i, j] ** 2 / (lam * max(e, 1e-9))
            if none:
                best = tail_a[i, j] + 10.0
            for d in range(3):
                jac_out[i, j, d] = 0.0 if none else jac_all[i, j, slot, d]
            used = mask[i, j] and not none
            slot_out[i, j] = slot
            res_out[i, j] = e
            w_out[i, j] = w if used else 0.0
            cost_out[i, j] = best if mask[i, j] else 0.0
            tail_out[i, j] = is_tail and mask[i, j]
            none_out[i, j] = none and mask[i, j]
