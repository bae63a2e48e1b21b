"""The tracker's compiled measurement model against its numpy reference.

:func:`diffpos.tracking.model._model` (one compiled pass, ``diffpos.tracking.model_nb``)
must give the same numbers bit for bit as :func:`diffpos.tracking.model._model_numpy` (the
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

The selection's kernels leave log and exp to numpy (on the packed candidates), so it is bit-
identical to ``_select_numpy`` too. The fused IEKF cannot be: its 6 x 6 solve/inverse/
log-determinant is LU with partial pivoting in the kernel, LAPACK's (another operation order)
in numpy, and libm's log differs from numpy's in the last bit; it and the prior's information
are held to their references (``_iekf_numpy``, ``_prior_information_numpy``) within stated
tolerances. The measurement update is held bit for bit to itself node by node (no result
depends on the batch it is computed in).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diffpos.paths.mechanisms import MECHANISMS
from diffpos.paths.model_nb import building_planes
from diffpos.scenario import Building, default_scenario
from diffpos.tracking.initialisation import _grid_cells, _grid_starts_numpy, grid_starts
from diffpos.tracking.initialisation_nb import GRID_BOUND_SLACK_M, grid_cost_kernel
from diffpos.tracking.links import (
    _IS_BAND,
    _IS_DIFF,
    Links,
    _all_paths_numpy,
    all_paths,
    candidates,
)
from diffpos.tracking.model import (
    Selection,
    _box,
    _iekf_numpy,
    _iekf_terms,
    _iekf_terms_numpy,
    _model,
    _model_numpy,
    _paths_at,
    _prior_information_numpy,
    _select_fixed,
    _select_numpy,
    _select_prep,
    _select_prep_numpy,
    iekf,
    link_weights,
    measurement_update,
    prior_information,
    select,
    select_persistent,
    snr_cost_near,
)
from diffpos.tracking.state import TrackerConfig, clamp_to_floor

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


def _grid_totals(links, floors, b, cfg, keep, w_out):
    """Every cell's total of :func:`grid_cost_kernel` as ``grid_starts`` calls it."""
    cells = _grid_cells(b, cfg.init_grid_m)
    n, nf = floors.shape
    z = np.ascontiguousarray(b.floor_z_m(floors) + b.nominal_node_height_m, dtype=np.float64)
    var = np.ascontiguousarray((links.var + (0.5 * cfg.init_grid_m) ** 2)[:, 0])
    total = np.empty((n, nf, cells.shape[0]))
    grid_cost_kernel(np.ascontiguousarray(cells), z, np.ascontiguousarray(floors, np.float64),
                     np.ascontiguousarray(links.anchors[:, 0]),
                     np.ascontiguousarray(links.rho[:, 0]), var,
                     np.ascontiguousarray(links.mask[:, 0]), _IS_BAND, _IS_DIFF,
                     0.5 * cfg.init_grid_m, float(w_out), keep, *building_planes(b), total)
    return total


def _assert_same_kept(got, full, keep):
    """The ``keep`` cheapest cells per (node, floor) of the pruned totals ``got`` are those of
    the full evaluation ``full``: same cells, same stable order, same totals bit for bit;
    returns their indices."""
    o_full = np.argsort(full, axis=2, kind="stable")[..., :keep]
    o_got = np.argsort(got, axis=2, kind="stable")[..., :keep]
    np.testing.assert_array_equal(o_got, o_full)
    np.testing.assert_array_equal(np.take_along_axis(got, o_got, 2),
                                  np.take_along_axis(full, o_full, 2))
    return o_full


