"""The published covariance under the published floor probabilities
(``TrackerConfig.cov_published_floors``, :func:`diffpos.tracking.state.floor_reweighted`,
:func:`diffpos.tracking.state.mixture_mse_cov`; issue 34: the 95 % ellipsoid's coverage).

The covariance of the published point is the mean-square error of that point under the
hypotheses' mixture. The reference is brute force: samples of the mixture (floor drawn with the
published probabilities, the mode with the filter's split within the floor, the position from
the hypothesis' Gaussian) and their second moment about the point.
"""

from __future__ import annotations

import numpy as np
from stairs_walk import walk as _walk

from diffpos.scenario import default_scenario
from diffpos.tracking.state import (
    TrackerConfig,
    credible_floor_weights,
    floor_reweighted,
    mixture_mse_cov,
)

SC = default_scenario()
B = SC.building


def _random_mixture(rng, n: int, nf: int):
    """``n`` nodes with ``nf`` floors (H = 2 nf): the hypotheses' means spread by metres, one
    random SPD covariance per node shared by its hypotheses, filter probabilities ``prob_h``
    and published floor probabilities ``q`` (a different vector)."""
    h = 2 * nf
    mean = rng.normal(0.0, 1.5, (n, h, 6))
    a = rng.normal(0.0, 0.3, (n, 3, 3))
    p3 = np.einsum("nij,nkj->nik", a, a) + 0.05 * np.eye(3)
    cov = np.zeros((n, h, 6, 6))
    cov[:, :, :3, :3] = p3[:, None]
    cov[:, :, 3:, 3:] = np.eye(3)
    prob_h = rng.dirichlet(np.full(h, 0.5), n)
    q = rng.dirichlet(np.full(nf, 1.0), n)
    return mean, cov, p3, prob_h, q


def test_floor_reweighted_marginals_and_mode_split():
    """Exact: the reweighted hypotheses' floor marginals are ``q`` and each floor's two modes
    keep the filter's ratio (rtol 1e-12); a floor without filter mass splits evenly."""
    rng = np.random.default_rng(3)
    _, _, _, prob_h, q = _random_mixture(rng, 200, 4)
    prob_h[0, [1, 5]] = 0.0
    w = floor_reweighted(prob_h, q)
    np.testing.assert_allclose(w[:, :4] + w[:, 4:], q, rtol=1e-12)
    ok = np.ones_like(q, bool)
    ok[0, 1] = False
    np.testing.assert_allclose((w[:, :4][ok] / (w[:, :4] + w[:, 4:])[ok]),
                               prob_h[:, :4][ok] / (prob_h[:, :4] + prob_h[:, 4:])[ok], rtol=1e-12)
    assert w[0, 1] == w[0, 5] == 0.5 * q[0, 1]


def test_mixture_mse_against_monte_carlo():
    """Random mixtures (seed 7, 6 nodes x 3 floors): with the best floor's two modes at one
    mean (no within-floor mode spread) and one covariance per node, ``mixture_mse_cov`` under
    ``floor_reweighted(prob_h, q)`` equals the second moment about the published point of
    400 000 samples of the mixture whose floors have the probabilities ``q`` (every entry
    within 4 Monte-Carlo standard errors + 1e-3 m^2); the untempered weights ``prob_h`` do not
    (some entry off by > 10 standard errors)."""
    rng = np.random.default_rng(7)
    n, nf, m = 6, 3, 400_000
    mean, cov, p3, prob_h, q = _random_mixture(rng, n, nf)
    best = np.argmax(q, axis=1)
    rows = np.arange(n)
    mean[rows, best + nf] = mean[rows, best]
    pos = mean[rows, best, :3]
    vf = np.ones(n)
    w_h = floor_reweighted(prob_h, q)
    got = mixture_mse_cov(mean, cov, w_h, pos, best, q[rows, best], vf)
    old = mixture_mse_cov(mean, cov, prob_h, pos, best, (prob_h[:, :nf] + prob_h[:, nf:])[
        rows, best], vf)
    far = 0
    for i in range(n):
        f = rng.choice(nf, m, p=q[i])
        share = prob_h[i, f] / (prob_h[i, f] + prob_h[i, f + nf])
        hyp = np.where(rng.random(m) < share, f, f + nf)
        x = mean[i, hyp, :3] + rng.multivariate_normal(np.zeros(3), p3[i], m)
        e = x - pos[i]
        outer = np.einsum("ki,kj->kij", e, e)
        ref, se = outer.mean(axis=0), outer.std(axis=0) / np.sqrt(m)
        assert np.all(np.abs(got[i] - ref) <= 4 * se + 1e-3), (i, got[i], ref)
        far += int(np.any(np.abs(old[i] - ref) > 10 * se))
    assert far >= 1


