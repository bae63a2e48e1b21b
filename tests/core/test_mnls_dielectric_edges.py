"""M-NLS's SNR model with the window edges as dielectric sheets (:class:`diffpos.estimators.mnls.rules.SnrRule`
``dielectric_edges``, session 27): the slots' SNR M-NLS predicts is the numpy emulator's at
channel order 3 (the channel's sheet edges, an independent computation: ``emulate_channel``'s
slot builders, not the compiled kernel), it differs from the conductor's on the diffracted
slots only, and a Sionna RT receiver it puts on its floor."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np

from diffpos.channel.emulator import emulate_channel, pair_snr_db
from diffpos.estimators.mnls.rules import DEFAULT_SNR_RULE, SNR_SIGMA_DB, SnrRule, snr_radio
from diffpos.estimators.mnls.solver import mnls
from diffpos.paths.mechanisms import DIFFRACTION_SLOTS, MECHANISMS
from diffpos.scenario import default_scenario

_K = len(MECHANISMS)
_mn = sys.modules["diffpos.estimators.mnls.solver"]
_prob = sys.modules["diffpos.estimators.mnls.problem"]


def _nodes(b, n_per_floor: int = 6) -> np.ndarray:
    rng = np.random.default_rng(3)
    out = []
    for f in range(b.n_floors):
        z = b.floor_z_m(f) + rng.uniform(0.5, b.floor_height_m - 0.5, n_per_floor)
        x = rng.uniform(-b.width_m / 2 + 0.5, b.width_m / 2 - 0.5, n_per_floor)
        y = rng.uniform(0.5, b.depth_m - 0.5, n_per_floor)
        out.append(np.stack([x, y, z], axis=-1))
    return np.concatenate(out)


def test_snr_model_is_the_channels_sheet_edge():
    """With ``dielectric_edges`` M-NLS's radio gives every one of the 18 slots the SNR of the
    numpy emulator at channel order 3 (1e-6 dB, same non-existing slots); the specular slots
    are those of the order-2 conductor, the sill's and lintel's diffraction is not (median
    |difference| > 0.5 dB on the paper building); the default rule and a radio already at
    order >= 3 are left as they are."""
    sc = default_scenario()
    b, radio = sc.building, sc.radio
    assert radio.channel_max_order == 2
    anchors = np.asarray(sc.anchor_positions_m(), dtype=np.float64)
    nodes = _nodes(b)
    sheet = snr_radio(radio, SnrRule(dielectric_edges=1.0))
    got = pair_snr_db(anchors, nodes, building=b, radio=sheet)
    ref = emulate_channel(anchors, nodes, building=b,
                          radio=dataclasses.replace(radio, channel_max_order=3)).snr_db[..., :_K]
    np.testing.assert_array_equal(np.isfinite(got), np.isfinite(ref))
    fin = np.isfinite(ref)
    np.testing.assert_allclose(got[fin], ref[fin], atol=1e-6, rtol=0)
    pec = pair_snr_db(anchors, nodes, building=b, radio=radio)
    diff = np.zeros(_K, dtype=bool)
    diff[list(DIFFRACTION_SLOTS)] = True
    both = np.isfinite(pec) & fin
    np.testing.assert_allclose(got[both & ~diff], pec[both & ~diff], atol=1e-9, rtol=0)
    d_lower = both[..., 8]
    assert d_lower.sum() > 20
    assert np.median(np.abs(got[..., 8][d_lower] - pec[..., 8][d_lower])) > 0.5
    assert snr_radio(radio, DEFAULT_SNR_RULE) is radio
    at3 = dataclasses.replace(radio, channel_max_order=3)
    assert snr_radio(at3, SnrRule(dielectric_edges=1.0)) is at3
    assert snr_radio(None, SnrRule(dielectric_edges=1.0)) is None


#: Sionna RT's paper building (docs/raytrace_study.md "Session 27"), receiver 177 of the study's
#: 200 (`diffpos raytrace paper --receivers 200 --samples 1000000 --max-depth 4`, the study's
#: first arrivals at seed 0): top floor (4) at (6.75, 10.0, 17.5), four anchors detected.
_R177 = {
    "truth_floor": 4,
    "range": [44.95541043059141, 33.85918019014048, 25.41560904304772, 38.4737623808426],
    "sigma": [0.05047779799574086, 0.06783247207918698, 0.0669822212849008,
              0.05316684251262638],
    "snr": [21.708172583835164, 5.2965514900851645, 5.5401733162570395, 13.37965085531954],
}


def _r177(rule):
    sc = default_scenario()
    radio = sc.radio
    return mnls(sc.anchor_positions_m(), np.array(_R177["range"]), np.array(_R177["sigma"]),
                building=sc.building, snr_db=np.array(_R177["snr"]), radio=radio, max_order=4,
                bandwidth_hz=radio.bandwidth_hz, error_floor_m=radio.range_error_floor_m,
                snr_rule=rule)


def test_sionna_receiver_on_its_floor_with_sheet_edges():
    """Sionna's receiver 177 (top floor, four links): with the skip prior (w 0.8) M-NLS
    publishes floor 1 (the true floor at p < 0.4: measured 0.36); with the sheet edges as
    well, floor 4 (measured p 0.70): what the option changes."""
    f = _R177["truth_floor"]
    off = _r177(SnrRule(first_arrival_prior=0.8))
    assert off.floor[0] != f
    assert off.floor_probability[0, f] < 0.4
    on = _r177(SnrRule(first_arrival_prior=0.8, dielectric_edges=1.0))
    assert on.floor[0] == f
    assert on.floor_probability[0, f] > 0.6


def test_unknown_edge_material_mixes_the_two_predictions():
    """``0 < dielectric_edges < 1``: each slot's SNR cost is ``-log((1 - q) exp(-c_pec) +
    q exp(-c_sheet))`` of the Gaussian terms of the conductor's and the sheet's prediction
    (both from the numpy emulator here), plus the detector's shortfall term of the radio's
    prediction; q = 0 is the default's cost bit for bit."""
    sc = default_scenario()
    b, radio = sc.building, sc.radio
    anchors = np.asarray(sc.anchor_positions_m(), dtype=np.float64)
    nodes = _nodes(b, 2)
    n, m = nodes.shape[0], anchors.shape[0]
    meas = np.random.default_rng(5).uniform(-8.0, 30.0, (n, m))
    floors = b.floor_index(nodes[:, 2])

    def cost(q):
        p = _prob._problem(np.broadcast_to(anchors, (n, m, 3)).copy(), np.full((n, m), 30.0),
                           np.full((n, m), 0.05), np.ones((n, m), dtype=bool), floors, b, 0.75,
                           np.full((n, m), np.nan), 0.0107, None, SnrRule(dielectric_edges=q))
        p.snr_meas, p.radio = meas, radio
        return _mn._snr_cost(p, nodes, b)

    pec = emulate_channel(anchors, nodes, building=b, radio=radio).snr_db[..., :_K]
    sheet = emulate_channel(anchors, nodes, building=b,
                            radio=dataclasses.replace(radio, channel_max_order=3)).snr_db[..., :_K]
    g_pec = 0.5 * ((meas[..., None] - pec) / SNR_SIGMA_DB) ** 2
    g_sheet = 0.5 * ((meas[..., None] - sheet) / SNR_SIGMA_DB) ** 2
    thr = np.maximum(pec.max(axis=-1, keepdims=True) - radio.fap_threshold_db,
                     radio.detection_snr_db)
    short = 0.5 * (np.maximum(thr - SNR_SIGMA_DB - meas[..., None], 0.0) / SNR_SIGMA_DB) ** 2
    fin = np.isfinite(pec)
    for q in (0.3, 0.5):
        want = -np.logaddexp(np.log(1 - q) - g_pec, np.log(q) - g_sheet) + short
        got = cost(q)
        np.testing.assert_array_equal(np.isfinite(got), fin)
        np.testing.assert_allclose(got[fin], want[fin], rtol=1e-9, atol=1e-9)
        assert np.any(np.abs(got[fin] - (g_pec + short)[fin]) > 0.05)
    np.testing.assert_array_equal(cost(0.0), _mn._snr_cost(
        dataclasses.replace(_prob._problem(
            np.broadcast_to(anchors, (n, m, 3)).copy(), np.full((n, m), 30.0),
            np.full((n, m), 0.05), np.ones((n, m), dtype=bool), floors, b, 0.75,
            np.full((n, m), np.nan), 0.0107, None, None), snr_meas=meas, radio=radio), nodes, b))
