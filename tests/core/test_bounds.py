"""Fisher information, PEB / z bound and identifiability against independent references.

- Monte-Carlo: a Gauss-Newton ML estimator (written here, started at the truth) on the
  diffraction model with tiny noise is efficient, so its sample covariance must match
  ``J_alpha^-1``.
- The FIM equals ``G^T W G`` with ``G`` from central finite differences of path lengths computed
  by brute-force Fermat minimisation (not by the model's own Jacobian).
- Closed forms for diagonal FIMs, the paper's non-identifiable example (Corollary 3 discussion),
  and the expected physical differences between the diffraction and LoS models.
"""

from __future__ import annotations

import numpy as np
import pytest

from diffpos.bounds import (
    bounds_from_fim,
    fisher_information,
    identifiability,
    path_jacobian,
    position_error_bound,
)
from diffpos.geometry import diffraction_point, window_edge_path

#: the paper's anchors (Table of simulation parameters; anchor 2 at y = -15, outside)
ANCHORS = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.0]])
W = 1.5


def _gauss_newton(anchors, r, start, sig, n_iter=6, **kw):
    """Weighted Gauss-Newton on the diffraction model, vectorised over K measurement sets.

    r : (K, M) ranges, start : (3,), sig : (M,). Returns (K, 3) estimates.
    """
    est = np.broadcast_to(start, (r.shape[0], 3)).copy()
    wgt = 1.0 / sig**2
    for _ in range(n_iter):
        path = window_edge_path(anchors[None], est[:, None], window_height_m=W, **kw)
        g = path.jacobian  # (K, M, 3)
        res = r - path.length_m
        a = np.einsum("kmi,m,kmj->kij", g, wgt, g)
        b = np.einsum("kmi,m,km->ki", g, wgt, res)
        est = est + np.linalg.solve(a, b[..., None])[..., 0]
    return est


@pytest.mark.parametrize(
    "node", [np.array([3.0, 6.0, 7.5]), np.array([-12.0, 15.0, 13.5]), np.array([18.0, 2.0, 4.5])]
)
def test_fim_matches_monte_carlo_covariance_of_efficient_estimator(node) -> None:
    rng = np.random.default_rng(20)
    sig = np.array([2e-3, 1e-3, 1.5e-3, 3e-3])  # tiny: the model is linear at this scale
    k = 4000
    truth = window_edge_path(ANCHORS, node, window_height_m=W).length_m
    r = truth + rng.normal(size=(k, 4)) * sig
    est = _gauss_newton(ANCHORS, r, node, sig)
    err = est - node
    cov = err.T @ err / k  # the ML estimator is unbiased to first order; truth is known
    b = position_error_bound(ANCHORS, node, sig, W)
    # whitened covariance L^T C L (J_alpha = L L^T) must be the identity
    chol = np.linalg.cholesky(b.fim)
    white = chol.T @ cov @ chol
    # sampling std of the entries is ~sqrt(2/k) = 0.022 on the diagonal, 0.016 off it
    np.testing.assert_allclose(white, np.eye(3), atol=0.1)
    np.testing.assert_allclose(np.sqrt(np.trace(cov)), b.peb_m, rtol=0.1)
    np.testing.assert_allclose(np.sqrt(cov[2, 2]), b.z_bound_m, rtol=0.1)


def _brute_force_length(anchors, node, w=W, edge_half_m=1e3):
    """Upper-edge diffraction length from diffraction_point on a long explicit edge."""
    ze = node[..., 2] + 0.5 * w
    p0 = np.stack([np.full_like(ze, -edge_half_m), np.zeros_like(ze), ze], axis=-1)
    p1 = np.stack([np.full_like(ze, edge_half_m), np.zeros_like(ze), ze], axis=-1)
    return diffraction_point(
        anchors, node[..., None, :], p0[..., None, :], p1[..., None, :]
    ).length_m


