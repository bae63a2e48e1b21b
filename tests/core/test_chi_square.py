"""diffpos.chi_square: the chi-square(3) CDF, survival function and quantile against scipy's
(an independent implementation: the regularised incomplete gamma function), in both tails,
and the CDF against a Monte Carlo sample of |N(0, I3)|^2."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from diffpos.chi_square import chi2_3_cdf, chi2_3_quantile, chi2_3_sf


@pytest.mark.parametrize("p", [1e-12, 1e-9, 1e-6, 1e-3, 0.05, 0.3, 0.5, 0.9, 0.95, 0.99,
                               0.999, 1 - 1e-6, 1 - 1e-9, 1 - 1e-12])
def test_quantile_matches_scipy(p):
    """Within 1e-13 relative in both tails (the closed form alone: 2e-11 at p = 1e-9, 2e-10
    at 1 - 1e-9, 2e-6 at 1 - 1e-12, from the cancellation of its two terms / of 1 - F)."""
    q = chi2_3_quantile(p)
    assert q == pytest.approx(chi2.ppf(p, 3), rel=1e-13)
    assert chi2_3_cdf(q) == pytest.approx(p, rel=1e-12, abs=1e-15)
    assert chi2_3_sf(q) == pytest.approx(1 - p, rel=1e-12)


def test_cdf_and_sf_match_scipy_and_a_sample():
    x = np.concatenate([np.linspace(0.0, 40.0, 401), np.geomspace(1e-10, 1.0, 101),
                        np.linspace(40.0, 100.0, 61)])
    ours = np.array([chi2_3_cdf(v) for v in x])
    tail = np.array([chi2_3_sf(v) for v in x])
    assert np.allclose(ours, chi2.cdf(x, 3), rtol=1e-13, atol=0.0)  # relative, also near 0
    assert np.allclose(tail, chi2.sf(x, 3), rtol=1e-13, atol=0.0)  # relative, also near 1
    assert np.all(np.diff(ours[:401]) > 0) and chi2_3_cdf(0.0) == 0.0 and chi2_3_sf(0.0) == 1.0
    d2 = np.sum(np.random.default_rng(0).standard_normal((200_000, 3)) ** 2, axis=1)
    for v in (0.5, 2.366, 7.815):  # 4 sigma of a binomial proportion over 200k draws
        assert np.mean(d2 <= v) == pytest.approx(chi2_3_cdf(v), abs=4 * 0.5 / np.sqrt(2e5))


@pytest.mark.parametrize("p", [0.0, 1.0, -0.1, 1.5, float("nan")])
def test_quantile_rejects_what_is_not_a_probability(p):
    with pytest.raises(ValueError, match="strictly between 0 and 1"):
        chi2_3_quantile(p)
