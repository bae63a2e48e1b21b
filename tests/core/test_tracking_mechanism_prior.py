"""``TrackerConfig.mechanism_prior_min_links``: a node with fewer ranges than the setting gets
the flat inlier prior ``log(1 - eps)`` for every candidate mechanism of a link instead of the
uniform ``log((1 - eps) / n_cand)``; a node with at least that many ranges is scored as
before, bit for bit (docs/tracking_evidence.md "Session 27: the 3-UAV building").

Reference: the emulator's own first arrivals (:func:`diffpos.channel.emulator.first_arrival`)
at random level positions of the existence-margin tests' building (not a shipped scenario),
ranged from three of its UAVs (one floor hypothesis fits three ranges exactly) and from all
four; the candidate count of every link from the selection's numpy reference
(:func:`diffpos.tracking.model._select_prep_numpy`: the mechanisms that exist and carry power).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from margin_building import ANCHORS, BUILDING, SCENARIO, level_arrivals
from margin_building import pre27_config as _cfg

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.tracking.links import Links, all_paths
from diffpos.tracking.model import (
    _select_numpy,
    _select_prep_numpy,
    select,
    snr_cost_near,
)
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import init_state, update

_B = BUILDING


def _case(seed: int, n: int = 400):
    """Level positions on every floor, the emulator's first arrivals from the four UAVs; the
    first half of the nodes keep three of them (the fourth masked), the rest all four (only
    the nodes with every kept link detected); the paths and SNR costs at the truth."""
    rng = np.random.default_rng(seed)
    floor, nodes, fa = level_arrivals(rng, n)
    mask = fa.detected.copy()
    mask[: n // 2, 3] = False
    keep = np.flatnonzero(mask[:, :3].all(axis=1) & (mask[:, 3] | (np.arange(n) < n // 2)))
    links = Links.from_arrays(np.broadcast_to(ANCHORS, (n, 4, 3)), fa.range_m, fa.sigma_m, mask,
                              _cfg().sigma_model_m, snr_db=fa.snr_db,
                              radio=SCENARIO.radio).take(keep)
    pos, fl = nodes[keep][:, None], floor[keep][:, None]
    pe = all_paths(pos, links, fl, _B, 0.2)
    snr_c = snr_cost_near(pos, links, fl, _B, 0.2, pe)
    cov = np.broadcast_to(np.diag([0.04, 0.04, 0.01]), (keep.size, 1, 3, 3)).copy()
    return cov, links, pe, snr_c


def test_three_ranges_flat_prior_four_unchanged():
    """With the setting 4: every link of a three-range node that both selections call an
    inlier with the same mechanism has the log-weight of the setting off plus ``log n_cand``
    (1e-12 nats), and no link of such a node that was an inlier becomes an outlier; the
    four-range nodes' selections are those of the setting off, bit for bit; 0 is the setting
    off."""
    for seed in (1, 2):
        cov, links, pe, snr_c = _case(seed)
        off = select(cov, links, pe, _cfg(), snr_c)
        on = select(cov, links, pe, _cfg(mechanism_prior_min_links=4), snr_c)
        zero = select(cov, links, pe, _cfg(mechanism_prior_min_links=0), snr_c)
        three = links.mask[:, 0].sum(axis=1) == 3
        assert three.sum() > 50 and (~three).sum() > 50
        for f in ("slot", "log_weight", "nis", "extra_var"):
            np.testing.assert_array_equal(getattr(on, f)[~three], getattr(off, f)[~three])
            np.testing.assert_array_equal(getattr(zero, f), getattr(off, f))
        valid, _, _ = _select_prep_numpy(cov, links, pe, snr_c)
        n_cand = np.maximum(valid.sum(axis=-1), 1)
        same = three[:, None, None] & (on.slot == off.slot) & (off.slot >= 0)
        assert same.sum() > 100 and np.any(n_cand[same] > 1)
        np.testing.assert_allclose(on.log_weight[same] - off.log_weight[same],
                                   np.log(n_cand[same]), rtol=0, atol=1e-12)
        assert not np.any(three[:, None, None] & (off.slot >= 0) & (on.slot < 0))


def test_kernel_equals_reference_with_the_setting():
    """The compiled selection with the setting gives its numpy reference's slots, log-weights,
    NIS and variances bit for bit (three- and four-range nodes in one call)."""
    cov, links, pe, snr_c = _case(3)
    cfg = _cfg(mechanism_prior_min_links=4)
    got, ref = select(cov, links, pe, cfg, snr_c), _select_numpy(cov, links, pe, cfg, snr_c)
    for f in ("slot", "log_weight", "nis", "extra_var"):
        np.testing.assert_array_equal(getattr(got, f), getattr(ref, f), err_msg=f)


def test_config_records_the_setting():
    """The settings are recorded TrackerConfig fields, on by default since session 27 (gate
    4, persistent prior 0.3)."""
    assert TrackerConfig().mechanism_prior_min_links == 4
    assert TrackerConfig().mechanism_switch_p == 0.3
    assert "mechanism_switch_p" in {f.name for f in dataclasses.fields(TrackerConfig)}
    assert "mechanism_prior_min_links" in {f.name for f in dataclasses.fields(TrackerConfig)}


def _persistent_reference(cov, links, pe, snr_c, prev, eps, q):
    """Per link, from the candidates' likelihoods (range Gaussian with the selection's
    innovation variance, plus SNR log-likelihood; :func:`_select_prep_numpy`): the prior
    ``(1 - eps)(1 - q)`` for the previous mechanism, ``(1 - eps) q / (n - 1)`` for the others,
    ``(1 - eps) / n`` for all without a previous one; returns the argmax slot and the
    log-weight ``log sum_k prior_k L_k - log G_best`` (the chosen slot's range Gaussian is the
    IEKF's residual), looped link by link."""
    valid, s_ll, s_var = _select_prep_numpy(cov, links, pe, snr_c)
    s_ll = np.broadcast_to(s_ll, valid.shape)
    slot = np.full(valid.shape[:-1], -1)
    lw = np.full(valid.shape[:-1], np.nan)
    for i, h, m in zip(*np.nonzero(valid.any(axis=-1)), strict=True):
        ks = np.flatnonzero(valid[i, h, m])
        e = links.rho[i, 0, m] - pe.length[i, h, m, ks]
        g = -0.5 * (e * e / s_var[i, h, m, ks] + np.log(2 * np.pi * s_var[i, h, m, ks]))
        n, p = ks.size, prev[i, h, m]
        if p in ks:
            pri = np.where(ks == p, np.log1p(-q), np.log(q) - np.log(max(n - 1, 1)))
        else:
            pri = np.full(n, -np.log(n))
        t = np.log1p(-eps) + pri + g + s_ll[i, h, m, ks]
        b = int(np.argmax(t))
        slot[i, h, m] = ks[b]
        lw[i, h, m] = np.log(np.sum(np.exp(t - t[b]))) + t[b] - g[b]
    return slot, lw


def test_persistent_prior_against_reference():
    """``mechanism_switch_p`` (with the gate 4): a three-range node's links, their previous
    mechanism the one today's selection chose (or none: NaN), get the reference's slot and
    log-weight (1e-9 nats) wherever both call the link an inlier; a kept mechanism costs
    ``log(1 - q)`` whatever the link's candidate count (the count is gone), none costs today's
    count; four-range nodes and ``prev_slot`` None are the flat setting's bit for bit."""
    cfg = _cfg(mechanism_prior_min_links=4, mechanism_switch_p=0.3)
    flat = _cfg(mechanism_prior_min_links=4)
    for seed in (1, 2):
        cov, links, pe, snr_c = _case(seed)
        off = select(cov, links, pe, _cfg(), snr_c)
        three = links.mask[:, 0].sum(axis=1) == 3
        rng = np.random.default_rng(seed)
        prev = np.where(rng.random(off.slot.shape) < 0.7, off.slot, np.nan).astype(float)
        got = select(cov, links, pe, cfg, snr_c, prev_slot=prev)
        ref_slot, ref_lw = _persistent_reference(cov, links, pe, snr_c, prev,
                                                 cfg.outlier_weight, cfg.mechanism_switch_p)
        fl = select(cov, links, pe, flat, snr_c)
        for f in ("slot", "log_weight", "nis", "extra_var"):
            np.testing.assert_array_equal(getattr(got, f)[~three], getattr(fl, f)[~three])
            np.testing.assert_array_equal(getattr(select(cov, links, pe, cfg, snr_c), f),
                                          getattr(fl, f))
        ins = three[:, None, None] & (got.slot >= 0)
        assert ins.sum() > 100
        np.testing.assert_array_equal(got.slot[ins], ref_slot[ins])
        np.testing.assert_allclose(got.log_weight[ins], ref_lw[ins], rtol=0, atol=1e-9)
        valid, s_ll, _ = _select_prep_numpy(cov, links, pe, snr_c)
        n_cand = valid.sum(axis=-1)
        kept = ins & (got.slot == prev) & (n_cand > 1)
        fresh = ins & np.isnan(prev) & (n_cand > 1)
        assert kept.sum() > 50 and fresh.sum() > 10
        # without a previous mechanism: today's count (the setting off), not the flat prior
        np.testing.assert_allclose(got.log_weight[fresh], off.log_weight[fresh], rtol=0,
                                   atol=1e-9)
        # a kept mechanism: log(1 - eps) + log(1 - q) + its SNR term + the mixture's log(sum /
        # max) >= 0, i.e. no -log n_cand (today's weight sits log n_cand lower, less the mixture)
        s_best = np.take_along_axis(np.broadcast_to(s_ll, valid.shape),
                                    np.maximum(got.slot, 0)[..., None], -1)[..., 0]
        rest = got.log_weight - np.log1p(-cfg.outlier_weight) - np.log1p(-0.3) - s_best
        assert np.all(rest[kept] >= -1e-12) and np.all(rest[kept] <= np.log(n_cand[kept]) + 1e-12)


def test_tracker_keeps_previous_mechanisms_only_with_the_setting():
    """Over a few epochs of the margin tests' building from three UAVs, the tracker keeps
    every updated hypothesis' chosen mechanisms (``TrackerState.link_slot``: some slots >= 0,
    at most three links per node) with ``mechanism_switch_p``; without it none (NaN)."""
    rng = np.random.default_rng(5)
    nodes = np.array([[x, 4.0, _B.floor_z_m(f) + _B.nominal_node_height_m]
                      for x, f in ((-3.0, 0), (2.0, 1), (5.0, 2))])
    for cfg, kept in ((_cfg(), False),
                      (_cfg(mechanism_prior_min_links=4, mechanism_switch_p=0.3), True)):
        st = init_state(len(nodes), _B)
        for k in range(6):
            fa = first_arrival(emulate_channel(ANCHORS[:3], nodes, building=_B,
                                               radio=SCENARIO.radio), radio=SCENARIO.radio,
                               rng=rng)
            st, _ = update(st, np.broadcast_to(ANCHORS[:3], (len(nodes), 3, 3)), fa.range_m,
                           fa.sigma_m, fa.detected, np.full(len(nodes), k * 100_000_000),
                           _B, cfg, snr_db=fa.snr_db, radio=SCENARIO.radio)
        fin = np.isfinite(st.link_slot)
        assert fin.any() == kept
        if kept:
            assert np.any(st.link_slot[fin] >= 0) and fin.any(axis=1).sum(axis=-1).max() <= 3
