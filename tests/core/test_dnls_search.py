"""The bounded D-NLS exclusion search (``dnls(exclusion_ftol=, exclusion_recheck_ratio=,
exclusion_bound=)``, docs/dnls_cost.md) against the exhaustive one and a brute force.

* The LM continuation the search relies on: solving to a loose ``ftol`` and continuing with the
  returned damping is the same iteration as one run to the full test (kernel and reference).
* On 8-anchor fixes with one positive fault of metres, the bounded search excludes the anchor
  a brute force picks (every leave-one-out subset solved from every start to convergence, the
  smallest test statistic) wherever the exhaustive search does, at the same position.
* It does less work: fewer LM iterations (counted in the numpy reference) than the exhaustive
  search on the same fixes.
"""

from __future__ import annotations

import numpy as np
import pytest
from lm_iterations import count_lm_iterations
from outside_fixes import SIG_M, W_M, outside_fixes

from diffpos.estimators.dnls.solver import dnls
from diffpos.estimators.lm import PathModel, levenberg_marquardt
from diffpos.estimators.lm_nb import LAMBDA0, lm_fit_ftol
from diffpos.estimators.result import ExclusionReason

EXHAUSTIVE = {"exclusion_ftol": None, "exclusion_recheck_ratio": None, "exclusion_bound": None}


def _faulty_nodes(seed: int, n: int, m: int = 8):
    """The nodes of :func:`_faulty` (same seed)."""
    return outside_fixes(np.random.default_rng(seed), n, m)[1]


def _faulty(seed: int, n: int, m: int = 8):
    """Anchors outside, nodes on 9 floors, 5 cm noise and one fault of +3..10 m per fix."""
    rng = np.random.default_rng(seed)
    a, _, r = outside_fixes(rng, n, m)
    bad = rng.integers(0, m, n)
    r[np.arange(n), bad] += rng.uniform(3.0, 10.0, n)
    return a, r, bad


def test_loose_solve_continued_with_its_damping_is_one_full_solve():
    a, r, _ = _faulty(1, 40)
    x0 = np.tile([0.0, 3.0, 12.0], (40, 1))
    sw = np.full(r.shape, 1.0 / SIG_M)
    mdl = PathModel(window_height_m=W_M, delta_m=0.0, edge_x_m=None)
    full = levenberg_marquardt(a, r, sw, x0, mdl, max_iter=50)
    loose = levenberg_marquardt(a, r, sw, x0, mdl, max_iter=50, ftol=1e-6)
    assert np.all(loose.iterations <= full.iterations)
    assert np.any(loose.iterations < full.iterations)  # the loose test stops earlier
    cont = levenberg_marquardt(a, r, sw, loose.x_m, mdl, max_iter=50, lambda0=loose.lam)
    np.testing.assert_array_equal(loose.iterations + cont.iterations, full.iterations)
    np.testing.assert_allclose(cont.x_m, full.x_m, atol=1e-9, rtol=0)
    used = np.ones(r.shape[1], bool)
    for i in range(40):  # the kernel: the same property, one problem at a time
        xf, xl, xc = np.empty(3), np.empty(3), np.empty(3)
        lam_f, lam_l = np.full(1, LAMBDA0), np.full(1, LAMBDA0)
        args = (a[i], r[i], sw[i], used)
        tail = (0.5 * W_M, -np.inf, np.inf, 0, 1.5, 50, 1e-10)
        _, itf, _ = lm_fit_ftol(*args, x0[i], *tail, 1e-12, np.inf, 0, lam_f, xf)
        _, itl, _ = lm_fit_ftol(*args, x0[i], *tail, 1e-6, np.inf, 0, lam_l, xl)
        _, itc, _ = lm_fit_ftol(*args, xl.copy(), *tail, 1e-12, np.inf, 0, lam_l, xc)
        assert itl + itc == itf
        np.testing.assert_allclose(xc, xf, atol=1e-9, rtol=0)


def _brute_force_exclusion(a, r):
    """Per fix: the anchor whose leave-one-out subset has the smallest statistic, every subset
    solved from every start to convergence (no gating, no screening)."""
    n, m = r.shape
    t = np.full((n, m), np.inf)
    for j in range(m):
        mask = np.ones((n, m), bool)
        mask[:, j] = False
        f = dnls(a, r, SIG_M, mask=mask, window_height_m=W_M, gating=None, keep_starts=None)
        t[:, j] = np.nansum(((f.residuals_m / SIG_M) ** 2), axis=1)
    return np.argmin(t, axis=1)


@pytest.mark.parametrize("kernel", [True, False])
def test_bounded_search_excludes_the_brute_force_anchor(kernel):
    a, r, bad = _faulty(7, 120)
    brute = _brute_force_exclusion(a, r)
    new = dnls(a, r, SIG_M, window_height_m=W_M, kernel=kernel)
    old = dnls(a, r, SIG_M, window_height_m=W_M, kernel=kernel, **EXHAUSTIVE)
    raim_new = new.exclusion_reason == ExclusionReason.RAIM
    raim_old = old.exclusion_reason == ExclusionReason.RAIM
    one = raim_old.sum(axis=1) == 1  # the exhaustive search removed exactly one anchor
    assert one.sum() >= 80  # the faults are found and removed in most fixes
    assert np.mean(brute == bad) >= 0.95  # the brute force names the faulty anchor
    np.testing.assert_array_equal(raim_new, raim_old)  # the same exclusions everywhere
    hit = one & (np.argmax(raim_old, axis=1) == brute)
    assert hit.sum() >= 0.95 * one.sum()
    np.testing.assert_array_equal(new.status, old.status)
    np.testing.assert_allclose(new.position_m, old.position_m, atol=1e-6, rtol=0)


def test_bounded_search_does_less_work(monkeypatch):
    """Warm-started fixes (the fusion's: one start near the node), where the candidates' LM
    iterations are most of the work (cold fixes add 13 screened starts per candidate)."""
    a, r, _ = _faulty(11, 60)
    x0 = _faulty_nodes(11, 60) + np.random.default_rng(0).normal(0.0, 0.5, (60, 3))
    count = count_lm_iterations(monkeypatch)
    work = {}
    for name, kw in (("bounded", {}), ("exhaustive", EXHAUSTIVE)):
        count["it"] = 0
        dnls(a, r, SIG_M, window_height_m=W_M, kernel=False, x0_m=x0, **kw)
        work[name] = count["it"]
    assert work["bounded"] < 0.7 * work["exhaustive"], work  # measured: 0.44


@pytest.mark.parametrize("kw", [{"exclusion_ftol": 0.0}, {"exclusion_ftol": 1.0},
                                {"exclusion_recheck_ratio": 0.5}, {"exclusion_bound": 0.9}])
def test_search_options_are_validated(kw):
    a, r, _ = _faulty(3, 2)
    with pytest.raises(ValueError, match=next(iter(kw))):
        dnls(a, r, SIG_M, window_height_m=W_M, **kw)
