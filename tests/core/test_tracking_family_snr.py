"""Two recorded tracker settings of issue 34 (docs/tracking_evidence.md "Families scored with
their SNR, the gate's misfit at the fit"):

* ``TrackerConfig.family_snr``: an extra family's share of the out-of-model component carries
  the robust SNR likelihood the 18 mechanisms get, against the numpy emulator's SNR for that
  family (:func:`diffpos.channel.emulator.emulate_channel`, an independent implementation of
  the compiled :func:`diffpos.channel.emulator.pair_family_snr_db`).
* ``TrackerConfig.family_fit="residual"``: the family gate's ``link_fit`` is the fitted
  residual over the range noise, ``(rho - L)^2 / var`` at the updated state, recomputed here
  from the path model's lengths at the state the tracker kept.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from static_track import ANCHORS, NODE, SIGMA, B, first_arrivals, track

from diffpos.channel.emulator import emulate_channel
from diffpos.paths.model import first_arrival_paths, graded_paths
from diffpos.scenario import default_scenario
from diffpos.tracking.families import extra_families, family_log_weight
from diffpos.tracking.links import Links
from diffpos.tracking.model import SNR_SIGMA_DB, SNR_SPAN_DB
from diffpos.tracking.state import TrackerConfig

RADIO = default_scenario().radio


def _reference(anchor, node, rho, var, snr, cfg):
    """``family_log_weight`` of ``"mechanism"`` weighting at a point position, prior outlier
    weight, each family's Gaussian weighted by ``exp(term)``: ``term = -min(z^2 / 2, cap) -
    log(S sqrt(2 pi)) + log(SNR_SPAN_DB)``, ``z = (snr - S_k) / S``, ``S_k`` the numpy
    emulator's SNR of the family (order 3; ``-inf``: no power, no candidate); ``snr`` None: no
    SNR term."""
    mset, slots = extra_families(3)
    g = graded_paths(node[None], anchor[None], B, relax_m=cfg.exist_margin_m,
                     floor=np.array([2]), mechanisms=mset)
    ok = g.loose[0] & np.isfinite(g.length_m[0])
    n_base, ok, length = int(ok[:18].sum()), ok[18:], g.length_m[0, 18:]
    dens = np.exp(-0.5 * (rho - length) ** 2 / var) / np.sqrt(2 * np.pi * var)
    if snr is not None:
        ch = emulate_channel(anchor[None], node[None], building=B,
                             radio=dataclasses.replace(RADIO, channel_max_order=3))
        pred = ch.snr_db[0, 0, 18:18 + len(slots)]
        z = (snr - pred) / SNR_SIGMA_DB
        term = (-np.minimum(0.5 * z * z, cfg.snr_cost_cap_nats)
                - np.log(SNR_SIGMA_DB * np.sqrt(2 * np.pi)) + np.log(SNR_SPAN_DB))
        dens = np.where(np.isfinite(pred), dens * np.exp(term), 0.0)
    n_fam = int(ok.sum())
    f = np.sum(np.where(ok, dens, 0.0)) / n_fam
    e0 = cfg.outlier_weight
    return np.log1p((1 - e0) / e0 * cfg.outlier_span_m * n_fam / (n_base + n_fam) * f), pred \
        if snr is not None else None


def test_family_scored_with_its_snr():
    """At the length of the strongest extra family (the numpy emulator's SNR) from the first
    anchor to the static node (a point position on floor 2 of the paper building, 3 cm range
    sigma): with ``family_snr`` the link's family log-weight equals the reference
    within 1e-6 nats, for a measured SNR 4 dB from the family's prediction (uncapped) and one
    40 dB away (capped at ``snr_cost_cap_nats``); the two differ by the Gaussian term's
    difference (> 2 nats) and neither equals the weight without the setting; an unknown SNR
    (NaN) gives that weight."""
    a, n = ANCHORS[0], NODE
    var = SIGMA ** 2 + TrackerConfig().sigma_model_m ** 2
    cfg = dataclasses.replace(TrackerConfig(), max_order=3, family_weight="mechanism",
                              family_snr=True, family_few_links=0)
    mset, _ = extra_families(3)
    g = graded_paths(n[None], a[None], B, relax_m=cfg.exist_margin_m, floor=np.array([2]),
                     mechanisms=mset)
    _, pred = _reference(a, n, 0.0, var, 0.0, cfg)
    ok = g.loose[0, 18:] & np.isfinite(g.length_m[0, 18:]) & np.isfinite(pred)
    assert ok.sum() >= 2, "families with power exist at the node"
    k = int(np.argmax(np.where(ok, pred, -np.inf)))  # the strongest existing family
    rho = float(g.length_m[0, 18 + k])
    snrs = np.array([pred[k] + 4.0, pred[k] - 40.0, np.nan])
    links = Links.from_arrays(np.stack([a] * 3)[None], np.full((1, 3), rho),
                              np.full((1, 3), SIGMA), np.ones((1, 3), bool),
                              cfg.sigma_model_m, snr_db=snrs[None], radio=RADIO)

    def weights(c):
        return family_log_weight(n[None], np.zeros((1, 3, 3)), links, np.array([0]),
                                 np.array([2]), np.ones((1, 3), bool), B, c,
                                 snr_sigma_db=SNR_SIGMA_DB, snr_span_db=SNR_SPAN_DB)[0]

    w = weights(cfg)
    w_off = weights(dataclasses.replace(cfg, family_snr=False))
    off_ref, _ = _reference(a, n, rho, var, None, cfg)
    assert w_off == pytest.approx([off_ref] * 3, abs=1e-6)
    for i in range(2):
        ref, _ = _reference(a, n, rho, var, snrs[i], cfg)
        assert w[i] == pytest.approx(ref, abs=1e-6), (i, w, ref)
        assert abs(w[i] - w_off[i]) > 0.1
    assert w[0] - w[1] > 2.0
    assert w[2] == pytest.approx(w_off[2], abs=1e-12)


@pytest.mark.parametrize("fit", ["prior", "residual"])
def test_gate_misfit_at_the_fit(fit):
    """Static node, floor 2, four anchors, 30 epochs (seed 3; the node's first arrivals with
    3 cm noise): with ``family_fit="residual"`` every link fitted by the true floor's level
    hypothesis has ``link_fit = (rho - L)^2 / var`` within 1e-6 relative, ``L`` the path
    model's length nearest the range at the state the tracker kept (the fitted mechanism: the
    others are metres away), ``var`` the range variance; ``"prior"`` (the NIS at the prior
    covariance) does not (the prior's spread enters it)."""
    cfg = dataclasses.replace(TrackerConfig(), family_fit=fit)
    rho0 = first_arrivals(NODE, ANCHORS, 2)
    states = track(cfg, ANCHORS, rho0, epochs=30, seed=3)
    rng = np.random.default_rng(3)
    for _ in range(30):
        rho = rho0 + rng.normal(0.0, SIGMA, len(ANCHORS))
    st = states[-1]
    h = 2  # level mode, floor 2
    pos = st.mean[0, h, :3]
    ps = first_arrival_paths(np.broadcast_to(pos, (len(ANCHORS), 3)), ANCHORS, B, floor=2)
    length = np.where(ps.valid, ps.length_m, np.nan)
    var = SIGMA ** 2 + cfg.sigma_model_m ** 2
    col = [int(np.flatnonzero(np.all(np.isclose(st.link_anchor[0], a), axis=-1))[0])
           for a in ANCHORS]
    got = st.link_fit[0, h, col]
    assert np.all(np.isfinite(got))
    res = rho - length[np.arange(len(ANCHORS)), np.nanargmin(np.abs(rho[:, None] - length),
                                                             axis=1)]
    want = res * res / var
    close = np.isclose(got, want, rtol=1e-6, atol=1e-9)
    assert close.all() if fit == "residual" else not close.all(), (got, want)
