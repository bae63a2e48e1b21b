"""The tracker's learned family prior (``TrackerConfig.family_learned_links``;
:func:`diffpos.tracking.evidence.count_unexplained`, :func:`~diffpos.tracking.evidence.unexplained_log_odds`).

A node with four ranges gets the higher-order families only once its track has learned that its
channel has first arrivals out of the 18 mechanisms: epochs in which EVERY hypothesis misfits a
present link, more often than the path model predicts with its outlier prior and NIS tail.
References: hand-made learned arrays (the counting rule), the chi-square tail (the model's
rate), and the same tracker runs without the setting (bit for bit where it must not act).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import integrate
from scipy.stats import binom, chi2
from static_track import ANCHORS, NODE, first_arrivals, same, track, triple_bounce

from diffpos.tracking.evidence import (
    count_unexplained,
    model_unexplained_rate,
    unexplained_log_odds,
)
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import _family_gate


def _run(config, out_of_model: bool, epochs=30, seed=4):
    """Track the static node over ``epochs`` with its four ranges, the first one the triple
    bounce if ``out_of_model``: every epoch's state."""
    rho0 = first_arrivals(NODE, ANCHORS, 2)
    if out_of_model:
        rho0[0] = triple_bounce(ANCHORS[0], NODE, 2)
    return track(config, ANCHORS, rho0, epochs=epochs, seed=seed)


def test_model_rate_is_the_outlier_prior_and_the_chi_square_tail():
    """The model's rate of epochs with a misfit at the true state: every range an outlier
    (``outlier_weight``) or beyond ``nis_limit`` (chi-square, one degree of freedom)."""
    cfg = TrackerConfig()
    p = 1.0 - cfg.outlier_weight - chi2.sf(cfg.nis_limit, 1)
    got = model_unexplained_rate(np.array([4, 5, 8]), cfg)
    assert np.allclose(got, 1.0 - p ** np.array([4, 5, 8]), rtol=1e-12)


def test_log_odds_is_the_bayes_factor_of_a_uniform_rate_against_the_models():
    """Integer counts: the log Bayes factor equals the one integrated numerically, the
    binomial likelihood of ``u`` of ``r`` under a uniform rate over that under the model's
    rate (the binomial coefficients cancel); nothing counted is 0; one unexplained epoch of
    one favours the out-of-model channel, one of four and three of twenty do not, five of
    twenty do."""
    cfg = TrackerConfig()
    r0 = float(model_unexplained_rate(np.array([4]), cfg)[0])
    u = np.array([0.0, 1.0, 1.0, 3.0, 5.0, 12.0])
    r = np.array([0.0, 1.0, 4.0, 20.0, 20.0, 20.0])
    got = unexplained_log_odds(u, r, np.full(u.size, 4), cfg)
    for k in range(u.size):
        uni = integrate.quad(lambda q, k=k: binom.pmf(u[k], r[k], q), 0.0, 1.0,
                             epsabs=1e-14)[0]
        assert np.isclose(got[k], np.log(uni / binom.pmf(u[k], r[k], r0)), rtol=1e-8,
                          atol=1e-9), k
    assert got[0] == 0.0 and got[1] > 0 and got[2] < 0 and got[3] < 0 and got[4] > 0


def test_an_epoch_counts_only_when_every_hypothesis_misfits():
    """Hand-made last fits (``nis_limit`` 9, forgetting 0.95): node 0, every hypothesis misfits
    one present link (NIS 20 or an outlier) -> unexplained; node 1, one hypothesis fits every
    present link (its misfit is on an absent link) -> not; node 2, a hypothesis that has not
    fitted the link (NaN) is no misfit -> not; node 3, three ranges -> not counted at all."""
    cfg = TrackerConfig()
    f = cfg.link_forget
    fit = np.array([  # (node, hypothesis, link); the fifth link is absent this epoch
        [[20.0, 1.0, 1.0, 1.0, 1.0], [1.0, np.inf, 1.0, 1.0, 1.0]],
        [[20.0, 1.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, 1.0, 50.0]],
        [[20.0, 1.0, 1.0, 1.0, 1.0], [np.nan, 1.0, 1.0, 1.0, 1.0]],
        [[20.0, 1.0, 1.0, 1.0, 1.0], [1.0, np.inf, 1.0, 1.0, 1.0]],
    ])
    col = np.tile(np.arange(5), (4, 1))
    mask = np.ones((4, 5), bool)
    mask[:, 4] = False
    mask[3, 3] = False
    n_meas = mask.sum(axis=1)
    u0, r0 = np.full(4, 1.0), np.full(4, 2.0)
    u, r = count_unexplained(u0, r0, fit, col, mask, n_meas, cfg)
    assert np.allclose(u, [f * 1.0 + 1.0, f * 1.0, f * 1.0, 1.0])
    assert np.allclose(r, [f * 2.0 + 1.0, f * 2.0 + 1.0, f * 2.0 + 1.0, 2.0])


def test_gate_opens_four_ranges_only_where_learned():
    """:func:`_family_gate` with the default ``family_min_links`` 5: a misfit link of a node
    with four ranges is offered the families only when the node is ``learned``."""
    cfg = dataclasses.replace(TrackerConfig(), family_learned_links=4,
                              family_worst_min_links=0,  # the worst-link gate apart
                              family_few_links=0)  # and the three-range families
    fit = np.array([[[20.0, 1.0, 1.0, 1.0]]])
    lk = {"link_fit": fit, "link_all": np.full(fit.shape, 20.0), "link_out": np.zeros(fit.shape)}
    col = np.array([[0, 1, 2, 3]])
    n4 = np.array([4])
    assert not _family_gate(lk, col, n4, cfg, None, np.array([False])).any()
    assert _family_gate(lk, col, n4, cfg, None, np.array([True])).tolist() == [
        [[True, False, False, False]]]
    assert not _family_gate(lk, col, np.array([3]), cfg, None, np.array([True])).any()


def test_in_model_channel_learns_nothing_and_changes_nothing():
    """Four in-model ranges: no epoch is unexplained, so with ``family_learned_links=4`` (the
    default) the run equals the run without it (families from five ranges only) bit for
    bit."""
    assert TrackerConfig().family_learned_links == 4
    cfg = dataclasses.replace(TrackerConfig(), family_learned_links=0)
    ref = _run(cfg, False)
    got = _run(dataclasses.replace(cfg, family_learned_links=4), False)
    assert all(same(g, r) for g, r in zip(got, ref, strict=True))
    assert got[-1].redundant[0] > 10 and got[-1].unexplained[0] == 0.0
    assert ref[-1].redundant[0] == 0.0  # off: nothing counted


def test_out_of_model_link_opens_the_families_at_four_ranges():
    """Four ranges, one the triple bounce: the track's counts come to favour an out-of-model
    channel (by more than 20:1 within the first second), and with ``family_learned_links=4``
    the run differs from the one without it (which never offers a family to four ranges)."""
    cfg = dataclasses.replace(TrackerConfig(), family_learned_links=0)
    ref = _run(cfg, True)
    got = _run(dataclasses.replace(cfg, family_learned_links=4), True)
    odds = [unexplained_log_odds(s.unexplained, s.redundant, np.array([4]), cfg)[0] for s in got]
    assert max(odds[:10]) > 3.0
    assert not all(same(g, r) for g, r in zip(got, ref, strict=True))
