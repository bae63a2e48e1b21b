"""The tracker's compiled measurement model against its numpy reference.

:func:`diffpos.tracking_model._model` (one compiled pass, ``diffpos._kernels.tracking_nb``)
must give the same numbers bit for bit as :func:`diffpos.tracking_model._model_numpy` (the
path model once per distinct slot + the straight line by ``einsum``): the kernel calls the
same per-row path function the path kernel runs for ``graded_paths`` and computes the
straight line with the same operations in the same order, so equality is exact, not a
tolerance. One caveat: numpy's ``einsum`` sums a 3-vector's squares in an order set by its
SIMD dispatch (``(d0^2 + d2^2) + d1^2`` on the AVX-512 machine this was written on, the
order the kernel uses); where numpy sums otherwise (:func:`_einsum_order_matches` probes it)
the straight line of a hinge link may differ in the last bit, and only there a 2-ulp
tolerance applies. Inputs are random (fixed seeds) on buildings other than the shipped ones: other
floor heights and window sizes, anchors above the windows and beyond the facade ends, every
slot including -1 (outlier), missing links and hinge links (range shorter than the line).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diffpos.paths import MECHANISMS
from diffpos.scenario import Building, default_scenario
from diffpos.tracking import TrackerConfig
from diffpos.tracking_model import (
    Links,
    Selection,
    _all_paths_numpy,
    _box,
    _grid_starts_numpy,
    _iekf_terms,
    _iekf_terms_numpy,
    _model,
    _model_numpy,
    _select_prep,
    _select_prep_numpy,
    all_paths,
    clamp_to_floor,
    grid_starts,
    snr_cost_near,
)

_BUILDINGS = [
    Building(),
    dataclasses.replace(Building(), n_floors=7, floor_height_m=3.6, first_floor_z_m=3.0,
                        sill_height_m=0.9, window_height_m=2.0, width_m=30.0, depth_m=15.0,
                        partitions=()),
    dataclasses.replace(Building(), floor_height_m=2.7, window_height_m=0.8, sill_height_m=1.2),
]


def _case(b, seed, n=7, h=6, m=9):
    rng = np.random.default_rng(seed)
    x0, x1 = b.edge_x_m
    floor = rng.integers(0, b.n_floors, (n, h))
    zf = b.floor_z_m(floor)
    pos = np.stack([rng.uniform(x0 - 2, x1 + 2, (n, h)), rng.uniform(0.05, b.depth_m, (n, h)),
                    zf + rng.uniform(-0.2, b.floor_height_m + 0.2, (n, h))], axis=-1)
    # anchors: in front, above the windows, beyond the facade ends
    anc = np.stack([rng.uniform(x0 - 10, x1 + 10, (n, m)), rng.uniform(-30, -2, (n, m)),
                    rng.uniform(0, b.floor_z_m(b.n_floors - 1) + 6, (n, m))], axis=-1)
    ranges = np.linalg.norm(pos[:, :1, None] - anc[:, None], axis=-1)[:, 0] \
        + rng.uniform(-1.0, 6.0, (n, m))  # some shorter than the straight line (hinge)
    mask = rng.random((n, m)) > 0.15
    links = Links.from_arrays(anc, ranges, rng.uniform(0.01, 0.3, (n, m)), mask, 0.03)
    slot = np.where(rng.random((n, h, m)) < 0.2, -1,
                    rng.integers(0, len(MECHANISMS), (n, h, m)))
    sel = Selection(slot=slot, log_weight=np.zeros((n, h, m)), nis=np.zeros((n, h, m)),
                    extra_var=rng.uniform(0, 0.1, (n, h, m)) * (slot >= 0))
    return pos, links, floor, sel


def _einsum_order_matches() -> bool:
    """Whether numpy's einsum sums 3-vectors as the kernel does (module docstring)."""
    d = np.random.default_rng(0).normal(size=(4096, 3)) * 30.0
    return bool(np.array_equal(np.einsum("...i,...i->...", d, d),
                               (d[:, 0] * d[:, 0] + d[:, 2] * d[:, 2]) + d[:, 1] * d[:, 1]))


def _assert_same_model(got, ref, sel):
    hinge = (sel.slot < 0) & (ref[2] > 0)
    exact = _einsum_order_matches()
    for g, r in zip(got, ref, strict=True):
        assert g.shape == r.shape
        if exact:
            np.testing.assert_array_equal(g, r)
            continue
        other = ~hinge if g.ndim == 3 else ~hinge[..., None] & np.ones(g.shape, bool)
        np.testing.assert_array_equal(g[other], r[other])
        np.testing.assert_allclose(g[~other], r[~other], rtol=4.5e-16, atol=0.0)


@pytest.mark.parametrize("bi", range(len(_BUILDINGS)))
def test_model_kernel_bit_identical_to_numpy(bi):
    b = _BUILDINGS[bi]
    for seed in range(4):
        pos, links, floor, sel = _case(b, 100 * bi + seed)
        got = _model(pos, links, floor, sel, b)
        ref = _model_numpy(pos, links, floor, sel, b)
        _assert_same_model(got, ref, sel)
        # the case exercises every branch: used slots, hinges and unused links
        w = ref[2]
        assert np.any(w > 0) and np.any(w == 0)
        assert np.any((sel.slot < 0) & (w > 0))  # a hinge


