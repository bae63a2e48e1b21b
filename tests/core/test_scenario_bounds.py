"""Scenario counts are bounded and refused before any entry is parsed, naming the limit; the
co-location check is O(n log n) (issue 36, item 5: 5,000 anchors ran > 120 s of CPU, 10^6
reached 23.7 GB)."""

from __future__ import annotations

import copy
import itertools

import numpy as np
import pytest

import diffpos.scenario as scenario_module
from diffpos.scenario import (
    MAX_ANCHORS,
    MAX_GRID_POSITIONS,
    MAX_NODES,
    MAX_PARTITIONS,
    MAX_WAYPOINTS,
    MIN_ANCHOR_SEPARATION_M,
    Scenario,
    ScenarioError,
    _check_grid_size,
    _close_pairs,
    default_scenario,
)


@pytest.fixture
def paper():
    return copy.deepcopy(default_scenario().to_dict())


def _anchor(i: int) -> dict:
    return {"id": f"u{i}", "position_m": [float(i % 1000), -20.0 - i // 1000, 1.0]}


def _err(d) -> str:
    with pytest.raises(ScenarioError) as ei:
        Scenario.from_dict(d)
    return str(ei.value)


def test_documented_limits():
    assert (MAX_ANCHORS, MAX_NODES, MAX_PARTITIONS, MAX_WAYPOINTS, MAX_GRID_POSITIONS) == (
        256, 100_000, 1024, 10_000, 10_000_000)
    doc = __import__("diffpos.scenario", fromlist=["x"]).__doc__
    for text in ("256 anchors", "100,000 listed", "1,024 partitions", "10,000 waypoints",
                 "10^7 positions"):
        assert text in doc


def test_five_thousand_anchors_are_refused_naming_the_limit(paper):
    paper["anchors"] = [_anchor(i) for i in range(5000)]
    msg = _err(paper)
    assert msg.startswith("anchors: 5,000 anchors; at most 256"), msg
    assert "MAX_ANCHORS" in msg


def test_a_million_anchors_are_refused_before_any_is_parsed(paper):
    paper["anchors"] = [None] * 1_000_000  # no entry is looked at: a bad one would fail first
    assert "1,000,000 anchors; at most 256" in _err(paper)


def test_limit_itself_is_accepted(paper):
    paper["anchors"] = [_anchor(i) for i in range(MAX_ANCHORS)]
    assert len(Scenario.from_dict(paper).anchors) == MAX_ANCHORS


@pytest.mark.parametrize(
    ("patch", "path", "fragment"),
    [
        (lambda d: d["nodes"].update(list=[None] * (MAX_NODES + 1)), "nodes.list",
         "100,001 nodes; at most 100,000 are allowed (diffpos.scenario.MAX_NODES)"),
        (lambda d: d["building"].update(partitions=[None] * (MAX_PARTITIONS + 1)),
         "building.partitions", "1,025 partitions; at most 1,024"),
        (lambda d: d["anchors"].__setitem__(0, {"id": "uav1", "trajectory": {
            "kind": "waypoints", "points_m": [[0.0, -20.0, 1.0]] * (MAX_WAYPOINTS + 1),
            "speed_m_s": 1.0}}),
         "anchors[0].trajectory.points_m", "10,001 waypoints; at most 10,000"),
        (lambda d: (d["nodes"].update(grid={"spacing_m": 0.05}),
                    d["building"].update(width_m=1000.0)), "nodes.grid.spacing_m",
         "the grid has 43,080,605 positions (19,991 columns x 431 rows x floors); at most "
         "10,000,000"),
    ],
)
def test_other_counts_are_refused_naming_the_limit(paper, patch, path, fragment):
    paper["building"]["width_m"] = 40.0
    patch(paper)
    paper["nodes"].setdefault("list", [{"id": "n1", "position_m": [0.0, 5.0, 5.5]}])
    msg = _err(paper)
    assert msg.startswith(path + ":"), msg
    assert fragment in msg, msg


def test_close_pairs_match_brute_force():
    rng = np.random.default_rng(7)
    r = MIN_ANCHOR_SEPARATION_M
    base = rng.uniform(-0.05, 0.05, (150, 3))  # dense: many pairs near the 1 cm radius
    pts = np.concatenate([base, base[:20] + rng.normal(0, 0.004, (20, 3))])
    want = [(i, j) for i, j in itertools.combinations(range(len(pts)), 2)
            if np.linalg.norm(pts[j] - pts[i]) < r]
    assert len(want) > 20
    assert _close_pairs(pts, r) == want


def test_colocated_pair_among_the_maximum_is_found(paper):
    anchors = [_anchor(i) for i in range(MAX_ANCHORS)]
    anchors[200] = {"id": "late", "position_m": [17.004, -20.0, 1.003]}  # 5 mm from u17
    paper["anchors"] = anchors
    msg = _err(paper)
    assert msg.startswith("anchors[200]: anchor 'late' is co-located with anchor 'u17'"), msg


def test_colocated_only_at_first_is_not_colocated(paper):
    p0 = paper["anchors"][0]["trajectory"]["position_m"]
    paper["anchors"][1] = {"id": "uav2", "trajectory": {
        "kind": "waypoints", "points_m": [p0, [0.0, -30.0, 1.0]], "speed_m_s": 1.0}}
    assert Scenario.from_dict(paper).anchors[1].id == "uav2"  # it leaves: valid


@pytest.mark.parametrize("spacing", [0.5, 0.3, 0.77, 2.0])
def test_grid_count_matches_the_built_grid(paper, spacing, monkeypatch):
    """The count the limit checks is the number of positions the grid builds."""
    paper["nodes"]["grid"]["spacing_m"] = spacing
    s = Scenario.from_dict(paper)
    n = len(s.node_grid.positions_m(s.building))
    monkeypatch.setattr(scenario_module, "MAX_GRID_POSITIONS", n)
    _check_grid_size(s.node_grid, s.building)  # exactly at the limit: accepted
    monkeypatch.setattr(scenario_module, "MAX_GRID_POSITIONS", n - 1)
    with pytest.raises(ScenarioError, match=f"the grid has {n:,} positions"):
        _check_grid_size(s.node_grid, s.building)
