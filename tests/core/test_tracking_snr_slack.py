"""The diffraction slots' upward SNR slack (``TrackerConfig.snr_diffraction_slack_db``,
``snr_slack_max_links``; :func:`diffpos.tracking.model.diffraction_slack`).

* The slack's SNR likelihood is a proper density over the measured SNR: ``exp(-cost) /
  (sigma sqrt(2 pi))`` integrates to 1 (trapezoid over a fine grid, 1e-6), for several slacks
  and predictions; its value is 0 nats plus the normaliser anywhere on the flat top, and the
  Gaussian of ``SNR_SIGMA_DB`` from ``pred + slack`` above it (scipy.stats.norm's log-pdf,
  1e-9 nats).
* The tracker's SNR term (:func:`diffpos.tracking.model.snr_term`) with the setting, on the
  default building, anchors below and beside the windows: every diffraction slot of a node
  with three ranges equals that reference built from the emulator's amplitude model
  (:func:`diffpos.channel.emulator.pair_snr_db` at the point, the detector's threshold of
  :func:`diffpos.tracking.model.snr_cost`, the cap), 1e-9 nats; every other slot, and every
  slot of a node with four ranges under ``snr_slack_max_links`` 3, is bit for bit the term
  without the setting; and the setting moves some diffraction slot by more than 0.1 nats
  (fails with the tracker ignoring it).
* ``snr_slack_skip``: the term equals the slack's costs plus the skipped paths' numpy
  reference fed the prediction raised by half the slack on those slots (1e-9 nats).
Fixed seeds."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis_cases import random_hypotheses
from scipy.stats import norm

import diffpos.tracking.model as tm
from diffpos.channel.emulator import pair_snr_db
from diffpos.paths.mechanisms import MECHANISMS
from diffpos.scenario import Radio
from diffpos.tracking.links import Links, all_paths
from diffpos.tracking.state import TrackerConfig

SIG = float(tm.SNR_SIGMA_DB)
DIFF = np.array(["-D(" in m for m in MECHANISMS])


def _slack_cost(pred: float, meas: np.ndarray, d: float, cap: float) -> np.ndarray:
    """diffraction_slack's cost of one diffraction slot predicted at ``pred`` for every
    measured SNR ``meas`` (P,), the detector's threshold far below (no threshold term)."""
    k = len(MECHANISMS)
    p = meas.size
    cost = np.zeros((p, 1, 1, k))
    pred_a = np.full((p, 1, 1, k), pred)
    thr = np.full((p, 1, 1), -500.0)
    cfg = TrackerConfig(snr_diffraction_slack_db=d, snr_cost_cap_nats=cap)
    out = tm.diffraction_slack(cost, pred_a, thr, meas[:, None], np.ones((p, 1), bool), cfg)
    return out[:, 0, 0, int(np.flatnonzero(DIFF)[0])]


@pytest.mark.parametrize("d", [1.0, 6.0, 15.0])
@pytest.mark.parametrize("pred", [-3.0, 20.0])
def test_the_slack_is_a_normalised_density(d, pred):
    s = np.linspace(pred - 120.0, pred + d + 120.0, 400001)
    c = _slack_cost(pred, s, d, cap=0.0)
    dens = np.exp(-c) / (SIG * np.sqrt(2.0 * np.pi))
    assert abs(np.trapezoid(dens, s) - 1.0) < 1e-6
    # flat top: the normaliser only; beyond it and below the prediction: the Gaussian
    norm_c = np.log1p(d / (SIG * np.sqrt(2.0 * np.pi)))
    top = (s >= pred) & (s <= pred + d)
    assert np.allclose(c[top], norm_c, atol=1e-12, rtol=0)
    lp = np.where(s > pred + d, norm.logpdf(s, pred + d, SIG), norm.logpdf(s, pred, SIG))
    ref = -(lp + np.log(SIG * np.sqrt(2.0 * np.pi))) + norm_c
    out = ~top
    assert np.allclose(c[out], ref[out], atol=1e-9, rtol=0)


def test_the_cap_holds_beyond_the_slack():
    c = _slack_cost(0.0, np.array([100.0, -100.0]), 6.0, cap=4.5)
    assert np.allclose(c, 4.5 + np.log1p(6.0 / (SIG * np.sqrt(2.0 * np.pi))), atol=1e-12)


def _case(seed: int):
    rng, b, pos, floor, anchors, mask = random_hypotheses(seed, anchor_top_m=6.0)
    n, m = mask.shape
    # measured SNRs around the model's strongest diffraction, up to 12 dB above it
    pred = pair_snr_db(anchors, pos[:, 0], building=b, radio=Radio())
    best = np.max(np.where(DIFF, pred, -np.inf), axis=-1)
    snr = np.where(np.isfinite(best), best, 0.0) + rng.uniform(-6.0, 12.0, (n, m))
    rho = np.linalg.norm(pos[:, :1] - anchors, axis=-1) + 0.5
    links = Links.from_arrays(anchors, rho, np.full((n, m), 0.1), mask, 0.03, snr_db=snr,
                              radio=Radio())
    return b, pos, floor, links, mask


