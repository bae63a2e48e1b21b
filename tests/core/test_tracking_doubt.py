"""The published floor probabilities' model doubt and one-link-out robustness
(:func:`diffpos.tracking.evidence.model_doubt`, :func:`diffpos.tracking.state.robust_floor_log_prob`,
``TrackerConfig.floor_model_doubt`` / ``floor_robust_links``; issue 34 item 5).

The fixture of the first test is physics we did not write: the mean first arrivals that Sionna
RT traced (``diffpos raytrace``, paper building with its partitions, 1e6 samples, depth 4;
receiver 177 of /work/rt/paper-200-1e6-d4.npz) at a static receiver on floor 4 of the paper
building from the default scenario's four UAVs: ranges [m], their sigmas and SNRs [dB]. Every
link is 2.8-5.8 m longer than the straight line; the tracker (the emulator's path model) puts
the receiver on floor 1, and before the model doubt published that floor at p >= 0.95.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from diffpos.scenario import default_scenario
from diffpos.tracking.evidence import model_doubt
from diffpos.tracking.state import (
    TrackerConfig,
    evidence_temper,
    floor_probabilities,
    published_floor_probabilities,
    robust_floor_log_prob,
)
from diffpos.tracking.tracker import init_state, update

SC = default_scenario()
ANCHORS = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.0]])
RX = np.array([6.75, 10.0, 17.5])  # floor 4
RANGE_M = np.array([44.967, 37.091, 25.49, 40.233])
SIGMA_M = np.array([0.05, 0.065, 0.067, 0.05])
SNR_DB = np.array([21.7, 6.3, 5.5, 28.3])


def _track(cfg: TrackerConfig, seed: int, epochs: int = 40):
    """The receiver tracked over ``epochs`` 10 Hz epochs (range noise of its sigmas, 1 dB SNR
    noise); the last output."""
    rng = np.random.default_rng(seed)
    st = init_state(1, SC.building)
    for k in range(epochs):
        r = RANGE_M + rng.standard_normal(4) * SIGMA_M
        s = SNR_DB + rng.standard_normal(4)
        st, out = update(st, ANCHORS[None], r[None], SIGMA_M[None], np.ones((1, 4), bool),
                         k * 100_000_000, SC.building, cfg, snr_db=s[None], radio=SC.radio)
    return st, out


def test_sionna_receiver_on_a_mirror_floor_is_not_published_confident():
    """Seeds 0-2: without the model doubt the wrong floor (1, truth 4) is published at
    >= 0.95 (measured 0.969-0.985); with it below 0.95 (measured 0.59-0.60); the filter is
    the same (same floor, position bit for bit): publication only."""
    assert SC.building.floor_index(RX[2]) == 4
    assert np.all(RANGE_M - np.linalg.norm(ANCHORS - RX, axis=1) > 2.5)  # all out of LOS
    for seed in range(3):
        _, old = _track(TrackerConfig(floor_model_doubt=False), seed)
        st, new = _track(TrackerConfig(), seed)
        assert old.floor_index[0] != 4 and new.floor_index[0] == old.floor_index[0]
        assert old.floor_probabilities[0, old.floor_index[0]] >= 0.95
        assert new.floor_probabilities[0, new.floor_index[0]] < 0.95
        assert np.array_equal(new.position_m, old.position_m)
        assert model_doubt(st.log_prob, st.link_out, st.link_all, TrackerConfig())[0] > 0.3


def _brute_doubt(lp, out, n_all, cfg, n_links=None):
    """One node at a time: the probability of at least ``max(n_links - 3, 1)`` links out of
    the model, by enumerating every subset of the links that are not at the prior."""
    res = []
    for i in range(lp.shape[0]):
        p = np.exp(lp[i])
        nf = p.size // 2
        f = int(np.argmax(p[:nf] + p[nf:]))
        h = f if p[f] >= p[f + nf] else f + nf
        q = []
        for o, a in zip(out[i, h], n_all[i, h], strict=True):
            eps = (cfg.outlier_weight * cfg.link_prior_updates + o) / (cfg.link_prior_updates + a)
            eps = min(max(eps, cfg.outlier_weight), cfg.link_outlier_max)
            q.append(1 - (1 - eps) / (1 - cfg.outlier_weight))
        q = [v for v in q if v > 0]  # the others are never out (probability 0)
        r = 1 if n_links is None else max(int(n_links[i]) - 3, 1)
        tail = 0.0
        for bits in itertools.product((0, 1), repeat=len(q)):
            if sum(bits) >= r:
                tail += float(np.prod([v if b else 1 - v for v, b in zip(q, bits, strict=True)]))
        res.append(tail)
    return np.array(res)


def test_model_doubt_and_mixing_closed_form():
    """Random banks (5 floors, 16 links, at most 5 learned per hypothesis): :func:`model_doubt`
    equals the probability of at least ``max(n_links - 3, 1)`` out-of-model links enumerated
    one node at a time (no ``n_links``, 4, 6 and 9 ranges; 1e-12); more ranges, less doubt;
    nothing learned gives exactly 0 and the published
    probabilities are then bit for bit those without the doubt; with a doubt ``w`` they are
    ``(1 - w) q + w / F`` of the tempered ``q`` (1e-12), the most probable floor unchanged."""
    cfg = TrackerConfig()
    rng = np.random.default_rng(4)
    n, h, nl = 64, 10, 16
    lp = rng.normal(0, 6, (n, h))
    lp -= np.log(np.exp(lp).sum(axis=1, keepdims=True))
    n_all = rng.uniform(0, 20, (n, h, nl)) * (np.arange(nl) < 5)
    out = n_all * rng.random((n, h, nl)) * (rng.random((n, h, nl)) < 0.5)
    w = model_doubt(lp, out, n_all, cfg)
    np.testing.assert_allclose(w, _brute_doubt(lp, out, n_all, cfg), rtol=0, atol=1e-12)
    last = w
    for k in (4, 6, 9):
        nk = np.full(n, k)
        wk = model_doubt(lp, out, n_all, cfg, nk)
        np.testing.assert_allclose(wk, _brute_doubt(lp, out, n_all, cfg, nk), rtol=0,
                                   atol=1e-12)
        assert np.all(wk <= last + 1e-15)
        last = wk
    assert np.any(last < w - 0.01)
    assert np.all(model_doubt(lp, 0 * out, 0 * n_all, cfg) == 0.0)
    q = published_floor_probabilities(lp, cfg)
    np.testing.assert_array_equal(published_floor_probabilities(lp, cfg, doubt=0 * w), q)
    got = published_floor_probabilities(lp, cfg, doubt=w)
    np.testing.assert_allclose(got, (1 - w)[:, None] * q + w[:, None] / 5, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.argmax(got, axis=1), np.argmax(floor_probabilities(lp), 1))
    np.testing.assert_allclose(got.sum(axis=1), 1.0, atol=1e-12)


def test_robust_floor_log_prob_closed_form():
    """:func:`robust_floor_log_prob` against a per-floor loop: the top floor keeps its
    log-marginal; every other floor's deficit ``G`` becomes ``G (1 - s) + min(G s, cap)``,
    ``s`` the share of the per-link evidence differences (links both best hypotheses saw)
    carried by the largest ``k`` positive ones (k = 1, 2; cap 0 and 3.9 nats; 1e-9); 0 links
    dropped: the log-marginals; and the published probabilities (k = 1, no doubt) are those
    log-marginals with ``cap = ln((1 - e0) / e0)`` tempered by kappa."""
    rng = np.random.default_rng(7)
    n, h, nl = 40, 8, 16
    nf = h // 2
    lp = rng.normal(0, 8, (n, h))
    lp -= np.log(np.exp(lp).sum(axis=1, keepdims=True))
    ev = rng.normal(-5, 3, (n, h, nl))
    n_all = rng.uniform(0, 10, (n, h, nl)) * (rng.random((n, h, nl)) < 0.5)
    p = np.exp(lp)
    lf = np.log(p[:, :nf] + p[:, nf:])
    np.testing.assert_array_equal(robust_floor_log_prob(lp, ev, n_all, 0), lf)
    for k, cap in ((1, 0.0), (2, 0.0), (1, 3.9), (2, 3.9)):
        got = robust_floor_log_prob(lp, ev, n_all, k, cap)
        for i in range(n):
            f = int(np.argmax(lf[i]))
            best = [g if p[i, g] >= p[i, g + nf] else g + nf for g in range(nf)]
            for g in range(nf):
                both = (n_all[i, best[f]] > 0) & (n_all[i, best[g]] > 0)
                d = np.where(both, ev[i, best[f]] - ev[i, best[g]], 0.0)
                lead = np.sort(np.maximum(d, 0))[::-1][:k].sum()
                s = min(lead / d.sum(), 1.0) if d.sum() > 0 else 0.0
                gap = lf[i, f] - lf[i, g]
                want = lf[i, f] - gap * (1 - s) - min(gap * s, cap)
                assert abs(got[i, g] - want) < 1e-9, (i, g, got[i, g], want)
    cfg = dataclasses.replace(TrackerConfig(), floor_robust_links=1)
    pub = published_floor_probabilities(lp, cfg, link_ev=ev, link_all=n_all)
    e0 = cfg.outlier_weight
    t = robust_floor_log_prob(lp, ev, n_all, 1, np.log((1 - e0) / e0)) / evidence_temper(cfg)
    t = np.exp(t - t.max(axis=1, keepdims=True))
    np.testing.assert_allclose(pub, t / t.sum(axis=1, keepdims=True), rtol=0, atol=1e-12)
