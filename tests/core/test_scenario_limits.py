"""Scenario validation bounds every coordinate and size, rejects co-located anchors and warns
when no fix is ever possible (issue 15, item 13)."""

from __future__ import annotations

import copy
import logging

import pytest
from diffpos_services.scenario_io import SCENARIO_DIR, load_scenario, scenario_from_toml

from diffpos.scenario import (
    MAX_BUILDING_SIZE_M,
    MAX_COORDINATE_M,
    Scenario,
    ScenarioError,
    default_scenario,
)


@pytest.fixture
def paper_dict():
    return copy.deepcopy(default_scenario().to_dict())


def _err(d) -> str:
    with pytest.raises(ScenarioError) as ei:
        Scenario.from_dict(d)
    return str(ei.value)


def _set_anchor(d, i, pos):
    d["anchors"][i] = {"id": d["anchors"][i]["id"], "position_m": pos}


@pytest.mark.parametrize(
    ("patch", "path", "fragment"),
    [
        (lambda d: _set_anchor(d, 0, [-15.0, -1e300, 1.0]), "anchors[0].position_m",
         "allowed |x|, |y|, |z| <= 100000 m"),
        (lambda d: _set_anchor(d, 0, [1e6, -20.0, 1.0]), "anchors[0].position_m",
         "out of range"),
        (lambda d: _set_anchor(d, 0, [0.0, -20.0, 2e5]), "anchors[0].position_m",
         "out of range"),
        (lambda d: d["anchors"].__setitem__(0, {"id": "uav1", "trajectory": {
            "kind": "orbit", "center_m": [0.0, -1e9, 3.0], "radius_m": 4.0,
            "period_s": 60.0}}),
         "anchors[0].trajectory", "somewhere along its trajectory"),
        (lambda d: d["building"].update(width_m=1e300), "building.width_m",
         "allowed (0, 10000]"),
        (lambda d: d["building"].update(depth_m=2e4), "building.depth_m", "allowed (0, 10000]"),
        (lambda d: d["building"].update(center_x_m=-1e300), "building.center_x_m",
         "allowed [-100000, 100000]"),
        (lambda d: d["building"].update(first_floor_z_m=1e300), "building.first_floor_z_m",
         "allowed [0, 100000]"),
        (lambda d: d["building"].update(floor_height_m=1e300), "building.floor_height_m",
         "out of range"),
        (lambda d: d["building"].update(n_floors=200, floor_height_m=60.0),
         "building.floor_height_m", "exceeds the building height limit 10000 m"),
        (lambda d: d["building"].update(n_floors=1001), "building.n_floors", "[1, 200]"),
        (lambda d: d["building"].update(wall_thickness_m=1e300), "building.wall_thickness_m",
         "out of range"),
        (lambda d: d["building"]["partitions"][3].update(span_m=[-1e300, 20.0]),
         "building.partitions[3].span_m", "allowed |c| <= 100000 m"),
    ],
)
def test_absurd_coordinates_and_sizes_are_rejected_naming_the_field(paper_dict, patch, path,
                                                                    fragment):
    patch(paper_dict)
    msg = _err(paper_dict)
    assert msg.startswith(path + ":"), msg
    assert fragment in msg, msg


def test_limits_are_the_documented_ones():
    assert MAX_COORDINATE_M == 100_000.0
    assert MAX_BUILDING_SIZE_M == 10_000.0
    doc = __import__("diffpos.scenario", fromlist=["x"]).__doc__
    assert "100 km" in doc and "10 km" in doc


def test_limits_themselves_are_accepted(paper_dict):
    _set_anchor(paper_dict, 0, [-MAX_COORDINATE_M, -MAX_COORDINATE_M, MAX_COORDINATE_M])
    paper_dict["building"].update(width_m=MAX_BUILDING_SIZE_M, depth_m=100.0)
    s = Scenario.from_dict(paper_dict)
    assert s.building.width_m == MAX_BUILDING_SIZE_M


def test_colocated_anchors_are_rejected_naming_both_ids(paper_dict):
    _set_anchor(paper_dict, 3, list(paper_dict["anchors"][1]["trajectory"]["position_m"]))
    msg = _err(paper_dict)
    assert msg.startswith("anchors[3]:"), msg
    assert "'uav4'" in msg and "'uav2'" in msg and "co-located" in msg, msg


def test_colocated_moving_anchors_are_rejected_but_crossing_ones_are_not(paper_dict):
    orbit = {"kind": "orbit", "center_m": [0.0, -15.0, 3.0], "radius_m": 4.0, "period_s": 60.0}
    paper_dict["anchors"][0] = {"id": "uav1", "trajectory": dict(orbit)}
    paper_dict["anchors"][3] = {"id": "uav4", "trajectory": dict(orbit)}
    msg = _err(paper_dict)
    assert msg.startswith("anchors[3]:") and "'uav1'" in msg, msg
    # same orbit, opposite direction: they meet twice a period but are not co-located
    paper_dict["anchors"][3]["trajectory"]["clockwise"] = True
    assert len(Scenario.from_dict(paper_dict).anchors) == 4


@pytest.mark.parametrize("n", [1, 2])
def test_fewer_than_three_anchors_is_valid_with_a_warning(paper_dict, n):
    paper_dict["anchors"] = paper_dict["anchors"][:n]
    s = Scenario.from_dict(paper_dict)
    assert len(s.anchors) == n
    assert len(s.warnings) == 1
    w = s.warnings[0]
    assert w.startswith("anchors:") and "no 3D fix is ever possible" in w, w


def test_shipped_scenarios_stay_valid_without_warnings():
    for name in ("paper", "large"):
        s = load_scenario(SCENARIO_DIR / f"{name}.toml")
        assert s.warnings == (), (name, s.warnings)
    assert default_scenario().warnings == ()
    # warnings are not part of the value (round trip and equality unchanged)
    s = default_scenario()
    assert Scenario.from_dict(s.to_dict()) == s


def test_loader_logs_the_scenarios_warnings(caplog):
    """A valid scenario with two anchors loads, and the loader says why it is useless."""
    lines = (SCENARIO_DIR / "paper.toml").read_text().splitlines(keepends=True)
    starts = [i for i, ln in enumerate(lines) if ln.startswith("[[anchors]]")]
    assert len(starts) == 4
    # drop the last two anchor tables: keep up to the third, then skip to the next table
    nxt = next(i for i in range(starts[3] + 1, len(lines)) if lines[i].startswith("["))
    two = "".join(lines[: starts[2]] + lines[nxt:])
    with caplog.at_level(logging.WARNING, logger="diffpos.scenario"):
        sc = scenario_from_toml(two, source="two.toml")
    assert len(sc.anchors) == 2 and sc.warnings
    assert any(r.getMessage().startswith("two.toml: ") and "anchor" in r.getMessage()
               for r in caplog.records), caplog.text