def test_fim_equals_finite_difference_fim() -> None:
    rng = np.random.default_rng(21)
    nodes = np.stack(
        [rng.uniform(-19, 19, 200), rng.uniform(0.5, 19, 200), rng.uniform(4, 16, 200)], 1
    )
    sig = np.array([0.01, 0.02, 0.015, 0.03])
    h = 1e-5
    g = np.stack(
        [
            (
                _brute_force_length(ANCHORS, nodes + h * e)
                - _brute_force_length(ANCHORS, nodes - h * e)
            )
            / (2 * h)
            for e in np.eye(3)
        ],
        axis=-1,
    )  # (N, M, 3)
    fim_fd = np.einsum("nmi,m,nmj->nij", g, 1 / sig**2, g)
    b = position_error_bound(ANCHORS, nodes, sig, W)
    np.testing.assert_allclose(b.fim, fim_fd, rtol=1e-5)
    inv_fd = np.linalg.inv(fim_fd)
    np.testing.assert_allclose(b.peb_m, np.sqrt(np.trace(inv_fd, axis1=1, axis2=2)), rtol=1e-5)
    np.testing.assert_allclose(b.z_bound_m, np.sqrt(inv_fd[:, 2, 2]), rtol=1e-5)


def test_bounds_from_fim_closed_form() -> None:
    rng = np.random.default_rng(22)
    d = rng.uniform(0.5, 1e4, size=(50, 3))
    fim = np.zeros((50, 3, 3))
    fim[:, [0, 1, 2], [0, 1, 2]] = d
    b = bounds_from_fim(fim)
    np.testing.assert_allclose(b.peb_m, np.sqrt((1 / d).sum(axis=1)), rtol=1e-13)
    np.testing.assert_allclose(b.z_bound_m, 1 / np.sqrt(d[:, 2]), rtol=1e-13)
    np.testing.assert_allclose(b.axis_bounds_m, 1 / np.sqrt(d), rtol=1e-13)
    # rotation invariance of the PEB (trace), not of the z bound
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rot = bounds_from_fim(q @ fim @ q.T)
    np.testing.assert_allclose(rot.peb_m, b.peb_m, rtol=1e-10)
    # singular and near-singular FIMs are flagged and get infinite bounds
    bad = bounds_from_fim(np.diag([1.0, 1.0, 0.0]))
    assert not bad.identifiable and np.isinf(bad.peb_m) and np.isinf(bad.z_bound_m)
    assert not bounds_from_fim(np.diag([1.0, 1.0, 1e-13])).identifiable
    assert bounds_from_fim(np.diag([1.0, 1.0, 1e-11])).identifiable
    assert not bounds_from_fim(np.zeros((3, 3))).identifiable


def test_bounds_from_fim_fast_and_slow_paths_agree_with_lapack() -> None:
    """Closed-form inverse (fast path) and eigvalsh fallback vs numpy.linalg on hard FIMs."""
    rng = np.random.default_rng(26)
    n = 3000
    q, _ = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    scale = 10 ** rng.uniform(-6, 8, n)
    lam = scale[:, None] * 10 ** -np.stack(
        [np.zeros(n), rng.uniform(0, 14, n), rng.uniform(0, 14, n)], axis=1
    )
    fim = np.einsum("nij,nj,nkj->nik", q, lam, q)
    fim = 0.5 * (fim + np.swapaxes(fim, 1, 2))
    # rank-1 and rank-2 FIMs from 1 or 2 Jacobian rows: never identifiable
    g = rng.normal(size=(400, 2, 3))
    low = np.concatenate(
        [
            np.einsum("ni,nj->nij", g[:200, 0], g[:200, 0]),
            np.einsum("nmi,nmj->nij", g[200:], g[200:]),
        ]
    )
    b = bounds_from_fim(np.concatenate([fim, low]))
    assert not b.identifiable[n:].any() and np.isinf(b.peb_m[n:]).all()
    eig = np.linalg.eigvalsh(fim)
    log_ratio = np.log10(eig[:, 0] / eig[:, -1])
    clear = np.abs(log_ratio + 12.0) > 0.3  # away from the 1e12 threshold itself
    ok_ref = log_ratio > -12.0
    np.testing.assert_array_equal(b.identifiable[:n][clear], ok_ref[clear])
    assert 0.2 < ok_ref.mean() < 0.9
    ok = b.identifiable[:n]
    inv = np.linalg.inv(fim[ok])
    cond = 10 ** -log_ratio[ok]
    rel = np.abs(b.peb_m[:n][ok] - np.sqrt(np.trace(inv, axis1=1, axis2=2))) / b.peb_m[:n][ok]
    assert (rel < 1e-13 * cond + 1e-12).all()
    rel_z = np.abs(b.z_bound_m[:n][ok] - np.sqrt(inv[:, 2, 2])) / b.z_bound_m[:n][ok]
    assert (rel_z < 1e-13 * cond + 1e-12).all()


# ---------------------------------------------------------------------- identifiability

