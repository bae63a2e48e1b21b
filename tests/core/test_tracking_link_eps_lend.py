"""Who borrows the node's model-averaged outlier weight (``TrackerConfig.link_eps_posterior``):
``link_eps_lend_contest_s`` (0, off by default) lends it only at nodes whose floor was
contested within that many seconds (``TrackerState.lead_ns``), ``link_eps_lend_below_p`` (0,
off) only at nodes whose published floor probability was below that, ``link_eps_lend_fewer`` (off by
default) only to the hypotheses that have learned fewer present links as outliers than the
node's most probable hypothesis (docs/tracking_evidence.md "Session 30: lending the outlier
weight only while the floor is in doubt").

Why: the posterior mean cannot tell whether the believed floor is the true one; on Sionna
``large`` a true floor believed for seconds lent its weight to a wrong floor (Session 29).
References: the learned weight's Beta posterior mean from the counts (tests/core/learned_counts.py),
the learned-outlier count and the model average computed here by loops over nodes, hypotheses
and links; the static node of tests/core/static_track.py with one range 3 m long.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from learned_counts import (
    EXCESS_M,
    FLOOR,
    beta_eps,
    link_inputs_at,
    long_link_states,
    weights_from_counts,
)
from static_track import ANCHORS, NODE, SIGMA, B, first_arrivals

from diffpos.tracking.evidence import LEND_OUTLIER_EPS, fewer_outliers, posterior_weights
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import init_state, update


def _reference_fewer(ref, log_prob, present):
    """Loop reference of :func:`fewer_outliers` from the reference eps (n, H, M)."""
    n, h, m = ref.shape
    out = np.zeros((n, h), bool)
    for i in range(n):
        counts = [sum(1 for j in range(m) if present[i, j] and ref[i, k, j] > LEND_OUTLIER_EPS)
                  for k in range(h)]
        top = max(range(h), key=lambda k: log_prob[i, k])
        for k in range(h):
            out[i, k] = counts[k] < counts[top]
    return out


def test_fewer_outliers_against_a_loop_over_the_reference_eps():
    """The hypotheses that learned fewer present links as outliers (reference eps > 0.1) than
    the node's most probable one, exactly; absent links are not counted; both answers occur."""
    seen = set()
    for seed in range(6):
        rng = np.random.default_rng(seed)
        n_all = rng.uniform(0.0, 30.0, (3, 6, 3))
        w, ref = weights_from_counts(n_all, n_all * rng.uniform(0.0, 1.0, (3, 6, 3))**2)[1:]
        log_prob = rng.normal(0.0, 3.0, (3, 6))
        present = rng.uniform(size=(3, 3)) < 0.8
        got = fewer_outliers(w, log_prob, present)
        assert np.array_equal(got, _reference_fewer(ref, log_prob, present))
        seen.update(got.ravel().tolist())
    assert seen == {True, False}


def test_posterior_weights_lend_only_to_the_borrowers():
    """With a (n, H) borrower mask every borrower's outlier component is its own plus ``log
    max(eps_h, sum_k p_k eps_k) - log eps_h`` (1e-12 nats) and every other hypothesis keeps
    its weights bit for bit; the inlier weights are unchanged."""
    rng = np.random.default_rng(3)
    n_all = rng.uniform(0.0, 20.0, (3, 4, 3))
    w, ref = weights_from_counts(n_all, n_all * rng.uniform(0.0, 1.0, (3, 4, 3)))[1:]
    log_prob = rng.normal(0.0, 3.0, (3, 4))
    use = rng.uniform(size=(3, 4)) < 0.5
    use[0] = [True, False, True, False]
    got = posterior_weights(w, log_prob, use)
    assert np.array_equal(got[..., 0], w[..., 0])
    moved = 0
    for i in range(3):
        p = np.exp(log_prob[i] - log_prob[i].max())
        p = p / p.sum()
        for m in range(3):
            mean = sum(p[k] * ref[i, k, m] for k in range(4))
            for k in range(4):
                if not use[i, k]:
                    assert got[i, k, m, 1] == w[i, k, m, 1]
                    continue
                lift = np.log(max(ref[i, k, m], mean)) - np.log(ref[i, k, m])
                assert abs(got[i, k, m, 1] - w[i, k, m, 1] - lift) < 1e-12
                moved += lift > 1e-3
    assert moved > 0


def _lent(prev, col, cfg, borrow):
    """Reference outlier-component lift (H, M) of the hypotheses ``borrow`` (H,) from the
    previous state's counts and probabilities."""
    p = np.exp(prev.log_prob[0] - np.max(prev.log_prob[0]))
    p = p / p.sum()
    ref = _ref_eps(prev, col, cfg)  # (H, M)
    mean = p @ ref
    return np.where(np.asarray(borrow)[:, None],
                    np.log(np.maximum(ref, mean[None, :])) - np.log(ref), 0.0)


def _weights_at(prev, rho0, k, cfg, base):
    """The link weights (H, M, 2) and links' columns (M,) of epoch ``k`` from ``prev`` with
    ``cfg``, and the weights with ``base``."""
    got = link_inputs_at(prev, rho0, k, cfg)
    return got[4][0], got[1][0], link_inputs_at(prev, rho0, k, base)[4][0]


def _assert_lift(w, off, lift):
    """The in-model weights as ``off``'s and the outlier weights raised by ``lift`` (1e-9)."""
    assert np.allclose(w[..., 0], off[..., 0], rtol=0, atol=1e-9)
    assert np.allclose(w[..., 1] - off[..., 1], lift, rtol=0, atol=1e-9)


