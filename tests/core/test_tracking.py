"""Tracker (diffpos.tracking): motion model, measurement update, lifecycle, determinism.

Every reference is independent of the code under test: Van Loan's matrix-exponential
discretisation for the process noise, a brute-force grid posterior for the update, the
emulator's channel for the ranges. Fixed seeds, tolerances stated per test.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

from diffpos.channel import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.tracking import (
    TrackerConfig,
    TrackStatus,
    init_state,
    process_noise,
    update,
)
from diffpos.tracking_model import Links, Selection, eval_paths, iekf
from diffpos.trajectory import trajectory_from_dict

SC = default_scenario()
B = SC.building
RADIO = SC.radio
CFG = TrackerConfig()
ANCHORS8 = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.0],
                     [-25.0, -12.0, 3.0], [25.0, -12.0, 3.0], [-8.0, -10.0, 2.0],
                     [8.0, -25.0, 0.5]])


def _epochs(traj_list, anchors, t_s, seed):
    rng = np.random.default_rng(seed)
    for t in t_s:
        nodes = np.stack([tr.position_m(t) for tr in traj_list])
        fa = first_arrival(emulate_channel(anchors, nodes, building=B, radio=RADIO),
                           radio=RADIO, rng=rng)
        a = np.broadcast_to(anchors, (len(traj_list), *anchors.shape))
        yield round(t * 1e9), a, fa.range_m, fa.sigma_m, fa.detected, nodes, fa.snr_db


def _walker(points, speed=1.0):
    return trajectory_from_dict({"kind": "waypoints", "points_m": points, "speed_m_s": speed})


def test_process_noise_matches_van_loan():
    """Q(dt) equals the exact discretisation of white acceleration (rtol 1e-10)."""
    dt = 0.37
    f = np.zeros((6, 6))
    f[:3, 3:] = np.eye(3)
    g = np.zeros((6, 3))
    g[3:] = np.eye(3)
    qc = np.diag([CFG.q_h_m2_s3, CFG.q_h_m2_s3, CFG.q_v_m2_s3])
    m = np.block([[-f, g @ qc @ g.T], [np.zeros((6, 6)), f.T]]) * dt
    e = expm(m)
    phi = e[6:, 6:].T
    q_ref = phi @ e[:6, 6:]
    np.testing.assert_allclose(process_noise(dt, CFG), q_ref, rtol=1e-10, atol=1e-14)


def test_update_matches_grid_posterior():
    """IEKF posterior mean/covariance vs a brute-force grid posterior (one floor, fixed
    mechanisms: the lower-edge diffraction of 6 anchors). Tolerances: mean within 0.15 sigma,
    standard deviations within 15 % (the Laplace approximation of a mildly nonlinear model)."""
    truth = np.array([2.0, 3.0, 8.4])
    floor = 1
    anchors = ANCHORS8[:6]
    pe = eval_paths(truth[None], anchors, floor, B, 0.0, slots=[8])
    assert np.all(pe.strict)
    rho = pe.length[:, 0] + np.array([0.03, -0.05, 0.02, 0.04, -0.01, 0.0])
    sig = np.full(6, 0.05)
    links = Links.from_arrays(anchors[None], rho[None], sig[None], np.ones((1, 6), bool), 0.0)
    x0 = np.zeros((1, 1, 6))
    x0[0, 0, :3] = truth + np.array([0.1, -0.15, 0.05])
    p0 = np.diag([0.2, 0.2, 0.1, 1.0, 1.0, 0.1]) ** 2
    sel = Selection(slot=np.full((1, 1, 6), 8), log_weight=np.zeros((1, 1, 6)),
                    nis=np.zeros((1, 1, 6)), extra_var=np.zeros((1, 1, 6)))
    cfg = TrackerConfig(height_sigma_m=1e6, stairs_weight=1e-9, gn_iterations=8)
    x, p, _, _ = iekf(x0, p0[None, None], links, np.array([floor]), sel, B, cfg)
    # grid posterior over position (velocity is unobserved: its marginal stays the prior's)
    sd = np.sqrt(np.diag(p[0, 0])[:3])
    ax = [np.linspace(x[0, 0, i] - 5 * sd[i], x[0, 0, i] + 5 * sd[i], 41) for i in range(3)]
    g = np.stack(np.meshgrid(*ax, indexing="ij"), axis=-1).reshape(-1, 3)
    pg = eval_paths(g[:, None, :], anchors[None], floor, B, 0.0, slots=[8])
    r = rho[None] - pg.length[..., 0]
    d = g - x0[0, 0, :3]
    logp = -0.5 * np.sum(r * r, axis=1) / 0.05**2 - 0.5 * np.einsum(
        "ki,ij,kj->k", d, np.linalg.inv(p0[:3, :3]), d)
    w = np.exp(logp - logp.max())
    w /= w.sum()
    mean = w @ g
    cov = (g - mean).T @ ((g - mean) * w[:, None])
    assert np.all(np.abs(x[0, 0, :3] - mean) < 0.15 * np.sqrt(np.diag(cov)))
    np.testing.assert_allclose(sd, np.sqrt(np.diag(cov)), rtol=0.15)


def _run(trajs, anchors, t_s, seed=0, cfg=CFG):
    state = init_state(len(trajs), B)
    outs = []
    for t_ns, a, r, s, m, truth, snr in _epochs(trajs, anchors, t_s, seed):
        state, out = update(state, a, r, s, m, t_ns, B, cfg, snr_db=snr, radio=RADIO)
        outs.append((out, truth))
    return state, outs


def test_coasting_grows_covariance():
    """Without ranges the status is COASTING and the covariance trace grows every epoch."""
    tr = [_walker([[-5.0, 4.0, 8.5], [5.0, 4.0, 8.5]])]
    state, _ = _run(tr, ANCHORS8, np.arange(0, 1.0, 0.1))
    traces = []
    n, m = 1, len(ANCHORS8)
    for k in range(1, 11):
        state, out = update(state, np.zeros((n, m, 3)), np.full((n, m), np.nan),
                            np.full((n, m), np.inf), np.zeros((n, m), bool),
                            round((1.0 + 0.1 * k) * 1e9), B, CFG)
        assert out.status[0] == TrackStatus.COASTING
        traces.append(np.trace(out.covariance_m2[0]))
    assert np.all(np.diff(traces) > 0)


def test_deterministic_bit_identical():
    """Two runs on the same inputs give bit-identical outputs."""
    tr = [_walker([[-5.0, 4.0, 8.5], [5.0, 4.0, 8.5]]), _walker([[3.0, 9.0, 11.5], [3.0, 2.0, 11.5]])]
    t = np.arange(0, 0.6, 0.1)
    _, o1 = _run(tr, ANCHORS8, t)
    _, o2 = _run(tr, ANCHORS8, t)
    for (a, _), (b, _) in zip(o1, o2, strict=True):
        for f in ("position_m", "covariance_m2", "floor_probabilities", "residual_m"):
            assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True)
        assert np.array_equal(a.mechanism, b.mechanism)


def test_divergence_reinitialises():
    """Ranges that jump to a node 12 m away make the track re-initialise (INITIALISING again
    within diverge_epochs + 2 epochs) and the new position is near the new truth (< 3 m)."""
    tr = [_walker([[-8.0, 4.0, 8.5], [-6.0, 4.0, 8.5]], speed=0.5)]
    state, _ = _run(tr, ANCHORS8, np.arange(0, 1.0, 0.1))
    jumped = [_walker([[6.0, 15.0, 8.5], [6.5, 15.0, 8.5]], speed=0.2)]
    seen = False
    for t_ns, a, r, s, m, truth, snr in _epochs(jumped, ANCHORS8, 1.0 + 0.1 * np.arange(16), 1):
        state, out = update(state, a, r, s, m, t_ns, B, CFG, snr_db=snr, radio=RADIO)
        if out.status[0] == TrackStatus.INITIALISING:
            seen = True
            assert np.linalg.norm(out.position_m[0] - truth[0]) < 3.0
            break
    assert seen


def test_stairs_floor_change_within_2s():
    """A responder walking up and one walking down the stairs (1.2 m/s, 6 m run per 3 m
    rise, 8 UAVs, ranges and SNR of the emulator's channel; both tracked in one vectorised
    run, which halves the cost of two runs) change floor in the estimate within 2 s of the
    truth and stay there; before, each was on the right floor for >= 80 % of the epochs
    after the first second."""
    z0 = float(B.floor_z_m(1)) + B.nominal_node_height_m
    pts = [[10.0, 5.0, z0], [12.0, 5.0, z0], [12.0, 7.0, z0], [6.0, 7.0, z0 + 3.0],
           [2.0, 7.0, z0 + 3.0]]
    trs = [_walker(pts, speed=1.2), _walker(pts[::-1], speed=1.2)]
    t = np.arange(0, 11.0, 0.1)
    _, outs = _run(trs, ANCHORS8, t)
    for i, (f_from, f_to) in enumerate([(1, 2), (2, 1)]):
        true_f = np.array([B.floor_index(tr_[i, 2]) for _, tr_ in outs])
        est_f = np.array([o.floor_index[i] for o, _ in outs])
        assert true_f[-1] == f_to
        t_true = t[np.argmax(true_f == f_to)]
        settled = np.flatnonzero(est_f != f_to)
        assert settled.size == 0 or settled[-1] + 1 < t.size, "never settled on the new floor"
        t_est = t[settled[-1] + 1] if settled.size else t[0]
        assert t_est - t_true <= 2.0, (i, t_est, t_true)
        before = (t >= 1.0) & (t < t_true - 1.0)
        assert np.mean(est_f[before] == f_from) >= 0.8  # and it was on the right floor before