@pytest.mark.parametrize("bi", range(len(_BUILDINGS)))
def test_grid_cost_kernel_pruning_keeps_the_best_cells_exactly(bi):
    """With ``keep`` the kernel abandons cells that cannot be among the ``keep`` cheapest of
    their (node, floor): against the full evaluation (``keep`` 0) the ``keep`` cheapest cells
    are the same cells, in the same (stable) order, with the same totals bit for bit, and
    every abandoned cell's full total is larger than the ``keep``-th. Ranges are first
    arrivals of a true point (the earliest candidate path, plus noise), so cheap cells exist
    and the pruning does abandon cells (checked); with a negative outlier cost (link costs
    may be negative) nothing is abandoned."""
    b = _BUILDINGS[bi]
    cfg = TrackerConfig()
    rng = np.random.default_rng(40 + bi)
    n, m = 5, 8
    _, links, _, _ = _case(b, 900 + bi, n=n, h=1, m=m)
    x0, x1 = b.edge_x_m
    fl_true = rng.integers(0, b.n_floors, (n, 1))
    truth = np.stack([rng.uniform(x0 + 1, x1 - 1, (n, 1)), rng.uniform(1, b.depth_m - 1, (n, 1)),
                      b.floor_z_m(fl_true) + b.nominal_node_height_m], axis=-1)
    pe = all_paths(truth, links, fl_true, b, 0.0)
    first = np.where(candidates(pe), pe.length, np.inf).min(axis=-1)[:, 0]  # (n, m)
    rho = np.where(np.isfinite(first), first + rng.normal(0, 0.05, (n, m)), 40.0)
    links = Links.from_arrays(links.anchors[:, 0], rho, np.full((n, m), 0.05), links.mask[:, 0],
                              0.03)
    floors = np.broadcast_to(np.arange(b.n_floors), (n, b.n_floors))
    w_out = np.log(cfg.outlier_span_m / cfg.outlier_weight)
    full = _grid_totals(links, floors, b, cfg, 0, w_out)
    abandoned = 0
    for keep in (1, 3, 7):
        got = _grid_totals(links, floors, b, cfg, keep, w_out)
        o_full = _assert_same_kept(got, full, keep)
        gone = np.isinf(got) & np.isfinite(full)
        kth = np.take_along_axis(full, o_full[..., -1:], 2)
        assert np.all(full[gone] > np.broadcast_to(kth, full.shape)[gone])
        kept = ~gone
        np.testing.assert_array_equal(got[kept], full[kept])
        abandoned += int(gone.sum())
    assert abandoned > full.size  # the pruning is not vacuous (over the three keeps)
    neg = _grid_totals(links, floors, b, cfg, 3, -1.0)
    np.testing.assert_array_equal(neg, _grid_totals(links, floors, b, cfg, 0, -1.0))


@pytest.mark.parametrize("bi", range(len(_BUILDINGS)))
def test_no_mechanism_is_shorter_than_the_straight_line(bi):
    """The premise of the grid search's lower bound (``grid_cost_kernel``): every slot's
    computed length, wherever it exists (loose), is at least the straight line from the
    anchor to the point minus ``GRID_BOUND_SLACK_M``; points anywhere on and between the
    floors (window heights, the facade plane, beyond the facade ends), anchors in front,
    above the windows and beyond the facade ends, the band widened. Over the same points the
    smallest excess over the straight line is close to 0 (paths through the opening exist
    and are almost straight), so the test would see a path cut short."""
    b = _BUILDINGS[bi]
    pos, links, floor, _ = _case(b, 700 + bi, n=40, h=25, m=12)
    pe = all_paths(pos, links, floor, b, 0.3)
    los = np.linalg.norm(pos[:, :, None, :] - links.anchors, axis=-1)  # (N, H, M)
    excess = np.where(pe.loose, pe.length - los[..., None], np.inf)
    assert np.all(np.nan_to_num(excess, nan=np.inf) >= -GRID_BOUND_SLACK_M)
    assert np.isfinite(excess).sum() > 10_000
    assert np.nanmin(excess) < 0.05


