"""Negative information of silent anchors (``TrackerConfig.silent_anchor_nats``,
``silent_anchor_margin_db``, ``silent_anchor_max_links``; :mod:`diffpos.tracking.silent`).

* :func:`~diffpos.tracking.silent.silent_cost` equals a reference built one (anchor,
  hypothesis) pair at a time: the strongest slot of the emulator's amplitude model
  (:func:`diffpos.channel.emulator.pair_snr_db` of that pair alone), ``-log(e + (1 - e)
  Phi((T + margin - S) / SNR_SIGMA_DB))`` with scipy.stats.norm's CDF, summed over the
  node's silent anchors (1e-9 nats); it never exceeds the cap times the silent anchors, and
  a hypothesis without a predicted path costs nothing.
* The tracker (:func:`diffpos.tracking.tracker.update`) with the setting (and with
  ``silent_anchor_spread``: the cost of the hypotheses' sigma points): from the same
  state, one epoch in which an anchor of the TRACKING nodes is silent (masked, SNR -inf,
  its position given): the hypotheses' means are the run's without the silent anchor bit
  for bit and their log-probabilities are that run's less the reference cost at those
  means, renormalised (1e-9); the setting moves some hypothesis by more than 0.1 nats
  (fails with the tracker ignoring silent anchors). With ``silent_anchor_max_links`` below
  the nodes' ranges, and with the setting off, the run equals the run without the silent
  anchor bit for bit.
* ``silent_anchor_spread``'s sigma points carry each hypothesis' mean and covariance
  exactly; the averaged cost equals a point-by-point reference.
* ``floor_hold_max_links``: nodes with that many ranges or fewer keep the predicted
  log-probabilities (:func:`diffpos.tracking.tracker.predict`), everything else as without.
Fixed seeds."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import norm

from diffpos.channel.emulator import emulate_channel, first_arrival, pair_snr_db
from diffpos.scenario import default_scenario
from diffpos.tracking.model import SNR_SIGMA_DB
from diffpos.tracking.silent import sigma_points, silent_cost
from diffpos.tracking.state import TrackerConfig, TrackStatus
from diffpos.tracking.tracker import init_state, predict, update

SC = default_scenario()
B, RADIO = SC.building, SC.radio
ON = TrackerConfig(silent_anchor_nats=3.0, silent_anchor_margin_db=20.0)
ANCHORS = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.0],
                    [-25.0, -12.0, 3.0], [8.0, -10.0, 2.0]])
NODES = np.array([[-4.0, 3.0, 4.5], [2.0, 6.0, 7.5], [6.0, 2.5, 10.5], [-1.0, 8.0, 13.5]])


def _reference(pos, anchors, silent, config):
    """The cost (N, H) one pair at a time (module docstring)."""
    n, h = pos.shape[:2]
    e = np.exp(-config.silent_anchor_nats)
    out = np.zeros((n, h))
    for i, m in zip(*np.nonzero(silent), strict=True):
        for j in range(h):
            s = np.max(pair_snr_db(anchors[i, m][None, None], pos[i, j][None], building=B,
                                   radio=RADIO))
            if not np.isfinite(s):
                continue
            z = (RADIO.detection_snr_db + config.silent_anchor_margin_db - s) / SNR_SIGMA_DB
            out[i, j] -= np.log(e + (1 - e) * norm.cdf(z))
    return out


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("margin", [0.0, 10.0])
def test_silent_cost_against_a_pair_by_pair_reference(seed, margin):
    rng = np.random.default_rng(seed)
    n, h, m = 5, 4, 3
    x0, x1 = B.edge_x_m
    fl = rng.integers(0, B.n_floors, (n, h))
    pos = np.stack([rng.uniform(x0 + 0.5, x1 - 0.5, (n, h)), rng.uniform(0.5, B.depth_m - 0.5,
                    (n, h)), B.floor_z_m(fl) + rng.uniform(0.5, 2.5, (n, h))], axis=-1)
    anchors = np.stack([rng.uniform(x0 - 10, x1 + 10, (n, m)), -rng.uniform(2, 30, (n, m)),
                        rng.uniform(0.3, 15.0, (n, m))], axis=-1)
    silent = rng.random((n, m)) < 0.6
    silent[0] = False  # a node without silent anchors
    cfg = dataclasses.replace(ON, silent_anchor_margin_db=margin)
    got = silent_cost(pos, anchors, silent, B, RADIO, cfg, SNR_SIGMA_DB)
    ref = _reference(pos, anchors, silent, cfg)
    assert np.allclose(got, ref, atol=1e-9, rtol=0)
    assert np.all(got[0] == 0.0)
    assert np.all(got <= cfg.silent_anchor_nats * silent.sum(axis=1)[:, None] + 1e-12)
    assert got.max() > 0.1  # the case is not trivial


def _state(seed: int = 3):
    """Four static nodes TRACKING after eight epochs of the emulator's ranges, and a ninth
    epoch's inputs."""
    rng = np.random.default_rng(seed)
    a = np.broadcast_to(ANCHORS, (len(NODES), *ANCHORS.shape)).copy()
    state = init_state(len(NODES), B)
    for k in range(9):
        fa = first_arrival(emulate_channel(ANCHORS, NODES, building=B, radio=RADIO), radio=RADIO,
                           rng=rng)
        t = np.full(len(NODES), round(k * 0.1e9), np.int64)
        inputs = (a, fa.range_m, fa.sigma_m, fa.detected.copy(), t, fa.snr_db.copy())
        if k < 8:
            state, _ = update(state, *inputs[:5], B, TrackerConfig(), snr_db=inputs[5],
                              radio=RADIO)
    assert np.all(state.status == int(TrackStatus.TRACKING))
    return state, inputs


