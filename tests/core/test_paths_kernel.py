"""The compiled path model (diffpos.paths.model_nb) against the numpy reference.

:func:`diffpos.paths.model.first_arrival_paths` runs the numba kernel; the reference is the numpy
implementation kept beside it (:func:`diffpos.paths.model._first_arrival_paths_numpy`, itself tested
against a brute-force optimiser and the channel emulator in tests/core/test_paths.py). The
kernel performs the reference's floating-point operations in the same order, so:

* existence (``valid``) must agree exactly, also on the window-band boundaries and at the edge
  ends (strict inequalities), where one rounding step flips the verdict;
* lengths, deviation cosines and anchor -> edge lengths to <= 1e-12 relative, Jacobians (unit
  vectors) to <= 1e-12 absolute; NaN exactly where the reference has NaN.

Geometries are random (fixed seeds) over buildings other than the shipped ones (floor heights,
window bands, widths, depths, an off-centre facade), anchors below, at and above the windows
and beyond the facade ends, nodes inside and straying outside their floor (estimator iterates).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diffpos.paths import model_nb as paths_nb
from diffpos.paths.mechanisms import MECHANISMS, RECIPES, mechanism_set
from diffpos.paths.model import (
    FloorFrame,
    _first_arrival_paths_numpy,
    diffracted_path,
    direct_opening,
    first_arrival_paths,
    graded_paths,
    specular_path,
)
from diffpos.scenario import Building

RTOL = 1e-12
ATOL_JAC = 1e-12

BUILDINGS = {
    "default": Building(),
    "tall_floors": Building(width_m=25.0, depth_m=12.0, n_floors=3, floor_height_m=4.2,
                            first_floor_z_m=0.0, sill_height_m=1.1, window_height_m=2.3),
    "slit_windows": Building(width_m=60.0, center_x_m=7.5, depth_m=30.0, n_floors=8,
                             floor_height_m=2.8, first_floor_z_m=6.0, sill_height_m=0.3,
                             window_height_m=0.6),
    "low_wide": Building(width_m=12.0, center_x_m=-4.0, depth_m=8.0, n_floors=2,
                         floor_height_m=3.5, first_floor_z_m=1.0, sill_height_m=0.9,
                         window_height_m=1.8),
}


def _geometries(b: Building, rng: np.random.Generator, n: int) -> tuple[np.ndarray, ...]:
    """Nodes (some outside their floor), anchors (below/at/above windows, beyond the ends)."""
    x0, x1 = b.edge_x_m
    w = x1 - x0
    nodes = np.stack([rng.uniform(x0 - 0.1 * w, x1 + 0.1 * w, n),
                      rng.uniform(-0.3, b.depth_m + 0.3, n),
                      rng.uniform(b.first_floor_z_m - 1.0, b.top_z_m + 1.0, n)], axis=-1)
    anchors = np.stack([rng.uniform(x0 - 0.8 * w, x1 + 0.8 * w, n),
                        rng.uniform(-3.0 * b.depth_m, -0.5, n),
                        rng.uniform(0.0, b.top_z_m + 15.0, n)], axis=-1)
    floors = rng.integers(0, b.n_floors, n)
    return nodes, anchors, floors


def _assert_same(ref, got) -> None:
    np.testing.assert_array_equal(got.valid, ref.valid)
    np.testing.assert_array_equal(got.floor, ref.floor)
    for name in ("length_m", "deviation_cos", "outside_m"):
        r, g = getattr(ref, name), getattr(got, name)
        assert g.shape == r.shape, name
        np.testing.assert_array_equal(np.isnan(g), np.isnan(r), err_msg=name)
        # a cosine near 0 (cancellation) is held to its scale, 1
        atol = ATOL_JAC if name == "deviation_cos" else 0.0
        np.testing.assert_allclose(g, r, rtol=RTOL, atol=atol, equal_nan=True, err_msg=name)
    assert got.jacobian.shape == ref.jacobian.shape
    np.testing.assert_allclose(got.jacobian, ref.jacobian, rtol=0.0, atol=ATOL_JAC)


@pytest.mark.parametrize("name", sorted(BUILDINGS))
def test_kernel_equals_reference_on_random_geometries(name: str) -> None:
    b = BUILDINGS[name]
    rng = np.random.default_rng(sum(map(ord, name)))
    nodes, anchors, floors = _geometries(b, rng, 3000)
    for floor in (None, floors):  # the node's own floor, and a hypothesis it may stray from
        ref = _first_arrival_paths_numpy(nodes, anchors, b, floor=floor)
        got = first_arrival_paths(nodes, anchors, b, floor=floor)
        _assert_same(ref, got)
        # the sample exercises every slot both existing and not
        assert np.all(ref.valid.any(axis=0)) and np.all((~ref.valid).any(axis=0))


def test_window_band_boundaries_and_edge_ends_agree_exactly() -> None:
    """Entry points exactly on (and one rounding step around) the band limits; Fermat points
    exactly at, just inside and just beyond the edge ends."""
    b = BUILDINGS["tall_floors"]
    rng = np.random.default_rng(7)
    x0, x1 = b.edge_x_m
    k = rng.integers(0, b.n_floors, 400)
    lo, hi = b.window_z_m(k)
    nodes, anchors = [], []
    for z_b in (lo, hi):  # direct path crossing the facade at z_b: anchor and node mirrored
        for dz in (0.0, 1e-13, -1e-13, 1e-9, -1e-9):
            xb = rng.uniform(x0 + 0.5, x1 - 0.5, k.size)
            h = rng.uniform(0.1, 1.0, k.size)
            y = rng.uniform(0.5, 5.0, k.size)
            nodes.append(np.stack([xb, y, z_b + dz + h], -1))
            anchors.append(np.stack([xb, -y, z_b + dz - h], -1))
    for xe in (x0, x1):  # node and anchor at the edge end's x: Fermat point on the end
        for dx in (0.0, 1e-12, -1e-12, 1e-6, -1e-6):
            n_ = k.size
            z = b.floor_z_m(k) + rng.uniform(0.2, b.floor_height_m - 0.2, n_)
            nodes.append(np.stack([np.full(n_, xe + dx), rng.uniform(0.5, 5, n_), z], -1))
            anchors.append(np.stack([np.full(n_, xe + dx), rng.uniform(-20, -1, n_),
                                     rng.uniform(0, 20, n_)], -1))
    nodes, anchors = np.concatenate(nodes), np.concatenate(anchors)
    floors = np.tile(k, len(nodes) // k.size)
    ref = _first_arrival_paths_numpy(nodes, anchors, b, floor=floors)
    got = first_arrival_paths(nodes, anchors, b, floor=floors)
    _assert_same(ref, got)
    # exactly on a band limit the direct path does not exist (strict inequality) ...
    on_band = slice(0, k.size)
    assert not got.valid[on_band, 0].any()
    # ... and exactly at an edge end no edge diffraction exists (corner diffraction dropped)
    at_end = slice(10 * k.size, 11 * k.size)
    assert not got.valid[at_end, 7].any() and not got.valid[at_end, 8].any()


def test_shapes_slot_subsets_and_broadcasting() -> None:
    b = BUILDINGS["slit_windows"]
    rng = np.random.default_rng(3)
    nodes, anchors, floors = _geometries(b, rng, 40)
    n3 = nodes.reshape(8, 5, 3)[:, :, None, :]  # (8, 5, 1, 3)
    a3 = anchors[:6][None, None]  # (1, 1, 6, 3)
    f3 = floors.reshape(8, 5)[:, :, None]
    for slots in (None, [9, 0, 17], 13, [-1, 2], np.array([7, 7, 8])):
        ref = _first_arrival_paths_numpy(n3, a3, b, floor=f3, slots=slots)
        got = first_arrival_paths(n3, a3, b, floor=f3, slots=slots)
        _assert_same(ref, got)
        assert got.length_m.shape[:3] == (8, 5, 6)
    single = first_arrival_paths(nodes[0], anchors[0], b)  # one pair: batch shape ()
    _assert_same(_first_arrival_paths_numpy(nodes[0], anchors[0], b), single)
    assert single.length_m.shape == (len(MECHANISMS),)
    empty = first_arrival_paths(np.zeros((0, 3)), anchors[0], b)
    assert empty.length_m.shape == (0, len(MECHANISMS)) and empty.jacobian.shape == (0, 18, 3)


def test_bad_input_nan_and_out_of_range_slots() -> None:
    b = BUILDINGS["default"]
    node = np.array([[0.0, 5.0, np.nan], [1.0, 4.0, 8.5]])
    anchor = np.array([[0.0, -10.0, 5.0], [np.inf, -10.0, 5.0]])
    with np.errstate(invalid="ignore"):
        ref = _first_arrival_paths_numpy(node, anchor, b, floor=1)
    got = first_arrival_paths(node, anchor, b, floor=1)
    _assert_same(ref, got)
    assert not got.valid.any()
    with pytest.raises(IndexError, match="slots"):
        first_arrival_paths(node, anchor, b, slots=[18])


def test_raw_mode_gives_unmasked_geometry_and_band_free_existence() -> None:
    """``raw=True`` (for graded existence, e.g. the tracker's widened band): lengths and
    Jacobians of :func:`specular_path` / :func:`diffracted_path` where the path does not exist
    too, and existence with a widened band = raw existence & entry height inside that band."""
    b = BUILDINGS["low_wide"]
    rng = np.random.default_rng(11)
    nodes, anchors, floors = _geometries(b, rng, 2000)
    relax = 0.05
    fr = FloorFrame.from_building(b, floors)
    loose = dataclasses.replace(fr, win_lo=fr.win_lo - relax, win_hi=fr.win_hi + relax)
    lo, hi = b.window_z_m(floors)
    slots = np.arange(18, dtype=np.int64)
    length, ok, jac, dev, _, entry_z = paths_nb.eval_paths_kernel(
        nodes.copy(), anchors.copy(), floors.astype(np.float64), paths_nb.building_planes(b),
        slots, raw=True)
    with np.errstate(invalid="ignore"):
        widened = ok & (entry_z > lo[:, None] - relax) & (entry_z < hi[:, None] + relax)
    for s, rec in enumerate(RECIPES):
        if rec.kind == "spec":
            g = specular_path(anchors, nodes, loose, rec.planes, ground=rec.ground)
            np.testing.assert_array_equal(widened[:, s], g.valid)
            np.testing.assert_allclose(entry_z[:, s], g.points[0][:, 2], rtol=RTOL)
        elif rec.kind == "diff":
            g = diffracted_path(anchors, nodes, fr, rec.edge, rec.planes, ground=rec.ground)
            np.testing.assert_array_equal(ok[:, s], g.valid)
            np.testing.assert_allclose(dev[:, s], g.deviation_cos, rtol=RTOL)
        else:
            continue
        np.testing.assert_allclose(length[:, s], g.length_m, rtol=RTOL)
        np.testing.assert_allclose(jac[:, s], g.jacobian, rtol=0.0, atol=ATOL_JAC)


def test_graded_paths_widened_and_narrowed_band() -> None:
    """graded_paths: strict = first_arrival_paths' existence; loose = the reference geometry
    with the window band widened by relax_m; sure = narrowed (away from rounding ties); raw
    lengths and Jacobians everywhere."""
    b = BUILDINGS["tall_floors"]
    rng = np.random.default_rng(5)
    nodes, anchors, floors = _geometries(b, rng, 3000)
    relax = 0.2
    g = graded_paths(nodes, anchors, b, floor=floors, relax_m=relax)
    ref = _first_arrival_paths_numpy(nodes, anchors, b, floor=floors)
    np.testing.assert_array_equal(g.strict, ref.valid)
    fr = FloorFrame.from_building(b, floors)
    wide = dataclasses.replace(fr, win_lo=fr.win_lo - relax, win_hi=fr.win_hi + relax)
    narrow = dataclasses.replace(fr, win_lo=fr.win_lo + relax, win_hi=fr.win_hi - relax)
    for s, rec in enumerate(RECIPES):
        if rec.kind == "direct":
            _, zc, loose = direct_opening(anchors, nodes, wide)
            sure, z_in = direct_opening(anchors, nodes, narrow)[2], zc
        elif rec.kind == "spec":
            gw = specular_path(anchors, nodes, wide, rec.planes, ground=rec.ground)
            loose, z_in = gw.valid, gw.points[0][:, 2]
            sure = specular_path(anchors, nodes, narrow, rec.planes, ground=rec.ground).valid
            np.testing.assert_allclose(g.length_m[:, s], gw.length_m, rtol=RTOL)
            np.testing.assert_allclose(g.jacobian[:, s], gw.jacobian, rtol=0, atol=ATOL_JAC)
        else:
            gd = diffracted_path(anchors, nodes, fr, rec.edge, rec.planes, ground=rec.ground)
            loose = sure = gd.valid
            z_in = None
            np.testing.assert_allclose(g.length_m[:, s], gd.length_m, rtol=RTOL)
        np.testing.assert_array_equal(g.loose[:, s], loose)
        far = np.ones(len(nodes), dtype=bool)
        if z_in is not None:
            lo, hi = b.window_z_m(floors)
            with np.errstate(invalid="ignore"):
                far = np.minimum(np.abs(z_in - lo - relax), np.abs(hi - relax - z_in)) > 1e-9
        np.testing.assert_array_equal(g.sure[far, s], sure[far])
        assert np.all(g.strict[:, s] <= g.loose[:, s]) and np.all(g.sure[:, s] <= g.strict[:, s])
    # the band grading matters on this sample
    assert g.loose.sum() > g.strict.sum() > g.sure.sum()
    with pytest.raises(ValueError, match="relax_m"):
        graded_paths(nodes, anchors, b, relax_m=-0.1)


def test_compiled_recipes_match_the_reference_recipes() -> None:
    """The literal default table (frozen into the compiled code) is that of RECIPES; its
    columns are the channel's slot tables."""
    tab = paths_nb.mechanism_table(RECIPES)
    np.testing.assert_array_equal(paths_nb.DEFAULT_TABLE, tab)
    code = {"floor": 0, "ceiling": 1, "back": 2, "side x1": 3, "side x2": 4}
    for s, rec in enumerate(RECIPES):
        planes = [code[p] for p in rec.planes] + [-1, -1]
        assert paths_nb.SLOT_KIND[s] == {"direct": 0, "spec": 1, "diff": 2}[rec.kind]
        assert paths_nb.SLOT_GROUND[s] == int(rec.ground)
        assert paths_nb.SLOT_EDGE[s] == {None: -1, "upper": 0, "lower": 1}[rec.edge]
        assert (paths_nb.SLOT_PLANE0[s], paths_nb.SLOT_PLANE1[s]) == tuple(planes[:2])


@pytest.mark.parametrize("name", sorted(BUILDINGS))
def test_kernel_equals_reference_on_the_higher_order_families(name: str) -> None:
    """The extended mechanism set (max order 4: slab image series, ground bounce before the
    diffraction, wall reflections): the kernel with the set's table against the numpy
    reference, every family exercised existing and not; the first 18 slots equal the default
    call's."""
    b = BUILDINGS[name]
    mech = mechanism_set(4)
    rng = np.random.default_rng(sum(map(ord, name)) + 1)
    nodes, anchors, floors = _geometries(b, rng, 3000)
    ref = _first_arrival_paths_numpy(nodes, anchors, b, floor=floors, mechanisms=mech)
    got = first_arrival_paths(nodes, anchors, b, floor=floors, mechanisms=mech)
    _assert_same(ref, got)
    base = first_arrival_paths(nodes, anchors, b, floor=floors)
    for f in ("length_m", "valid", "jacobian", "deviation_cos", "outside_m"):
        np.testing.assert_array_equal(getattr(got, f)[:, :18], getattr(base, f))
    assert got.length_m.shape == (3000, len(mech))
    seen = ref.valid.any(axis=0)
    assert seen.mean() > 0.9, [lab for lab, v in zip(mech.labels, seen, strict=True) if not v]
    sub = [20, 3, len(mech) - 1]
    _assert_same(_first_arrival_paths_numpy(nodes, anchors, b, floor=floors, mechanisms=mech,
                                            slots=sub),
                 first_arrival_paths(nodes, anchors, b, floor=floors, mechanisms=mech,
                                     slots=sub))
    g = graded_paths(nodes, anchors, b, floor=floors, relax_m=0.1, mechanisms=mech)
    np.testing.assert_array_equal(g.strict, ref.valid)
    with pytest.raises(IndexError, match="slots"):
        first_arrival_paths(nodes, anchors, b, mechanisms=mech, slots=[len(mech)])


def test_one_compiled_signature_and_idempotent_warm_up() -> None:
    paths_nb.warm_paths()
    assert paths_nb.warm_paths() == 0.0
    b = BUILDINGS["default"]
    # read-only / broadcast / int inputs must not create another specialisation
    nodes = np.broadcast_to(np.array([1, 5, 8]), (4, 3))
    first_arrival_paths(nodes, np.array([[0.0, -10.0, 5.0]]), b, floor=np.int32(1))
    first_arrival_paths(nodes.astype(np.float32), np.array([0.0, -10.0, 5.0]), b, slots=[3])
    ro = np.array([[1.0, 5.0, 8.5]])
    ro.flags.writeable = False
    first_arrival_paths(ro, ro * [1, -1, 1], b, floor=np.broadcast_to(np.float64(2), (1,)))
    assert len(paths_nb.paths_kernel.signatures) == 1
