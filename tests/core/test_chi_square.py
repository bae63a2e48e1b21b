"""diffpos.chi_square: the closed-form chi-square(3) CDF and its quantile against scipy's
(an independent implementation), and the CDF against a Monte Carlo sample of |N(0, I3)|^2."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from diffpos.chi_square import chi2_3_cdf, chi2_3_quantile


@pytest.mark.parametrize("p", [1e-9, 1e-3, 0.05, 0.3, 0.5, 0.9, 0.95, 0.99, 0.999, 1 - 1e-6])
def test_quantile_matches_scipy(p):
    q = chi2_3_quantile(p)
    assert q == pytest.approx(chi2.ppf(p, 3), rel=1e-10)
    assert chi2_3_cdf(q) == pytest.approx(p, rel=1e-12, abs=1e-15)


def test_cdf_matches_scipy_and_a_sample():
    x = np.concatenate([np.linspace(0.0, 40.0, 401), [1e-6, 1e-3]])
    ours = np.array([chi2_3_cdf(v) for v in x])
    assert np.allclose(ours, chi2.cdf(x, 3), rtol=1e-12, atol=1e-15)
    d2 = np.sum(np.random.default_rng(0).standard_normal((200_000, 3)) ** 2, axis=1)
    for v in (0.5, 2.366, 7.815):  # 4 sigma of a binomial proportion over 200k draws
        assert np.mean(d2 <= v) == pytest.approx(chi2_3_cdf(v), abs=4 * 0.5 / np.sqrt(2e5))


@pytest.mark.parametrize("p", [0.0, 1.0, -0.1, 1.5, float("nan")])
def test_quantile_rejects_what_is_not_a_probability(p):
    with pytest.raises(ValueError, match="strictly between 0 and 1"):
        chi2_3_quantile(p)