def _run(state, inputs, config, silent_col=None):
    a, r, s, m, t, snr = (x.copy() for x in inputs)
    if silent_col is not None:  # the anchor reported no path: masked, SNR -inf
        m[:, silent_col] = False
        snr[:, silent_col] = -np.inf
    return update(state, a, r, s, m, t, B, config, snr_db=snr, radio=RADIO)[0]


@pytest.mark.parametrize("spread", [False, True])
def test_the_tracker_takes_the_silent_anchor_into_each_hypothesis(spread):
    state, inputs = _state()
    col = 2  # the anchor closest to the facade: strong predicted paths everywhere
    cfg = dataclasses.replace(ON, silent_anchor_spread=spread)
    m_off = inputs[3].copy()
    m_off[:, col] = False
    base = update(state, inputs[0], inputs[1], inputs[2], m_off, inputs[4], B, cfg,
                  snr_db=np.where(m_off, inputs[5], np.nan), radio=RADIO)[0]
    on = _run(state, inputs, cfg, silent_col=col)
    assert on.mean.tobytes() == base.mean.tobytes()
    silent = np.zeros(m_off.shape, bool)
    silent[:, col] = True
    if spread:  # the points of each hypothesis (tested above), the cost of their average
        pts = sigma_points(base.mean[..., :3], base.cov[..., :3, :3],
                           np.tile(np.arange(B.n_floors), 2), B)
        cost = silent_cost(pts, inputs[0], silent, B, RADIO, cfg, SNR_SIGMA_DB)
    else:
        cost = _reference(base.mean[..., :3], inputs[0], silent, cfg)
    x = base.log_prob - cost
    x = np.maximum(x - x.max(axis=1, keepdims=True), -700.0)
    ref = x - np.log(np.exp(x).sum(axis=1, keepdims=True))
    assert np.allclose(on.log_prob, ref, atol=1e-9, rtol=0)
    assert np.abs(on.log_prob - base.log_prob).max() > 0.1


@pytest.mark.parametrize("config", [TrackerConfig(), dataclasses.replace(
    ON, silent_anchor_max_links=4)], ids=["off", "max_links"])
def test_without_the_setting_a_silent_anchor_changes_nothing(config):
    state, inputs = _state()
    col = 2
    on = _run(state, inputs, config, silent_col=col)
    m_off = inputs[3].copy()
    m_off[:, col] = False
    assert m_off.sum(axis=1).min() > 4  # every node has more ranges than max_links
    base = update(state, inputs[0], inputs[1], inputs[2], m_off, inputs[4], B, config,
                  snr_db=np.where(m_off, inputs[5], np.nan), radio=RADIO)[0]
    for f in dataclasses.fields(on):
        assert getattr(on, f.name).tobytes() == getattr(base, f.name).tobytes(), f.name


