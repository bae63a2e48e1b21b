"""All 18 default slots of a row at once (``diffpos.tracking.model_nb.default_slots_row``,
the tracker's ``all_paths_kernel``) against the per-slot path model (``paths_kernel`` with
``raw=True``, ``want_jac=True``: ``slot_path`` of every slot), bit for bit: lengths,
Jacobians, entry heights (raw bytes, NaN and -0.0 included) and existence.

Rows: random geometries over buildings other than the shipped ones (nodes inside and
straying outside their floor, anchors below, at and above the windows and beyond the facade
ends), entry points and Fermat points exactly on and one rounding step around the band
limits and the edge ends, and degenerate rows (an anchor on the facade plane, at the node,
NaN coordinates)."""

from __future__ import annotations

import numpy as np
import pytest
from numba import njit
from test_paths_kernel import BUILDINGS as ALL_BUILDINGS
from test_paths_kernel import _geometries

from diffpos.paths import model_nb as paths_nb
from diffpos.scenario import Building
from diffpos.tracking.model_nb import default_slots_row

BUILDINGS = {k: b for k, b in ALL_BUILDINGS.items() if k != "default"}


@njit(cache=False, error_model="numpy")
def _rows(nodes, anchors, floor, first_z, floor_h, sill, win_h, x0, x1, depth, length, valid,
          jac, entry_z):
    edge = paths_nb.edge_axis(x0, x1)
    for p in range(nodes.shape[0]):
        zf, zc, lo, hi = paths_nb.row_planes(floor[p], first_z, floor_h, sill, win_h)
        default_slots_row(anchors[p, 0], anchors[p, 1], anchors[p, 2], nodes[p, 0],
                          nodes[p, 1], nodes[p, 2], zf, zc, lo, hi, x0, x1, depth, edge,
                          length[p], valid[p], jac[p], entry_z[p])


def _check(b: Building, nodes, anchors, floors) -> np.ndarray:
    nodes, anchors = np.ascontiguousarray(nodes), np.ascontiguousarray(anchors)
    fl = np.ascontiguousarray(floors, dtype=np.float64)
    planes = paths_nb.building_planes(b)
    ref_len, ref_ok, ref_jac, _, _, ref_ez = paths_nb.eval_paths_kernel(
        nodes, anchors, fl, planes, np.arange(18, dtype=np.int64), raw=True, want_jac=True)
    p = nodes.shape[0]
    length, valid = np.empty((p, 18)), np.empty((p, 18), np.bool_)
    jac, ez = np.empty((p, 18, 3)), np.empty((p, 18))
    _rows(nodes, anchors, fl, *planes, length, valid, jac, ez)
    assert length.tobytes() == ref_len.tobytes()
    assert jac.tobytes() == ref_jac.tobytes()
    assert ez.tobytes() == ref_ez.tobytes()
    np.testing.assert_array_equal(valid, ref_ok)
    return valid


@pytest.mark.parametrize("name", sorted(BUILDINGS))
def test_row_equals_slot_path_on_random_geometries(name: str) -> None:
    b = BUILDINGS[name]
    rng = np.random.default_rng(sum(map(ord, name)) + 1)
    nodes, anchors, drawn = _geometries(b, rng, 4000)
    for floors in (drawn, b.floor_index(nodes[:, 2])):
        valid = _check(b, nodes, anchors, floors)
        # every slot both existing and not in the sample
        assert valid.any(axis=0).all() and (~valid).any(axis=0).all()


def test_row_equals_slot_path_on_band_limits_edge_ends_and_degenerate_rows() -> None:
    b = BUILDINGS["tall_floors"]
    rng = np.random.default_rng(3)
    x0, x1 = b.edge_x_m
    k = rng.integers(0, b.n_floors, 300)
    lo, hi = b.window_z_m(k)
    nodes, anchors = [], []
    for z_b in (lo, hi):  # the direct path crossing the facade at z_b (+- a rounding step)
        for dz in (0.0, 1e-13, -1e-13, 1e-9, -1e-9):
            xb = rng.uniform(x0 + 0.5, x1 - 0.5, k.size)
            h = rng.uniform(0.1, 1.0, k.size)
            y = rng.uniform(0.5, 5.0, k.size)
            nodes.append(np.stack([xb, y, z_b + dz + h], -1))
            anchors.append(np.stack([xb, -y, z_b + dz - h], -1))
    for xe in (x0, x1):  # node and anchor at the edge end's x: Fermat point on the end
        for dx in (0.0, 1e-12, -1e-12, 1e-6, -1e-6):
            z = b.floor_z_m(k) + rng.uniform(0.2, b.floor_height_m - 0.2, k.size)
            nodes.append(np.stack([np.full(k.size, xe + dx), rng.uniform(0.5, 5, k.size), z], -1))
            anchors.append(np.stack([np.full(k.size, xe + dx), rng.uniform(-20, -1, k.size),
                                     rng.uniform(0, 20, k.size)], -1))
    z = b.floor_z_m(k) + 1.0
    nd = np.stack([np.full(k.size, 3.0), np.full(k.size, 2.0), z], -1)
    nodes += [nd, nd, nd, nd]
    anchors += [np.stack([np.full(k.size, 3.0), np.zeros(k.size), z], -1),  # on the facade
                nd.copy(),  # at the node
                np.stack([np.full(k.size, np.nan), np.full(k.size, -5.0), z], -1),
                np.stack([np.full(k.size, 1.0), np.full(k.size, -5.0), np.full(k.size, np.inf)],
                         -1)]
    floors = np.tile(k, len(nodes))
    _check(b, np.concatenate(nodes), np.concatenate(anchors), floors)
