"""``TrackerConfig.family_fit_links``: a link an extra family explains stays in the hypothesis'
fit as that family's path (docs/tracking_evidence.md "Session 31").

Independent references:

* every extra family's closed-form length (:func:`diffpos.tracking.families.graded_split`, the
  compiled kernel the tracker reads) against a brute-force construction written here: the
  anchor imaged in the ground, the node imaged across the recipe's planes one by one (last
  first), a diffraction point found by a dense search along the edge's line then a golden
  section (no Fermat / Keller formula); 1e-6 m, every family of ``max_order`` 3 and 4 that
  exists at random points of the paper building;
* the families' Jacobians with respect to the node position against central finite
  differences of those lengths (1e-5);
* :func:`diffpos.tracking.model.fold_ranges` (sequential Kalman updates, Joseph form)
  against the information-form batch update (1e-9);
* :func:`diffpos.tracking.model.family_refit` (the IEKF from the folded prior) against a
  Gauss-Newton MAP of the full cost written here with the family's EXACT (not linearised)
  length: posterior mean within 2 mm, covariance within 2 %, while the update that leaves the
  family link out is > 5 cm away;
* :func:`diffpos.tracking.families.family_log_weight` with ``fit`` returns the same change
  bit for bit (the default's replays are unchanged); off by default.

Rows independence with the setting on: tests/core/test_tracking_rows.py (``fit``).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from static_track import ANCHORS, NODE, SIGMA, B

from diffpos.paths.mechanisms import MECHANISMS, mechanism_set
from diffpos.paths.model import graded_paths
from diffpos.scenario import default_scenario
from diffpos.tracking.families import extra_families, family_log_weight, graded_split
from diffpos.tracking.links import Links
from diffpos.tracking.model import (
    SNR_SIGMA_DB,
    SNR_SPAN_DB,
    Selection,
    family_refit,
    fold_ranges,
    iekf,
)
from diffpos.tracking.state import TrackerConfig

RADIO = default_scenario().radio
NB = len(MECHANISMS)
OFFSET = np.array([0.2, -0.15, 0.1])


def _planes(floor: int) -> dict:
    """Axis and coordinate of every plane a recipe names, floor ``floor``."""
    zf = float(B.floor_z_m(floor))
    x0, x1 = B.edge_x_m
    return {"floor": (2, zf), "ceiling": (2, zf + B.floor_height_m), "back": (1, B.depth_m),
            "side x1": (0, x0), "side x2": (0, x1)}


def _edge(edge: str, floor: int) -> tuple[np.ndarray, np.ndarray]:
    """Start and end of a window edge's line (facade y = 0)."""
    lo, hi = (float(v) for v in B.window_z_m(floor))
    x0, x1 = B.edge_x_m
    if edge in ("upper", "lower"):
        z = hi if edge == "upper" else lo
        return np.array([x0, 0.0, z]), np.array([x1, 0.0, z])
    x = x0 if edge == "vertical x1" else x1
    return np.array([x, 0.0, lo]), np.array([x, 0.0, hi])


def _brute_length(recipe, anchor, node, floor: int) -> float:
    """A recipe's path length by explicit images and a searched diffraction point."""
    src = anchor.copy()
    if recipe.ground:
        src[2] = -src[2]
    obs = node.copy()
    pl = _planes(floor)
    for name in reversed(recipe.planes):
        axis, c = pl[name]
        obs[axis] = 2.0 * c - obs[axis]
    if recipe.kind != "diff":
        return float(np.linalg.norm(obs - src))
    p0, p1 = _edge(recipe.edge, floor)

    def f(t):
        e = p0 + np.multiply.outer(t, p1 - p0)
        return np.linalg.norm(e - src, axis=-1) + np.linalg.norm(e - obs, axis=-1)

    t = np.linspace(-2.0, 3.0, 2001)  # the edge's line, well beyond the segment (convex)
    k = int(np.argmin(f(t)))
    a, b = t[max(k - 1, 0)], t[min(k + 1, t.size - 1)]
    g = (np.sqrt(5.0) - 1.0) / 2.0
    for _ in range(90):  # golden section on the bracket
        c, d = b - g * (b - a), a + g * (b - a)
        if f(np.array(c)) < f(np.array(d)):
            b = d
        else:
            a = c
    return float(f(np.array(0.5 * (a + b))))


