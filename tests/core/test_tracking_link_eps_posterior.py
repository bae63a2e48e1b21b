"""``TrackerConfig.link_eps_posterior`` (0, off by default): at a node with at least that many
present ranges, every hypothesis' outlier component of a link uses the larger of its own
learned outlier weight and the node's posterior mean of its hypotheses' weights
(``sum_k p_k eps_k``); the inlier weight stays its own
(docs/tracking_evidence.md "Session 29: the model-averaged outlier weight").

Why: learned per hypothesis, the weight rewards a wrong floor for its own history of calling a
link an outlier (Session 28); the node's LARGEST weight (``link_eps_node``) shared it, but the
largest came mostly from hypotheses without probability that call every link an outlier at
``link_outlier_max``, which made every outlier cheap on every floor. The posterior mean is
lent by the hypotheses the node believes. References: the learned weight's Beta posterior
mean computed here from the counts (``eps = clip((e0 S + out) / (S + all), e0, eps_max)``), a
loop over nodes, hypotheses and links; the static node of tests/core/static_track.py with one
range 3 m long (a first arrival out of the model).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from learned_counts import beta_eps, link_inputs_at, long_link_states, weights_from_counts
from static_track import ANCHORS, B

from diffpos.tracking.evidence import node_weights, posterior_weights
from diffpos.tracking.state import TrackerConfig


def _weights(n_all, n_out):
    """Learned weights (n, H, L, 2) from the counts (link 2 of node 2 never learned), and the
    counts' reference eps (n, H, L)."""
    return weights_from_counts(n_all, n_out)[1:]


def test_posterior_weights_against_the_model_average_of_the_reference_eps():
    """Inlier weights unchanged (bit for bit); every outlier component of a node used is its
    own plus ``log max(eps_h, sum_k p_k eps_k) - log eps_h`` (1e-12 nats), ``p`` the
    normalised probabilities, ``eps`` the reference Beta means of the counts; a node not used
    keeps its weights bit for bit."""
    for seed in (0, 1, 2):
        rng = np.random.default_rng(seed)
        n_all = rng.uniform(0.0, 20.0, (3, 4, 3))
        w, ref = _weights(n_all, n_all * rng.uniform(0.0, 1.0, (3, 4, 3)))
        assert np.allclose(w[..., 0], np.log1p(-ref), rtol=0, atol=1e-12)
        log_prob = rng.normal(0.0, 3.0, (3, 4)) - 10.0  # unnormalised on purpose
        log_prob[1, 2] = -np.inf  # a hypothesis with no probability
        use = np.array([True, True, False])
        got = posterior_weights(w, log_prob, use)
        assert np.array_equal(got[..., 0], w[..., 0])
        assert np.array_equal(got[2], w[2])  # a node not used: unchanged
        assert np.array_equal(posterior_weights(w, log_prob)[:2], got[:2])
        for i in range(2):
            p = [np.exp(v) for v in log_prob[i]]
            p = [v / sum(p) for v in p]
            for m in range(3):
                mean = sum(p[k] * ref[i, k, m] for k in range(4))
                for k in range(4):
                    want = w[i, k, m, 1] + np.log(max(ref[i, k, m], mean)) - np.log(ref[i, k, m])
                    assert abs(got[i, k, m, 1] - want) < 1e-12


def test_a_hypothesis_without_probability_lends_no_weight():
    """One hypothesis of each node calls every link an outlier (eps at ``link_outlier_max``)
    at probability 1e-9: the posterior mean moves the others' outlier components by less than
    1e-6 nats, while the node's largest weight (``link_eps_node``) lends them its full
    ``log(eps_max / eps_h)``; with that hypothesis believed (probability 1 - 1e-9) every
    other hypothesis' outlier component takes its weight (within 1e-6 nats)."""
    cfg = TrackerConfig()
    n_all = np.full((3, 4, 3), 40.0)
    n_out = np.zeros((3, 4, 3))
    n_out[:, 3] = 40.0
    w, ref = _weights(n_all, n_out)
    known = np.ones((3, 3), bool)
    known[2, 2] = False  # node 2's link 2: never learned
    assert np.allclose(ref[:, 3][known], cfg.link_outlier_max)
    for believed, moved in ((False, False), (True, True)):
        log_prob = np.log(np.where(np.arange(4) == 3, 1e-9, 1.0))[None].repeat(3, axis=0)
        if believed:
            log_prob = np.log(np.where(np.arange(4) == 3, 1.0 - 1e-9, 1e-9 / 3))[None].repeat(3, 0)
        got = posterior_weights(w, log_prob)[:, :3, :, 1] - w[:, :3, :, 1]
        full = np.log(ref[:, 3:4] / ref[:, :3])
        learned = np.broadcast_to(known[:, None, :], full.shape)
        assert np.all(full[learned] > 3.0) and np.all(full[~learned] == 0.0)
        if moved:
            assert np.allclose(got[learned], full[learned], rtol=0, atol=1e-6)
        else:
            assert np.all(np.abs(got) < 1e-6)
        largest = node_weights(w)[:, :3, :, 1] - w[:, :3, :, 1]
        assert np.allclose(largest[learned], full[learned], rtol=0, atol=1e-12)


def test_tracker_uses_the_model_averaged_weight():
    """The static node with one out-of-model range: with the setting, at every epoch, every
    hypothesis' inlier weight of a link is ``log(1 - eps_h)`` and its outlier component is
    the default's plus ``log max(eps_h, sum_k p_k eps_k) - log eps_h`` (1e-9 nats), from the
    previous state's counts and probabilities; the setting raises some hypothesis' outlier
    component of the long link by > 0.1 nats (not idle) and the tracked runs differ. With a
    count above the node's four ranges the weights are the default's. Off by default."""
    assert TrackerConfig().link_eps_posterior == 0
    base = TrackerConfig()
    cfg = dataclasses.replace(base, link_eps_posterior=4)
    above = dataclasses.replace(base, link_eps_posterior=5)
    rho0, states = long_link_states(cfg)
    hs = 2 * B.n_floors
    raised = 0.0
    for k in range(1, len(states)):
        prev = states[k - 1]
        got = link_inputs_at(prev, rho0, k, cfg)
        off = link_inputs_at(prev, rho0, k, base)[4][0]
        assert np.array_equal(link_inputs_at(prev, rho0, k, above)[4][0], off)
        w, col = got[4][0], got[1][0]  # (H, M, 2), (M,)
        p = np.exp(prev.log_prob[0] - np.max(prev.log_prob[0]))
        p = p / p.sum()
        for m in range(len(ANCHORS)):
            ref = [beta_eps(prev.link_out[0, h, col[m]], prev.link_all[0, h, col[m]], cfg)
                   if col[m] >= 0 else cfg.outlier_weight for h in range(hs)]
            mean = sum(p[h] * ref[h] for h in range(hs))
            for h in range(hs):
                assert abs(w[h, m, 0] - np.log1p(-ref[h])) < 1e-9
                lift = np.log(max(ref[h], mean)) - np.log(ref[h])
                assert abs(w[h, m, 1] - off[h, m, 1] - lift) < 1e-9
                if m == 1:
                    raised = max(raised, lift)
    assert raised > 0.1
    _, a = long_link_states(base)
    _, b = long_link_states(cfg)
    assert not np.array_equal(a[-1].log_prob, b[-1].log_prob)
