"""Dormant hypotheses of the tracker (diffpos.tracking.tracker, ``TrackerConfig.dormant``).

A hypothesis the data has decided against skips its measurement update until a refresh, an
inflow of probability through a physical transition, or a poorly fitting best hypothesis
wakes it. References: the full run (every hypothesis updated every epoch, ``dormant=False``),
the (N, H) measurement update of :func:`diffpos.tracking.model.measurement_update`, closed-form
refresh times, the IMM's own predicted probabilities. Ranges and SNR from the emulator's
channel (fixed seeds); tolerances stated per test.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.tracking.evidence import model_doubt
from diffpos.tracking.imm import _mix
from diffpos.tracking.links import Links
from diffpos.tracking.model import measurement_update
from diffpos.tracking.state import (
    TrackerConfig,
    TrackStatus,
    hypothesis_floor,
    hypothesis_vertical,
    published_floor_probabilities,
)
from diffpos.tracking.tracker import (
    _dormant_log_p,
    _refresh_due,
    _update_pairs,
    init_state,
    predict,
    update,
)
from diffpos.trajectory import trajectory_from_dict

SC = default_scenario()
B = SC.building
RADIO = SC.radio
#: the contest rule off: the published probabilities are recomputed from the state below
ON = TrackerConfig(dormant=True, floor_contest_s=0.0)
OFF = TrackerConfig(dormant=False, floor_contest_s=0.0)
ANCHORS8 = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.0],
                     [-25.0, -12.0, 3.0], [25.0, -12.0, 3.0], [-8.0, -10.0, 2.0],
                     [8.0, -25.0, 0.5]])


def _walker(points, speed=1.0):
    return trajectory_from_dict({"kind": "waypoints", "points_m": points, "speed_m_s": speed})


def _inputs(position_fn, n: int, t_s, seed: int):
    """Epochs ``(t_ns, anchors, ranges, sigmas, mask, snr, truth)`` of ``n`` nodes at
    ``position_fn(t)`` (n, 3), the emulator's channel and detector."""
    rng = np.random.default_rng(seed)
    out = []
    for t in t_s:
        nodes = position_fn(t)
        fa = first_arrival(emulate_channel(ANCHORS8, nodes, building=B, radio=RADIO),
                           radio=RADIO, rng=rng)
        out.append((round(t * 1e9), np.broadcast_to(ANCHORS8, (n, *ANCHORS8.shape)),
                    fa.range_m, fa.sigma_m, fa.detected, fa.snr_db, nodes))
    return out


def _track(inputs, config, rows=None):
    """Run the tracker over ``inputs`` (only the nodes ``rows``); states and outputs."""
    sel = slice(None) if rows is None else rows
    state = init_state(inputs[0][2][sel].shape[0], B)
    states, outs = [], []
    for t_ns, a, r, s, m, snr, _ in inputs:
        state, out = update(state, a[sel], r[sel], s[sel], m[sel], t_ns, B, config,
                            snr_db=snr[sel], radio=RADIO)
        states.append(state)
        outs.append(out)
    return states, outs


WALKERS = [_walker([[-5.0, 4.0, 8.5], [5.0, 4.0, 8.5]]),
           _walker([[3.0, 9.0, 11.5], [3.0, 2.0, 11.5]], speed=0.8),
           _walker([[-12.0, 15.0, 5.5], [-4.0, 15.0, 5.5]], speed=1.2)]


@functools.lru_cache(maxsize=1)
def _walk_inputs():
    return _inputs(lambda t: np.stack([w.position_m(t) for w in WALKERS]), len(WALKERS),
                   np.arange(0.0, 3.0, 0.1), seed=3)


