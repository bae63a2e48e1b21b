"""The published floor's probability against its height band (``TrackerConfig.floor_band_bound``,
:func:`diffpos.tracking.state.height_band_bound`; issue 34 item 5).

A node whose published height ``N(z, P_zz)`` straddles a slab can be on either floor; the
published floor's probability must not exceed the mass of that distribution on the floor's
height band (the building model's ``floor_z_m``; the end floors' bands extended). The
references here are scipy's normal CDF and the building's own floor heights.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.stats import norm
from stairs_walk import walk as _walk

from diffpos.scenario import default_scenario
from diffpos.tracking.state import TrackerConfig, height_band_bound

SC = default_scenario()
B = SC.building


def _band_mass(z: float, sd: float, floor: int) -> float:
    """Mass of N(z, sd^2) on ``floor``'s band, the lowest and highest bands open-ended."""
    lo = -np.inf if floor == 0 else float(B.floor_z_m(floor))
    hi = np.inf if floor == B.n_floors - 1 else float(B.floor_z_m(floor + 1))
    return float(norm.cdf(hi, z, sd) - norm.cdf(lo, z, sd))


def test_band_bound_against_the_normal_cdf():
    """Random probability vectors, heights and sigmas (seed 5): the published floor's
    probability is min(p, max(band mass, 1/2)) by scipy's CDF (atol 1e-12), it stays the
    largest, the vector sums to 1, the others never decrease; rows within the bound, without
    a floor or with a NaN height are returned bit for bit."""
    rng = np.random.default_rng(5)
    n, nf = 400, B.n_floors
    p = rng.dirichlet(np.full(nf, 0.3), n)
    k = np.argmax(p, axis=1)
    p[np.arange(n), k] += 3.0  # a clear most probable floor
    p /= p.sum(axis=1, keepdims=True)
    z = B.floor_z_m(k) + rng.uniform(-0.6, B.floor_height_m + 0.6, n)
    sd = rng.uniform(0.02, 1.5, n)
    floor = k.copy()
    floor[:10] = -1
    z[10:20] = np.nan
    out = height_band_bound(p, floor, z, sd**2, B.first_floor_z_m, B.floor_height_m)
    np.testing.assert_allclose(out.sum(axis=1), 1.0, atol=1e-12)
    changed = 0
    for i in range(n):
        if i < 20:
            assert np.array_equal(out[i], p[i])
            continue
        cap = max(_band_mass(z[i], sd[i], k[i]), 0.5)
        np.testing.assert_allclose(out[i, k[i]], min(p[i, k[i]], cap), atol=1e-12)
        assert np.argmax(out[i]) == k[i]
        assert np.all(np.delete(out[i] - p[i], k[i]) >= -1e-15)
        if p[i, k[i]] <= cap:
            assert np.array_equal(out[i], p[i])
        else:
            changed += 1
    assert changed > 50


def test_stairs_never_published_above_the_band_mass():
    """Down the stairs across the slab between floors 2 and 1: with the bound every epoch's
    published floor probability is at most max(band mass of its published height, 1/2) (by
    scipy's CDF, +1e-9); without it some epoch near the slab exceeds it (the rule binds); the
    filter, floor, position, covariance and status are the same bit for bit, and only the
    published floor probabilities differ."""
    # the published covariance of the filter's floor weights ("off"): with "credible" (the
    # session 28 default) it follows the bounded probabilities, so the cap is not re-derivable
    base = TrackerConfig(cov_published_floors="off")
    on = _walk(dataclasses.replace(base, floor_band_bound=True))
    off = _walk(base)
    bound_binds = 0
    for (o1, s1), (o0, s0) in zip(on, off, strict=True):
        assert np.array_equal(s1.log_prob, s0.log_prob)
        assert np.array_equal(s1.mean, s0.mean)
        for f in ("position_m", "covariance_m2", "floor_index", "status", "nis"):
            assert np.array_equal(getattr(o1, f), getattr(o0, f), equal_nan=True), f
        k = int(o1.floor_index[0])
        if k < 0:
            continue
        cap = max(_band_mass(o1.position_m[0, 2], np.sqrt(o1.covariance_m2[0, 2, 2]), k), 0.5)
        assert o1.floor_probabilities[0, k] <= cap + 1e-9
        assert np.argmax(o1.floor_probabilities[0]) == k
        if o0.floor_probabilities[0, k] > cap + 1e-6:
            bound_binds += 1
    assert bound_binds >= 1


def test_stairs_mode_contests_the_floor():
    """``floor_contest_vertical``: on the same walk, every epoch in which the most probable
    floor's stairs mode is more probable than its level mode (computed here from the state's
    hypotheses, ``h = mode * F + floor``) restarts the contest clock (``lead_ns`` = that
    epoch); some such epochs do not restart it without the setting, and there the published
    floor is less sure (kappa 10 instead of 3.9); the filter, floor and position are those of
    the default bit for bit."""
    on = _walk(TrackerConfig(floor_contest_vertical=True, stairs_follow=0))
    off = _walk(TrackerConfig(stairs_follow=0))  # (the modes' own tracks)
    nf = B.n_floors
    added = 0
    for k, ((o1, s1), (o0, s0)) in enumerate(zip(on, off, strict=True)):
        assert np.array_equal(s1.log_prob, s0.log_prob)
        assert np.array_equal(o1.position_m, o0.position_m, equal_nan=True)
        assert np.array_equal(o1.floor_index, o0.floor_index)
        f = int(o1.floor_index[0])
        p = np.exp(s1.log_prob[0])
        if f < 0 or p[f + nf] <= p[f]:
            continue
        t_ns = k * 100_000_000
        assert s1.lead_ns[0] == t_ns
        if s0.lead_ns[0] != t_ns and (t_ns - s0.lead_ns[0]) * 1e-9 >= 3.0:
            added += 1
            assert o1.floor_probabilities[0, f] < o0.floor_probabilities[0, f]
    assert added >= 1
