"""diffpos.emulation: the anchor measurement model (pure, seeded)."""

from __future__ import annotations

import types

import numpy as np
import pytest

from diffpos.channel.linkbudget import db_to_linear, ranging_crlb_m
from diffpos.emulation import (
    NavigationError,
    TimeBase,
    clock_time_ns,
    emulation_nodes,
    first_arrivals,
    responders,
)
from diffpos.geometry import window_edge_path
from diffpos.scenario import default_scenario


@pytest.fixture(scope="module")
def paper():
    return default_scenario()


def test_time_base_maps_wall_and_emulated_time_both_ways():
    tb = TimeBase(t0_ns=1_000, wall_t0_ns=50_000, speed=4.0, duration_ns=0)
    for t in (1_000, 9_000, 1_000_001_000):
        assert tb.now_ns(tb.wall_of(t)) == t
    assert tb.wall_of(1_000 + 4_000_000) == 50_000 + 1_000_000  # 4x faster than the wall
    assert tb.t_s(1_000 + 2_500_000_000) == pytest.approx(2.5)
    rc = types.SimpleNamespace(t0_ns=1, wall_t0_ns=2, speed=0.5, duration_ns=3)
    assert TimeBase.from_control(rc) == TimeBase(1, 2, 0.5, 3)
    hour = 3600 * 10**9
    free = TimeBase.free_running(5 * hour + 123)
    assert free == TimeBase(5 * hour, 5 * hour, 1.0, 0)


def test_navigation_error_is_reproducible_and_has_the_stated_variances():
    kw = dict(sigma_h_m=0.02, sigma_v_m=0.05, bias_fraction=0.5, tau_s=30.0,
              velocity_sigma_m_s=0.1)
    a = NavigationError(rng=np.random.default_rng(1), **kw)
    b = NavigationError(rng=np.random.default_rng(1), **kw)
    ta = [a.position(t) for t in np.arange(5) * 0.1]
    tb = [b.position(t) for t in np.arange(5) * 0.1]
    np.testing.assert_array_equal(ta, tb)
    # stationary: bias variance f * sigma^2 plus white (1 - f) * sigma^2 = sigma^2 per axis,
    # over many independent anchors (samples far apart in time are independent too)
    n = 4000
    errs = np.array([NavigationError(rng=np.random.default_rng(s), **kw).position(0.0)
                     for s in range(n)])
    np.testing.assert_allclose(errs.std(axis=0), [0.02, 0.02, 0.05], rtol=0.05)
    vel = np.array([a.velocity() for _ in range(n)])
    np.testing.assert_allclose(vel.std(axis=0), 0.1, rtol=0.05)


def test_navigation_bias_decorrelates_with_the_time_constant():
    # the bias follows x' = a x + sqrt(1 - a^2) w with a = exp(-dt / tau): with tau >> dt
    # consecutive errors differ only by their white part
    kw = dict(sigma_h_m=1.0, sigma_v_m=1.0, bias_fraction=1.0, velocity_sigma_m_s=0.0)
    slow = NavigationError(tau_s=1e9, rng=np.random.default_rng(2), **kw)
    e0 = slow.position(0.0)
    np.testing.assert_allclose(slow.position(1.0), e0, atol=1e-3)
    fast = NavigationError(tau_s=1e-9, rng=np.random.default_rng(2), **kw)
    samples = np.array([fast.position(float(t)) for t in range(1, 3000)])
    # a = 0: independent draws, lag-1 correlation ~ 0
    c = np.corrcoef(samples[:-1, 0], samples[1:, 0])[0, 1]
    assert abs(c) < 0.08


def test_clock_time_is_offset_plus_jitter():
    rng = np.random.default_rng(3)
    assert clock_time_ns(10**12, offset_ns=-7, jitter_ns=0, rng=rng) == 10**12 - 7
    j = np.array([clock_time_ns(0, offset_ns=100, jitter_ns=20_000, rng=rng)
                  for _ in range(4000)]) - 100
    assert abs(j.mean()) < 1_500 and j.std() == pytest.approx(20_000, rel=0.05)


def test_ideal_first_arrivals_are_the_upper_edge_path_with_crlb_noise(paper):
    b = paper.building
    anchor = np.array([[-10.0, -15.0, 1.0]] * 2000)
    nodes = np.array([[2.0, 5.0, b.first_floor_z_m + 1.0], [8.0, 3.0, 10.0]])
    nodes_m = np.broadcast_to(nodes, (2000, 2, 3))
    r, sg, snr, det = first_arrivals(anchor, nodes_m, paper, channel="ideal",
                                     ideal_snr_db=15.0, rng=np.random.default_rng(4))
    assert r.shape == sg.shape == snr.shape == det.shape == (2000, 2) and det.all()
    expect_sigma = ranging_crlb_m(db_to_linear(15.0), paper.radio.bandwidth_hz)
    np.testing.assert_allclose(sg, expect_sigma)
    path = window_edge_path(anchor[:1, None, :], nodes[None], window_height_m=b.window_height_m,
                            edge_x_m=b.edge_x_m).length_m[0]
    np.testing.assert_allclose(r.mean(axis=0), path, atol=4 * expect_sigma / np.sqrt(2000))
    np.testing.assert_allclose(((r - path) / expect_sigma).std(axis=0), 1.0, rtol=0.05)


def test_emulator_first_arrivals_are_reproducible(paper):
    anchor = np.array([[-10.0, -15.0, 1.0]])
    nodes_m = np.array([[[2.0, 5.0, 4.5], [8.0, 3.0, 10.5]]])
    one = first_arrivals(anchor, nodes_m, paper, rng=np.random.default_rng(5))
    two = first_arrivals(anchor, nodes_m, paper, rng=np.random.default_rng(5))
    for x, y in zip(one, two, strict=True):
        np.testing.assert_array_equal(x, y)
        assert x.shape == (1, 2)


