"""The families' SNR evaluated only where it can matter (issue 37's cost of
``family_few_links``): :func:`diffpos.channel.emulator.pair_family_snr_db` with a ``mask``
and :func:`diffpos.tracking.families.family_snr_log_lik` with the families that exist.

The reference is the same function without the mask (every family of every link, itself
tested against the numpy emulator in tests/core/test_channel_families.py): equal bit for
bit where evaluated, ``-inf`` elsewhere; the families' mixture and best family, which is what
the tracker reads, unchanged bit for bit.
"""

from __future__ import annotations

import numpy as np

from diffpos.channel.emulator import pair_family_snr_db
from diffpos.scenario import default_scenario
from diffpos.tracking.families import (
    best_family,
    family_log_lik,
    family_snr_log_lik,
    family_terms,
    graded_split,
)
from diffpos.tracking.model import SNR_SIGMA_DB, SNR_SPAN_DB

SC = default_scenario()
B, RADIO = SC.building, SC.radio


def _pairs(seed: int, q: int):
    """``q`` random (node, anchor) pairs: nodes at walking height on random floors inside
    the paper building, anchors outside (y < 0)."""
    rng = np.random.default_rng(seed)
    fl = rng.integers(0, 4, q)
    pos = np.c_[rng.uniform(-8, 8, q), rng.uniform(1, 9, q),
                B.first_floor_z_m + fl * B.floor_height_m + 1.2]
    anc = np.c_[rng.uniform(-20, 20, q), rng.uniform(-25, -5, q), rng.uniform(0.5, 15, q)]
    return pos, anc, fl


def test_masked_kernel_equals_the_unmasked_where_evaluated():
    """400 pairs (seed 3), a random mask (half the families): bit for bit where True, -inf
    where False; the all-True mask is the unmasked result bit for bit."""
    pos, anc, _ = _pairs(3, 400)
    full = pair_family_snr_db(anc, pos, building=B, radio=RADIO, max_order=3)
    assert np.isfinite(full).mean() > 0.1  # families with power exist
    mask = np.random.default_rng(4).random(full.shape) < 0.5
    got = pair_family_snr_db(anc, pos, building=B, radio=RADIO, max_order=3, mask=mask)
    assert got[mask].tobytes() == full[mask].tobytes()
    assert np.all(np.isneginf(got[~mask]))
    ones = pair_family_snr_db(anc, pos, building=B, radio=RADIO, max_order=3,
                              mask=np.ones(full.shape, bool))
    assert ones.tobytes() == full.tobytes()


def test_family_terms_unchanged_by_the_restriction():
    """300 pairs (seed 5), measured SNRs with a third unknown (NaN): ``family_snr_log_lik``
    with the existing families is the unrestricted one where they exist and the SNR is known
    (bit for bit), 0 where the SNR is unknown, -inf elsewhere. ``family_terms``' log-density
    against the unrestricted sum (``ref``): equal bit for bit wherever it is finite; -inf
    only where ``ref`` is more than 745.2 nats below its link's largest (``exp`` is 0.0 there;
    some such families exist); the links' mixture densities (``family_log_lik``) and best
    families (``best_family``) bit for bit."""
    pos, anc, fl = _pairs(5, 300)
    rng = np.random.default_rng(6)
    snr = rng.uniform(-5, 30, 300)
    snr[rng.random(300) < 1 / 3] = np.nan
    _, _, ok, _ = graded_split(pos, anc, fl, B, 3, 0.2)
    args = (pos, anc, snr, B, RADIO, 3, SNR_SIGMA_DB, SNR_SPAN_DB, 4.5)
    full, got = family_snr_log_lik(*args), family_snr_log_lik(*args, ok)
    known = np.isfinite(snr)[:, None] & ok
    assert got[known].tobytes() == full[known].tobytes()
    assert np.all(got[~np.isfinite(snr)] == 0.0)
    assert np.all(np.isneginf(got[np.isfinite(snr)[:, None] & ~ok]))
    cov = np.broadcast_to(np.eye(3) * 0.05, (300, 3, 3)).copy()
    rho = np.linalg.norm(pos - anc, axis=1) + rng.uniform(0, 6, 300)
    var = np.full(300, 0.09)
    common = (pos, cov, anc, rho, var, fl, B, 3, 0.2, None, 4.5, SNR_SIGMA_DB)
    ll, ok2, length, jac, _ = family_terms(*common, (snr, RADIO), SNR_SPAN_DB)
    ll0, *_ = family_terms(*common, None, SNR_SPAN_DB)
    assert np.array_equal(ok2, ok)
    ref = np.where(ok, ll0 + full, -np.inf)
    fin = np.isfinite(ll)
    assert ll[fin].tobytes() == ref[fin].tobytes()
    pruned = ~fin & np.isfinite(ref)
    top = np.max(ref, axis=-1, keepdims=True)
    assert np.all((ref - top)[pruned] < -745.2) and pruned.sum() > 0
    assert np.isfinite(ll).sum() > 100
    got_mix = family_log_lik(*common, (snr, RADIO), SNR_SPAN_DB)
    assert got_mix[0].tobytes() == _mean_density_ref(ref, ok).tobytes()
    for a, b in zip(best_family(ll, ok, length, jac), best_family(ref, ok, length, jac),
                    strict=True):
        assert a.tobytes() == b.tobytes()


def _mean_density_ref(ll, ok):
    """``log mean_k exp(ll_k)`` over the existing families, as ``family_log_lik`` computes
    it (the same operations, on the unrestricted log-densities)."""
    n_ok = ok.sum(axis=-1)
    with np.errstate(divide="ignore"):
        top = np.max(ll, axis=-1)
        safe = np.where(np.isfinite(top), top, 0.0)
        tot = safe + np.log(np.sum(np.exp(ll - safe[:, None]), axis=-1))
        return np.where(n_ok > 0, tot - np.log(np.maximum(n_ok, 1)), -np.inf)