def _points(seed: int, n: int, floor: int = 2):
    """``n`` random (anchor, node) pairs: anchors outside the facade, nodes inside ``floor``."""
    rng = np.random.default_rng(seed)
    x0, x1 = B.edge_x_m
    zf = float(B.floor_z_m(floor))
    anchors = np.column_stack([rng.uniform(x0 - 10, x1 + 10, n), rng.uniform(-25, -3, n),
                               rng.uniform(0.5, B.floor_z_m(B.n_floors - 1) + 6, n)])
    nodes = np.column_stack([rng.uniform(x0 + 0.3, x1 - 0.3, n),
                             rng.uniform(0.5, B.depth_m - 0.3, n),
                             rng.uniform(zf + 0.2, zf + B.floor_height_m - 0.2, n)])
    return anchors, nodes


@pytest.mark.parametrize("order", [3, 4])
def test_family_lengths_equal_a_brute_force_construction(order):
    mset, _ = extra_families(order)
    anchors, nodes = _points(11 + order, 40)
    fl = np.full(len(nodes), 2)
    _, length, ok, _ = graded_split(nodes, anchors, fl, B, order, 0.0)
    assert ok.sum() >= 100  # many families exist at these points
    kinds = set()
    for q, f in zip(*np.nonzero(ok), strict=True):
        rec = mset.recipes[NB + f]
        ref = _brute_length(rec, anchors[q], nodes[q], 2)
        assert abs(length[q, f] - ref) < 1e-6, (rec.label, length[q, f], ref)
        kinds.add((rec.kind, rec.ground, len(rec.planes)))
    assert ("diff", False, 2) in kinds and ("spec", False, 3) in kinds


@pytest.mark.parametrize("order", [3, 4])
def test_family_jacobians_equal_finite_differences(order):
    anchors, nodes = _points(21 + order, 30)
    fl = np.full(len(nodes), 2)
    _, _, ok, jac = graded_split(nodes, anchors, fl, B, order, 0.0)
    h = 1e-5
    fd = np.empty(jac.shape)
    both = ok.copy()
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        _, lp, okp, _ = graded_split(nodes + d, anchors, fl, B, order, 0.0)
        _, lm, okm, _ = graded_split(nodes - d, anchors, fl, B, order, 0.0)
        fd[..., i] = (lp - lm) / (2 * h)
        both &= okp & okm
    assert both.sum() >= 80
    err = np.abs(fd - jac)[both]
    assert err.max() < 1e-5, err.max()
    # the Jacobian is a unit vector's reflection: |J| = 1 for every family
    assert np.allclose(np.linalg.norm(jac[both], axis=-1), 1.0, atol=1e-12)


def test_fold_ranges_equals_the_information_form():
    rng = np.random.default_rng(5)
    p_, m = 6, 3
    x0 = rng.normal(size=(p_, 6))
    a = rng.normal(size=(p_, 6, 6))
    p0 = np.einsum("pij,pkj->pik", a, a) + 0.1 * np.eye(6)
    at = x0[:, :3] + rng.normal(0.0, 0.2, (p_, 3))
    jac = rng.normal(size=(p_, m, 3))
    length = rng.uniform(20, 40, (p_, m))
    length[0, :] = np.nan  # no link used: the prior unchanged
    length[1, 1] = np.nan
    rho = length + rng.normal(0.0, 0.5, (p_, m))
    var = rng.uniform(0.01, 0.2, (p_, m))
    x, p = fold_ranges(x0, p0, np.nan_to_num(rho), length, jac, var, at)
    for i in range(p_):
        use = np.isfinite(length[i])
        h = np.zeros((use.sum(), 6))
        h[:, :3] = jac[i, use]
        z = rho[i, use] - length[i, use] + jac[i, use] @ at[i]  # = H x + e
        info = np.linalg.inv(p0[i]) + h.T @ np.diag(1.0 / var[i, use]) @ h
        ref_p = np.linalg.inv(info)
        ref_x = ref_p @ (np.linalg.solve(p0[i], x0[i]) + h.T @ (z / var[i, use]))
        assert np.allclose(x[i], ref_x, atol=1e-9, rtol=0)
        assert np.allclose(p[i], ref_p, atol=1e-9, rtol=0)
    assert np.array_equal(x[0], x0[0]) and np.allclose(p[0], p0[0], atol=1e-15)


