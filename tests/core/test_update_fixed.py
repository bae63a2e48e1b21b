"""The measurement update's compiled set-up (:func:`diffpos.tracking.model._update_fixed`,
:mod:`diffpos.tracking.update_nb`) against the numpy functions it replaces in
:func:`~diffpos.tracking.model.measurement_update`: the clamped prior and the nodes it moved
(:func:`~diffpos.tracking.state.clamp_to_floor`), the existence margins
(:func:`~diffpos.tracking.model.existence_margin`, the fixed one without vertical modes), the
prior information (:func:`~diffpos.tracking.model.prior_information`) and the IEKF's fixed
inputs (:func:`~diffpos.tracking.model._iekf_fixed`), bit for bit; and the posterior's clamp
(``clamp_kernel``). Priors inside and outside their floor's box, on every floor, a few not
finite; vertical modes given (the tracker) and not (the snapshot's max-mixture, both modes
chosen); two buildings; fixed seeds."""

from __future__ import annotations

import numpy as np
import pytest

import diffpos.tracking.model as tm
from diffpos.scenario import Building
from diffpos.tracking.links import Links
from diffpos.tracking.state import TrackerConfig, clamp_to_floor
from diffpos.tracking.update_nb import clamp_kernel

BUILDINGS = [
    Building(),
    Building(width_m=30.0, depth_m=15.0, n_floors=4, floor_height_m=3.6, first_floor_z_m=2.5,
             sill_height_m=1.0, window_height_m=1.2),
]
CFG = TrackerConfig()


def _prior(b: Building, rng, n: int, h: int):
    x0, x1 = b.edge_x_m
    floor = rng.integers(0, b.n_floors, (n, h))
    x = np.empty((n, h, 6))
    x[..., 0] = rng.uniform(x0 - 1.0, x1 + 1.0, (n, h))
    x[..., 1] = rng.uniform(-1.0, b.depth_m + 1.0, (n, h))
    x[..., 2] = b.floor_z_m(floor) + rng.uniform(-0.5, b.floor_height_m + 0.5, (n, h))
    x[..., 3:] = rng.normal(0.0, 0.5, (n, h, 3))
    inside = rng.random((n, h)) < 0.6  # most priors inside their box
    x[..., :3] = np.where(inside[..., None], clamp_to_floor(x[..., :3], floor, b, 0.3),
                          x[..., :3])
    a = rng.normal(size=(n, h, 6, 6))
    p = a @ np.swapaxes(a, -1, -2) * rng.uniform(0.01, 1.0, (n, h, 1, 1)) + \
        0.01 * np.eye(6)
    x[0, 0, 1] = np.nan  # a prior that is not finite: its node counts as moved
    return x, p, floor


def _links(n: int, m: int, rng) -> Links:
    anchors = rng.uniform(-20.0, 20.0, (n, m, 3))
    return Links.from_arrays(anchors, rng.uniform(5.0, 30.0, (n, m)), np.full((n, m), 0.1),
                             np.ones((n, m), bool), 0.1)


@pytest.mark.parametrize("bi", range(len(BUILDINGS)))
@pytest.mark.parametrize("with_level", [True, False])
def test_update_fixed_equals_the_numpy_pieces(bi, with_level):
    b = BUILDINGS[bi]
    rng = np.random.default_rng(7 + bi)
    n, h = 20, 4
    x, p, floor = _prior(b, rng, n, h)
    level = rng.random((n, h)) < 0.7 if with_level else None
    links = _links(n, 5, rng)
    xc, moved, relax, info, fix = tm._update_fixed(x, p, links, floor, b, CFG, level)
    ref_xc = clamp_to_floor(x[..., :3], floor, b, CFG.z_margin_m)
    np.testing.assert_array_equal(xc, ref_xc)
    ref_moved = np.flatnonzero(np.any(ref_xc != x[..., :3], axis=(-2, -1)))
    np.testing.assert_array_equal(moved, ref_moved)
    assert 0 < moved.size < n
    ref_relax = tm.existence_margin(p, CFG) if with_level else \
        np.full((n, h), CFG.exist_margin_m)
    np.testing.assert_array_equal(relax, ref_relax)
    ref_info = tm.prior_information(p)
    for got, ref in zip(info, ref_info, strict=True):
        np.testing.assert_array_equal(got, ref)
    ref_head, ref_tail = tm._iekf_fixed(x, p, links, floor, b, CFG, level, ref_info)
    for got, ref in zip(fix[0], ref_head, strict=True):
        np.testing.assert_array_equal(got, ref)
    assert len(fix[1]) == len(ref_tail)
    for got, ref in zip(fix[1], ref_tail, strict=True):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(ref))
    if not with_level:  # the max-mixture chose both modes somewhere
        assert len(np.unique(fix[0][7])) == 2


@pytest.mark.parametrize("bi", range(len(BUILDINGS)))
def test_clamp_kernel_equals_clamp_to_floor(bi):
    b = BUILDINGS[bi]
    rng = np.random.default_rng(3 + bi)
    x, _, floor = _prior(b, rng, 30, 3)
    out = np.empty_like(x)
    clamp_kernel(x, floor.astype(np.float64), tm._floor_box(b, CFG.z_margin_m), out)
    np.testing.assert_array_equal(out, clamp_to_floor(x, floor, b, CFG.z_margin_m))