def test_emulation_nodes_of_a_grid_scenario_are_six_responders_capped_by_max_nodes(paper):
    assert not paper.nodes
    nodes = emulation_nodes(paper)
    assert [n for n, _ in nodes] == [f"r{i:02d}" for i in range(1, 7)]
    assert [n for n, _ in emulation_nodes(paper, max_nodes=2)] == ["r01", "r02"]
    # the responders walk inside the building, at the nominal node height on level parts
    b = paper.building
    for i, (_, traj) in enumerate(responders(b, count=6, seed=0)):
        p = np.asarray(traj.position_m(0.0))
        assert p[1] > 0 and b.edge_x_m[0] < p[0] < b.edge_x_m[1]
        floor = i % b.n_floors
        assert p[2] == pytest.approx(float(b.floor_z_m(floor)) + b.nominal_node_height_m)


def test_responders_walk_inside_narrow_and_shallow_buildings_and_keep_the_paper_layout(paper):
    """A 15 m wide building (the start range ``[x_lo + 8, x_hi - 12]`` used to be empty: a
    numpy error) and a 9 m deep one (the walk back at ``y + 2`` m, ``y`` up to ``depth - 1``,
    went through the back wall): every responder stays inside the floors over a whole loop.
    Buildings at least 20 m wide and 13 m deep keep the layout they always had (the same
    draws: ``y ~ U(1.5, 10)``, ``x ~ U(x_lo + 8, x_hi - 12)``)."""
    import dataclasses

    t_s = np.linspace(0.0, 200.0, 2001)
    for width_m, depth_m in ((15.0, 22.5), (40.0, 9.0), (12.0, 5.0), (25.0, 12.5)):
        b = dataclasses.replace(paper.building, width_m=width_m, depth_m=depth_m, n_floors=3)
        for rid, traj in responders(b, count=6, seed=0):
            assert np.all(b.inside(traj.position_m(t_s))), (width_m, depth_m, rid)
    # one floor: no stairs to take, the loop stays on the level (it used to walk to floor -1)
    one = dataclasses.replace(paper.building, n_floors=1)
    for rid, traj in responders(one, count=3, seed=0):
        p = traj.position_m(t_s)
        assert np.all(one.inside(p)), rid
        assert np.all(p[:, 2] == float(one.floor_z_m(0)) + one.nominal_node_height_m), rid
    with pytest.raises(ValueError, match="wider than 11 m"):
        responders(dataclasses.replace(paper.building, width_m=10.0), count=1)
    rng = np.random.default_rng(0)
    x_lo, x_hi = paper.building.edge_x_m
    for _, traj in responders(paper.building, count=6, seed=0):
        y, xa = rng.uniform(1.5, 10.0), rng.uniform(x_lo + 8.0, x_hi - 12.0)
        assert traj.points[0][:2] == pytest.approx((xa, y), abs=1e-12)


def _old_responder_points(b, count, seed):
    """The waypoints of ``responders`` as it was before the narrow/shallow-building fix
    (commit 0acebf2, verbatim draws): the reference for the layouts that must not change."""
    rng = np.random.default_rng(seed)
    x_lo, x_hi = b.edge_x_m
    h = b.nominal_node_height_m
    out = []
    for i in range(count):
        f0 = i % b.n_floors
        f1 = f0 + 1 if f0 + 1 < b.n_floors else f0 - 1
        z0 = float(b.floor_z_m(f0)) + h
        z1 = float(b.floor_z_m(f1)) + h
        y = float(rng.uniform(1.5, min(b.depth_m - 1.0, 10.0)))
        xa = float(rng.uniform(x_lo + 8.0, x_hi - 12.0))
        xs = x_hi - 4.0
        out.append([[xa, y, z0], [xs, y, z0], [xs, y + 2.0, z0], [xs - 6.0, y + 2.0, z1],
                    [xa, y + 2.0, z1]])
    return out


def test_responders_keep_the_old_layout_in_buildings_at_least_20_m_wide_and_13_m_deep(paper):
    """The docstring's claim, checked against the old code on buildings other than the
    paper's: the bounds themselves (20 m wide, 13 m deep), off the origin, 2-7 floors, other
    seeds and counts; every waypoint identical. Just outside the bounds the layout does change
    (12.5 m deep) or the old code had none (19.5 m wide): the claim is not vacuous."""
    import dataclasses

    cases = [(20.0, 13.0, 2, 0.0), (20.0, 30.0, 7, -35.0), (60.0, 13.0, 3, 12.5),
             (33.3, 18.7, 4, 0.0), (40.0, 22.5, 5, 0.0)]
    for width_m, depth_m, n_floors, cx_m in cases:
        b = dataclasses.replace(paper.building, width_m=width_m, depth_m=depth_m,
                                n_floors=n_floors, center_x_m=cx_m)
        for seed, count in ((0, 6), (3, 9)):
            got = [traj.points for _, traj in responders(b, count=count, seed=seed)]
            want = _old_responder_points(b, count, seed)
            assert np.array_equal(np.asarray(got), np.asarray(want)), (width_m, depth_m, seed)
    shallow = dataclasses.replace(paper.building, depth_m=12.5)
    got = [traj.points for _, traj in responders(shallow, count=6, seed=0)]
    assert not np.array_equal(np.asarray(got), np.asarray(_old_responder_points(shallow, 6, 0)))
    narrow = dataclasses.replace(paper.building, width_m=19.5)
    with pytest.raises(ValueError):  # numpy's "low > high": the old code had no layout here
        _old_responder_points(narrow, 6, 0)
    assert len(responders(narrow, count=6, seed=0)) == 6
