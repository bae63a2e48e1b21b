"""The M-NLS tests' shared case: a 4-floor building, six anchors, random nodes inside it."""

from __future__ import annotations

import numpy as np

from diffpos.scenario import Building

B = Building(width_m=30.0, center_x_m=5.0, depth_m=15.0, n_floors=4, floor_height_m=3.5,
             first_floor_z_m=2.0, sill_height_m=1.0, window_height_m=1.2)
ANCHORS = np.array([[-16.0, -12.0, 1.0], [-5.0, -20.0, 0.5], [5.0, -9.0, 3.2],
                    [16.0, -16.0, 7.0], [25.0, -10.0, 2.0], [0.0, -25.0, 12.5]])


def random_nodes(b: Building, n: int, rng) -> np.ndarray:
    """``n`` nodes uniform over the building's rooms (0.5 m from the walls, 0.3 m from the
    slabs), on random floors."""
    x0, x1 = b.edge_x_m
    k = rng.integers(0, b.n_floors, n)
    return np.column_stack([rng.uniform(x0 + 0.5, x1 - 0.5, n),
                            rng.uniform(0.5, b.depth_m - 0.5, n),
                            b.floor_z_m(k) + rng.uniform(0.3, b.floor_height_m - 0.3, n)])