def test_pair_update_equals_the_full_layout():
    """The per-pair measurement update (each (node, hypothesis) as a node with one
    hypothesis) gives bit-identical means, covariances, evidences, mechanisms, NIS and
    residuals to :func:`measurement_update` over the (N, H) bank, on the predicted state of a
    real run (3 walkers, 8 UAVs, SNR, epoch 8)."""
    # the 18 alone (families: test_tracking_families); the edge retry's second update and the
    # persistent mechanism prior (session 27 defaults) are the tracker's, not this layout's
    off = dataclasses.replace(OFF, max_order=2, edge_retry_margin_m=0.0,
                              mechanism_prior_min_links=0)
    inputs = _walk_inputs()
    states, _ = _track(inputs[:8], off)
    t_ns, a, r, s, m, snr, _ = inputs[8]
    st = predict(states[-1], t_ns, B, off)
    links = Links.from_arrays(a, r, s, m, off.sigma_model_m, snr_db=snr, radio=RADIO)
    nf = B.n_floors
    x, p, ev, sel, res = measurement_update(st.mean, st.cov, links, hypothesis_floor(nf), B, off,
                                            level=~hypothesis_vertical(nf))
    rr, cc = np.nonzero(np.ones(st.log_prob.shape, bool))
    got = _update_pairs(st.mean, st.cov, links, rr, cc, nf, B, off)
    for g, ref in zip(got, (x, p, ev, sel.slot, sel.nis, res, sel.log_weight), strict=True):
        assert np.array_equal(g, ref[rr, cc], equal_nan=True)


def test_dormant_run_matches_the_full_run_and_is_row_independent():
    """3 walkers on 3 floors, 8 UAVs, 3 s: with dormant hypotheses (most of the bank is
    dormant after the tracks are confirmed: >= 50 % of the hypotheses in the last second) the
    published floor equals the full run's in every node-epoch, the position within 1 cm for
    95 % of node-epochs and 5 cm for all; a node tracked alone gives bit-identical outputs to
    its row of the 3-node run (what replay == live relies on), and so does the run with every
    time shifted by a constant (a live run's times are wall-clock);
    :func:`published_floor_probabilities` of the state is the published floor marginal (bit
    for bit, rows sum to 1 within 1e-12)."""
    inputs = _walk_inputs()
    s_on, o_on = _track(inputs, ON)
    _, o_off = _track(inputs, OFF)
    dormant = np.mean([np.isfinite(s.dormant_llr).mean() for s in s_on[-10:]])
    assert dormant >= 0.5, dormant
    assert any(np.any(s.status == TrackStatus.TRACKING) for s in s_on)
    f_on = np.array([o.floor_index for o in o_on])
    f_off = np.array([o.floor_index for o in o_off])
    assert np.array_equal(f_on, f_off)
    d = np.linalg.norm(np.array([o.position_m for o in o_on])
                       - np.array([o.position_m for o in o_off]), axis=-1)
    assert np.percentile(d, 95) < 0.01 and d.max() < 0.05, (np.percentile(d, 95), d.max())
    # published_floor_probabilities(): the published floor marginal, bit for bit
    last = s_on[-1]
    p = published_floor_probabilities(
        last.log_prob, ON, link_ev=last.link_ev, link_all=last.link_all,
        doubt=model_doubt(last.log_prob, last.link_out, last.link_all, ON,
                          np.sum(np.asarray(inputs[-1][4], bool) & np.isfinite(inputs[-1][2]),
                                 axis=1)))
    assert np.array_equal(p, o_on[-1].floor_probabilities)
    np.testing.assert_allclose(p.sum(axis=1), 1.0, atol=1e-12)
    _, alone = _track(inputs, ON, rows=[1])
    # every input time shifted by a wall-clock-like constant: bit-identical outputs
    shift = 1_795_770_043_376_313_643
    _, shifted = _track([(t + shift, *rest) for t, *rest in inputs], ON)
    for o, os_ in zip(o_on, shifted, strict=True):
        for f in ("position_m", "covariance_m2", "floor_probabilities", "nis"):
            assert np.array_equal(getattr(o, f), getattr(os_, f), equal_nan=True), f
    for o, oa in zip(o_on, alone, strict=True):
        for f in ("position_m", "covariance_m2", "floor_probabilities", "residual_m", "nis"):
            assert np.array_equal(getattr(o, f)[1:2], getattr(oa, f), equal_nan=True), f


