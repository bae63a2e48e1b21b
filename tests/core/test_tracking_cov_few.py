"""The published covariance's floor weights at nodes whose floor the families' SNR tested
(``TrackerConfig.cov_few_floors``; issue 34: the 95 % ellipsoid of the 3-UAV building).

The reference is written here from the definitions: the filter's floor marginals (both
modes), every log-odds divided by ``kappa = (1 + rho) / (1 - rho)`` (``rho`` the evidence's
lag-1 correlation), mixed towards uniform by the model doubt ("temper" only), the 95 %
credible set by a sort-and-add loop (the filter's probability for the floors outside it),
and the mean-square error of the published point as an explicit loop over the state's
hypotheses. A walker down the stairs (the stairs walk's four UAVs and path, seed 11) with
``family_few_links`` 4, so every epoch with three or four ranges is such a node.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from stairs_walk import arrivals
from stairs_walk import walk as _stairs_walk

from diffpos.scenario import default_scenario
from diffpos.tracking.evidence import model_doubt
from diffpos.tracking.state import TrackerConfig

SC = default_scenario()
B = SC.building
FEW = TrackerConfig(family_few_links=4, cov_few_floors="off")
MODEL = TrackerConfig(family_few_links=4, cov_few_floors="model")
TEMPER = TrackerConfig(family_few_links=4, cov_few_floors="temper")
PUBLISHED = ("position_m", "floor_index", "floor_probabilities", "status", "nis")


def _walk(cfg: TrackerConfig, epochs: int = 57):
    """Per epoch (output, state, number of ranges) of the stairs walk (tests/core/stairs_walk.py)."""
    _, draws = arrivals(epochs)
    return [(out, st, int(fa.detected[0].sum()))
            for (out, st), (_, fa) in zip(_stairs_walk(cfg, epochs), draws, strict=True)]


def _floors(st) -> np.ndarray:
    p = np.exp(st.log_prob[0])
    nf = p.size // 2
    return p[:nf] + p[nf:]


def _qualifies(st, prev, n_ranges: int) -> bool:
    """Three or four ranges, and the filter's most probable floor is the previous update's
    lead with at least 1/2 (not contested by the floors)."""
    pf = _floors(st)
    return (3 <= n_ranges <= 4 and int(np.argmax(pf)) == int(prev.lead_floor[0])
            and pf.max() >= 0.5)


def _reference_cov(out, st, rho: float, doubt: float) -> np.ndarray:
    """The published covariance under the setting's floor weights, from the definitions."""
    p, pf = np.exp(st.log_prob[0]), _floors(st)
    nf, k = pf.size, int(out.floor_index[0])
    kappa = (1.0 + rho) / (1.0 - rho)
    q = np.exp((np.log(pf) - np.log(pf).max()) / kappa)
    q = (1.0 - doubt) * q / q.sum() + doubt / nf
    w_floor, total = pf.copy(), 0.0  # the credible set keeps q, the others the filter's
    # (not renormalised: ``cov_published_floors`` "credible", session 28)
    for f in sorted(range(nf), key=lambda f: -q[f]):
        if total >= 0.95:
            break
        w_floor[f], total = q[f], total + q[f]
    pos = out.position_m[0]
    wb = p[[k, k + nf]] / p[[k, k + nf]].sum()
    ref = max(float(st.nis[0]), 1.0) * sum(wb[j] * st.cov[0, k + j * nf, :3, :3]
                                          for j in range(2))
    for hyp in range(2 * nf):
        fl = hyp % nf
        d = st.mean[0, hyp, :3] - pos
        ref = ref + w_floor[fl] * p[hyp] / (p[fl] + p[fl + nf]) * np.outer(d, d)
    for j in range(2):  # the best floor's mode spread for the mass not on it
        d = st.mean[0, k + j * nf, :3] - pos
        ref = ref + wb[j] * (1.0 - w_floor[k]) * np.outer(d, d)
    return ref


@pytest.mark.parametrize("cfg", [MODEL, TEMPER], ids=["model", "temper"])
def test_weights_against_the_definitions(cfg):
    """The publication (position, floor, probabilities, status) is "off"'s bit for bit at
    every epoch; at every epoch of a node the families' SNR tested and the floors did not
    contest the covariance is the reference (rtol 1e-9; "temper" with the model doubt of the
    state, :func:`model_doubt`) and narrower in height than "off"'s by > 10 % at some epoch;
    at every other epoch it is "off"'s bit for bit."""
    on, off = _walk(cfg), _walk(FEW)
    tested = narrower = other = 0
    for i in range(1, len(on)):
        (o1, s1, n_ranges), (o0, s0, _) = on[i], off[i]
        assert np.array_equal(s1.log_prob, s0.log_prob)
        for f in PUBLISHED:
            assert np.array_equal(getattr(o1, f), getattr(o0, f), equal_nan=True), f
        if int(o1.floor_index[0]) < 0:
            continue
        if _qualifies(s1, on[i - 1][1], n_ranges):
            d = (float(model_doubt(s1.log_prob, s1.link_out, s1.link_all, cfg,
                                   np.array([n_ranges]))[0])
                 if cfg.cov_few_floors == "temper" else 0.0)
            np.testing.assert_allclose(o1.covariance_m2[0],
                                       _reference_cov(o1, s1, cfg.floor_evidence_lag1_corr, d),
                                       rtol=1e-9, atol=1e-12)
            tested += 1
            narrower += int(o1.covariance_m2[0, 2, 2] < 0.9 * o0.covariance_m2[0, 2, 2])
        else:
            assert o1.covariance_m2[0].tobytes() == o0.covariance_m2[0].tobytes()
            other += 1
    assert tested >= 10 and narrower >= 1 and other >= 1, (tested, narrower, other)


@pytest.mark.parametrize("cfg", [MODEL, TEMPER], ids=["model", "temper"])
def test_inert_without_family_few_links(cfg):
    """Without ``family_few_links`` the setting changes nothing (the stairs walk, bit for
    bit)."""
    on = _stairs_walk(dataclasses.replace(cfg, family_few_links=0))
    off = _stairs_walk(dataclasses.replace(cfg, family_few_links=0, cov_few_floors="off"))
    for (o1, _), (o0, _) in zip(on, off, strict=True):
        assert o1.covariance_m2.tobytes() == o0.covariance_m2.tobytes()