def test_model_kernel_floor_broadcast():
    """A per-hypothesis floor vector (H,) as the tracker passes it gives the same values as
    the explicit (N, H) array."""
    b = _BUILDINGS[1]
    pos, links, floor, sel = _case(b, 7, h=b.n_floors)
    fl = np.arange(b.n_floors)
    got = _model(pos, links, fl, sel, b)
    ref = _model_numpy(pos, links, np.broadcast_to(fl, floor.shape), sel, b)
    _assert_same_model(got, ref, sel)


@pytest.mark.parametrize("bi", range(len(_BUILDINGS)))
def test_select_prep_kernel_bit_identical_to_numpy(bi):
    """Candidates, SNR term and innovation variance of the compiled selection equal the numpy
    reference exactly (no transcendental function in the kernel: the constants come in), with
    and without the SNR, with unknown SNRs and non-finite raw path values."""
    b = _BUILDINGS[bi]
    radio = default_scenario().radio
    for seed in range(3):
        pos, links, floor, _ = _case(b, 50 + 100 * bi + seed)
        rng = np.random.default_rng(seed)
        n, h, m = pos.shape[0], pos.shape[1], links.rho.shape[-1]
        snr = np.where(rng.random((n, m)) < 0.2, np.nan, rng.uniform(-5, 40, (n, m)))
        ls = Links(links.rho, links.var, links.mask, links.anchors, snr[:, None], radio)
        pos = clamp_to_floor(pos, floor, b, 0.05)
        pe = all_paths(pos, ls, floor, b, 0.2)
        a = rng.normal(size=(n, h, 3, 3)) * 0.5
        cov = a @ np.swapaxes(a, -1, -2) + 0.01 * np.eye(3)
        for snr_c in (snr_cost_near(pos, ls, floor, b, 0.2, pe), None):
            got = _select_prep(cov, ls, pe, snr_c)
            ref = _select_prep_numpy(cov, ls, pe, snr_c)
            for g, r in zip(got, ref, strict=True):
                assert g.shape == r.shape and g.dtype == r.dtype
                np.testing.assert_array_equal(g, r)
            assert np.any(got[0]) and not np.all(got[0])


@pytest.mark.parametrize("bi", range(len(_BUILDINGS)))
def test_grid_starts_kernel_bit_identical_to_numpy(bi):
    """The compiled grid search of the snapshot initialisation picks the same cells (same
    positions, same order) as the numpy reference, with missing links, 3 to 9 anchors (numpy's
    pairwise summation below and above 8 terms) and a subset of floors per node."""
    b = _BUILDINGS[bi]
    cfg = TrackerConfig()
    for seed, m in ((0, 3), (1, 8), (2, 9)):
        _, links, _, _ = _case(b, 200 + 10 * bi + seed, n=4, m=m)
        rng = np.random.default_rng(seed)
        floors = np.sort(rng.choice(b.n_floors, (4, 2)), axis=1)
        got = grid_starts(links, floors, b, cfg)
        ref = _grid_starts_numpy(links, floors, b, cfg)
        np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("bi", range(len(_BUILDINGS)))
def test_all_paths_kernel_bit_identical_to_graded_paths(bi):
    """Every slot's raw length, Jacobian and existence grades of the compiled pass equal
    :func:`diffpos.paths.graded_paths` (the tracker's previous route), for hypotheses inside
    and outside their floor's box and several band widenings (0 included)."""
    b = _BUILDINGS[bi]
    for seed, relax in ((0, 0.0), (1, 0.2), (2, 1.0)):
        pos, links, floor, _ = _case(b, 300 + 10 * bi + seed)
        got = all_paths(pos, links, floor, b, relax)
        ref = _all_paths_numpy(pos, links, floor, b, relax)
        for f in ("length", "jac", "strict", "loose", "sure"):
            g, r = getattr(got, f), getattr(ref, f)
            assert g.shape == r.shape and g.dtype == r.dtype
            np.testing.assert_array_equal(g, r, err_msg=f)
        assert np.any(ref.strict) and np.any(~ref.loose)
        if relax > 0:  # the case has links within the widening of a band edge
            assert np.any(ref.loose & ~ref.sure)


def test_iekf_terms_kernel_bit_identical_to_numpy():
    """The Gauss-Newton terms of the compiled IEKF iteration (information matrix, residuals,
    gradient) equal numpy's einsum/indexing version exactly, with hypotheses inside and outside
    their floor's box (box pseudo-measurements on and off), level and vertical modes and
    unused links (weight 0)."""
    b = _BUILDINGS[1]
    for seed in range(3):
        pos, links, floor, sel = _case(b, 400 + seed)
        n, h = pos.shape[:2]
        rng = np.random.default_rng(seed)
        model, jm, w = _model(pos, links, floor, sel, b)
        a0 = rng.normal(size=(n, h, 6, 6))
        y = a0 @ np.swapaxes(a0, -1, -2) + np.eye(6)
        x = np.concatenate([pos, rng.normal(size=(n, h, 3))], axis=-1)
        lo, hi = _box(x, floor, b, 0.05)
        z_nom = b.floor_z_m(floor) + b.nominal_node_height_m
        wh = np.where(rng.random((n, h)) < 0.5, 1 / 0.3**2, 0.0)
        got = _iekf_terms(y, x, lo, hi, z_nom, links.rho, model, jm, w, 2500.0, wh)
        ref = _iekf_terms_numpy(y, x, lo, hi, z_nom, links.rho, model, jm, w, 2500.0, wh)
        for g, r in zip(got, ref, strict=True):
            assert g.shape == r.shape
            np.testing.assert_array_equal(g, r)
        eb = ref[2]
        assert np.any(eb != 0) and np.any(eb == 0) and np.any(w == 0)