def test_dormant_floor_revived_after_a_lift_ride():
    """A node standing 3 s on one floor, then on another at the same (x, y) (a lift: no
    stairs motion, so no probability flows into the new floor through the mixing), 8 UAVs,
    SNR. Before the ride the new floor's hypotheses are dormant; they get a real update
    within ``dormant_refresh_s`` of the ride, the published floor is the new one within 3 s
    and stays so over the last second, and it gets there at most ``dormant_refresh_s`` later
    than the full run (measured on six such rides: new floor after 0-2.6 s with dormant
    hypotheses, 0-3.1 s in the full run; this one: 0.9 s and 0 s)."""
    t_s = np.arange(0.0, 6.0, 0.1)
    k_ride = 30
    for x, y, f_a, f_b in ((4.0, 6.0, 1, 2),):
        za, zb = (float(B.floor_z_m(f)) + B.nominal_node_height_m for f in (f_a, f_b))
        inputs = _inputs(lambda t, za=za, zb=zb, x=x, y=y: np.array(
            [[x, y, za if t < t_s[k_ride] - 1e-9 else zb]]), 1, t_s, seed=5)
        on_b = hypothesis_floor(B.n_floors) == f_b
        s_on, o_on = _track(inputs, ON)
        _, o_off = _track(inputs, OFF)
        assert o_on[k_ride - 1].floor_index[0] == f_a
        assert np.all(np.isfinite(s_on[k_ride - 1].dormant_llr[0, on_b]))  # dormant before
        k_up = k_ride + round(ON.dormant_refresh_s * 10)
        woken = [np.all(s.updated_ns[0, on_b] >= inputs[k_ride][0]) for s in s_on[k_ride:k_up]]
        assert any(woken)
        f_on = np.array([o.floor_index[0] for o in o_on])
        f_off = np.array([o.floor_index[0] for o in o_off])
        assert np.all(f_on[-10:] == f_b) and np.all(f_off[-10:] == f_b)
        settled_on = np.flatnonzero(f_on != f_b)[-1] + 1
        settled_off = np.flatnonzero(f_off != f_b)[-1] + 1
        assert t_s[settled_on] - t_s[k_ride] <= 3.0 + 1e-9
        assert settled_on - settled_off <= round(ON.dormant_refresh_s * 10), (x, y)


def test_refresh_schedule_once_per_period_spread_over_the_period():
    """10 Hz epochs over 5 s, every hypothesis updated when :func:`_refresh_due` says so:
    after its first refresh every hypothesis is refreshed exactly every ``dormant_refresh_s``
    (the closed form: at ``k T - h T / H``), and no epoch refreshes more than ``ceil(H / 10)``
    hypotheses (10 epochs per period)."""
    h, period = 10, 1.0
    origin = 1_795_770_043_376_313_643  # a wall-clock time in ns: the schedule is relative
    upd = np.full((1, h), origin, np.int64)
    times = [[] for _ in range(h)]
    for k in range(1, 51):
        t = np.array([origin + k * 10**8], np.int64)
        due = _refresh_due(upd, t, np.array([origin]), period)[0]
        assert due.sum() <= 1
        for j in np.flatnonzero(due):
            times[j].append(k * 10**8)
        upd[0, due] = t[0]
    for j in range(h):
        gaps = np.diff(times[j])
        assert gaps.size >= 3 and np.all(gaps == 10**9), (j, times[j])
        # first refresh at the first epoch on or after T - h T / H (after the origin)
        assert times[j][0] == max(10**8, 10**9 - j * 10**8)


def test_threshold_is_below_the_jump_mass():
    """A hypothesis the data does not decide against never becomes dormant: with all the
    probability on one hypothesis, the IMM's predicted probability of every other floor in
    the same mode (the jump's mass, from :func:`_mix` itself) is above the dormant threshold
    by the margin (within 1e-6 nats), at 1, 10 and 100 Hz and for 2-7 floors."""
    for n_floors in (2, 5, 7):
        b = dataclasses.replace(B, n_floors=n_floors)
        st = init_state(1, b)
        h = 2 * n_floors
        mean = np.zeros((1, h, 6))
        mean[0, :, 2] = b.floor_z_m(hypothesis_floor(n_floors)) + b.nominal_node_height_m
        lp = np.full((1, h), -700.0)
        lp[0, 0] = 0.0
        st = dataclasses.replace(st, mean=mean, cov=np.broadcast_to(np.eye(6) * 0.01,
                                                                   (1, h, 6, 6)).copy(),
                                 log_prob=lp, status=np.array([2], np.int8))
        for dt in (1.0, 0.1, 0.01):
            _, _, log_pred, _ = _mix(st, np.array([dt]), b, ON)
            thr = _dormant_log_p(np.array([dt]), n_floors, ON)[0]
            others = log_pred[0, 1:n_floors]
            assert np.all(others >= thr + ON.dormant_margin_nats - 1e-6), (n_floors, dt)