def _refit_case():
    """Three links of the static node (paper building, floor 2): two in-model first arrivals
    fitted with their slot, the first link's range the length of an extra family that exists
    there (NaN-free, noise-free ranges); a prior 0.3 m off the node, 0.5 m wide."""
    mset, _ = extra_families(3)
    a = ANCHORS[[0, 1, 3]]
    n = NODE
    g = graded_paths(np.broadcast_to(n, (3, 3)), a, B, relax_m=0.0, floor=np.full(3, 2),
                     mechanisms=mset)
    ok = g.loose & np.isfinite(g.length_m)
    fam = [f for f in range(NB, len(mset)) if ok[0, f]]
    assert fam
    f = fam[int(np.argmin(g.length_m[0, fam]))]
    slots = [int(np.nanargmin(np.where(ok[i, :NB], g.length_m[i, :NB], np.nan)))
             for i in (1, 2)]
    rho = np.array([g.length_m[0, f], g.length_m[1, slots[0]], g.length_m[2, slots[1]]])
    links = Links.from_arrays(a[None], rho[None], np.full((1, 3), SIGMA), np.ones((1, 3), bool),
                              TrackerConfig().sigma_model_m)
    x0 = np.zeros((1, 1, 6))
    x0[0, 0, :3] = n + OFFSET
    p0 = np.diag([0.25, 0.25, 0.25, 0.5, 0.5, 0.1])[None, None]
    sel = Selection(slot=np.array([[[-1, *slots]]]), log_weight=np.zeros((1, 1, 3)),
                    nis=np.full((1, 1, 3), np.nan), extra_var=np.zeros((1, 1, 3)))
    return mset, f, slots, a, links, x0, p0, sel


def _map_reference(mset, f, slots, a, links, x0, p0, lin=None):
    """Gauss-Newton MAP of the full cost and its Laplace log-evidence: the Gaussian prior,
    the three ranges (the family on link 0, the slots on links 1-2), the vertical mode's
    flat height (``-log floor_height``, no height term) and no active box (the fit is inside
    the floor). The family's exact length, or with ``lin`` ``(L, J, at)`` the line
    ``L + J (x - at)``."""
    y0 = np.linalg.inv(p0[0, 0])
    var = links.var[0, 0]
    x = x0[0, 0].copy()
    for _ in range(50):
        g = graded_paths(np.broadcast_to(x[:3], (3, 3)), a, B, relax_m=1.0,
                         floor=np.full(3, 2), mechanisms=mset)
        k = [f, *slots]
        ln = np.array([g.length_m[i, k[i]] for i in range(3)])
        jn = np.array([g.jacobian[i, k[i]] for i in range(3)])
        if lin is not None:
            ln[0], jn[0] = lin[0] + lin[1] @ (x[:3] - lin[2]), lin[1]
        h = np.zeros((3, 6))
        h[:, :3] = jn
        info = y0 + h.T @ (h / var[:, None])
        grad = -y0 @ (x - x0[0, 0]) + h.T @ ((links.rho[0, 0] - ln) / var)
        step = np.linalg.solve(info, grad)
        x = x + step
        if np.abs(step).max() < 1e-12:
            break
    d = x - x0[0, 0]
    e = links.rho[0, 0] - ln
    log_z = (-np.log(B.floor_height_m) + np.sum(-0.5 * (np.log(var) + np.log(2 * np.pi)))
             - 0.5 * (d @ y0 @ d + np.sum(e * e / var))
             - 0.5 * (np.linalg.slogdet(info)[1] - np.linalg.slogdet(y0)[1]))
    return x, np.linalg.inv(info), log_z