#: the paper's example: three anchors, all at x_a = 0
ANCHORS_X0 = np.array([[0.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0]])


@pytest.mark.parametrize("model", ["diffraction", "los"])
def test_papers_example_not_identifiable_in_x(model) -> None:
    node = np.array([0.0, 6.0, 7.5])
    jac = path_jacobian(ANCHORS_X0, node, model=model, window_height_m=W)
    np.testing.assert_array_equal(jac[:, 0], 0.0)  # dp_j/dx_n = 0 for every anchor
    res = identifiability(jac, np.full(3, 0.01))
    assert not res.identifiable and res.rank == 2 and np.isinf(res.condition)
    np.testing.assert_allclose(res.weakest_direction, [1.0, 0.0, 0.0], atol=1e-12)
    msg = res.message[0]
    assert msg.startswith("not identifiable: rank 2 < 3") and "about x" in msg, msg
    assert "1 of 1 geometries not identifiable" in res.summary()
    b = position_error_bound(ANCHORS_X0, node, 0.01, W, model=model)
    assert not b.identifiable and np.isinf(b.peb_m) and np.isinf(b.z_bound_m)


def test_papers_example_near_and_away_from_the_symmetry_plane() -> None:
    nodes = np.array([[1e-7, 6.0, 7.5], [3.0, 6.0, 7.5]])
    jac = path_jacobian(ANCHORS_X0, nodes, window_height_m=W)
    res = identifiability(jac, np.full(3, 0.01))
    assert res.identifiable.tolist() == [False, True]
    assert res.rank.tolist() == [3, 3]
    assert res.message[0].startswith("ill-conditioned") and "mostly x" in res.message[0]
    assert res.message[1].startswith("identifiable")
    # moving one anchor off x = 0 breaks the symmetry even for the node at x_n = 0
    moved = ANCHORS_X0.copy()
    moved[2, 0] = 5.0
    assert bool(position_error_bound(moved, [0.0, 6.0, 7.5], 0.01, W).identifiable)


def test_fewer_than_three_anchors_is_never_identifiable() -> None:
    rng = np.random.default_rng(23)
    nodes = np.stack(
        [rng.uniform(-19, 19, 100), rng.uniform(0.5, 19, 100), rng.uniform(4, 16, 100)], 1
    )
    jac = path_jacobian(ANCHORS[:2], nodes, window_height_m=W)
    res = identifiability(jac, np.full(2, 0.01))
    assert not res.identifiable.any() and (res.rank <= 2).all()
    # the mask and sigma = inf drop links the same way
    full = path_jacobian(ANCHORS, nodes, window_height_m=W)
    masked = identifiability(full, np.full(4, 0.01), mask=[True, True, False, False])
    inf_sig = identifiability(full, [0.01, 0.01, np.inf, np.inf])
    assert not masked.identifiable.any() and not inf_sig.identifiable.any()
    np.testing.assert_array_equal(masked.rank, res.rank)


def test_identifiability_agrees_with_bounds() -> None:
    rng = np.random.default_rng(24)
    nodes = np.stack(
        [rng.uniform(-19, 19, 2000), rng.uniform(0.5, 19, 2000), rng.uniform(4, 16, 2000)], 1
    )
    anchors = ANCHORS_X0
    sig = np.full(3, 0.01)
    b = position_error_bound(anchors, nodes, sig, W, max_condition=30.0)
    res = identifiability(path_jacobian(anchors, nodes, window_height_m=W), sig, max_condition=30.0)
    assert 0.05 < res.identifiable.mean() < 0.95, "both verdicts are exercised"
    np.testing.assert_array_equal(b.identifiable, res.identifiable)
    # the bound along the weakest direction is the largest eigen-bound of the CRLB
    ok = res.identifiable
    np.testing.assert_allclose(
        res.weakest_sigma_m[ok], np.sqrt(np.linalg.eigvalsh(b.crlb_m2[ok])[:, -1]), rtol=1e-8
    )


# ---------------------------------------------------------------------- model comparison


