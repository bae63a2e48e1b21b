"""The batched Levenberg-Marquardt core: the depth parameter u = y^2 and its bound u >= 0.

The path model depends on the depth ``y`` only through ``y^2``; the solver iterates in
``u = y^2`` with ``u >= 0``. References: ``scipy.optimize.least_squares`` on the ``(x, y, z)``
problem built on :func:`diffpos.geometry.window_edge_path` (bounded ``trf`` with ``y >= 0``
where the optimum is on the wall plane, MINPACK ``lm`` elsewhere) and finite differences.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares

from diffpos.estimators.lm import PathModel, levenberg_marquardt
from diffpos.geometry import window_edge_path

#: 8 UAVs on an arc in front of the facade (the geometry of the fusion's synthetic replay).
ARC_ANCHORS_M = np.array([
    [-18.0, -8.0, 1.0], [-12.857, -12.339, 4.0], [-7.714, -15.818, 1.0],
    [-2.571, -17.749, 4.0], [2.571, -17.749, 1.0], [7.714, -15.818, 4.0],
    [12.857, -12.339, 1.0], [18.0, -8.0, 4.0],
])

TIGHT = {"xtol_m": 1e-13, "ftol": 1e-15, "gtol": 1e-14}


def _wall_cases(seed: int, n: int):
    """Shallow nodes (truth y in [0.3, 0.7] m), sigma 0.112 m: noise pushes many optima onto
    the wall plane y = 0 (the cases that made the y-parameterised LM crawl to max_iter)."""
    rng = np.random.default_rng(seed)
    nodes = np.stack([rng.uniform(-17, 19, n), rng.uniform(0.3, 0.7, n),
                      rng.uniform(5.5, 18.5, n)], axis=-1)
    a = np.broadcast_to(ARC_ANCHORS_M, (n, 8, 3)).copy()
    edge = (-20.0, 20.0)
    sigma = 0.112
    r = window_edge_path(a, nodes[:, None, :], window_height_m=1.5, edge_x_m=edge).length_m
    r = r + sigma * rng.standard_normal(r.shape)
    sw = np.full(r.shape, 1.0 / sigma)
    x0 = nodes + rng.normal(0.0, 0.3, nodes.shape)  # warm start, y of either sign
    return a, r, sw, x0, edge


def _scipy_ref(a, r, sw, x0, *, wh, delta=0.0, edge=None, bounded=False, loss="linear",
               f_scale=1.0):
    """One fix with scipy on the (x, y, z) problem of window_edge_path, tight tolerances."""
    def fun(x):
        return (r - window_edge_path(a, x, window_height_m=wh, delta_m=delta,
                                     edge_x_m=edge).length_m) * sw

    def jac(x):
        return -window_edge_path(a, x, window_height_m=wh, delta_m=delta,
                                 edge_x_m=edge).jacobian * sw[:, None]

    tol = {"xtol": 1e-15, "ftol": 1e-15, "gtol": 1e-15}
    if bounded:
        s0 = np.array([x0[0], abs(x0[1]), x0[2]])
        ref = least_squares(fun, s0, jac=jac, bounds=([-np.inf, 0.0, -np.inf], np.inf),
                            method="trf", **tol)
    elif loss == "linear":
        ref = least_squares(fun, x0, jac=jac, method="lm", **tol)
    else:
        ref = least_squares(fun, x0, jac=jac, method="trf", loss=loss, f_scale=f_scale,
                            max_nfev=5000, **tol)
    x = ref.x.copy()
    x[1] = abs(x[1])
    return x, ref.cost


def test_wall_plane_optima_converge_fast_and_match_bounded_scipy():
    """Optimum on the wall plane: converged, <= 8 iterations (measured on this seed: 3-7,
    mean 4.1; the y-parameterised LM needed 50+ on such rows), and the bounded scipy
    minimum to 1e-6 m (default tolerances for the rows at y = 0, tight ones for all)."""
    a, r, sw, x0, edge = _wall_cases(5, 200)
    model = PathModel(window_height_m=1.5, delta_m=0.0, edge_x_m=edge)
    fit = levenberg_marquardt(a, r, sw, x0, model)
    assert np.all(fit.converged)
    assert fit.iterations.max() <= 8, np.bincount(fit.iterations)
    assert fit.iterations.mean() <= 5.0
    on_wall = fit.x_m[:, 1] == 0.0
    assert on_wall.mean() >= 0.2  # the bound is really exercised
    assert np.all(fit.x_m[:, 1] >= 0.0)
    tight = levenberg_marquardt(a, r, sw, x0, model, **TIGHT)
    assert np.all(tight.converged)
    for i in range(len(r)):
        ref, ref_cost = _scipy_ref(a[i], r[i], sw[i], x0[i], wh=1.5, edge=edge, bounded=True)
        assert np.linalg.norm(tight.x_m[i] - ref) < 1e-6, (i, tight.x_m[i], ref)
        assert tight.cost[i] <= ref_cost * (1 + 1e-12) + 1e-12
        if on_wall[i]:
            assert np.linalg.norm(fit.x_m[i] - ref) < 1e-6, (i, fit.x_m[i], ref)
            assert ref[1] < 1e-6


def _random_problems(rng, n, m, *, delta_m, edge, sigma_m):
    a = np.stack([rng.uniform(-30, 30, (n, m)), rng.uniform(-40, -5, (n, m)),
                  rng.uniform(0, 40, (n, m))], axis=-1)
    nodes = np.stack([rng.uniform(-15, 15, n), rng.uniform(0.5, 20, n),
                      rng.uniform(0, 27, n)], axis=-1)
    r = window_edge_path(a, nodes[:, None, :], window_height_m=1.2, delta_m=delta_m,
                         edge_x_m=edge).length_m
    r = r + sigma_m * rng.standard_normal(r.shape)
    return a, r, nodes


@pytest.mark.parametrize(("delta_m", "edge"), [(0.0, None), (1.5, None), (0.4, (-25.0, 25.0))])
@pytest.mark.parametrize("sigma_m", [0.0, 0.05])
def test_general_problems_same_minimum_as_scipy(delta_m, edge, sigma_m):
    """Nodes y in [0.5, 20] m, 6 anchors, warm starts (truth + 0.5 m noise): the minimum of
    scipy's MINPACK LM on (x, y, z) from the same start to 1e-7 m; noise-free: the truth to
    1e-6 m at default tolerances. Iterations (default tolerances) mean <= 4.5 and max <= 10
    (measured with the y-parameterised LM on such problems: mean 4.0-4.2, max 14-34)."""
    rng = np.random.default_rng(41 + int(10 * delta_m) + int(100 * sigma_m))
    n = 60
    a, r, nodes = _random_problems(rng, n, 6, delta_m=delta_m, edge=edge, sigma_m=sigma_m)
    sw = np.full(r.shape, 1.0 / max(sigma_m, 0.05))
    x0 = nodes + rng.normal(0.0, 0.5, nodes.shape)
    model = PathModel(window_height_m=1.2, delta_m=delta_m, edge_x_m=edge)
    fit = levenberg_marquardt(a, r, sw, x0, model)
    assert np.all(fit.converged)
    assert fit.iterations.mean() <= 4.5 and fit.iterations.max() <= 10, fit.iterations
    if sigma_m == 0.0:
        assert np.max(np.linalg.norm(fit.x_m - nodes, axis=1)) < 1e-6
    tight = levenberg_marquardt(a, r, sw, x0, model, **TIGHT)
    for i in range(n):
        ref, ref_cost = _scipy_ref(a[i], r[i], sw[i], x0[i], wh=1.2, delta=delta_m, edge=edge)
        assert np.linalg.norm(tight.x_m[i] - ref) < 1e-7, (i, tight.x_m[i], ref)
        assert np.isclose(tight.cost[i], ref_cost, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("loss", ["huber", "soft_l1"])
def test_robust_losses_same_minimum_as_scipy(loss):
    """One +0.5 m outlier per fix (10 sigma), robust loss with scale 1.5: scipy's trf with the
    same loss from the same start, to 1e-6 m (tight tolerances: the reweighted normal
    equations converge linearly)."""
    rng = np.random.default_rng(43 if loss == "huber" else 44)
    n = 40
    a, r, nodes = _random_problems(rng, n, 6, delta_m=1.5, edge=None, sigma_m=0.05)
    r[:, 0] += 0.5
    sw = np.full(r.shape, 1.0 / 0.05)
    x0 = nodes + rng.normal(0.0, 0.5, nodes.shape)
    model = PathModel(window_height_m=1.2, delta_m=1.5, edge_x_m=None)
    fit = levenberg_marquardt(a, r, sw, x0, model, loss=loss, loss_scale=1.5, max_iter=500,
                              **TIGHT)
    assert np.all(fit.converged)
    for i in range(n):
        ref, ref_cost = _scipy_ref(a[i], r[i], sw[i], x0[i], wh=1.2, delta=1.5, loss=loss,
                                   f_scale=1.5)
        assert np.linalg.norm(fit.x_m[i] - ref) < 1e-6, (i, fit.x_m[i], ref)
        assert np.isclose(fit.cost[i], ref_cost, rtol=1e-9)


def test_start_on_the_wall_plane_leaves_it():
    """A start exactly at y = 0 (where dp/dy = 0: a y-parameterised LM cannot leave it) and
    noise-free ranges of nodes 1-15 m deep: the truth to 1e-6 m."""
    rng = np.random.default_rng(45)
    n = 50
    a, r, nodes = _random_problems(rng, n, 5, delta_m=0.0, edge=None, sigma_m=0.0)
    x0 = nodes + rng.normal(0.0, 0.5, nodes.shape)
    x0[:, 1] = 0.0
    fit = levenberg_marquardt(a, r, np.full(r.shape, 20.0), x0, PathModel(1.2, 0.0, None))
    assert np.all(fit.converged)
    assert np.max(np.linalg.norm(fit.x_m - nodes, axis=1)) < 1e-6


def test_mirrored_start_gives_the_same_result():
    """The model is even in y: a start with y < 0 gives the result of its mirror image, with
    y >= 0."""
    a, r, sw, x0, edge = _wall_cases(6, 40)
    model = PathModel(window_height_m=1.5, delta_m=0.0, edge_x_m=edge)
    pos = x0.copy()
    pos[:, 1] = np.abs(pos[:, 1]) + 0.2
    neg = pos * [1.0, -1.0, 1.0]
    fp = levenberg_marquardt(a, r, sw, pos, model)
    fn = levenberg_marquardt(a, r, sw, neg, model)
    assert np.array_equal(fp.x_m, fn.x_m)
    assert np.array_equal(fp.iterations, fn.iterations)
    assert np.all(fn.x_m[:, 1] >= 0.0)


@pytest.mark.parametrize("edge", [None, (-5.0, 8.0)])
def test_u_jacobian_by_finite_differences(edge):
    """evaluate_u: lengths equal evaluate's; dp/du equals central differences of the lengths in
    u (y = sqrt(u)) to 1e-5 relative, including one-sided differences at u = 0, with
    per-problem window heights and offsets Delta (also Delta > w / 2: edge below the node)."""
    rng = np.random.default_rng(46)
    n = 100
    a, _, nodes = _random_problems(rng, n, 5, delta_m=0.0, edge=None, sigma_m=0.0)
    nodes[:10, 1] = 0.0
    model = PathModel(rng.uniform(0.8, 2.0, n), rng.uniform(-1.0, 1.5, n), edge)
    v = nodes.copy()
    v[:, 1] = nodes[:, 1] ** 2
    p, jac_u = model.evaluate_u(a, v)
    p_xyz, jac_xyz = model.evaluate(a, nodes)
    assert np.array_equal(p, p_xyz)
    assert np.array_equal(jac_u[..., 0::2], jac_xyz[..., 0::2])
    for k, hk in ((0, 1e-6), (1, 1e-6), (2, 1e-6)):
        lo = v.copy()
        hi = v.copy()
        hi[:, k] += hk
        if k == 1:  # forward difference (second order) at u = 0, central elsewhere
            lo[:, k] -= np.where(v[:, 1] > hk, hk, 0.0)
            h2 = v.copy()
            h2[:, k] += 2 * hk
            fd_c = (model.evaluate_u(a, hi)[0] - model.evaluate_u(a, lo)[0]) / (2 * hk)
            fd_f = (4 * model.evaluate_u(a, hi)[0] - model.evaluate_u(a, h2)[0] - 3 * p) / (2 * hk)
            fd = np.where((v[:, 1] > hk)[:, None], fd_c, fd_f)
        else:
            lo[:, k] -= hk
            fd = (model.evaluate_u(a, hi)[0] - model.evaluate_u(a, lo)[0]) / (2 * hk)
        assert np.allclose(jac_u[..., k], fd, rtol=1e-5, atol=1e-8), k
    # the u column is the y column divided by 2 y
    deep = nodes[:, 1] > 0
    assert np.allclose(jac_u[deep, :, 1] * 2 * nodes[deep, 1:2], jac_xyz[deep, :, 1],
                       rtol=1e-13, atol=0)


def test_batch_equals_single_problems_with_nonfinite_rows_and_model_arrays():
    """A batch mixing rows with a NaN range and an infinite start (returned as given:
    unconverged, 0 iterations, start unchanged), per-problem window heights and offsets, and
    rows finishing at different iterations (compaction of the working set): every finite row
    equals its problem solved alone to 1e-9 m, and the iteration counts are identical."""
    rng = np.random.default_rng(47)
    n = 30
    a, r, nodes = _random_problems(rng, n, 6, delta_m=0.0, edge=None, sigma_m=0.0)
    wh = rng.uniform(0.8, 2.0, n)
    de = rng.uniform(-0.5, 1.5, n)
    r = window_edge_path(a, nodes[:, None, :], window_height_m=wh[:, None],
                         delta_m=de[:, None]).length_m + 0.05 * rng.standard_normal((n, 6))
    sw = np.full(r.shape, 20.0)
    x0 = nodes + rng.normal(0.0, 1.0, nodes.shape)
    x0[5] = [1.0, -2.0, 3.0]
    r[5, 2] = np.nan
    x0[9, 2] = np.inf
    model = PathModel(wh, de, None)
    with np.errstate(invalid="ignore"):  # the model at an infinite start is NaN
        fit = levenberg_marquardt(a, r, sw, x0, model)
    for i in (5, 9):
        assert not fit.converged[i] and fit.iterations[i] == 0
        assert np.array_equal(fit.x_m[i], x0[i])
        assert not np.isfinite(fit.cost[i])
    rows = [i for i in range(n) if i not in (5, 9)]
    assert np.all(fit.converged[rows])
    assert len(set(fit.iterations[rows].tolist())) > 1
    for i in rows:
        one = levenberg_marquardt(a[i:i + 1], r[i:i + 1], sw[i:i + 1], x0[i:i + 1],
                                  PathModel(wh[i:i + 1], de[i:i + 1], None))
        assert np.allclose(one.x_m[0], fit.x_m[i], atol=1e-9, rtol=0)
        assert one.iterations[0] == fit.iterations[i]
