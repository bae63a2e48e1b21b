"""The ray-traced study's helpers in benchmarks/: the held-out scenario files of
``heldout.py --write-scenarios`` (which samples, that they load back as the same scenarios, no
overwrite) and ``study_raytrace.py``'s receivers and right-floor shares."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from diffpos_services.scenario_io import load_scenario

from diffpos.scenario import Scenario, default_scenario

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import heldout
import study_raytrace


def test_partitioned_scenarios_are_the_first_random_samples_with_partitions():
    got = heldout.partitioned_scenarios(3, 3)
    # independent reference: walk the samples of seed 3 in order
    want, i = [], 0
    while len(want) < 3:
        d = heldout.random_scenario(3, i)
        if heldout.family(i) == "both" and len(d["building"]["partitions"]) > 0:
            want.append(d)
        i += 1
    assert list(got.values()) == want
    assert list(got) == [d["name"] for d in want]


def test_written_scenarios_load_back_unchanged_and_are_never_overwritten(tmp_path):
    paths = heldout.write_scenarios(tmp_path, 2, 5)
    assert [p.name for p in paths] == ["heldout-1.toml", "heldout-2.toml"]
    for p, d in zip(paths, heldout.partitioned_scenarios(2, 5).values(), strict=True):
        s = load_scenario(p)
        assert s == Scenario.from_dict(d)
        assert len(s.building.partitions) >= 1
        assert p.read_text().startswith(f"# {d['name']}: written by `python benchmarks/heldout.py"
                                        " --write-scenarios DIR --count 2 --seed 5`")
    before = paths[0].read_text()
    paths[1].unlink()
    with pytest.raises(FileExistsError, match=r"heldout-1\.toml"):
        heldout.write_scenarios(tmp_path, 2, 5)
    assert paths[0].read_text() == before and not paths[1].exists()


def test_same_receivers_puts_the_dataset_receivers_in_the_scenario():
    sc = default_scenario()
    pts = np.array([[1.0, 2.0, 5.5], [-3.0, 10.0, 8.5], [0.5, 4.0, 11.2]])
    out = study_raytrace.same_receivers(sc, pts)
    assert out.node_grid is None and len(out.nodes) == 3
    np.testing.assert_array_equal(out.node_positions_m(), pts)
    assert out.building == sc.building and out.anchors == sc.anchors


def test_floor_shares_count_misses_and_the_detected_subset():
    b = default_scenario().building  # floors from 4 m, 3 m each
    z_floor = lambda k: b.first_floor_z_m + (k + 0.5) * b.floor_height_m  # noqa: E731
    truth = np.array([[0, 5, z_floor(k)] for k in (0, 1, 2, 3, 4)])
    est = truth.copy()
    est[1, 2] = z_floor(0)  # wrong floor, 4 anchors detected
    est[2] = np.nan  # failed fix, 3 detected
    est[4, 2] = z_floor(3)  # wrong floor, 2 detected
    det = np.array([[1, 1, 1, 1], [1, 1, 1, 1], [1, 1, 1, 0], [1, 1, 1, 0], [1, 1, 0, 0]], bool)
    r = study_raytrace.floor_shares(est, truth, det, b)
    # receivers 0..3 have >= 3 anchors; right floor: 0 and 3 of them; of all: 0 and 3
    conf_wrong = r.pop("conf_wrong")
    assert r == {"n": 5, "n_det": 4, "floor_det": 0.5, "floor_all": 0.4}
    assert np.isnan(conf_wrong)  # no floor probabilities given
    # receiver 1 (wrong floor 0) at p = 0.97 is confidently wrong, receiver 3 (right) at 0.99
    # is not, receiver 2 (no fix) never is: 1 of the 4 with >= 3 anchors
    prob = np.full((5, b.n_floors), 0.01)
    prob[[0, 1, 3, 4], [0, 0, 3, 3]] = [0.5, 0.97, 0.99, 0.97]
    r = study_raytrace.floor_shares(est, truth, det, b, floor_probability=prob)
    assert r["conf_wrong"] == 0.25
