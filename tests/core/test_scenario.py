"""Scenario model, TOML loading and trajectories."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from diffpos_services.scenario_io import SCENARIO_DIR, load_scenario

from diffpos.scenario import Scenario, ScenarioError, default_scenario
from diffpos.trajectory import Hover, Orbit, Static, Waypoints, trajectory_from_dict


@pytest.fixture(scope="module")
def paper_dict():
    return default_scenario().to_dict()


def _err(d) -> str:
    with pytest.raises(ScenarioError) as ei:
        Scenario.from_dict(d)
    return str(ei.value)


# ------------------------------------------------------------------ the paper's scenario
def test_default_scenario_is_the_papers_geometry():
    s = default_scenario()
    np.testing.assert_array_equal(
        s.anchor_positions_m(),
        [[-15, -20, 1], [0, -15, 0], [0, -7, 4], [15, -20, 1]],
    )
    assert s.anchor_ids == ["uav1", "uav2", "uav3", "uav4"]
    b, r = s.building, s.radio
    assert b.n_floors == 5 and b.edge_x_m == (-20.0, 20.0)
    assert (r.frequency_hz, r.bandwidth_hz, r.noise_temperature_k) == (28e9, 400e6, 300.0)
    assert (r.processing_gain_db, r.fap_threshold_db) == (20.0, 15.0)
    assert r.polarization == (1.0, 0.0, 0.0)
    nodes = s.node_positions_m()
    assert nodes.shape == (17600, 3)  # paper: 17,485 over five floors
    assert abs(len(nodes) - 17485) / 17485 < 0.01
    assert np.all(b.inside(nodes))
    # every floor (and window) above every anchor ("each floor is located above the UAV")
    assert b.first_floor_z_m >= s.anchor_positions_m()[:, 2].max()
    # nodes at the window mid-height of their floor (Assumption 1)
    lo, hi = b.window_z_m(b.floor_index(nodes[:, 2]))
    np.testing.assert_allclose(nodes[:, 2], 0.5 * (lo + hi))
    assert len(np.unique(nodes[:, 2])) == 5


def test_paper_toml_equals_default_and_large_toml_is_valid():
    assert load_scenario(SCENARIO_DIR / "paper.toml") == default_scenario()
    assert load_scenario("paper") == default_scenario()
    s = load_scenario("large")
    assert len(s.anchors) == 8 and len(s.nodes) == 50
    assert [n.id for n in s.nodes] == [f"n{i:02d}" for i in range(1, 51)]
    assert [a.id for a in s.anchors] == [f"uav{i}" for i in range(1, 9)]
    t = np.linspace(0.0, 900.0, 3001)
    for n in s.nodes:
        assert np.all(s.building.inside(n.trajectory.position_m(t))), n.id
    for a in s.anchors:
        assert np.all(a.trajectory.position_m(t)[:, 1] < 0), a.id
    kinds = {type(a.trajectory) for a in s.anchors}
    assert kinds == {Hover, Orbit, Waypoints}
    # some responders change floors (stairs)
    floors = [np.unique(s.building.floor_index(n.trajectory.position_m(t)[:, 2]))
              for n in s.nodes]
    assert sum(len(f) > 1 for f in floors) >= 5


@pytest.mark.parametrize("name", ["paper", "large"])
def test_round_trip(name):
    s = load_scenario(name)
    assert Scenario.from_dict(s.to_dict()) == s


# ------------------------------------------------------------------ validation messages
def test_anchor_inside_building_names_the_field(paper_dict):
    d = copy.deepcopy(paper_dict)
    d["anchors"][1] = {"id": "uav2", "position_m": [0.0, 15.0, 0.0]}
    assert _err(d) == ("anchors[1].position_m: y=15 is inside the building "
                       "(anchors must be outside, y < 0)")


def test_orbit_crossing_the_facade_is_rejected(paper_dict):
    d = copy.deepcopy(paper_dict)
    d["anchors"][0] = {"id": "u", "trajectory": {"kind": "orbit", "center_m": [0, -3, 2],
                                                 "radius_m": 5, "period_s": 30}}
    msg = _err(d)
    assert msg.startswith("anchors[0].trajectory: y=")
    assert "along its trajectory" in msg


@pytest.mark.parametrize(
    ("patch", "path", "fragment"),
    [
        (lambda d: d["radio"].update(frequency_hz=1e12), "radio.frequency_hz",
         "allowed [1e+09, 1e+11]"),
        (lambda d: d["radio"].update(bogus=1), "radio.bogus", "unknown key"),
        (lambda d: d["radio"].update(polarization="w"), "radio.polarization", "'x', 'y', 'z'"),
        (lambda d: d["building"].update(window_height_m=2.5), "building.window_height_m",
         "exceeds floor_height_m"),
        (lambda d: d["building"].update(wall_material="cheese"), "building.wall_material",
         "unknown material"),
        (lambda d: d["building"]["partitions"][0].update(axis="z"),
         "building.partitions[0].axis", "must be 'x'"),
        (lambda d: d["anchors"][0].update(trajectory={"kind": "hover", "center_m": [0, -5, 1],
                                                      "wander_m": -1}),
         "anchors[0].trajectory.wander_m", "must be >= 0 m"),
        (lambda d: d["anchors"][2].update(id="uav1"), "anchors[2].id", "duplicate id"),
        (lambda d: d.update(anchors=[]), "anchors", "at least one"),
        (lambda d: d["nodes"]["grid"].update(y_max_m=30.0), "nodes.grid.y_max_m",
         "out of range"),
        (lambda d: d["nodes"].update(list=[{"id": "n01", "position_m": [0, 30, 5]}]),
         "nodes.list[0].position_m", "outside the building"),
        (lambda d: d["nodes"].update(list=[{"id": "n01", "position_m": [0, 3]}]),
         "nodes.list[0].position_m", "expected [x, y, z]"),
    ],
)
def test_invalid_fields_are_named(paper_dict, patch, path, fragment):
    d = copy.deepcopy(paper_dict)
    patch(d)
    msg = _err(d)
    assert msg.startswith(path + ":") or msg.startswith(path + "."), msg
    assert fragment in msg, msg


def test_trajectory_field_errors_carry_the_full_path(paper_dict):
    d = copy.deepcopy(paper_dict)
    d["anchors"][0] = {"id": "u", "trajectory": {"kind": "orbit", "center_m": [0, -30, 5],
                                                 "radius_m": -1, "period_s": 3}}
    assert _err(d) == "anchors[0].trajectory.radius_m: must be > 0 m, got -1.0"


def test_toml_errors_are_one_clear_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\n[building\nwidth_m = 3\n')
    with pytest.raises(ScenarioError, match=r"bad.toml: TOML syntax error: .*line 2"):
        load_scenario(bad)
    with pytest.raises(ScenarioError, match="no such scenario file"):
        load_scenario(tmp_path / "missing.toml")
    inv = tmp_path / "inv.toml"
    inv.write_text('[[anchors]]\nid = "a"\nposition_m = [0, 1, 0]\n[nodes.grid]\n')
    with pytest.raises(ScenarioError, match=r"inv.toml: anchors\[0\].position_m: y=1 is inside"):
        load_scenario(inv)


# ------------------------------------------------------------------ trajectories
TRAJS = [
    Static((1.0, -2.0, 3.0)),
    Hover((0.0, -10.0, 2.0), wander_m=0.4, period_s=7.0, phase_deg=30.0),
    Orbit((0.0, -20.0, 5.0), radius_m=4.0, period_s=12.0, phase_deg=10.0),
    Orbit((0.0, -20.0, 5.0), radius_m=4.0, period_s=12.0, clockwise=True),
    trajectory_from_dict({"kind": "waypoints", "points_m": [[0, 1, 5], [4, 1, 5], [4, 4, 8]],
                          "speed_m_s": 1.5, "loop": True}),
]


@pytest.mark.parametrize("traj", TRAJS, ids=lambda t: t.kind)
def test_velocity_is_the_derivative_of_position(traj):
    t = np.linspace(0.13, 40.0, 997)
    h = 1e-5
    fd = (traj.position_m(t + h) - traj.position_m(t - h)) / (2 * h)
    v = traj.velocity_m_s(t)
    if isinstance(traj, Waypoints):  # piecewise linear: skip samples next to a knot
        ok = np.all(np.isclose(fd, v, atol=1e-6), axis=-1)
        assert ok.mean() > 0.98
    else:
        np.testing.assert_allclose(fd, v, atol=1e-6)
    assert traj.position_m(t).shape == (997, 3)
    assert traj.position_m(np.zeros((2, 3))).shape == (2, 3, 3)


def test_orbit_and_waypoint_geometry():
    o = Orbit((1.0, -20.0, 5.0), radius_m=4.0, period_s=12.0, phase_deg=90.0)
    t = np.linspace(0, 12, 50)
    p = o.position_m(t)
    np.testing.assert_allclose(np.hypot(p[:, 0] - 1, p[:, 1] + 20), 4.0)
    np.testing.assert_allclose(o.position_m(0.0), [1.0, -16.0, 5.0], atol=1e-12)
    np.testing.assert_allclose(o.position_m(12.0), o.position_m(0.0), atol=1e-12)
    w = trajectory_from_dict({"kind": "waypoints", "points_m": [[0, 1, 5], [3, 1, 5], [3, 5, 5]],
                              "times_s": [0, 3, 5]})
    np.testing.assert_allclose(w.position_m([0, 1.5, 3, 4, 5, 99]),
                               [[0, 1, 5], [1.5, 1, 5], [3, 1, 5], [3, 3, 5], [3, 5, 5],
                                [3, 5, 5]])
    np.testing.assert_allclose(w.velocity_m_s([1.0, 4.0, 99.0]), [[1, 0, 0], [0, 2, 0], [0, 0, 0]])
    loop = trajectory_from_dict({"kind": "waypoints", "points_m": [[0, 1, 5], [4, 1, 5]],
                                 "speed_m_s": 2.0, "loop": True})
    assert loop.duration_s == pytest.approx(4.0)  # 2 s out, 2 s back
    np.testing.assert_allclose(loop.position_m(3.0), [2, 1, 5])
    np.testing.assert_allclose(loop.position_m(7.0), loop.position_m(3.0))
    h = Hover((0, -5, 2), wander_m=0.3)
    p = h.position_m(np.linspace(0, 500, 5001))
    assert np.all(np.abs(p - [0, -5, 2]) <= np.array([0.3, 0.3, 0.15]) + 1e-12)


@pytest.mark.parametrize(
    ("d", "fragment"),
    [
        ({"kind": "spiral"}, "kind: must be one of"),
        ({"kind": "orbit", "center_m": [0, 0, 0], "radius_m": 1}, "period_s: required"),
        ({"kind": "waypoints", "points_m": [[0, 0, 0]]}, "at least 2 waypoints"),
        ({"kind": "waypoints", "points_m": [[0, 0, 0], [1, 0, 0]], "times_s": [1, 2]},
         "must start at 0"),
        ({"kind": "waypoints", "points_m": [[0, 0, 0], [1, 0, 0]], "times_s": [0, 1],
          "speed_m_s": 1}, "either times_s or speed_m_s"),
        ({"kind": "hover", "center_m": [0, 0]}, "center_m: expected 3"),
    ],
)
def test_trajectory_errors(d, fragment):
    with pytest.raises(ValueError, match=fragment.replace("(", r"\(")):
        trajectory_from_dict(d)


def test_first_arrival_edge_is_lower_only_when_every_anchor_is_below_the_windows():
    from diffpos.scenario import first_arrival_edge

    sc = default_scenario()
    lowest = float(sc.building.window_z_m(0)[0])
    assert max(a.position_m[2] for a in sc.anchors) < lowest
    assert first_arrival_edge(sc)[0] == "lower"
    d = sc.to_dict()
    d["anchors"][0]["trajectory"]["position_m"][2] = lowest + 0.01  # one UAV at the lowest window
    assert first_arrival_edge(Scenario.from_dict(d))[0] == "upper"