@pytest.mark.parametrize("bi", range(len(_BUILDINGS)))
def test_all_paths_kernel_bit_identical_to_graded_paths(bi):
    """Every slot's raw length, Jacobian and existence grades of the compiled pass equal
    :func:`diffpos.paths.model.graded_paths` (the tracker's previous route), for hypotheses inside
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


def _snr_links(links, seed):
    rng = np.random.default_rng(seed)
    n, m = links.rho.shape[0], links.rho.shape[-1]
    snr = np.where(rng.random((n, m)) < 0.2, np.nan, rng.uniform(-5, 40, (n, m)))
    return Links(links.rho, links.var, links.mask, links.anchors, snr[:, None],
                 default_scenario().radio)


def _spd(rng, shape, d, scale):
    a = rng.normal(size=(*shape, d, d)) * scale
    return a @ np.swapaxes(a, -1, -2) + 0.01 * scale**2 * np.eye(d)


@pytest.mark.parametrize("bi", range(len(_BUILDINGS)))
def test_select_kernels_bit_identical_to_numpy(bi):
    """The compiled selection (three passes, numpy's log/exp on the packed candidates in
    between) gives the numpy reference's slots, log-weights, NIS and mechanism-ambiguity
    variances bit for bit, with and without SNR, with unknown SNRs, missing links, links
    ranged longer/shorter than every mechanism and non-finite raw path values."""
    b = _BUILDINGS[bi]
    cfg = TrackerConfig()
    for seed in range(3):
        pos, links, floor, _ = _case(b, 500 + 100 * bi + seed)
        ls = _snr_links(links, seed)
        rng = np.random.default_rng(seed)
        pos = clamp_to_floor(pos, floor, b, 0.05)
        pe = all_paths(pos, ls, floor, b, 0.2)
        cov = _spd(rng, pos.shape[:2], 3, 0.5)
        for snr_c in (snr_cost_near(pos, ls, floor, b, 0.2, pe), None):
            got = select(cov, ls, pe, cfg, snr_c)
            ref = _select_numpy(cov, ls, pe, cfg, snr_c)
            for f in ("slot", "log_weight", "nis", "extra_var"):
                g, r = getattr(got, f), getattr(ref, f)
                assert g.shape == r.shape
                np.testing.assert_array_equal(g, r, err_msg=f)
            # the cases hold inliers, outliers, missing links and ambiguous mechanisms
            assert np.any(ref.slot >= 0) and np.any((ref.slot < 0) & ls.mask)
            assert np.any(~ls.mask) and np.any(ref.extra_var > 0)


def _prev_slots(rng, flat_slot, n_k):
    """Previous slots of a persistent-prior case: the flat selection's choice, another slot
    (a candidate or not), NaN or -1 (none), each link at random."""
    u = rng.random(flat_slot.shape)
    other = rng.integers(0, n_k, flat_slot.shape)
    return np.where(u < 0.4, flat_slot, np.where(u < 0.7, other, np.where(u < 0.85, np.nan,
                                                                         -1.0))).astype(float)


@pytest.mark.parametrize("bi", range(len(_BUILDINGS)))
def test_select_persistent_kernel_bit_identical_to_numpy(bi):
    """The persistent mechanism prior in the compiled selection (``select_best_kernel`` with
    ``persist``) against its numpy reference :func:`select_persistent` on the gated nodes and
    :func:`_select_numpy` on the others, in one call: slots, log-weights, NIS and variances
    equal bit for bit (tolerance 0), with and without SNR, random learned link weights,
    previous slots that are a candidate, no candidate, NaN or -1, and q = 0.3 / 0.05."""
    b = _BUILDINGS[bi]
    for seed in range(3):
        pos, links, floor, _ = _case(b, 900 + 100 * bi + seed)
        ls = _snr_links(links, seed)
        rng = np.random.default_rng(seed)
        pos = clamp_to_floor(pos, floor, b, 0.05)
        pe = all_paths(pos, ls, floor, b, 0.2)
        cov = _spd(rng, pos.shape[:2], 3, 0.5)
        n, h, m = pe.length.shape[:3]
        count = ls.mask[:, 0].sum(axis=-1)  # gate at the largest count: nodes either side
        cfg = TrackerConfig(mechanism_prior_min_links=int(count.max()),
                            mechanism_switch_p=(0.3, 0.05)[seed % 2])
        few = count < count.max()
        rows = np.flatnonzero(few)
        assert 0 < rows.size < n
        for snr_c in (snr_cost_near(pos, ls, floor, b, 0.2, pe), None):
            lw = link_weights(ls, cfg, snr_c is not None, n, h) \
                + rng.normal(0.0, 0.5, (n, h, m, 2))  # learned weights differ link by link
            fixed = _select_fixed(cov, ls, cfg, snr_c, n, h, lw)
            prev = _prev_slots(rng, select(cov, ls, pe, cfg, snr_c, fixed).slot,
                               pe.length.shape[-1])
            got = select(cov, ls, pe, cfg, snr_c, fixed, prev)
            ref = _select_numpy(cov, ls, pe, cfg, snr_c, lw)
            pe_r = dataclasses.replace(pe, **{f: getattr(pe, f)[rows] for f in (
                "length", "jac", "strict", "loose", "sure")})
            alt = select_persistent(cov[rows], ls.take(rows), pe_r, cfg,
                                    None if snr_c is None else snr_c[rows], lw[rows], prev[rows])
            for f in ("slot", "log_weight", "nis", "extra_var"):
                r = getattr(ref, f)
                r[rows] = getattr(alt, f)
                np.testing.assert_array_equal(getattr(got, f), r, err_msg=f)
            # the prior matters: some gated links choose otherwise than the flat prior
            flat = select(cov, ls, pe, cfg, snr_c, fixed)
            assert np.any(flat.slot[rows] != got.slot[rows])
            assert np.any(ref.slot[rows] >= 0) and np.any(ref.extra_var[rows] > 0)


def test_prior_information_kernel_matches_numpy():
    """The LU inverse and log-determinant of the prior covariance against numpy's LAPACK:
    within 1e-12 of the matrix' largest element / 1e-12 absolute on the log-determinant, over
    covariances of condition numbers up to ~1e6 (a velocity block much looser than the
    position), and exactly Y P = I to 1e-9."""
    rng = np.random.default_rng(3)
    p = _spd(rng, (5, 4), 6, 1.0)
    p[..., 3:, :] *= 30.0
    p[..., :, 3:] *= 30.0
    y, ld = prior_information(p)
    y_ref, ld_ref = _prior_information_numpy(p)
    scale = np.abs(y_ref).max(axis=(-2, -1), keepdims=True)
    assert np.all(np.abs(y - y_ref) <= 1e-12 * scale)
    np.testing.assert_allclose(ld, ld_ref, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(y @ p, np.broadcast_to(np.eye(6), p.shape), atol=1e-9)


@pytest.mark.parametrize("level", [None, "mixed"])
def test_iekf_kernel_matches_numpy(level):
    """The fused IEKF (one pass per hypothesis, LU solve/inverse) gives numpy's posterior mean,
    covariance, log-evidence and residuals within stated tolerances: mean 1e-9 m, covariance
    1e-9 of its largest element, log-evidence 1e-8 nats, residuals 1e-9 m; hypotheses inside
    and outside their box, level, vertical and the max-mixture of both (``level`` None),
    unused and hinge links; two buildings."""
    cfg = TrackerConfig()
    for bi in (0, 1):
        b = _BUILDINGS[bi]
        for seed in range(2):
            pos, links, floor, sel = _case(b, 600 + 10 * bi + seed)
            rng = np.random.default_rng(seed)
            n, h = pos.shape[:2]
            x0 = np.concatenate([pos, rng.normal(size=(n, h, 3))], axis=-1)
            p0 = _spd(rng, (n, h), 6, 0.3)
            sel = Selection(sel.slot, rng.normal(size=sel.slot.shape), sel.nis, sel.extra_var)
            lv = None if level is None else rng.random((n, h)) < 0.5
            got = iekf(x0, p0, links, floor, sel, b, cfg, lv)
            ref = _iekf_numpy(x0, p0, links, floor, sel, b, cfg, lv)
            np.testing.assert_allclose(got[0], ref[0], rtol=0.0, atol=1e-9)
            scale = np.abs(ref[1]).max(axis=(-2, -1), keepdims=True)
            assert np.all(np.abs(got[1] - ref[1]) <= 1e-9 * scale)
            np.testing.assert_array_equal(got[1], np.swapaxes(got[1], -1, -2))
            np.testing.assert_allclose(got[2], ref[2], rtol=0.0, atol=1e-8)
            np.testing.assert_allclose(got[3], ref[3], rtol=0.0, atol=1e-9)
            # the case leaves the box (pseudo-measurements active) for some hypotheses
            lo, hi = _box(x0, floor, b, cfg.z_margin_m)
            assert np.any((x0[..., :3] < lo) | (x0[..., :3] > hi))


def test_measurement_update_independent_of_batch():
    """A node's update is the same bit for bit whether computed alone or in a batch in which
    other nodes' priors lie outside their floor's box (then only those nodes' paths are
    evaluated once more at the prior): per-node references, other building, with SNR."""
    b = _BUILDINGS[1]
    cfg = TrackerConfig()
    pos, links, _, _ = _case(b, 700, n=6, h=1)
    ls = _snr_links(links, 7)
    rng = np.random.default_rng(7)
    floor = np.floor((pos[..., 2] - b.first_floor_z_m) / b.floor_height_m).clip(
        0, b.n_floors - 1).astype(int)
    x0 = np.concatenate([pos, rng.normal(size=pos.shape) * 0.5], axis=-1)
    x0[:3, :, :3] = clamp_to_floor(x0[:3, :, :3], floor[:3], b, cfg.z_margin_m)
    x0[4, 0, 2] = b.floor_z_m(floor[4, 0]) - 0.2  # below its floor
    x0[5, 0, 0] = b.edge_x_m[1] + 1.0  # beyond the facade's end
    p0 = _spd(rng, pos.shape[:2], 6, 0.2)
    lv = rng.random(pos.shape[:2]) < 0.5
    inside = np.all(clamp_to_floor(x0[..., :3], floor, b, cfg.z_margin_m) == x0[..., :3],
                    axis=(-2, -1))
    assert np.any(inside) and not np.all(inside)
    got = measurement_update(x0, p0, ls, floor, b, cfg, level=lv)
    for i in range(pos.shape[0]):
        one = measurement_update(x0[i:i + 1], p0[i:i + 1], ls.take([i]), floor[i:i + 1], b,
                                 cfg, level=lv[i:i + 1])
        for g, r in zip((got[0], got[1], got[2], got[3].slot, got[3].log_weight, got[4]),
                        (one[0], one[1], one[2], one[3].slot, one[3].log_weight, one[4]),
                        strict=True):
            np.testing.assert_array_equal(g[i:i + 1], r)


def test_paths_at_equals_all_paths():
    """The prior's paths re-evaluated only for the nodes whose prior left its box equal
    :func:`all_paths` at the unclamped priors bit for bit (several hypotheses per node, one
    band widening per hypothesis), and the clamped ones' paths where nothing moved."""
    b = _BUILDINGS[2]
    cfg = TrackerConfig()
    pos, links, floor, _ = _case(b, 800, n=6, h=4)
    xc = clamp_to_floor(pos, floor, b, cfg.z_margin_m)
    pos[:3] = xc[:3]  # nodes 0-2 inside, 3-5 with at least one hypothesis outside
    pos[3:, 0, 2] = b.floor_z_m(floor[3:, 0]) - 0.3
    assert np.all(xc[:3] == pos[:3]) and np.all(np.any(xc[3:] != pos[3:], axis=(-2, -1)))
    relax = np.random.default_rng(8).uniform(0.0, 0.5, floor.shape)
    pe0 = all_paths(xc, links, floor, b, relax)
    got = _paths_at(pe0, np.arange(3, 6), pos, links, floor, b, relax)
    ref = all_paths(pos, links, floor, b, relax)
    for f in ("length", "jac", "strict", "loose", "sure"):
        np.testing.assert_array_equal(getattr(got, f), getattr(ref, f), err_msg=f)
    assert _paths_at(pe0, np.arange(0), pos, links, floor, b, relax) is pe0


