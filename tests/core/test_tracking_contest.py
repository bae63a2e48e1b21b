"""The published floor probabilities after a contest (``TrackerConfig.floor_contest_s`` /
``floor_contest_kappa``, :func:`diffpos.tracking.state.floor_contested`; issue 34 item 5).

The first test's fixture is physics we did not write (the Sionna RT receiver of
tests/core/test_tracking_doubt.py: mean first arrivals traced at a static receiver on floor 4
of the paper building), with three of its four UAVs: three ranges fit a position on any floor,
so the floor is never tested by them, and the tracker (the emulator's path model) puts the
receiver on floor 1 and publishes it at p >= 0.95 without the rule.
"""

from __future__ import annotations

import numpy as np

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.tracking.state import TrackerConfig, evidence_temper
from diffpos.tracking.tracker import init_state, update
from diffpos.trajectory import trajectory_from_dict

SC = default_scenario()
B = SC.building
KEEP = [0, 2, 3]  # the doubt test's UAVs 0, 2, 3
ANCHORS = np.array([[-15.0, -20.0, 1.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.0]])
RANGE_M = np.array([44.967, 25.49, 40.233])
SIGMA_M = np.array([0.05, 0.067, 0.05])
SNR_DB = np.array([21.7, 5.5, 28.3])
RX = np.array([6.75, 10.0, 17.5])  # floor 4


def _static(cfg: TrackerConfig, seed: int, epochs: int = 40):
    rng = np.random.default_rng(seed)
    st = init_state(1, B)
    for k in range(epochs):
        r = RANGE_M + rng.standard_normal(3) * SIGMA_M
        s = SNR_DB + rng.standard_normal(3)
        st, out = update(st, ANCHORS[None], r[None], SIGMA_M[None], np.ones((1, 3), bool),
                         k * 100_000_000, B, cfg, snr_db=s[None], radio=SC.radio)
    return st, out


def test_three_ranges_do_not_publish_a_mirror_floor_confident():
    """Seeds 0-2, after 4 s: without the rule the wrong floor 1 (truth 4) is published at
    >= 0.95 (measured 0.97-0.98); with ``floor_contest_s`` 3 s below 0.8 (measured
    0.65-0.69: three ranges keep the floor contested, its log-odds divided by 10 instead of
    3.9); the filter is the same (floor, position and state bit for bit): publication only."""
    assert B.floor_index(RX[2]) == 4
    for seed in range(3):
        st0, old = _static(TrackerConfig(floor_contest_s=0.0), seed)
        st1, new = _static(TrackerConfig(floor_contest_s=3.0), seed)
        assert old.floor_index[0] == new.floor_index[0] != 4
        assert old.floor_probabilities[0, old.floor_index[0]] >= 0.95
        assert new.floor_probabilities[0, new.floor_index[0]] < 0.8
        assert np.array_equal(new.position_m, old.position_m)
        assert np.array_equal(st0.log_prob, st1.log_prob)
        assert st1.lead_ns[0] == 39 * 100_000_000  # contested in every epoch (three ranges)


def _expected(log_prob, prev_floor, lead_ns, n_meas, t_ns, cfg):
    """One node's published floor probabilities by the rule's definition, computed here from
    the state's hypotheses (no doubt mix): the floor log-marginals by logaddexp of the two
    vertical modes, contested when the top floor changed, is below 1/2 or fewer than four
    ranges; the log-odds divided by floor_contest_kappa within floor_contest_s, else by kappa."""
    nf = log_prob.size // 2
    lf = np.logaddexp(log_prob[:nf], log_prob[nf:])
    top = int(np.argmax(lf))
    if top != prev_floor or np.exp(lf[top]) < 0.5 or n_meas < 4:
        lead_ns = t_ns
    recent = (t_ns - lead_ns) * 1e-9 < cfg.floor_contest_s
    k = cfg.floor_contest_kappa if recent else evidence_temper(cfg)
    q = np.exp((lf - lf.max()) / k)
    return q / q.sum(), top, lead_ns, recent


def test_published_log_odds_follow_the_contest_clock():
    """A walker on floor 1 of the default scenario (the emulator's channel, four UAVs; the
    fourth UAV's range dropped for epochs 15-19): every epoch's published probabilities equal
    the rule's definition computed independently from the state (rtol 1e-9), some epochs are
    within ``floor_contest_s`` of a contest and some not, the contested ones differ from the
    rule off, and the floor and position are those of the rule off bit for bit."""
    anchors = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0],
                        [15.0, -20.0, 1.0]])
    walker = trajectory_from_dict({"kind": "waypoints", "speed_m_s": 1.0,
                                   "points_m": [[-5.0, 4.0, 8.0], [5.0, 4.0, 8.0]]})
    assert B.floor_index(8.0) == 1
    cfg_on = TrackerConfig(floor_contest_s=1.0, floor_model_doubt=False)
    cfg_off = TrackerConfig(floor_contest_s=0.0, floor_model_doubt=False)
    rng = np.random.default_rng(3)
    s_on, s_off = init_state(1, B), init_state(1, B)
    prev, lead, seen = -1, 0, set()
    for k in range(45):
        t = k * 0.1
        fa = first_arrival(emulate_channel(anchors, walker.position_m(t)[None], building=B,
                                           radio=SC.radio), radio=SC.radio, rng=rng)
        mask = fa.detected.copy()
        if 15 <= k < 20:
            mask[:, 3] = False
        args = (anchors[None], fa.range_m, fa.sigma_m, mask, round(t * 1e9), B)
        s_on, on = update(s_on, *args, cfg_on, snr_db=fa.snr_db, radio=SC.radio)
        s_off, off = update(s_off, *args, cfg_off, snr_db=fa.snr_db, radio=SC.radio)
        assert np.array_equal(on.position_m, off.position_m, equal_nan=True)
        assert np.array_equal(on.floor_index, off.floor_index)
        if on.floor_index[0] < 0:
            continue
        n = int(np.count_nonzero(mask & np.isfinite(fa.range_m)))
        want, prev, lead, recent = _expected(s_on.log_prob[0], prev, lead, n, round(t * 1e9),
                                             cfg_on)
        if n < 3:  # the few-anchor cap (min_anchors_tracking) is applied after the rule
            continue
        np.testing.assert_allclose(on.floor_probabilities[0], want, rtol=1e-9, atol=1e-12)
        assert s_on.lead_ns[0] == lead
        if recent and off.floor_probabilities[0].max() < 1 - 1e-9:
            assert not np.allclose(on.floor_probabilities, off.floor_probabilities, rtol=1e-6)
        seen.add(bool(recent))
    assert seen == {True, False}