def _ref_eps(prev, col, cfg):
    hs = 2 * B.n_floors
    return np.array([[beta_eps(prev.link_out[0, h, col[m]], prev.link_all[0, h, col[m]], cfg)
                      if col[m] >= 0 else cfg.outlier_weight for m in range(len(ANCHORS))]
                     for h in range(hs)])


def test_tracker_lends_only_while_the_floor_is_contested():
    """The static node with one out-of-model range, ``link_eps_posterior`` 4 and
    ``link_eps_lend_contest_s`` 0.3 s: at every epoch the link weights are the default's plus
    the reference model-averaged lift where the previous update's ``lead_ns`` is within
    0.3 s of the epoch, and exactly the default's otherwise (1e-9 nats). Both cases occur,
    and in some epoch outside the window lending would have raised the long link > 0.1 nats
    (fails if the tracker ignores the window). Off by default."""
    assert TrackerConfig().link_eps_lend_contest_s == 0.0
    base = TrackerConfig()
    cfg = dataclasses.replace(base, link_eps_posterior=4, link_eps_lend_contest_s=0.3)
    rho0, states = long_link_states(cfg, epochs=30)
    hs = 2 * B.n_floors
    inside = outside = 0
    for k in range(1, len(states)):
        prev = states[k - 1]
        w, col, off = _weights_at(prev, rho0, k, cfg, base)
        t = 10**9 + k * 10**8
        lend = (t - int(prev.lead_ns[0])) * 1e-9 <= 0.3
        lift = _lent(prev, col, cfg, np.full(hs, lend))
        _assert_lift(w, off, lift)
        if lend:
            inside += 1
        elif np.max(_lent(prev, col, cfg, np.ones(hs, bool))[:, 1]) > 0.1:
            outside += 1
    assert inside > 0 and outside > 0


def test_tracker_lends_only_to_hypotheses_with_fewer_learned_outliers():
    """``link_eps_lend_fewer``: at every epoch the lift goes exactly to the hypotheses whose
    reference eps marks fewer present links as learned outliers than the most probable
    hypothesis' (1e-9 nats; the others keep the default's weights), the hypotheses that call
    the long link an outlier as the believed one does borrow nothing, and in some epoch a
    hypothesis left out would have been raised > 0.1 nats by the plain model average; the
    tracked runs differ from the plain model average's. Off by default."""
    assert TrackerConfig().link_eps_lend_fewer is False
    base = TrackerConfig()
    plain = dataclasses.replace(base, link_eps_posterior=4)
    cfg = dataclasses.replace(plain, link_eps_lend_fewer=True)
    rho0, states = long_link_states(cfg, epochs=30)
    hs = 2 * B.n_floors
    left_out = borrowed = 0
    for k in range(1, len(states)):
        prev = states[k - 1]
        w, col, off = _weights_at(prev, rho0, k, cfg, base)
        ref = _ref_eps(prev, col, cfg)
        borrow = _reference_fewer(ref[None], prev.log_prob[0][None],
                                  np.ones((1, len(ANCHORS)), bool))[0]
        lift = _lent(prev, col, cfg, borrow)
        _assert_lift(w, off, lift)
        full = _lent(prev, col, cfg, np.ones(hs, bool))
        left_out += int(np.any(full[~borrow, 1] > 0.1))
        borrowed += int(np.any(lift[:, 1] > 0.1))
    assert left_out > 0 and borrowed > 0
    _, a = long_link_states(plain, epochs=30)
    assert not np.array_equal(a[-1].log_prob, states[-1].log_prob)


def test_tracker_lends_only_below_the_published_probability():
    """``link_eps_lend_below_p``: the static node with one out-of-model range (tracked with
    ``update`` directly, keeping its published outputs) at 0.33: at every epoch the link
    weights are the default's plus the reference model-averaged lift where the node's
    previously PUBLISHED most probable floor's probability (the tracker's output of the epoch
    before, the reference) is below 0.33, and exactly the default's where it is above. Both
    cases occur, and above it lending would have raised the long link > 0.1 nats in some
    epoch (fails if the tracker ignores the setting). Off by default."""
    assert TrackerConfig().link_eps_lend_below_p == 0.0
    base = TrackerConfig()
    cfg = dataclasses.replace(base, link_eps_posterior=4, link_eps_lend_below_p=0.33)
    rho0 = first_arrivals(NODE, ANCHORS, FLOOR)
    rho0[1] += EXCESS_M
    rng = np.random.default_rng(4)
    n, hs = len(ANCHORS), 2 * B.n_floors
    state, tops, states = init_state(1, B), [], []
    for k in range(30):
        rho = rho0 + rng.normal(0.0, SIGMA, n)
        state, out = update(state, ANCHORS[None], rho[None], np.full((1, n), SIGMA),
                            np.ones((1, n), bool), 10**9 + k * 10**8, B, cfg)
        states.append(state)
        tops.append(float(np.max(out.floor_probabilities[0])))
    below = above = 0
    for k in range(1, len(states)):
        prev = states[k - 1]
        if abs(tops[k - 1] - 0.33) < 1e-6:
            continue
        w, col, off = _weights_at(prev, rho0, k, cfg, base)
        lend = tops[k - 1] < 0.33
        lift = _lent(prev, col, cfg, np.full(hs, lend))
        _assert_lift(w, off, lift)
        if lend:
            below += int(np.max(lift[:, 1]) > 0.1)
        elif np.max(_lent(prev, col, cfg, np.ones(hs, bool))[:, 1]) > 0.1:
            above += 1
    assert below > 0 and above > 0