def test_tracker_publishes_the_published_floors_covariance():
    """The stairs walk (seed 11): with the setting the filter,
    position, floor, probabilities and status are the default's bit for bit; the covariance
    is the brute-force sum over the state's hypotheses (explicit loop) weighted with the
    published floor probabilities (rtol 1e-9); it differs from "off"'s at some epoch."""
    on = _walk(TrackerConfig(cov_published_floors="all"))
    off = _walk(TrackerConfig(cov_published_floors="off"))
    differs = 0
    for (o1, s1), (o0, s0) in zip(on, off, strict=True):
        assert np.array_equal(s1.log_prob, s0.log_prob)
        for f in ("position_m", "floor_index", "floor_probabilities", "status", "nis"):
            assert np.array_equal(getattr(o1, f), getattr(o0, f), equal_nan=True), f
        k = int(o1.floor_index[0])
        if k < 0:
            continue
        q = o1.floor_probabilities[0] / o1.floor_probabilities[0].sum()
        p = np.exp(s1.log_prob[0])
        nf = q.size
        pos = o1.position_m[0]
        wb = p[[k, k + nf]] / p[[k, k + nf]].sum()
        ref = max(float(s1.nis[0]), 1.0) * sum(
            wb[j] * s1.cov[0, k + j * nf, :3, :3] for j in range(2))
        for hyp in range(2 * nf):
            fl = hyp % nf
            w = q[fl] * p[hyp] / (p[fl] + p[fl + nf])
            if hyp % nf == k:  # the best floor's modes: full within-floor weight
                w = wb[hyp // nf]
            d = s1.mean[0, hyp, :3] - pos
            ref = ref + w * np.outer(d, d)
        np.testing.assert_allclose(o1.covariance_m2[0], ref, rtol=1e-9, atol=1e-12)
        differs += int(not np.allclose(o1.covariance_m2[0], o0.covariance_m2[0], rtol=1e-6))
    assert differs >= 1


def test_credible_floor_weights_by_brute_force():
    """Random published and filter floor vectors (seed 9, 300 x 5, some with a floor at
    >= 0.95): per row the floors taken one by one in descending published probability until
    their sum reaches 0.95 keep the published probability, the others get the filter's
    (exact); a row whose best floor has >= 0.95 keeps only that floor's."""
    rng = np.random.default_rng(9)
    q = rng.dirichlet(np.full(5, 0.4), 300)
    q[:40] = 0.01 / 4
    q[np.arange(40), rng.integers(0, 5, 40)] = 0.99
    p = rng.dirichlet(np.full(5, 0.2), 300)
    got = credible_floor_weights(q, p)
    for i in range(300):
        ref, total = p[i].copy(), 0.0
        for f in sorted(range(5), key=lambda f: -q[i, f]):
            if total >= 0.95:
                break
            ref[f], total = q[i, f], total + q[i, f]
        np.testing.assert_array_equal(got[i], ref)
        if i < 40:
            assert np.sum(got[i] == q[i]) == 1 or np.allclose(p[i], q[i])


def test_tracker_credible_keeps_the_publication_and_uses_the_credible_floors():
    """The stairs walk with "credible": position, floor, probabilities and status are the
    default's bit for bit; the covariance is "all"'s (rtol 1e-9) at every epoch whose
    credible set holds every floor (the same weights: at least one such epoch) and differs
    from it at some epoch whose set leaves floors out."""
    cr = _walk(TrackerConfig(cov_published_floors="credible"))
    al = _walk(TrackerConfig(cov_published_floors="all"))
    off = _walk(TrackerConfig(cov_published_floors="off"))
    same = differ = 0
    for (o2, _), (o1, _), (o0, _s0) in zip(cr, al, off, strict=True):
        for f in ("position_m", "floor_index", "floor_probabilities", "status", "nis"):
            assert np.array_equal(getattr(o2, f), getattr(o0, f), equal_nan=True), f
        k = int(o2.floor_index[0])
        if k < 0:
            continue
        q = o2.floor_probabilities[0] / o2.floor_probabilities[0].sum()
        if np.sort(q)[::-1][:-1].sum() < 0.95:  # every floor but the least is needed
            np.testing.assert_allclose(o2.covariance_m2[0], o1.covariance_m2[0], rtol=1e-9)
            same += 1
        else:
            differ += int(not np.allclose(o2.covariance_m2[0], o1.covariance_m2[0], rtol=1e-6))
    assert same >= 1 and differ >= 1