def test_floor_hold_keeps_the_predicted_probabilities_of_few_range_nodes():
    """``floor_hold_max_links`` 2: from the same TRACKING state, an epoch in which nodes 0 and
    1 keep two ranges and nodes 2 and 3 all six: nodes 0-1's log-probabilities are the
    predicted ones (:func:`diffpos.tracking.tracker.predict` to the epoch's time, 1e-12),
    their means those of the run without the setting bit for bit; nodes 2-3 are that run's
    bit for bit; without the setting nodes 0-1's probabilities move (> 1e-6: fails with
    the setting ignored)."""
    state, inputs = _state()
    a, r, s, m, t, snr = (x.copy() for x in inputs)
    m[:2, 2:] = False
    hold = dataclasses.replace(TrackerConfig(), floor_hold_max_links=2)
    assert TrackerConfig().floor_hold_max_links == 2  # the default since 2026-12-07 23:50
    no_hold = dataclasses.replace(TrackerConfig(), floor_hold_max_links=0)
    off = update(state, a, r, s, m, t, B, no_hold, snr_db=snr, radio=RADIO)[0]
    on = update(state, a, r, s, m, t, B, hold, snr_db=snr, radio=RADIO)[0]
    pred = predict(state, t, B, TrackerConfig())
    assert np.allclose(on.log_prob[:2], pred.log_prob[:2], atol=1e-12, rtol=0)
    assert np.abs(off.log_prob[:2] - pred.log_prob[:2]).max() > 1e-6
    assert on.mean.tobytes() == off.mean.tobytes()
    assert on.log_prob[2:].tobytes() == off.log_prob[2:].tobytes()


def test_sigma_points_carry_the_covariance_and_average_the_silence():
    """:func:`~diffpos.tracking.silent.sigma_points` of hypotheses well inside their floor's
    box: the six points' mean is the position and their mean outer product the covariance
    (1e-9); a zero covariance gives six copies of the position, so the averaged cost equals
    the cost at the mean (1e-12); with a covariance, the averaged cost equals the reference
    ``-log(e + (1 - e) mean_q Phi_q)`` built point by point (1e-9)."""
    rng = np.random.default_rng(5)
    n, h = 3, 2
    fl = np.array([1, 2])
    pos = np.stack([rng.uniform(-5, 5, (n, h)), rng.uniform(4, 8, (n, h)),
                    B.floor_z_m(fl)[None, :] + 1.5 + np.zeros((n, h))], axis=-1)
    a = rng.normal(size=(n, h, 3, 3)) * 0.3
    cov = a @ np.swapaxes(a, -1, -2) + 0.01 * np.eye(3)
    pts = sigma_points(pos, cov, fl, B)
    assert pts.shape == (n, h, 6, 3)
    assert np.allclose(pts.mean(axis=2), pos, atol=1e-9)
    d = pts - pos[:, :, None, :]
    assert np.allclose(np.einsum("nhqi,nhqj->nhij", d, d) / 6.0, cov, atol=1e-9)
    anchors = np.stack([rng.uniform(-20, 20, (n, 2)), -rng.uniform(3, 20, (n, 2)),
                        rng.uniform(0.5, 12.0, (n, 2))], axis=-1)
    silent = np.ones((n, 2), bool)
    zero = sigma_points(pos, np.zeros_like(cov), fl, B)
    assert np.allclose(silent_cost(zero, anchors, silent, B, RADIO, ON, SNR_SIGMA_DB),
                       silent_cost(pos, anchors, silent, B, RADIO, ON, SNR_SIGMA_DB),
                       atol=1e-12, rtol=0)
    got = silent_cost(pts, anchors, silent, B, RADIO, ON, SNR_SIGMA_DB)
    e = np.exp(-ON.silent_anchor_nats)
    ref = np.zeros((n, h))
    for i in range(n):
        for m in range(2):
            for j in range(h):
                phi = []
                for q in range(6):
                    s = np.max(pair_snr_db(anchors[i, m][None, None], pts[i, j, q][None],
                                           building=B, radio=RADIO))
                    z = (RADIO.detection_snr_db + ON.silent_anchor_margin_db - s) / SNR_SIGMA_DB
                    phi.append(norm.cdf(z) if np.isfinite(s) else 1.0)
                ref[i, j] -= np.log(e + (1 - e) * np.mean(phi))
    assert np.allclose(got, ref, atol=1e-9, rtol=0)
    ref = silent_cost(pos, anchors, silent, B, RADIO, ON, SNR_SIGMA_DB)
    assert np.abs(got - ref).max() > 1e-3