#: A building unlike the shipped one and ``_BUILDINGS``: two tall floors, windows almost as
#: tall as the floor, a narrow deep plan (anchors beyond its facade ends are common).
_TALL = dataclasses.replace(Building(), n_floors=2, floor_height_m=5.0, first_floor_z_m=0.0,
                            sill_height_m=0.3, window_height_m=4.2, width_m=8.0, depth_m=25.0,
                            partitions=())


@pytest.mark.parametrize("case", ["nan", "var 0 and inf", "masked node", "ties",
                                  "infinite ranges", "few finite cells"])
def test_grid_cost_kernel_pruning_exact_on_degenerate_inputs(case):
    """The pruned grid search (visiting cells by their straight-line bound) keeps the same
    ``keep`` cheapest cells, order and totals as the full evaluation where its inputs are
    degenerate: NaN ranges, anchors and variances (a NaN link adds nothing to the bound and
    makes the total NaN), variances 0 and inf, a node with every link masked (all totals 0:
    ties), ranges rounded to 0.5 m and duplicated anchors (tied totals at the ``keep``-th),
    +-inf ranges, and fewer finite cells than ``keep``. Anchors in front, above the windows
    and beyond the facade ends of ``_TALL`` (and the shipped building)."""
    cfg = TrackerConfig()
    w_out = float(np.log(cfg.outlier_span_m / cfg.outlier_weight))
    seen = dict.fromkeys(("abandoned", "nan", "finite<keep"), 0)
    for bi, b in enumerate((_TALL, Building())):
        rng = np.random.default_rng(77 + bi)
        n, m = 3, 9
        x0, x1 = b.edge_x_m
        top = b.floor_z_m(b.n_floors - 1) + b.floor_height_m
        anc = np.stack([rng.uniform(x0 - 25, x1 + 25, (n, m)), rng.uniform(-35, -1, (n, m)),
                        rng.uniform(0, top + 12, (n, m))], axis=-1)
        fl_t = rng.integers(0, b.n_floors, (n, 1))
        truth = np.stack([rng.uniform(x0, x1, (n, 1)), rng.uniform(0.5, b.depth_m, (n, 1)),
                          b.floor_z_m(fl_t) + b.nominal_node_height_m], axis=-1)
        probe = Links.from_arrays(anc, np.full((n, m), 30.0), np.full((n, m), 0.05),
                                  np.ones((n, m), bool), 0.03)
        pe = all_paths(truth, probe, fl_t, b, 0.0)
        first = np.where(candidates(pe), pe.length, np.inf).min(axis=-1)[:, 0]
        rho = np.where(np.isfinite(first), first + rng.normal(0, 0.05, (n, m)), 35.0)
        var = np.full((n, m), 0.05)
        mask = rng.random((n, m)) > 0.1
        if case == "nan":
            rho[0, 1], anc[1, 2], var[2, 3] = np.nan, np.nan, np.nan
        elif case == "var 0 and inf":
            var[:, 0], var[:, 4] = -0.25 * cfg.init_grid_m**2, np.inf  # 0 once widened
        elif case == "masked node":
            mask[1] = False
        elif case == "ties":
            rho = np.round(rho * 2.0) / 2.0
            anc[:, 5:] = anc[:, :1]
            rho[:, 5:] = rho[:, :1]
        elif case == "infinite ranges":
            rho[0, :3], rho[1, 2] = np.inf, -np.inf
        else:  # every link of node 0 NaN but one: no finite cell there
            rho[0, :] = np.nan
        # raw arrays (Links.from_arrays would mask the non-finite links): the kernel's own claim
        links = Links(rho=rho[:, None], var=var[:, None], mask=mask[:, None],
                      anchors=anc[:, None])
        floors = np.broadcast_to(np.arange(b.n_floors), (n, b.n_floors))
        full = _grid_totals(links, floors, b, cfg, 0, w_out)
        for keep in (1, 4, 25):
            got = _grid_totals(links, floors, b, cfg, keep, w_out)
            _assert_same_kept(got, full, keep)
            differ = ~((got == full) | (np.isnan(got) & np.isnan(full)))
            assert np.all(np.isinf(got[differ]))  # only abandoned cells differ
            seen["abandoned"] += int(differ.sum())
            seen["nan"] += int(np.isnan(full).sum())
            seen["finite<keep"] += int((np.isfinite(full).sum(axis=2) < keep).sum())
    assert seen["abandoned"] > 0  # the pruning ran
    if case in ("nan", "few finite cells"):
        assert seen["nan"] > 0
    if case == "few finite cells":
        assert seen["finite<keep"] > 0