def test_los_and_diffraction_fims_differ_as_expected() -> None:
    sig = np.full(4, 0.01)
    depths = np.array([0.01, 2.0, 20.0])
    nodes = np.stack([np.full(3, 3.0), depths, np.full(3, 7.5)], axis=1)
    dif = position_error_bound(ANCHORS, nodes, sig, W, model="diffraction")
    los = position_error_bound(ANCHORS, nodes, sig, W, model="los")
    # LoS Jacobian rows are unit vectors; diffraction rows are not (|g|^2 = 1 - (w/2)^2/IPL^2
    # + ((z_e - z_a)/OPL)^2)
    g_los = path_jacobian(ANCHORS, nodes, model="los")
    g_dif = path_jacobian(ANCHORS, nodes, window_height_m=W)
    np.testing.assert_allclose(np.linalg.norm(g_los, axis=-1), 1.0, rtol=1e-14)
    assert np.abs(np.linalg.norm(g_dif, axis=-1) - 1.0).max() > 0.05
    # y information of the diffraction model comes only from the inside path (dp/dy_n =
    # y_n/IPL): it vanishes for a node at the window plane, unlike LoS
    assert dif.fim[0, 1, 1] < 1e-3 * los.fim[0, 1, 1]
    # z information comes from the outside path, (z_e - z_a)/OPL, so going deeper inside does
    # not dilute it; for LoS the elevation angle (and the z information) shrinks with depth
    assert dif.z_bound_m[2] <= 1.05 * dif.z_bound_m[1]
    assert los.z_bound_m[2] >= 1.5 * los.z_bound_m[1]
    assert dif.z_bound_m[2] < 0.5 * los.z_bound_m[2]


# ---------------------------------------------------------------------- broadcasting


def test_position_error_bound_broadcasting() -> None:
    rng = np.random.default_rng(25)
    nodes = np.stack(
        [rng.uniform(-19, 19, 60), rng.uniform(0.5, 19, 60), rng.uniform(4, 16, 60)], 1
    )
    sig_nm = rng.uniform(0.005, 0.05, size=(60, 4))
    b = position_error_bound(ANCHORS, nodes, sig_nm, W, 0.3, edge_x_m=(-20.0, 20.0))
    assert b.peb_m.shape == (60,) and b.z_bound_m.shape == (60,)
    assert b.crlb_m2.shape == (60, 3, 3) and b.fim.shape == (60, 3, 3)
    for i in range(0, 60, 7):  # one node at a time gives the same numbers
        one = position_error_bound(ANCHORS, nodes[i], sig_nm[i], W, 0.3, edge_x_m=(-20.0, 20.0))
        assert one.peb_m.shape == ()
        assert float(one.peb_m) == pytest.approx(b.peb_m[i], rel=1e-12)
        assert float(one.z_bound_m) == pytest.approx(b.z_bound_m[i], rel=1e-12)
    # grid of nodes (A, B, 3) with one sigma per anchor (M,)
    grid = nodes.reshape(6, 10, 3)
    g = position_error_bound(ANCHORS, grid, np.full(4, 0.01), W)
    assert g.peb_m.shape == (6, 10)
    flat = position_error_bound(ANCHORS, nodes, np.full(4, 0.01), W)
    np.testing.assert_allclose(g.peb_m.ravel(), flat.peb_m, rtol=1e-14)
    # per-node anchor sets (N, M, 3) with nodes (N, 3)
    per = position_error_bound(np.broadcast_to(ANCHORS, (60, 4, 3)), nodes, np.full(4, 0.01), W)
    np.testing.assert_allclose(per.peb_m, flat.peb_m, rtol=1e-14)


def test_bad_inputs_name_the_argument() -> None:
    with pytest.raises(ValueError, match="sigmas_m must be > 0"):
        position_error_bound(ANCHORS, [0.0, 5.0, 7.5], [0.01, 0.0, 0.01, 0.01], W)
    with pytest.raises(ValueError, match="sigmas_m"):
        position_error_bound(ANCHORS, [0.0, 5.0, 7.5], [0.01, 0.01], W)
    with pytest.raises(ValueError, match="anchors_m"):
        position_error_bound(ANCHORS[:, :2], [0.0, 5.0, 7.5], 0.01, W)
    with pytest.raises(ValueError, match="model"):
        position_error_bound(ANCHORS, [0.0, 5.0, 7.5], 0.01, W, model="nlos")
    with pytest.raises(ValueError, match="jacobian"):
        fisher_information(np.zeros((4, 2)), 0.01)


# ---------------------------------------------------------------------- `diffpos bounds`