@pytest.mark.parametrize("seed", [0, 1])
def test_the_tracker_snr_term_with_the_slack(seed):
    b, pos, floor, links, mask = _case(seed)
    base = TrackerConfig(snr_reuse_m=0.0, snr_reuse_anchor_m=0.0, first_arrival_prior=0.0,
                         snr_diffraction_slack_db=0.0)  # off: the default since 424510e
    on = dataclasses.replace(base, snr_diffraction_slack_db=6.0, snr_slack_max_links=3)
    relax = np.full(pos.shape[:2], 0.2)
    pe = all_paths(pos, links, floor, b, relax)
    c0 = tm.snr_term(pos, links, floor, b, relax, pe, base)
    c1 = tm.snr_term(pos, links, floor, b, relax, pe, on)
    few = mask.sum(axis=-1) <= 3
    # the reference: the emulator's prediction at the point, the detector's threshold
    pred = pair_snr_db(np.broadcast_to(links.anchors[:, 0][:, None], (*pos.shape[:2], 4, 3))
                       .reshape(-1, 4, 3), pos.reshape(-1, 3), building=b,
                       radio=Radio()).reshape(*pos.shape[:2], 4, -1)
    _, thr = tm._snr_cost_thr(pos, links, b, trust=pe.sure)
    meas = links.snr[:, 0][:, None, :, None]
    r = meas - pred
    r = np.where(r > 6.0, r - 6.0, np.minimum(r, 0.0))
    short = np.maximum(thr[..., None] - SIG - meas, 0.0)
    ref = np.minimum(0.5 * (r / SIG) ** 2 + 0.5 * (short / SIG) ** 2, base.snr_cost_cap_nats)
    ref = ref + np.log1p(6.0 / (SIG * np.sqrt(2.0 * np.pi)))
    scored = DIFF & np.isfinite(c0) & few[:, None, None, None] & mask[:, None, :, None]
    assert scored.sum() > 20
    assert np.allclose(c1[scored], ref[scored], atol=1e-9, rtol=0)
    same = ~scored
    assert np.array_equal(c1[same], c0[same], equal_nan=True)
    assert np.max(np.abs(c1[scored] - c0[scored])) > 0.1
    # every node gets it with snr_slack_max_links 0
    c2 = tm.snr_term(pos, links, floor, b, relax, pe,
                     dataclasses.replace(on, snr_slack_max_links=0))
    four = DIFF & np.isfinite(c0) & ~few[:, None, None, None] & mask[:, None, :, None]
    assert np.allclose(c2[four], ref[four], atol=1e-9, rtol=0)


def test_the_skipped_paths_read_the_slack_mean():
    """``snr_slack_skip``: the tracker's SNR term equals the slack's costs plus the skipped
    paths' numpy reference (:func:`diffpos.tracking.model.skip_cost`) fed the emulator's
    prediction raised by half the slack on the diffraction slots of the three-range nodes
    (1e-9 nats), and differs from the slack without it."""
    b, pos, floor, links, mask = _case(2)
    base = TrackerConfig(snr_reuse_m=0.0, snr_reuse_anchor_m=0.0, first_arrival_prior=0.0,
                         snr_diffraction_slack_db=6.0, snr_slack_max_links=3)
    on = dataclasses.replace(base, first_arrival_prior=0.8, snr_slack_skip=True)
    relax = np.full(pos.shape[:2], 0.2)
    pe = all_paths(pos, links, floor, b, relax)
    c_pre = tm.snr_term(pos, links, floor, b, relax, pe, base)
    c_on = tm.snr_term(pos, links, floor, b, relax, pe, on)
    c_off = tm.snr_term(pos, links, floor, b, relax, pe,
                        dataclasses.replace(on, snr_slack_skip=False))
    pred = pair_snr_db(np.broadcast_to(links.anchors[:, 0][:, None], (*pos.shape[:2], 4, 3))
                       .reshape(-1, 4, 3), pos.reshape(-1, 3), building=b,
                       radio=Radio()).reshape(*pos.shape[:2], 4, -1)
    pred = np.where(pe.loose | tm.ALWAYS_PREDICTED, pred, -np.inf)
    few = (mask.sum(axis=-1) <= 3)[:, None, None, None]
    pred = np.where(DIFF & few, pred + 3.0, pred)
    _, thr = tm._snr_cost_thr(pos, links, b, trust=pe.sure)
    ref = tm.skip_cost(pe, pred, thr, links.snr[:, 0], c_pre.copy(), Radio(), 0.8)
    fin = np.isfinite(ref)
    assert np.array_equal(fin, np.isfinite(c_on))
    assert np.allclose(c_on[fin], ref[fin], atol=1e-9, rtol=0)
    assert np.max(np.abs(c_on[fin] - c_off[fin])) > 0.01
