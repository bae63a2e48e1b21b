"""Random floor hypotheses with their anchors and range masks, shared by the tracker's SNR-term
tests (the diffraction slack, the skipped paths' threshold)."""

from __future__ import annotations

import numpy as np

from diffpos.scenario import Building


def random_hypotheses(seed: int, anchor_top_m: float):
    """12 nodes x 3 hypotheses on random floors of the default building, 4 anchors each in front
    of the facade (0.3 m to ``anchor_top_m`` high, 3-30 m out); the first half of the nodes with
    three ranges. Returns the generator (to draw on from), the building, the positions (12, 3,
    3), the floors (12, 3), the anchors (12, 4, 3) and the mask (12, 4)."""
    rng = np.random.default_rng(seed)
    b = Building()
    x0, x1 = b.edge_x_m
    n, h, m = 12, 3, 4
    floor = rng.integers(0, b.n_floors, (n, h))
    z = b.floor_z_m(floor) + rng.uniform(0.4, b.floor_height_m - 0.4, (n, h))
    pos = np.stack([rng.uniform(x0 + 0.5, x1 - 0.5, (n, h)),
                    rng.uniform(0.5, b.depth_m - 0.5, (n, h)), z], axis=-1)
    anchors = np.stack([rng.uniform(x0 - 10.0, x1 + 10.0, (n, m)), -rng.uniform(3.0, 30.0, (n, m)),
                        rng.uniform(0.3, anchor_top_m, (n, m))], axis=-1)
    mask = np.ones((n, m), bool)
    mask[: n // 2, 3] = False  # the first half: three ranges
    return rng, b, pos, floor, anchors, mask
