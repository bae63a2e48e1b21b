"""M-NLS's use of the detector's rule (:class:`diffpos.estimators.mnls.rules.SnrRule`, session
26): the soft skip prior against a brute-force product over the earlier paths, the measured
first arrival's lower bound on the detector threshold, the compiled M-NLS equal to its numpy
reference with both on, and the default M-NLS unchanged."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from scipy.stats import norm

from diffpos.channel.detection import skipped_cost
from diffpos.channel.emulator import emulate_channel, first_arrival, pair_snr_db
from diffpos.estimators.mnls.rules import DEFAULT_SNR_RULE, SNR_SIGMA_DB, SnrRule
from diffpos.estimators.mnls.solver import mnls
from diffpos.scenario import Radio, default_scenario

_mn = sys.modules["diffpos.estimators.mnls.solver"]
_prob = sys.modules["diffpos.estimators.mnls.problem"]
_rules = sys.modules["diffpos.estimators.mnls.rules"]


def _brute(length, valid, pred, thr, w):
    """-log(w prod_{j existing, L_j < L_k} Phi((T - S_j) / sigma) + 1 - w), link by link."""
    out = np.zeros(length.shape)
    for idx in np.ndindex(length.shape[:-1]):
        ok = valid[idx] & np.isfinite(pred[idx])
        for k in range(length.shape[-1]):
            if not ok[k]:
                continue
            prod = 1.0
            for j in range(length.shape[-1]):
                if ok[j] and length[idx][j] < length[idx][k]:
                    prod *= norm.cdf((thr[idx][0] - pred[idx][j]) / SNR_SIGMA_DB)
            out[idx][k] = -np.log(w * prod + 1.0 - w)
    return out


def test_skip_cost_equals_the_product_over_earlier_paths():
    """Random links (18 slots, missing paths, -inf SNRs, exact length ties): the sorted
    cumulative form equals the pairwise product to 1e-12; the first arrival of a link pays
    nothing, a slot behind a path predicted 30 dB above the threshold about -log(1 - w)."""
    rng = np.random.default_rng(3)
    n, m, k = 40, 5, 18
    length = rng.uniform(10, 40, (n, m, k))
    length[..., 5] = length[..., 4]  # ties: neither is before the other
    valid = rng.random((n, m, k)) > 0.3
    pred = rng.uniform(-20, 50, (n, m, k))
    pred[rng.random((n, m, k)) < 0.1] = -np.inf
    thr = rng.uniform(0, 30, (n, m, 1))
    for w in (0.5, 0.8):
        got = skipped_cost(length, valid & np.isfinite(pred), pred, thr, SNR_SIGMA_DB, w)
        np.testing.assert_allclose(got, _brute(length, valid, pred, thr, w), rtol=1e-12,
                                   atol=1e-12)
    one = skipped_cost(np.array([[10.0, 12.0]]), np.array([[True, True]]),
                       np.array([[60.0, 20.0]]), np.array([[30.0]]), SNR_SIGMA_DB, 0.8)
    assert one[0, 0] == 0.0
    assert one[0, 1] == pytest.approx(-np.log(0.8 * norm.cdf(-30 / SNR_SIGMA_DB) + 0.2))


def _problem_with_snr(rule):
    sc = default_scenario()
    b, radio = sc.building, sc.radio
    anchors = sc.anchor_positions_m()
    x = np.array([[0.0, 10.0, b.floor_z_m(4) + 1.2]])
    a = anchors[None]
    r = np.linalg.norm(a[0] - x, axis=-1)[None] + 2.0
    p = _prob._problem(a, r, np.full(r.shape, 0.05), np.ones(r.shape, bool), np.array([4]), b,
                       0.75, np.full(r.shape, np.nan), radio.wavelength_m, rule=rule)
    return p, x, b, radio


def test_measured_first_arrival_raises_the_threshold():
    """A first arrival measured far stronger than the model's strongest path: with the
    measured lower bound no earlier path is 'surely detected' unless predicted within
    fap_threshold_db - SNR_SIGMA_DB of the measured SNR; the predicted threshold alone flags
    the model's strong paths (the hard rule's input), and the SNR cost is otherwise equal."""
    p0, x, b, radio = _problem_with_snr(DEFAULT_SNR_RULE)
    p1, *_ = _problem_with_snr(SnrRule(measured_threshold=True))
    for p in (p0, p1):
        p.radio = radio
    # the measured SNR: 25 dB above the model's strongest path of each link
    s = pair_snr_db(p0.anchors, x, building=b, radio=radio)
    meas = np.max(s, axis=-1) + 25.0
    p0.snr_meas = p1.snr_meas = meas
    c0, c1 = _mn._snr_cost(p0, x, b), _mn._snr_cost(p1, x, b)
    np.testing.assert_array_equal(c0, c1)
    assert p0.strong.any()
    thr = meas[..., None] - radio.fap_threshold_db
    np.testing.assert_array_equal(p1.strong, s >= thr + SNR_SIGMA_DB)
    assert not p1.strong.any()


def _same_fixes(got, ref) -> None:
    """As tests/core/test_mnls.py: same floors, mechanisms, statuses, links used; positions
    and floor probabilities to 1e-9."""
    for k in ("floor", "mechanism", "status", "used", "excluded"):
        np.testing.assert_array_equal(getattr(got, k), getattr(ref, k), err_msg=k)
    np.testing.assert_allclose(got.position_m, ref.position_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.floor_probability, ref.floor_probability, rtol=0,
                               atol=1e-9)


def test_compiled_equals_reference_with_the_rule_on_and_default_is_unchanged():
    """12 emulated fixes on the paper's building (a caller's mask with gaps): with the
    measured threshold and the skip prior on (with and without the hard rule kept),
    ``kernel=True`` equals the numpy reference
    steps (the rule enters both through the same SNR terms); the default ``SnrRule()`` is
    bitwise the call without it; and the rule changes some fix's cost (it is applied)."""
    sc = default_scenario()
    b, anchors, radio = sc.building, sc.anchor_positions_m(), Radio()
    rng = np.random.default_rng(26)
    n = 12
    x0, x1 = b.edge_x_m
    k = rng.integers(0, b.n_floors, n)
    nodes = np.column_stack([rng.uniform(x0 + 0.5, x1 - 0.5, n), rng.uniform(0.5, 20.0, n),
                             b.floor_z_m(k) + rng.uniform(0.3, b.floor_height_m - 0.3, n)])
    fa = first_arrival(emulate_channel(anchors, nodes, building=b, radio=radio), radio=radio,
                       rng=rng)
    mask = fa.detected & (rng.random(fa.detected.shape) > 0.1)
    args = (np.broadcast_to(anchors, (n, *anchors.shape)),
            np.where(fa.detected, fa.range_m, 0.0), np.where(fa.detected, fa.sigma_m, 1.0))
    kw = {"mask": mask, "building": b, "snr_db": fa.snr_db, "radio": radio}
    for on in (SnrRule(True, 0.8, keep_hard_rule=True), SnrRule(True, 0.8)):
        got = mnls(*args, snr_rule=on, **kw)
        _same_fixes(got, mnls(*args, snr_rule=on, kernel=False, **kw))
    base = mnls(*args, **kw)
    same = mnls(*args, snr_rule=SnrRule(), **kw)
    np.testing.assert_array_equal(base.position_m, same.position_m)
    np.testing.assert_array_equal(base.floor_probability, same.floor_probability)
    assert not np.allclose(got.cost, base.cost, equal_nan=True)
    with pytest.raises(ValueError):
        SnrRule(first_arrival_prior=1.0)


