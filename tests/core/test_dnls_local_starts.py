"""``dnls(exclusion_starts="local")``: a cold fix's exclusion candidates solved from their own
LLS position and the current solution only (instead of every start of the first fit: the
height grid and LLS, screened, plus the current solution).

* The compiled kernel and the numpy reference agree with the option (statuses, used anchors,
  exclusions; positions at the rounding level), as they do without it.
* On cold 8-anchor fixes with one positive fault of metres, the local search excludes the
  anchor a brute force picks (every leave-one-out subset solved from every start to
  convergence, the smallest test statistic) as often as the grid search does, and the
  same anchor as the grid search in nearly every fix.
* It does less work: fewer LM iterations (counted in the numpy reference) on the same fixes.
* Warm-started fixes (``x0_m``) are unaffected: identical results.
"""

from __future__ import annotations

import numpy as np
import pytest
from lm_iterations import count_lm_iterations
from outside_fixes import SIG_M, W_M, outside_fixes

from diffpos.estimators.dnls.solver import dnls
from diffpos.estimators.result import ExclusionReason, FixStatus

POS_TOL_M = 1e-5  # rounding-level differences of kernel and reference (test_dnls_kernel.py)


def _faulty(seed: int, n: int, m: int = 8, faults: int = 1):
    """Anchors outside, nodes on 9 floors, 5 cm noise and ``faults`` faults of +3..10 m per
    fix; 10 % of the links missing. Returns anchors, ranges, mask, nodes and the faulty
    anchor (the first one)."""
    rng = np.random.default_rng(seed)
    a, nodes, r = outside_fixes(rng, n, m)
    bad = np.stack([rng.permutation(m)[:faults] for _ in range(n)])
    for k in range(faults):
        r[np.arange(n), bad[:, k]] += rng.uniform(3.0, 10.0, n)
    mask = rng.random((n, m)) > 0.1
    mask[np.arange(n), bad[:, 0]] = True
    return a, r, mask, nodes, bad[:, 0]


def _brute_force_exclusion(a, r, mask):
    """Per fix: the anchor whose leave-one-out subset has the smallest statistic, every subset
    solved from every start to convergence (no gating, no screening)."""
    n, m = r.shape
    t = np.full((n, m), np.inf)
    for j in range(m):
        mj = mask.copy()
        mj[:, j] = False
        f = dnls(a, r, SIG_M, mask=mj, window_height_m=W_M, gating=None, keep_starts=None)
        t[:, j] = np.where(mask[:, j], np.nansum(((f.residuals_m / SIG_M) ** 2), axis=1),
                           np.inf)
    return np.argmin(t, axis=1)


@pytest.mark.parametrize("m,faults", [(5, 1), (8, 1), (8, 2)])
def test_kernel_equals_reference_with_local_starts(m, faults):
    a, r, mask, _, _ = _faulty(100 + 10 * m + faults, 150, m, faults)
    ref = dnls(a, r, SIG_M, mask=mask, window_height_m=W_M, kernel=False,
               exclusion_starts="local")
    k = dnls(a, r, SIG_M, mask=mask, window_height_m=W_M, exclusion_starts="local")
    assert np.sum(k.exclusion_reason == ExclusionReason.RAIM) >= 80  # the search runs
    np.testing.assert_array_equal(k.status, ref.status)
    np.testing.assert_array_equal(k.used, ref.used)
    np.testing.assert_array_equal(k.exclusion_reason, ref.exclusion_reason)
    unique = np.isfinite(ref.position_m).all(axis=1) & (ref.dof >= 1) & (
        ref.status != FixStatus.NOT_IDENTIFIABLE)
    d = np.abs(k.position_m[unique] - ref.position_m[unique]).max(initial=0.0)
    assert d <= POS_TOL_M, f"largest position difference {d:.3g} m"


@pytest.mark.parametrize("kernel", [True, False])
def test_local_starts_exclude_the_brute_force_anchor(kernel):
    a, r, mask, _, bad = _faulty(7, 120)
    brute = _brute_force_exclusion(a, r, mask)
    res = {s: dnls(a, r, SIG_M, mask=mask, window_height_m=W_M, kernel=kernel,
                   exclusion_starts=s) for s in ("grid", "local")}
    raim = {s: f.exclusion_reason == ExclusionReason.RAIM for s, f in res.items()}
    one = {s: x.sum(axis=1) == 1 for s, x in raim.items()}
    hit = {s: one[s] & (np.argmax(raim[s], axis=1) == brute) for s in raim}
    assert np.mean(brute == bad) >= 0.95  # the brute force names the faulty anchor
    assert one["grid"].sum() >= 80  # the faults are found and removed in most fixes
    assert hit["local"].sum() >= hit["grid"].sum() - 1, {s: int(h.sum()) for s, h in hit.items()}
    same = (raim["local"] == raim["grid"]).all(axis=1)
    assert same.mean() >= 0.97, same.mean()
    ok = (res["grid"].status == FixStatus.OK) & (res["local"].status == FixStatus.OK) & same
    np.testing.assert_allclose(res["local"].position_m[ok], res["grid"].position_m[ok],
                               atol=1e-3, rtol=0)


def test_local_starts_do_less_work(monkeypatch):
    a, r, mask, _, _ = _faulty(11, 40)
    count = count_lm_iterations(monkeypatch)
    work = {}
    for starts in ("grid", "local"):
        count["it"] = 0
        dnls(a, r, SIG_M, mask=mask, window_height_m=W_M, kernel=False, exclusion_starts=starts)
        work[starts] = count["it"]
    assert work["local"] < 0.6 * work["grid"], work  # measured: 0.33


@pytest.mark.parametrize("kernel", [True, False])
def test_warm_started_fixes_are_unaffected(kernel):
    a, r, mask, nodes, _ = _faulty(13, 60)
    x0 = nodes + np.random.default_rng(1).normal(0.0, 0.5, nodes.shape)
    grid, local = (dnls(a, r, SIG_M, mask=mask, window_height_m=W_M, kernel=kernel, x0_m=x0,
                        exclusion_starts=s) for s in ("grid", "local"))
    for f in ("position_m", "status", "used", "exclusion_reason", "iterations"):
        np.testing.assert_array_equal(getattr(local, f), getattr(grid, f))


def test_exclusion_starts_is_validated():
    a, r, mask, _, _ = _faulty(3, 2)
    with pytest.raises(ValueError, match="exclusion_starts"):
        dnls(a, r, SIG_M, mask=mask, window_height_m=W_M, exclusion_starts="everywhere")
