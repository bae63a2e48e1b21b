"""``TrackerConfig.link_eps_node`` (off by default): every hypothesis of a node uses, for each
link, the node's learned outlier weight, the largest ``eps`` any of its hypotheses learned
(``link_eps_node_awake``: any of its awake ones), instead of its own
(docs/tracking_evidence.md "Session 28: the learned outlier weight").

Why: whether a link's first arrival is out of the path model is the channel's property, not a
hypothesis'; learned per hypothesis, the weight rewards a hypothesis for having called the
link an outlier before (on Sionna RT's paper building a wrong floor that had tracked for a
while paid less for the links it did not explain than the true floor's track 0.5 m from the
truth). References: the learned weight's Beta posterior mean computed here from the state's
counts (``eps = clip((e0 S + out) / (S + all), e0, eps_max)``), a loop over nodes, hypotheses
and links; the static node of tests/core/static_track.py with one range 3 m long (a first
arrival out of the model).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from learned_counts import beta_eps, link_inputs_at, long_link_states, weights_from_counts
from static_track import ANCHORS, B

from diffpos.tracking.evidence import node_weights
from diffpos.tracking.state import TrackerConfig


def _random_weights(seed):
    """Learned weights of 3 nodes x 4 hypotheses x 3 links from random counts (link 2 of
    node 2 never learned), and the counts' reference eps (n, H, L)."""
    rng = np.random.default_rng(seed)
    n_all = rng.uniform(0.0, 20.0, (3, 4, 3))
    return weights_from_counts(n_all, n_all * rng.uniform(0.0, 1.0, (3, 4, 3)))


def test_node_weights_are_the_largest_learned_weight_of_the_node():
    """Every hypothesis' inlier weight is ``log(1 - e)`` and its outlier weight its own plus
    ``log e - log eps_h`` (1e-12 nats), ``e`` the largest reference eps over the node's
    hypotheses (``use``: over the marked ones; a node with none marked: over all); the
    weights themselves start from the reference eps (1e-12)."""
    for seed in (0, 1, 2):
        _, w, ref = _random_weights(seed)
        assert np.allclose(w[..., 0], np.log1p(-ref), rtol=0, atol=1e-12)
        use = np.array([[True, False, True, False], [False] * 4, [False, True, True, True]])
        for mask in (None, use):
            got = node_weights(w, mask)
            for i in range(ref.shape[0]):
                hyps = [k for k in range(ref.shape[1])
                        if mask is None or mask[i, k] or not mask[i].any()]
                for m in range(ref.shape[2]):
                    e = max(ref[i, k, m] for k in hyps)
                    for k in range(ref.shape[1]):
                        assert abs(got[i, k, m, 0] - np.log1p(-e)) < 1e-12
                        want = w[i, k, m, 1] + np.log(e) - np.log(ref[i, k, m])
                        assert abs(got[i, k, m, 1] - want) < 1e-12


def test_tracker_shares_the_weights_of_a_link_across_the_node():
    """The static node with one out-of-model range: with the setting every hypothesis' weights
    of a link are the node's (the largest reference eps of the previous state's counts, over
    all hypotheses; with ``link_eps_node_awake`` over the awake ones), at every epoch; without
    it the hypotheses' weights of the long link differ (the setting is not idle), and the
    tracked runs differ. Default off."""
    assert not TrackerConfig().link_eps_node and not TrackerConfig().link_eps_node_awake
    base = TrackerConfig()
    differed = False
    for awake in (False, True):
        cfg = dataclasses.replace(base, link_eps_node=True, link_eps_node_awake=awake)
        rho0, states = long_link_states(cfg)
        for k in range(1, len(states)):
            prev = states[k - 1]
            w = link_inputs_at(prev, rho0, k, cfg)[4][0]  # (H, M, 2)
            col = link_inputs_at(prev, rho0, k, cfg)[1][0]
            on = ~np.isfinite(prev.dormant_llr[0]) if awake else np.ones(2 * B.n_floors, bool)
            if not on.any():
                on[:] = True
            for m in range(len(ANCHORS)):
                ref = [beta_eps(prev.link_out[0, h, col[m]], prev.link_all[0, h, col[m]], cfg)
                       if col[m] >= 0 else cfg.outlier_weight for h in range(2 * B.n_floors)]
                e = max(r for r, u in zip(ref, on, strict=True) if u)
                assert np.allclose(w[:, m, 0], np.log1p(-e), rtol=0, atol=1e-12)
            off = link_inputs_at(prev, rho0, k, base)[4][0]
            differed |= bool(np.ptp(off[:, 1, 0]) > 0.1)
    assert differed
    _, a = long_link_states(base)
    _, b = long_link_states(dataclasses.replace(base, link_eps_node=True))
    assert not np.array_equal(a[-1].log_prob, b[-1].log_prob)