#: Sionna RT's paper building (docs/raytrace_study.md "Session 26"), receiver 163 of the study's
#: 200 (`diffpos raytrace paper --receivers 200 --samples 1000000 --max-depth 4`, the study's
#: first arrivals at seed 0): top floor (4) at (-12.25, 2.5, 17.5), four anchors detected.
_R163 = {
    "truth_floor": 4,
    "range": [29.94131955847266, 29.60028558684614, 21.07203164948355, 41.38768343977155],
    "sigma": [0.05005665814449021, 0.050007494817127233, 0.05333364305581977,
              0.05018641847414208],
    "snr": [30.986233496921102, 39.77338101889376, 13.149708533542196, 25.808338904635946],
}


def _r163(rule):
    sc = default_scenario()
    radio = sc.radio
    return mnls(sc.anchor_positions_m(), np.array(_R163["range"]), np.array(_R163["sigma"]),
                building=sc.building, snr_db=np.array(_R163["snr"]), radio=radio, max_order=3,
                bandwidth_hz=radio.bandwidth_hz, error_floor_m=radio.range_error_floor_m,
                snr_rule=rule)


def test_top_floor_receiver_found_with_the_skip_prior():
    """Sionna's receiver 163 (top floor): M-NLS with the detector's rule as the tracker's
    (measured lower bound on the threshold, skip prior w = 0.8) puts it on its floor at
    p >= 0.99; the default M-NLS (hard rule, predicted threshold) publishes floor 2 (the
    true floor at p < 0.5): what the option changes."""
    on = _r163(SnrRule(measured_threshold=True, first_arrival_prior=0.8))
    assert on.floor[0] == _R163["truth_floor"]
    assert on.floor_probability[0, _R163["truth_floor"]] >= 0.99
    off = _r163(DEFAULT_SNR_RULE)
    assert off.floor[0] != _R163["truth_floor"]
    assert off.floor_probability[0, _R163["truth_floor"]] < 0.5
