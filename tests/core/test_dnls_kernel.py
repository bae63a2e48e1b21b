"""The compiled D-NLS kernel against the numpy reference (``dnls(..., kernel=False)``).

Same statuses, used anchors and exclusion reasons on every problem; positions equal within
``POS_TOL_M``: both implementations run the same iteration, but sums over anchors are taken in
another order and the kernel solves every 3x3 system by cofactors (the reference uses LAPACK
for small batches), so iterates differ at the rounding level and each stops where its own
convergence test passes (step <= 1e-10 relative, or a relative cost decrease <= 1e-12): the
stopping points then differ by up to ~1e-7 m on noisy 8-anchor fixes (measured max 9e-7 m
without gating). ``POS_TOL_M`` leaves 10x margin over that. Not identifiable fixes have a
flat cost (e.g. a node beyond the clamped edge ends, where LM wanders along the flat
direction and may stop in another basin): there only the status must agree. Fixes on
exactly 3 anchors
(0 dof) are the exception: their ranges have several exact solutions (cost 0 up to rounding),
and which start's exact solution has the smaller rounding-level cost is arbitrary; there both
must fit every used range exactly instead.
"""

from __future__ import annotations

import numpy as np
import pytest

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.estimators.dnls.fit_nb import warm_dnls
from diffpos.estimators.dnls.solver import dnls
from diffpos.estimators.gating import GatingConfig
from diffpos.estimators.result import FixStatus
from diffpos.geometry import window_edge_path
from diffpos.scenario import default_scenario

POS_TOL_M = 1e-5
W_M = 1.2


def _scene(seed: int, n: int, m: int, *, fault_rate: float, delta_m: float = 0.0):
    """Random anchors outside, nodes on 9 floors; ranges with 5 cm noise, positive faults
    of 0.5-10 m on ``fault_rate`` of the links and 15 % of the links missing."""
    rng = np.random.default_rng(seed)
    a = np.stack([rng.uniform(-30, 30, (n, m)), rng.uniform(-40, -5, (n, m)),
                  rng.uniform(0, 40, (n, m))], axis=-1)
    nodes = np.stack([rng.uniform(-15, 15, n), rng.uniform(0.2, 15, n),
                      1.5 + 3.0 * rng.integers(0, 9, n)], axis=-1)
    r = window_edge_path(a, nodes[:, None, :], window_height_m=W_M, delta_m=delta_m).length_m
    r = r + rng.normal(0.0, 0.05, (n, m))
    r = r + (rng.random((n, m)) < fault_rate) * rng.uniform(0.5, 10.0, (n, m))
    mask = rng.random((n, m)) > 0.15
    return a, r, mask, nodes


def _assert_same(ref, k) -> None:
    np.testing.assert_array_equal(k.status, ref.status)
    np.testing.assert_array_equal(k.used, ref.used)
    np.testing.assert_array_equal(k.exclusion_reason, ref.exclusion_reason)
    np.testing.assert_array_equal(k.dof, ref.dof)
    solved = np.isfinite(ref.position_m).all(axis=1)
    np.testing.assert_array_equal(np.isfinite(k.position_m).all(axis=1), solved)
    flat = ref.status == FixStatus.NOT_IDENTIFIABLE  # a flat cost: the position is not unique
    unique = solved & (ref.dof >= 1) & ~flat
    d = np.abs(k.position_m[unique] - ref.position_m[unique]).max(initial=0.0)
    assert d <= POS_TOL_M, f"largest position difference {d:.3g} m"
    # covariances of badly conditioned FIMs (condition up to 1e6 is identifiable) amplify the
    # rounding-level position differences: measured up to 3.4e-4 relative on emulated ranges
    np.testing.assert_allclose(k.covariance_m2[unique], ref.covariance_m2[unique], rtol=2e-3,
                               atol=1e-12)
    np.testing.assert_allclose(k.cost[unique], ref.cost[unique], rtol=1e-6, atol=1e-9)
    # 0 dof: the same position, or both at (different) exact solutions
    same = np.abs(k.position_m - ref.position_m).max(axis=1) <= POS_TOL_M
    both_exact = (np.nanmax(np.abs(np.nan_to_num(k.residuals_m)), axis=1) < 1e-6) & (
        np.nanmax(np.abs(np.nan_to_num(ref.residuals_m)), axis=1) < 1e-6)
    assert np.all((same | both_exact)[solved & (ref.dof == 0) & ~flat])