def test_family_refit_equals_the_map_of_the_full_cost():
    mset, f, slots, a, links, x0, p0, sel = _refit_case()
    cfg = TrackerConfig()
    fl = np.array([[2]])
    level = np.array([[False]])  # the vertical mode: no height prior
    at = x0[:, 0, :3].copy()
    _, length, ok, jac = graded_split(at, a[:1], np.array([2]), B, 3, cfg.exist_margin_m)
    j = f - NB
    assert ok[0, j]
    fam_l = np.array([[length[0, j], np.nan, np.nan]])
    fam_j = np.zeros((1, 3, 3))
    fam_j[0, 0] = jac[0, j]
    x, p, ev, res = family_refit(x0, p0, links, fl, sel, fam_l, fam_j, links.var[:, 0], at, B,
                                 cfg, level)
    ref_x, ref_p, _ = _map_reference(mset, f, slots, a, links, x0, p0)
    assert np.abs(x[0, 0, :3] - ref_x[:3]).max() < 2e-3
    assert np.allclose(p[0, 0, :3, :3], ref_p[:3, :3], rtol=0.02, atol=1e-6)
    # the evidence: the joint's Laplace evidence (the family linearised at the prior, as the
    # refit does; its Jacobian's change over the 0.27 m to the fit moves the log-determinant
    # by ~0.01 nats) over the family link's predictive density at the prior (which its
    # log-weight carries in the tracker; here the log-weights are 0)
    jf = fam_j[0, 0]
    _, _, log_z = _map_reference(mset, f, slots, a, links, x0, p0, (fam_l[0, 0], jf, at[0]))
    s_f = jf @ p0[0, 0, :3, :3] @ jf + links.var[0, 0, 0]
    e_f = links.rho[0, 0, 0] - fam_l[0, 0] - jf @ (x0[0, 0, :3] - at[0])
    log_pred = -0.5 * (e_f * e_f / s_f + np.log(s_f) + np.log(2 * np.pi))
    assert abs(ev[0, 0] - (log_z - log_pred)) < 1e-6
    assert np.all(np.isfinite(res[0, 0, 1:])) and np.isnan(res[0, 0, 0])
    # without the family link the two other ranges leave the fit elsewhere, and wider
    x1, p1, _, _ = iekf(x0, p0, links, fl, sel, B, cfg, level)
    assert np.abs(x1[0, 0, :3] - ref_x[:3]).max() > 0.05
    assert np.trace(p1[0, 0, :3, :3]) > 1.5 * np.trace(p[0, 0, :3, :3])


def test_fit_returns_the_same_change_and_defaults_to_three():
    assert TrackerConfig().family_fit_links == 3  # default since 2026-12-08
    cfg = dataclasses.replace(TrackerConfig(), max_order=3, family_few_links=3)
    rng = np.random.default_rng(9)
    anchors, nodes = _points(31, 8)
    pos = nodes[:4]
    rho = rng.uniform(20, 45, (4, 3))
    links = Links.from_arrays(np.stack([anchors[4:7]] * 4), rho, np.full((4, 3), SIGMA),
                              np.ones((4, 3), bool), cfg.sigma_model_m,
                              snr_db=rng.uniform(0, 20, (4, 3)), radio=RADIO)
    args = (pos, np.broadcast_to(0.04 * np.eye(3), (4, 3, 3)), links, np.arange(4),
            np.full(4, 2), np.ones((4, 3), bool), B, cfg)
    kw = {"snr_sigma_db": SNR_SIGMA_DB, "snr_span_db": SNR_SPAN_DB}
    w0 = family_log_weight(*args, **kw)
    w1, (length, jac, spread) = family_log_weight(*args, fit=True, **kw)
    assert np.array_equal(w0, w1)
    assert length.shape == (4, 3) and jac.shape == (4, 3, 3) and spread.shape == (4, 3)
    # explained (finite) only where the families' part beats the uniform outlier's
    assert np.all(np.isfinite(length) <= (w1 > np.log(2.0)))
    assert 0 < np.isfinite(length).sum() < length.size
    assert np.all(spread >= 0.0)
    assert mechanism_set(3) is not None
