"""Test helper: D-NLS fixes from anchors outside the building to nodes on its floors, the
clean-plus-noise part the exclusion-search tests share (each adds its own faults)."""

from __future__ import annotations

import numpy as np

from diffpos.geometry import window_edge_path

#: window edge height of the fixes [m] and the ranging noise [m]
W_M = 1.2
SIG_M = 0.05


def outside_fixes(rng: np.random.Generator, n: int, m: int = 8):
    """``n`` fixes of ``m`` anchors outside (x in [-30, 30], y in [-40, -5], z in [0, 40] m),
    nodes on 9 floors, ranges along the window-edge path with 5 cm Gaussian noise (drawn from
    ``rng`` in that order). Returns anchors (n, m, 3), nodes (n, 3), ranges (n, m)."""
    a = np.stack([rng.uniform(-30, 30, (n, m)), rng.uniform(-40, -5, (n, m)),
                  rng.uniform(0, 40, (n, m))], axis=-1)
    nodes = np.stack([rng.uniform(-15, 15, n), rng.uniform(0.5, 15, n),
                      1.5 + 3.0 * rng.integers(0, 9, n)], axis=-1)
    r = window_edge_path(a, nodes[:, None, :], window_height_m=W_M).length_m
    return a, nodes, r + rng.normal(0.0, SIG_M, (n, m))
