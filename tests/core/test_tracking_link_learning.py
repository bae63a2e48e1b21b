"""Two guards of the learned per-link outlier weight (``TrackerConfig.link_learn``), both off
by default (measured in docs/tracking_evidence.md "Learning from a wrong state"):
``link_learn_unexplained``, the learned weights only where the track learned an
out-of-model channel (:func:`diffpos.tracking.evidence.learned_weights`), and
``link_learn_minority``, the counts learned only from updates in which the hypothesis calls
fewer than half of the ranges outliers (:func:`diffpos.tracking.evidence.learn`).

Why: a hypothesis whose state is wrong (a track's start, a dormant hypothesis woken stale, a
bad epoch) calls its links outliers; the learned outlier weight (``link_learn``) then rises
on those links, and once the state is right again the hypothesis pays ``log(1 - eps)`` on
every range it fits, a floor decided by a few nats with four ranges (the README's main
command, seeds 1-4: docs/tracking_evidence.md "Learning from a wrong state"). The learned
weight stands for first arrivals out of the path model; the floor-independent evidence of
those is the track's count of epochs that every hypothesis misfits
(:func:`diffpos.tracking.evidence.unexplained_log_odds`), so the learned weights are used
only once that favours an out-of-model channel. References: the same run with the learned
weight pinned at the prior (``link_outlier_max = outlier_weight``), and the weights without
the gate.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
from static_track import ANCHORS, NODE, SIGMA, B, first_arrivals, same, track

from diffpos.tracking.evidence import learned_weights
from diffpos.tracking.links import Links
from diffpos.tracking.model import SNR_SIGMA_DB, SNR_SPAN_DB
from diffpos.tracking.state import TrackerConfig

FLOOR = 2
#: after 5 epochs the true floor's tracks (both modes) are moved 2 m towards the facade and
#: 1.2 m down (tests/core/test_tracking_family_minority.py): a wrong state
DISPLACE_AT, DISPLACEMENT = 5, np.array([0.0, -2.0, -1.2])


def _run(config, seed=3, epochs=30):
    """Every epoch's state of the static node (tests/core/static_track.py) tracked from its
    four noisy in-model ranges (every range its first arrival among the 18 mechanisms, the
    emulator's in-model channel), the true floor's tracks displaced once (dormant off:
    every hypothesis updated every epoch)."""
    return track(config, ANCHORS, first_arrivals(NODE, ANCHORS, FLOOR), epochs=epochs,
                 seed=seed, displace=(DISPLACE_AT, FLOOR, DISPLACEMENT))


def test_in_model_channel_keeps_the_prior_weight():
    """In-model ranges, a wrong state of the true floor: no epoch is misfit by every
    hypothesis, so with the gate the run equals, bit for bit, the one whose learned weights
    are pinned at the prior; without it the wrong state raises the true floor's learned
    outlier weights and the run differs. The counts are learned either way."""
    cfg = dataclasses.replace(TrackerConfig(), dormant=False)
    assert not cfg.link_learn_unexplained  # default off (docs/tracking_evidence.md)
    ref = _run(dataclasses.replace(cfg, link_outlier_max=cfg.outlier_weight))
    got = _run(dataclasses.replace(cfg, link_learn_unexplained=True))
    off = _run(cfg)
    assert all(same(g, r) for g, r in zip(got, ref, strict=True))
    assert got[-1].unexplained[0] == 0.0 and got[-1].redundant[0] > 10
    assert np.max(got[-1].link_out[0, [FLOOR, FLOOR + B.n_floors]]) > 1.0  # still counted
    assert not all(same(o, r) for o, r in zip(off, ref, strict=True))


def test_weights_of_closed_nodes_are_the_prior_and_of_open_ones_unchanged():
    """Hand-made learned counts (two nodes, two hypotheses, three links, one outlier count of
    5 of 10 updates on link 1): node 0 closed has every link's weights at the prior
    (``log(1 - e0)``, ``log(e0 / span) - log(SNR span)``), node 1 open has exactly the
    weights without the gate, its link 1 with the learned ``eps = (e0 S + 5) / (S + 10)``."""
    cfg = TrackerConfig()
    e0, s = cfg.outlier_weight, cfg.link_prior_updates
    n, h, nl = 2, 2, 3
    lk = {"link_out": np.zeros((n, h, nl)), "link_all": np.full((n, h, nl), 10.0),
          "link_bias": np.full((n, h, nl), np.nan), "link_bias_var": np.full((n, h, nl), np.nan),
          "link_snr": np.full((n, h, nl), np.nan), "link_t_ns": np.zeros((n, h, nl), np.int64)}
    lk["link_out"][:, :, 1] = 5.0
    col = np.tile(np.arange(nl), (n, 1))
    anchors = np.broadcast_to(ANCHORS[:nl], (n, 1, nl, 3)).copy()
    links = Links(anchors=anchors, rho=np.full((n, 1, nl), 20.0),
                  var=np.full((n, 1, nl), SIGMA**2), mask=np.ones((n, 1, nl), bool),
                  snr=np.full((n, 1, nl), 20.0))
    x = np.zeros((n, h, 6))
    x[..., :3] = NODE
    p = np.broadcast_to(np.eye(6) * 0.01, (n, h, 6, 6)).copy()
    t = np.zeros(n, np.int64)
    free = learned_weights(lk, col, x, p, links, t, cfg, SNR_SIGMA_DB, SNR_SPAN_DB)
    got = learned_weights(lk, col, x, p, links, t, cfg, SNR_SIGMA_DB, SNR_SPAN_DB,
                          np.array([True, False]))
    prior = (np.log1p(-e0), np.log(e0) - np.log(cfg.outlier_span_m) - np.log(SNR_SPAN_DB))
    assert np.allclose(got[0, ..., 0], prior[0], rtol=0, atol=1e-12)
    assert np.allclose(got[0, ..., 1], prior[1], rtol=0, atol=1e-12)
    assert np.array_equal(got[1], free[1])
    eps = (e0 * s + 5.0) / (s + 10.0)
    assert np.allclose(free[1, :, 1, 0], np.log1p(-eps), rtol=0, atol=1e-12)


def test_minority_rule_learns_only_from_updates_that_fit_most_ranges():
    """The displaced run, every hypothesis updated every epoch: the reference is each
    hypothesis' own last fits (``link_fit``, inf: called an outlier). With the rule, an update
    in which a hypothesis called at least half of its four ranges outliers leaves its counts
    (``link_out``, ``link_all``) as they were (no evidence: nothing added, nothing forgotten),
    any other forgets them by ``link_forget`` and adds its outliers and one update per link;
    without the rule every update does. The wrong state makes
    such updates happen (else the rule would not act)."""
    cfg = dataclasses.replace(TrackerConfig(), dormant=False)
    assert not cfg.link_learn_minority  # default off (docs/tracking_evidence.md)
    f = cfg.link_forget
    majority_seen = False
    for rule in (True, False):
        states = _run(dataclasses.replace(cfg, link_learn_minority=rule))
        for a, b in itertools.pairwise(states):
            n_out = np.sum(np.isinf(b.link_fit[0, :, :4]), axis=-1)  # (H,)
            skip = (2 * n_out >= 4) & rule
            g = np.where(skip, 1.0, f)  # skipped: unchanged (no evidence, nothing forgotten)
            d_out = np.sum(b.link_out[0, :, :4] - g[:, None] * a.link_out[0, :, :4], axis=-1)
            d_all = np.sum(b.link_all[0, :, :4] - g[:, None] * a.link_all[0, :, :4], axis=-1)
            majority_seen |= bool(np.any(2 * n_out >= 4))
            assert np.allclose(d_out, np.where(skip, 0.0, n_out), atol=1e-9)
            assert np.allclose(d_all, np.where(skip, 0.0, 4.0), atol=1e-9)
    assert majority_seen
