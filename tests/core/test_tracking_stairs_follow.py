"""The hypotheses that follow their node's leading hypothesis horizontally
(``TrackerConfig.stairs_follow``, :func:`diffpos.tracking.imm._follow_leader`; issue 34).

References: the followers of a leader written out as a loop over (floor, mode); the new
covariance as ``E_h P_lead E_h + E_v P_own E_v`` with the diagonal selectors of the horizontal
(x, y, vx, vy) and vertical (z, vz) components; the NCV prediction written out (``x + dt v``).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from stairs_walk import walk as _walk

from diffpos.scenario import default_scenario
from diffpos.tracking.imm import _follow_leader, _follow_nodes
from diffpos.tracking.state import TrackerConfig, TrackStatus, floor_probabilities
from diffpos.tracking.tracker import init_state, predict
from diffpos.trajectory import trajectory_from_dict

SC = default_scenario()
B = SC.building
#: the following off with its gates (on by default since 2026-12-08: these tests state each
#: rule on its own)
OFF = TrackerConfig(stairs_follow=0, stairs_follow_settled_s=0.0, stairs_follow_m=0.0,
                    stairs_follow_min_links=0)
E_H = np.diag([1.0, 1.0, 0.0, 1.0, 1.0, 0.0])
E_V = np.eye(6) - E_H


def _followers(lead: int, nf: int, scope: int) -> set[int]:
    """Hypotheses ``h = mode * nf + floor`` following ``lead``, written out."""
    lf, out = lead % nf, set()
    for mode in (0, 1):
        for f in range(nf):
            h = mode * nf + f
            if h == lead:
                continue
            if (scope in (1, 3) and f == lf) or (scope in (2, 3) and mode == 1
                                                 and abs(f - lf) == 1):
                out.add(h)
    return out


def _random_bank(rng, n: int, h: int):
    x = rng.normal(0.0, 5.0, (n, h, 6))
    a = rng.normal(0.0, 1.0, (n, h, 6, 6))
    p = a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(6)
    return x, p


@pytest.mark.parametrize(("scope", "some", "far_m"), [(1, False, 0.0), (2, False, 0.0),
                                                      (3, False, 0.0), (3, True, 0.0),
                                                      (3, False, 6.0)])
def test_follow_leader_against_the_loop_reference(scope, some, far_m):
    """Random banks (seed 3, 40 nodes, 5 floors, random leaders; ``some``: only a random half
    of the nodes, the others as without followers; ``far_m``: only followers whose
    horizontal mean is farther than that from the leader's, ``math.dist``): each follower's
    horizontal mean is its leader's and its height / vertical speed its own (exact); its
    covariance is ``E_h P_lead E_h + E_v P_own E_v`` (exact) and positive definite; the
    leader and every other hypothesis are returned bit for bit."""
    rng = np.random.default_rng(3)
    n, nf = 40, 5
    x, p = _random_bank(rng, n, 2 * nf)
    lead = rng.integers(0, 2 * nf, n)
    nodes = rng.random(n) < 0.5 if some else None
    x1, p1 = x.copy(), p.copy()
    _follow_leader(x1, p1, lead, nf, scope, nodes, far_m)
    n_follow = n_near = 0
    for i in range(n):
        fol = _followers(int(lead[i]), nf, scope) if nodes is None or nodes[i] else set()
        near = {h for h in fol if math.dist(x[i, h, :2], x[i, lead[i], :2]) <= far_m}
        n_near += len(near)
        fol -= near
        n_follow += len(fol)
        for h in range(2 * nf):
            if h in fol:
                want_x = E_H @ x[i, lead[i]] + E_V @ x[i, h]
                want_p = E_H @ p[i, lead[i]] @ E_H + E_V @ p[i, h] @ E_V
                assert np.array_equal(x1[i, h], want_x)
                assert np.array_equal(p1[i, h], want_p)
                assert np.linalg.eigvalsh(p1[i, h]).min() > 0
            else:
                assert x1[i, h].tobytes() == x[i, h].tobytes()
                assert p1[i, h].tobytes() == p[i, h].tobytes()
    # one follower per node of its own floor, one or two neighbours' vertical modes
    k = n if nodes is None else int(nodes.sum())
    assert 0 < k < n or nodes is None
    lo, hi = {1: (k, k), 2: (k + 1, 2 * k - 1), 3: (2 * k + 1, 3 * k - 1)}[scope]
    assert lo <= n_follow + n_near <= hi
    assert (n_near > 10 and n_follow > 10) if far_m > 0 else n_near == 0


def _tracking_state(cfg: TrackerConfig):
    """One TRACKING node on floor 2 of the default scenario walking along x at 1 m/s: its
    level mode (the leader) at the truth, its vertical mode 5 m off with its own height
    0.4 m above the level mode's and a vertical speed, floor 1's vertical mode 4 m off."""
    nf = B.n_floors
    st = init_state(1, B)
    mean = np.zeros((1, 2 * nf, 6))
    z2 = float(B.floor_z_m(2)) + B.nominal_node_height_m
    mean[0, :, :3] = [0.0, 5.0, z2]
    mean[0, :nf, 3] = 1.0
    for f in range(nf):
        mean[0, f, 2] = mean[0, f + nf, 2] = float(B.floor_z_m(f)) + B.nominal_node_height_m
    mean[0, nf + 2, :] = [5.0, 5.0, z2 + 0.4, -0.5, 0.0, 0.3]
    mean[0, nf + 1, :2] = [-4.0, 5.0]
    lp = np.full((1, 2 * nf), -20.0)
    lp[0, 2], lp[0, nf + 2] = 0.0, -3.0
    cov = np.broadcast_to(np.diag([0.04, 0.04, 0.09, 0.1, 0.1, 0.01]), (1, 2 * nf, 6, 6)).copy()
    return dataclasses.replace(st, mean=mean, cov=cov, log_prob=lp - np.log(np.exp(lp).sum()),
                               status=np.array([TrackStatus.TRACKING], np.int8))


@pytest.mark.parametrize("scope", [0, 1, 2, 3])
def test_predicted_vertical_mode_follows_the_level_leader(scope):
    """A 0.1 s prediction of :func:`_tracking_state`: with the setting the floor's vertical
    mode (bit 1) and the vertical mode of floor 1 (bit 2) are predicted from the level leader's
    horizontal state (x + dt vx, y, by the NCV formula written out, 1e-12) and its own
    height (z + dt vz); off, it keeps its own track 5 m away; the floor probabilities are the
    same with and without."""
    nf = B.n_floors
    cfg = dataclasses.replace(OFF, stairs_follow=scope)
    st = _tracking_state(cfg)
    dt = 0.1
    out = predict(st, np.array([round(dt * 1e9)]), B, cfg)
    v2, v1 = out.mean[0, nf + 2], out.mean[0, nf + 1]
    lead_x = np.array([0.0 + dt * 1.0, 5.0])
    assert v2[2] == pytest.approx(st.mean[0, nf + 2, 2] + dt * 0.3, abs=1e-12)
    if scope & 1:
        np.testing.assert_allclose(v2[:2], lead_x, atol=1e-12)
        assert v2[3] == pytest.approx(1.0, abs=1e-12)
    else:
        np.testing.assert_allclose(v2[:2], [5.0 - dt * 0.5, 5.0], atol=1e-12)
    if scope & 2:
        np.testing.assert_allclose(v1[:2], lead_x, atol=1e-12)
    else:
        np.testing.assert_allclose(v1[:2], [-4.0, 5.0], atol=1e-12)
    off = predict(st, np.array([round(dt * 1e9)]), B, OFF)
    np.testing.assert_allclose(floor_probabilities(out.log_prob),
                               floor_probabilities(off.log_prob), atol=1e-12)
    assert np.linalg.eigvalsh(out.cov[0]).min() > 0


def test_stairs_walk_with_the_adjacent_floors_following():
    """The shared stairs walk (floor 2 down to floor 1, emulator, seed 11, 60 epochs) with
    ``stairs_follow`` 3: the published floor is the truth's (the building's floor of the
    walker's height) in every epoch, as without the setting, and the true floor's vertical
    mode stays within 0.5 m (horizontally) of the walker."""
    walker = trajectory_from_dict({"kind": "waypoints", "speed_m_s": 0.8, "points_m": [
        [-4.0, 4.0, 11.6], [-3.0, 4.0, 11.6], [3.0, 4.0, 8.4], [5.0, 4.0, 8.4]]})
    nf = B.n_floors
    outs = _walk(dataclasses.replace(OFF, stairs_follow=3), 60)
    for k, (out, st) in enumerate(outs):
        x = walker.position_m(k * 0.1)
        tf = int(np.floor((x[2] - B.first_floor_z_m) / B.floor_height_m))
        assert out.floor_index[0] == tf, k
        if k >= 5:  # after the start-up
            assert np.hypot(*(st.mean[0, nf + tf, :2] - x[:2])) < 0.5, k


@pytest.mark.parametrize("contested_s", [0.5, 5.0])
def test_followers_wait_for_a_settled_floor(contested_s):
    """``stairs_follow_settled_s`` 3: the node of :func:`_tracking_state` last contested 0.5 s
    before its last update keeps the vertical mode's own track (x - dt 0.5); one contested
    5 s before follows the leader (x + dt 1.0), as without the gate."""
    nf = B.n_floors
    cfg = dataclasses.replace(OFF, stairs_follow=1, stairs_follow_settled_s=3.0)
    st = _tracking_state(cfg)
    t0 = round(10e9)
    st = dataclasses.replace(st, t_ns=np.array([t0]),
                             lead_ns=np.array([t0 - round(contested_s * 1e9)]))
    out = predict(st, np.array([t0 + round(0.1e9)]), B, cfg)
    want = 0.1 if contested_s > 3.0 else 5.0 - 0.05
    assert out.mean[0, nf + 2, 0] == pytest.approx(want, abs=1e-12)


def test_follow_nodes_gates():
    """Which nodes may follow (:func:`diffpos.tracking.imm._follow_nodes`), written out: no
    gate, every node (None); ``stairs_follow_settled_s`` 3, the nodes last contested >= 3 s
    before their last update; ``stairs_follow_min_links`` 4, the nodes with >= 4 ranges in
    the epoch (none in a prediction without ranges); both, the conjunction."""
    st = _tracking_state(OFF)
    t = np.array([10_000_000_000] * 4)
    st = dataclasses.replace(
        st, t_ns=t, lead_ns=t - np.array([0, 2_999_999_999, 3_000_000_000, 9_000_000_000]),
        mean=np.repeat(st.mean, 4, 0), cov=np.repeat(st.cov, 4, 0),
        log_prob=np.repeat(st.log_prob, 4, 0), status=np.repeat(st.status, 4))
    n_meas = np.array([4, 5, 3, 0])
    base = OFF
    assert _follow_nodes(st, base, n_meas) is None
    settled = dataclasses.replace(base, stairs_follow_settled_s=3.0)
    links = dataclasses.replace(base, stairs_follow_min_links=4)
    both = dataclasses.replace(settled, stairs_follow_min_links=4)
    assert _follow_nodes(st, settled, n_meas).tolist() == [False, False, True, True]
    assert _follow_nodes(st, links, n_meas).tolist() == [True, True, False, False]
    assert _follow_nodes(st, links, None).tolist() == [False] * 4
    assert _follow_nodes(st, both, n_meas).tolist() == [False, False, False, False]
    assert _follow_nodes(st, both, np.array([4, 4, 4, 4])).tolist() == [False, False, True, True]


@pytest.mark.parametrize("tracked_s", [0.5, 5.0])
def test_followers_wait_for_a_tracked_node(tracked_s):
    """``stairs_follow_after_s`` 3: the node of :func:`_tracking_state` initialised 0.5 s
    before its last update keeps the vertical mode's own track (x - dt 0.5, as in
    :func:`test_followers_wait_for_a_settled_floor`); one initialised 5 s before follows the
    leader (x + dt 1.0), as without the gate."""
    nf = B.n_floors
    cfg = dataclasses.replace(OFF, stairs_follow=1, stairs_follow_after_s=3.0)
    st = _tracking_state(cfg)
    t0 = round(10e9)
    st = dataclasses.replace(st, t_ns=np.array([t0]), lead_ns=np.array([t0 - round(9e9)]),
                             refresh_origin_ns=np.array([t0 - round(tracked_s * 1e9)]))
    out = predict(st, np.array([t0 + round(0.1e9)]), B, cfg)
    want = 0.1 if tracked_s > 3.0 else 5.0 - 0.05
    assert out.mean[0, nf + 2, 0] == pytest.approx(want, abs=1e-12)


def test_follow_nodes_after_gate_against_a_loop():
    """``stairs_follow_after_s`` 3 (:func:`diffpos.tracking.imm._follow_nodes`), alone and
    with ``stairs_follow_settled_s`` 3 and ``stairs_follow_min_links`` 4: random nodes (seed
    5, 50 nodes, initialised and contested 0-6 s before their last update at whole
    milliseconds, 0-6 ranges) against the rule written out per node with integer
    nanoseconds (tracked >= 3 s, contested >= 3 s ago, >= 4 ranges)."""
    rng = np.random.default_rng(5)
    n = 50
    st = _tracking_state(OFF)
    t = np.full(n, 20_000_000_000, np.int64)
    age = rng.integers(0, 6000, n) * 1_000_000
    age[:3] = [2_999_000_000, 3_000_000_000, 0]
    quiet = rng.integers(0, 6000, n) * 1_000_000
    n_meas = rng.integers(0, 7, n)
    st = dataclasses.replace(
        st, t_ns=t, refresh_origin_ns=t - age, lead_ns=t - quiet,
        mean=np.repeat(st.mean, n, 0), cov=np.repeat(st.cov, n, 0),
        log_prob=np.repeat(st.log_prob, n, 0), status=np.repeat(st.status, n))
    after = dataclasses.replace(OFF, stairs_follow_after_s=3.0)
    every = dataclasses.replace(after, stairs_follow_settled_s=3.0, stairs_follow_min_links=4)
    want_after = [int(age[i]) >= 3_000_000_000 for i in range(n)]
    want_every = [want_after[i] and int(quiet[i]) >= 3_000_000_000 and int(n_meas[i]) >= 4
                  for i in range(n)]
    assert _follow_nodes(st, after, n_meas).tolist() == want_after
    assert _follow_nodes(st, after, None).tolist() == want_after
    assert _follow_nodes(st, every, n_meas).tolist() == want_every
    assert 0 < sum(want_every) < sum(want_after) < n
