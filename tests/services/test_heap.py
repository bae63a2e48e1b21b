"""diffpos_services.heap.keep_heap: glibc's thresholds set (True) or nothing changed (False
elsewhere), bad values refused, and the tracker's numbers unchanged by it (an update of the
same inputs before and after, bit for bit)."""

from __future__ import annotations

import platform

import numpy as np
import pytest
from diffpos_services.heap import keep_heap

from diffpos.scenario import Building
from diffpos.tracking.links import Links
from diffpos.tracking.model import measurement_update
from diffpos.tracking.state import TrackerConfig


def _update():
    b = Building()
    rng = np.random.default_rng(3)
    n, h, m = 5, 2, 6
    x0, x1 = b.edge_x_m
    floor = rng.integers(0, b.n_floors, (n, h))
    pos = np.stack([rng.uniform(x0 + 1, x1 - 1, (n, h)), rng.uniform(1, b.depth_m - 1, (n, h)),
                    b.floor_z_m(floor) + 1.2], axis=-1)
    anc = np.stack([rng.uniform(x0 - 5, x1 + 5, (n, m)), rng.uniform(-25, -5, (n, m)),
                    rng.uniform(0, 20, (n, m))], axis=-1)
    ranges = np.linalg.norm(pos[:, :1, None] - anc[:, None], axis=-1)[:, 0] + 0.5
    links = Links.from_arrays(anc, ranges, np.full((n, m), 0.1), np.ones((n, m), bool), 0.03)
    x = np.concatenate([pos, np.zeros((n, h, 3))], axis=-1)
    p = np.broadcast_to(np.diag([0.3, 0.3, 0.1, 0.2, 0.2, 0.1]), (n, h, 6, 6))
    out = measurement_update(x, p, links, floor, b, TrackerConfig(), level=np.ones((n, h), bool))
    return [a.tobytes() for a in (out[0], out[1], out[2], out[3].slot, out[4])]


def test_keep_heap_changes_no_number():
    before = _update()
    applied = keep_heap()
    assert applied == (platform.libc_ver()[0] == "glibc")
    assert _update() == before


def test_keep_heap_refuses_non_positive_thresholds():
    with pytest.raises(ValueError):
        keep_heap(0, 2**20)
    with pytest.raises(ValueError):
        keep_heap(2**20, -1)
