"""The coordinator's floor plans and events: labels that never overlap, stairs where the
scenario's responders change floor, a normal end told from a lost service.

References: label boxes recomputed from the documented geometry (``declutter``: a box
``h`` high, ``0.62 h`` per character, padded ``0.15 h`` each side) and checked pairwise;
the stairs of ``scenarios/large.toml`` read off its waypoints by hand (the east stairwell,
x 17-18.5 m, y 17.5-20.5 m, joining F0-F1, F1-F2, F2-F3); the events of made-up liveliness
records whose outcome is known."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from diffpos_services.dashboard.events import liveliness_events
from diffpos_services.dashboard.plans import declutter
from diffpos_services.dashboard.scenario import building_from_scenario_file


def _box(anchor, text, h):
    half = 0.5 * 0.62 * h * max(len(text), 2) + 0.15 * h
    return anchor[0] - half, anchor[0] + half, anchor[1] - 0.6 * h, anchor[1] + 0.6 * h


@pytest.mark.parametrize("n", [6, 17, 50])
def test_plan_labels_never_overlap_and_name_every_responder(n):
    rng = np.random.default_rng(n)
    xy = np.column_stack([rng.uniform(-20, 20, n), -rng.uniform(0, 22.5, n)])
    names = [f"{i:02d}" for i in range(n)]
    labels = declutter(xy, names, height_m=40 / 24)
    boxes = [_box(a, t, 40 / 24) for a, t in labels]
    for a, c in itertools.combinations(boxes, 2):
        assert not (a[0] < c[1] and c[0] < a[1] and a[2] < c[3] and c[2] < a[3])
    shown, hidden = [], 0
    for _, text in labels:
        words = text.split()
        if words[-1].startswith("+"):
            hidden += int(words.pop()[1:])
        shown += words
    assert len(set(shown)) == len(shown) and set(shown) <= set(names)
    assert len(shown) + hidden == n


def test_stairs_of_the_large_scenario_are_its_stairwell():
    b = building_from_scenario_file("large")
    assert sorted((lo, hi) for *_, lo, hi in b.stairs) == [(0, 1), (1, 2), (2, 3)]
    for x0, x1, y0, y1, _, _ in b.stairs:
        assert x0 == pytest.approx(17.0, abs=0.1) and x1 == pytest.approx(18.5, abs=0.1)
        assert y0 == pytest.approx(17.5, abs=0.1) and y1 == pytest.approx(20.5, abs=0.1)
    assert len(b.walls) == 4  # the scenario's partitions


def test_a_normal_end_is_one_info_event_and_a_lost_anchor_a_warning():
    s = 1_000_000_000
    wall = np.arange(0, 10 * s + 1, s // 10)  # data published every 0.1 s up to 10 s
    records = [
        {"role": "anchor", "id": "uav1", "alive": True, "t_ns": 0},
        {"role": "anchor", "id": "uav2", "alive": False, "t_ns": 4 * s},  # lost mid-run
        {"role": "anchor", "id": "uav1", "alive": False, "t_ns": 10 * s},  # the end
        {"role": "fusion", "id": "", "alive": False, "t_ns": 10 * s + s // 2},
    ]
    ev = liveliness_events(records, wall_ns=wall, meas_ns=wall + 7)
    got = sorted(zip(ev.level.tolist(), ev.text.tolist(), strict=True))
    assert [lvl for lvl, _ in got] == ["INFO", "INFO", "WARN"]
    assert got[2][1].startswith("anchor uav2 left") and "lost" in got[2][1]
    end = [t for lvl, t in got if t.startswith("run ended")]
    assert len(end) == 1 and "anchor uav1" in end[0] and "fusion" in end[0]
    assert "normal end" in end[0]