CASES = {
    "default": {},
    "warm start": {"x0": True},
    "huber": {"loss": "huber"},
    "soft_l1 no gating": {"loss": "soft_l1", "gating": None},
    "no screening": {"keep_starts": None},
    # the edge clamp makes the model non-smooth: a rounding-level difference can send a
    # 4-iteration screening start down another branch, and (with the default
    # exclusion_recheck_ratio) a fix far from consistency is not re-solved from all starts
    # to hide it (measured: 1 of these 450 problems); the exhaustive recheck here
    "bounded edges, Case-2": {"edge_x_m": (-12.0, 12.0), "delta_m": 1.5,
                              "exclusion_recheck_ratio": None},
    "warm refits only": {"gating": GatingConfig(multistart_exclusion=False, max_exclusions=3)},
    "no sigmas, margin": {"sigmas": False, "gating": GatingConfig(pregate_margin_m=0.3)},
}


@pytest.mark.parametrize("m", [4, 5, 8])
@pytest.mark.parametrize("case", list(CASES))
def test_kernel_equals_reference_on_random_faulty_problems(case, m):
    opt = dict(CASES[case])
    a, r, mask, nodes = _scene(10 * m + len(case), 150, m, fault_rate=0.1,
                               delta_m=opt.get("delta_m", 0.0))
    kw = {k: v for k, v in opt.items() if k not in ("x0", "sigmas")}
    if opt.get("x0"):
        kw["x0_m"] = nodes + np.random.default_rng(m).normal(0.0, 0.7, nodes.shape)
    sig = 0.05 if opt.get("sigmas", True) else None
    ref = dnls(a, r, sig, mask=mask, window_height_m=W_M, kernel=False, **kw)
    k = dnls(a, r, sig, mask=mask, window_height_m=W_M, **kw)
    _assert_same(ref, k)


def test_kernel_equals_reference_on_emulated_channel_ranges():
    """Ranges of the channel emulator (first arrivals over every mechanism, detection, SNR
    sigmas) on the paper's building, 8 random anchors per fix; warm and cold fixes."""
    sc = default_scenario()
    b = sc.building
    rng = np.random.default_rng(2024)
    n, m = 250, 8
    nodes = np.stack([rng.uniform(-18, 18, n), rng.uniform(0.5, 20, n),
                      b.first_floor_z_m + b.floor_height_m * rng.integers(0, b.n_floors, n)
                      + 1.0], axis=-1)
    a = np.stack([rng.uniform(-35, 35, (n, m)), rng.uniform(-40, -5, (n, m)),
                  rng.uniform(0, 1.3 * b.n_floors * b.floor_height_m, (n, m))], axis=-1)
    r, s, mask = np.zeros((n, m)), np.ones((n, m)), np.zeros((n, m), bool)
    for i in range(n):  # one channel per fix: the 8 anchors of fix i against its node
        fa = first_arrival(emulate_channel(a[i], nodes[i][None], building=b, radio=sc.radio),
                           radio=sc.radio, rng=rng)
        r[i], s[i], mask[i] = fa.range_m[0], fa.sigma_m[0], fa.detected[0]
    r = np.where(mask, r, 0.0)
    common = dict(mask=mask, window_height_m=b.window_height_m, edge_x_m=b.edge_x_m)
    for kw in ({}, {"x0_m": nodes + rng.normal(0.0, 0.5, nodes.shape)}):
        ref = dnls(a, r, s, kernel=False, **common, **kw)
        k = dnls(a, r, s, **common, **kw)
        assert len(np.unique(ref.status)) >= 3  # realistic: a mix of outcomes, not all OK
        _assert_same(ref, k)


def test_kernel_handles_invalid_and_short_rows_like_the_reference():
    a, r, mask, _ = _scene(5, 40, 6, fault_rate=0.0)
    r[0, 0] = np.nan  # invalid input
    mask[1, :4] = False  # two anchors left: too few
    a[2, 1, 1] = -3.0
    r[2, 1] = 0.5  # shorter than the wall distance: wall pre-gate
    mask[2, 3:] = False  # ... and then too few anchors
    ref = dnls(a, r, 0.05, mask=mask, window_height_m=W_M, kernel=False)
    k = dnls(a, r, 0.05, mask=mask, window_height_m=W_M)
    _assert_same(ref, k)
    assert k.status[0] == FixStatus.INVALID_INPUT and k.status[1] == FixStatus.TOO_FEW_ANCHORS
    assert k.status[2] == FixStatus.TOO_FEW_ANCHORS and k.exclusion_reason[2, 1] == 2


def test_warm_dnls_returns_quickly_once_compiled():
    warm_dnls()
    assert warm_dnls() < 1.0  # compiled: a tiny solve, no compilation
