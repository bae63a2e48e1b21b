"""The M-NLS search grid: the cells that stay grid cells cover the whole floor plan.

The search replaces the last 7 cells of every floor's grid by closed-form starts; in raster
order the 5 cells left of the default 4 x 3 grid all lay at x < 0 (the left half of the plan).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from diffpos.estimators.mnls.starts import _grid
from diffpos.scenario import Building


def _covering_radius(cells: np.ndarray, plan: np.ndarray) -> float:
    """Largest distance from a plan point to its nearest cell (brute force over a dense grid)."""
    d = np.linalg.norm(plan[:, None, :] - cells[None, :, :], axis=-1)
    return float(d.min(axis=1).max())


def _plan(b: Building, n: int = 41) -> np.ndarray:
    x0, x1 = b.edge_x_m
    gx, gy = np.meshgrid(np.linspace(x0, x1, n), np.linspace(0.0, b.depth_m, n), indexing="ij")
    return np.stack([gx.ravel(), gy.ravel()], axis=-1)


@pytest.mark.parametrize("nx,ny", [(4, 3), (3, 3), (5, 2), (6, 4)])
def test_grid_is_a_permutation_of_the_raster_grid(nx: int, ny: int) -> None:
    b = Building()
    g = _grid(b, nx, ny)
    x0, x1 = b.edge_x_m
    xs = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
    ys = (np.arange(ny) + 0.5) * b.depth_m / ny
    raster = np.array(list(itertools.product(xs, ys)))
    assert g.shape == (nx * ny, 2)
    assert sorted(map(tuple, g)) == sorted(map(tuple, raster))


@pytest.mark.parametrize("building", [Building(), Building(width_m=60.0, depth_m=12.0)])
@pytest.mark.parametrize("kept", [2, 3, 5, 8])
def test_kept_cells_cover_the_plan_at_least_as_well_as_any_raster_prefix(building, kept) -> None:
    """For every prefix length, the farthest-point order's covering radius is no worse than the
    raster order's, and with 5 of 4 x 3 cells the kept ones straddle the plan's centre line."""
    g = _grid(building, 4, 3)
    plan = _plan(building)
    x0, x1 = building.edge_x_m
    xs = x0 + (np.arange(4) + 0.5) * (x1 - x0) / 4
    ys = (np.arange(3) + 0.5) * building.depth_m / 3
    raster = np.array(list(itertools.product(xs, ys)))
    assert _covering_radius(g[:kept], plan) <= _covering_radius(raster[:kept], plan) + 1e-9
    if kept == 5:
        centre = (x0 + x1) / 2
        assert (g[:kept, 0] < centre).any() and (g[:kept, 0] > centre).any()