@pytest.mark.slow  # matplotlib import + 5 PNGs: ~2 s idle, more on a loaded machine
def test_cli_bounds_writes_csv_and_pngs(tmp_path, capsys) -> None:
    import csv

    from diffpos_services.cli import main as cli

    out = tmp_path / "tmp"
    assert cli.main(["bounds", "--grid-step-m", "2", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "Position error bound per floor" in text and "z-axis bound" in text
    for k in range(1, 6):
        png = out / f"floor{k}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = list(csv.DictReader((out / "bounds.csv").open()))
    # the paper scenario's building (22.5 m deep, floors at z = 4, 7, ... 16 m)
    assert len(rows) == 5 * 19 * 11  # x = -18..18, y = 0.5..20.5 step 2, 5 floors
    assert {r["z_m"] for r in rows} == {"5.500", "8.500", "11.500", "14.500", "17.500"}
    # the CSV numbers are the core's numbers for the same sigmas
    r0 = rows[0]
    node = [float(r0["x_m"]), float(r0["y_m"]), float(r0["z_m"])]
    sig = [float(r0[f"sigma_m_a{j}"]) for j in range(1, 5)]
    b = position_error_bound(ANCHORS, node, sig, W, edge_x_m=(-20.0, 20.0))
    assert float(r0["peb_m"]) == pytest.approx(float(b.peb_m), rel=1e-5)
    assert float(r0["z_bound_m"]) == pytest.approx(float(b.z_bound_m), rel=1e-5)
    assert all(r["identifiable"] == "1" for r in rows)


def test_cli_bounds_papers_counter_example_and_errors(tmp_path, capsys) -> None:
    from diffpos_services.cli import main as cli

    out = tmp_path / "x0"
    args = ["bounds", "--grid-step-m", "2", "--no-plots", "--out", str(out)]
    assert cli.main([*args, "--anchors", "0,-20,1;0,-15,0;0,-7,4"]) == 0
    text = " ".join(capsys.readouterr().out.split())  # undo rich's line wrapping
    assert "5.3 %" in text  # the x = 0 column: 1 of 19 per floor
    assert "floor 1: 11 node(s) not identifiable, e.g. at (0, 0.5, 5.5) m" in text
    assert "no information about x" in text
    assert cli.main([*args, "--anchors", "-15,-20,1;0,15,0;0,-7,4"]) == 2
    err = capsys.readouterr().err
    assert "--anchors" in err and "inside the building" in err and "y < 0" in err
    assert cli.main([*args, "--anchors", "1,2"]) == 2
    assert "expected three numbers" in capsys.readouterr().err
    assert cli.main([*args, "--grid-step-m", "-1"]) == 2
    assert "--grid-step-m" in capsys.readouterr().err
    assert cli.main([*args, "--bandwidth-hz", "0"]) == 2
    assert "--bandwidth-hz: 0 is out of range" in capsys.readouterr().err


def test_cli_link_budget_fixed_and_utd() -> None:
    import dataclasses

    from diffpos.bound_maps import BoundMapSettings, compute, path_gain_db
    from diffpos.scenario import default_scenario

    paper = default_scenario()
    scenario = dataclasses.replace(
        paper, building=dataclasses.replace(paper.building, n_floors=2)
    )
    res = compute(scenario, BoundMapSettings(grid_step_m=4.0))
    r = res[1]
    xx, yy = np.meshgrid(r.x_m, r.y_m)
    nodes = np.stack([xx, yy, np.full_like(xx, 8.5)], axis=-1)
    path = window_edge_path(ANCHORS, nodes[..., None, :], window_height_m=W, edge_x_m=(-20, 20))
    lam = 299_792_458.0 / 28e9
    fspl_gain = 20 * np.log10(lam / (4 * np.pi * path.length_m))
    kt_b = 10 * np.log10(1.380649e-23 * 300 * 400e6 / 1e-3)
    np.testing.assert_allclose(r.snr_db, 30.0 + fspl_gain - 20.0 + 20.0 - kt_b, atol=1e-9)
    np.testing.assert_allclose(
        r.sigma_m, 299_792_458.0 / np.sqrt(8 * np.pi**2 * 400e6**2 * 10 ** (r.snr_db / 10))
    )
    # UTD: the diffracted field is weaker than free space over the same unfolded length
    utd = path_gain_db(paper, BoundMapSettings(diffraction="utd"), ANCHORS, nodes, path.length_m)
    assert utd.shape == fspl_gain.shape and np.isfinite(utd).all()
    assert (utd < fspl_gain - 10.0).all() and (utd > fspl_gain - 60.0).all()


def test_docstring_examples() -> None:
    import doctest

    import diffpos.bounds

    result = doctest.testmod(diffpos.bounds, raise_on_error=False)
    assert result.attempted >= 3 and result.failed == 0
