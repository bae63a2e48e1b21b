"""Row independence of :func:`diffpos.tracking.tracker.update`, bit for bit: the fusion's worker pool
(services/diffpos_services/fusion/workers.py) splits a batch's rows over processes and
relies on it. A batch with UNINITIALISED (new), INITIALISING, TRACKING and COASTING rows is
updated in one call, in two halves, interleaved (even/odd rows) and in three uneven chunks;
every output and every field of the new state must be the same bytes. The same for the M-NLS
snapshot fixes (:func:`diffpos.estimators.mnls.solver`), which the pool splits too."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.estimators.mnls import solver as est
from diffpos.scenario import default_scenario
from diffpos.tracking.state import TrackerConfig, TrackerState, TrackStatus
from diffpos.tracking.tracker import init_state, update

SC = default_scenario()
B = SC.building
RADIO = SC.radio
CFG = TrackerConfig()
#: the evidence-deficit re-seed (off by default) tested in every epoch, every floor: a
#: threshold of 0 nats re-seeds from the first test whose snapshot is any better
DEFICIT = dataclasses.replace(CFG, deficit_nats=1e-9, deficit_tests=1, deficit_period_s=0.1)
#: and the re-seeds held to their period's boundaries (``reseed_period_s``, off by default)
PERIOD = dataclasses.replace(DEFICIT, reseed_period_s=0.3)
#: the persistent mechanism prior (``mechanism_switch_p``, off by default) for every node
#: (fewer than 9 of the 8 ranges), so ``link_slot`` is kept and read
PERSIST = dataclasses.replace(CFG, mechanism_prior_min_links=9, mechanism_switch_p=0.3)
#: a node's link weights shared by its (awake) hypotheses (``link_eps_node``, off by default)
SHARED = dataclasses.replace(CFG, link_eps_node=True, link_eps_node_awake=True)
#: the re-seed on a burst of outliers of the believed floor (``reseed_outliers``, off by
#: default), here on a single outlier so it fires
BURST = dataclasses.replace(CFG, reseed_outliers=1)
#: the diffraction slots' upward SNR slack (``snr_diffraction_slack_db``; by default only at
#: nodes with at most three ranges) on every node
SLACK = dataclasses.replace(CFG, snr_diffraction_slack_db=6.0, snr_slack_max_links=0)
#: the SNR term's window edge as Sionna RT traces it (``snr_edge_model``, off by default)
WEDGE = dataclasses.replace(CFG, snr_edge_model="wedge")
#: the node's model-averaged outlier weight (``link_eps_posterior``, off by default)
POSTERIOR = dataclasses.replace(CFG, link_eps_posterior=4)
#: lent only at nodes contested within 0.3 s, published below 0.9, and only to hypotheses
#: with fewer learned outliers than the believed one (``link_eps_lend_contest_s``,
#: ``link_eps_lend_below_p``, ``link_eps_lend_fewer``, off by default)
LEND = dataclasses.replace(POSTERIOR, link_eps_lend_contest_s=0.3, link_eps_lend_below_p=0.9,
                           link_eps_lend_fewer=True)
#: a second level mode per floor (``challenger_m``, off by default) searched for every floor
#: in every epoch, scored from its first update, winning on any gain
CHAL = dataclasses.replace(CFG, challenger_m=0.2, challenger_period_s=0.1, challenger_floors=0,
                           challenger_grace=0, challenger_nats=1e-9, challenger_beat_lead=True)
#: the negative information of silent anchors (``silent_anchor_nats``, off by default); the
#: even rows' last anchor reports no path from epoch 2 on (:func:`_inputs`)
SILENT = dataclasses.replace(CFG, silent_anchor_nats=3.0, silent_anchor_margin_db=10.0)
#: the skipped paths' threshold raised by the strongest family (``skip_threshold_order``) and
#: the families on every fitted link scored with their SNR (``family_few_links``; both off by
#: default, by default only at few-range nodes) on every node (eight ranges at most)
FEW = dataclasses.replace(CFG, skip_threshold_order=3, skip_threshold_max_links=0,
                          family_few_links=9)
#: the worst-link families may take a link called an outlier (``family_worst_outliers``, off
#: by default), the worst-link gate at every node (fewer than 9 of the 8 ranges)
WORST = dataclasses.replace(CFG, family_worst_outliers=True, family_min_links=9)
#: and the family-explained links kept in the fit (``family_fit_links``, off by default) on
#: every node
FIT = dataclasses.replace(FEW, family_fit_links=9)
#: and the published covariance's floor weights at those nodes without the range-count contest
#: temper (``cov_few_floors``, off by default; "model": without the model doubt too)
FITCOV = dataclasses.replace(FIT, cov_few_floors="temper")
FITMODEL = dataclasses.replace(FIT, cov_few_floors="model")
#: the hypotheses following their node's leader horizontally, the adjacent floors' vertical
#: modes too, only those 0.1 m away, at nodes with four ranges or more (``stairs_follow``,
#: ``stairs_follow_m``, ``stairs_follow_min_links``, off by default)
STAIRS = dataclasses.replace(CFG, stairs_follow=3, stairs_follow_m=0.1, stairs_follow_min_links=4)
#: and only at nodes tracked for 0.5 s since their initialisation (``stairs_follow_after_s``)
STARTUP = dataclasses.replace(STAIRS, stairs_follow_after_s=0.5)
ANCHORS = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.0],
                    [-25.0, -12.0, 3.0], [25.0, -12.0, 3.0], [-8.0, -10.0, 2.0],
                    [8.0, -25.0, 0.5]])
# static nodes on several floors, x along the facade, y inside
NODES = np.array([[-4.0, 3.0, 4.5], [2.0, 6.0, 7.5], [6.0, 2.5, 10.5], [-1.0, 8.0, 13.5],
                  [3.5, 4.0, 4.2], [-6.0, 5.0, 7.8], [0.5, 3.0, 10.2], [5.0, 7.0, 4.6],
                  [-2.5, 2.0, 7.4], [1.5, 9.0, 13.2]])
N_EPOCHS = 8  # 0.0 ... 0.7 s; the batch under test is the last one


def _inputs(seed: int = 7, silent: bool = False):
    """Per epoch: (t_ns, anchors, range, sigma, mask, snr) for every node, the mask shaped by
    each row's role: rows 0-3 ranged every epoch (TRACKING by the last), rows 4-5 from epoch
    4 (INITIALISING), rows 6-7 until epoch 5 then none (COASTING), rows 8-9 only in the last
    epoch (new nodes, UNINITIALISED before it). ``silent``: the even rows' last anchor
    reports no path (masked, SNR -inf) from epoch 2 on."""
    rng = np.random.default_rng(seed)
    n = len(NODES)
    for k in range(N_EPOCHS):
        fa = first_arrival(emulate_channel(ANCHORS, NODES, building=B, radio=RADIO),
                           radio=RADIO, rng=rng)
        on = np.ones(n, bool)
        on[4:6] = k >= 4
        on[6:8] = k <= 5
        on[8:10] = k == N_EPOCHS - 1
        mask = fa.detected & on[:, None]
        a = np.broadcast_to(ANCHORS, (n, *ANCHORS.shape))
        snr = fa.snr_db
        if silent and k >= 2:
            mask[::2, -1] = False
            snr = snr.copy()
            snr[::2, -1] = -np.inf
        yield round(k * 0.1e9) + np.zeros(n, np.int64), a, fa.range_m, fa.sigma_m, mask, snr


def _rows(x, idx):
    return dataclasses.replace(x, **{f.name: getattr(x, f.name)[idx]
                                     for f in dataclasses.fields(x)})


def _assert_same(a, b) -> None:
    for f in dataclasses.fields(a):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        assert va.dtype == vb.dtype and va.shape == vb.shape, f.name
        assert va.tobytes() == vb.tobytes(), f.name  # bytes: NaN payloads and -0.0 too


@pytest.mark.parametrize("config", [CFG, DEFICIT, PERIOD, PERSIST, SHARED, BURST, SLACK,
                                    POSTERIOR, LEND, CHAL, WEDGE, SILENT, FEW, WORST, FIT,
                                    FITCOV, FITMODEL, STAIRS, STARTUP],
                         ids=["default", "deficit", "period", "persist", "shared", "burst",
                              "slack", "posterior", "lend", "challenger", "wedge", "silent",
                              "few", "worst", "fit", "fitcov", "fitmodel", "stairs",
                              "startup"])
def test_update_rows_are_independent_bit_for_bit(config):
    epochs = list(_inputs(silent=config.silent_anchor_nats > 0))
    state = init_state(len(NODES), B)
    for t, a, r, s, m, snr in epochs[:-1]:
        state, _ = update(state, a, r, s, m, t, B, config, snr_db=snr, radio=RADIO)
    t, a, r, s, m, snr = epochs[-1]
    before = set(state.status.tolist())
    assert {int(TrackStatus.UNINITIALISED), int(TrackStatus.INITIALISING),
            int(TrackStatus.TRACKING), int(TrackStatus.COASTING)} <= before, before
    assert not m[6:8].any() and m[8:10].any()  # coasting rows without, new rows with ranges
    whole_state, whole_out = update(state, a, r, s, m, t, B, config, snr_db=snr, radio=RADIO)
    if config.challenger_m > 0:  # the challengers are there to be split
        assert whole_state.chal_age.any() and state.chal_age.any()
    n = len(NODES)
    splits = {"halves": [np.arange(0, 5), np.arange(5, n)],
              "interleaved": [np.arange(0, n, 2), np.arange(1, n, 2)],
              "uneven": [np.array([9, 0, 6]), np.array([3, 8]), np.array([1, 2, 4, 5, 7])]}
    for parts in splits.values():
        new_state = dataclasses.replace(whole_state, **{
            f: np.empty_like(getattr(whole_state, f)) for f in TrackerState.__dataclass_fields__})
        outs = {}
        for idx in parts:
            ns, out = update(_rows(state, idx), a[idx], r[idx], s[idx], m[idx], t[idx], B, config,
                             snr_db=snr[idx], radio=RADIO)
            for f in TrackerState.__dataclass_fields__:
                getattr(new_state, f)[idx] = getattr(ns, f)
            for f in dataclasses.fields(out):
                v = getattr(out, f.name)
                dst = outs.setdefault(f.name, np.empty((n, *v.shape[1:]), v.dtype))
                dst[idx] = v
        _assert_same(whole_state, new_state)
        _assert_same(whole_out, dataclasses.replace(whole_out, **outs))


def test_mnls_rows_are_independent_bit_for_bit():
    """:func:`diffpos.estimators.mnls.solver` (the fusion's snapshot fixes, also split by the worker
    pool): one call on 10 nodes' epochs with the measured SNR equals the same rows in halves,
    interleaved and in uneven chunks, every field to the byte (messages too)."""
    _, a, r, s, m, snr = list(_inputs(seed=3))[-1]
    m = m.copy()
    m[6:8] = True  # every row with ranges here
    m[8, :3] = False  # a row with fewer anchors
    whole = est.mnls(a, r, s, building=B, mask=m, snr_db=snr, radio=RADIO)
    n = len(NODES)
    for parts in ([np.arange(0, 5), np.arange(5, n)], [np.arange(0, n, 2), np.arange(1, n, 2)],
                  [np.array([9, 0, 6]), np.array([3, 8]), np.array([1, 2, 4, 5, 7])]):
        fixes = [est.mnls(a[i], r[i], s[i], building=B, mask=m[i], snr_db=snr[i], radio=RADIO)
                 for i in parts]
        order = np.argsort(np.concatenate(parts))
        for f in dataclasses.fields(whole):
            v = getattr(whole, f.name)
            if isinstance(v, np.ndarray):
                got = np.concatenate([getattr(x, f.name) for x in fixes])[order]
                assert v.dtype == got.dtype and v.tobytes() == got.tobytes(), f.name
            else:
                assert all(getattr(x, f.name) == v for x in fixes), f.name
        msgs = [text for x in fixes for text in x.messages()]
        assert [msgs[i] for i in order] == whole.messages()
