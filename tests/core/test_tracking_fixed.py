"""The measurement update's shared kernel inputs (diffpos.tracking.model._iekf_fixed,
_select_fixed) and the broadcast without a copy (diffpos.tracking.links._cb).

:func:`diffpos.tracking.model.measurement_update` makes the inputs of the IEKF and of the
selection that depend on neither the paths nor the selection once per update and hands them
to every selection pass. The reference here is the update as it was before: every pass'
``select`` and ``iekf`` computing their own inputs (written out below from the public pieces);
the outputs must be the same bit for bit, and the shared inputs must not be written by the
kernels (a pass would otherwise read the previous pass' leftovers). Random cases (fixed
seeds) on buildings other than the shipped one (taller floors, small windows), anchors above
the windows and beyond the facade ends, priors outside their floor's box, with and without
SNR, several hypotheses per node and one (the tracker's pairs)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diffpos.paths.model_nb import building_planes
from diffpos.scenario import Building, default_scenario
from diffpos.tracking.iekf_nb import iekf_kernel
from diffpos.tracking.links import _IS_DIFF, Links, _c, _cb, all_paths
from diffpos.tracking.model import (
    _LOG2PI,
    _LOG_N,
    SNR_SIGMA_DB,
    SNR_SPAN_DB,
    Selection,
    _box,
    _height_prior,
    _iekf_fixed,
    _paths_at,
    _select_fixed,
    existence_margin,
    iekf,
    link_weights,
    measurement_update,
    prior_information,
    select,
    snr_cost_near,
)
from diffpos.tracking.model_nb import select_best_kernel, select_mix_kernel, select_pack_kernel
from diffpos.tracking.state import TrackerConfig, clamp_to_floor

_BUILDINGS = [
    dataclasses.replace(Building(), n_floors=6, floor_height_m=3.6, first_floor_z_m=2.0,
                        sill_height_m=0.9, window_height_m=2.0, width_m=30.0, depth_m=15.0,
                        partitions=()),
    dataclasses.replace(Building(), floor_height_m=2.7, window_height_m=0.8, sill_height_m=1.2),
]


def _case(b, seed, n=6, h=3, m=8, snr=True):
    """Priors (N, H, 6), covariances, links and floors; some priors outside their box."""
    rng = np.random.default_rng(seed)
    x0, x1 = b.edge_x_m
    floor = rng.integers(0, b.n_floors, (n, h))
    zf = b.floor_z_m(floor)
    pos = np.stack([rng.uniform(x0 - 1, x1 + 1, (n, h)), rng.uniform(0.05, b.depth_m, (n, h)),
                    zf + rng.uniform(-0.2, b.floor_height_m + 0.2, (n, h))], axis=-1)
    anc = np.stack([rng.uniform(x0 - 10, x1 + 10, (n, m)), rng.uniform(-30, -2, (n, m)),
                    rng.uniform(0, b.floor_z_m(b.n_floors - 1) + 6, (n, m))], axis=-1)
    ranges = np.linalg.norm(pos[:, :1, None] - anc[:, None], axis=-1)[:, 0] \
        + rng.uniform(-0.5, 5.0, (n, m))
    mask = rng.random((n, m)) > 0.15
    snr_db = np.where(rng.random((n, m)) < 0.2, np.nan, rng.uniform(-5, 40, (n, m)))
    sc = default_scenario()
    links = Links.from_arrays(anc, ranges, rng.uniform(0.01, 0.3, (n, m)), mask, 0.03,
                              snr_db=snr_db if snr else None, radio=sc.radio)
    x = np.concatenate([pos, rng.normal(size=(n, h, 3)) * 0.5], axis=-1)
    x[-1, 0, :3] = clamp_to_floor(x[-1, 0, :3], floor[-1, 0], b, 0.1)  # inside its box
    x[0, 0, 2] = b.floor_z_m(floor[0, 0]) - 0.2  # below its floor
    x[1, 0, 0] = x1 + 0.8  # beyond the facade's end
    a = rng.normal(size=(n, h, 6, 6)) * 0.4
    p = a @ np.swapaxes(a, -1, -2) + 0.01 * np.eye(6)
    level = rng.random((n, h)) < 0.6
    return x, p, links, floor, level


def _select_before(pos_cov, links, pe, config, snr_c):
    """``tracking_model.select`` as it was before the shared inputs (verbatim)."""
    shape = pe.length.shape
    n, h, m = shape[:3]
    use_snr = snr_c is not None
    snr = _c(links.snr[:, 0]) if use_snr else np.zeros((n, m))
    sc = _c(snr_c) if use_snr else np.zeros((1, 1, 1, 1))
    length, rho, mask = _c(pe.length), _c(links.rho[:, 0]), _c(links.mask[:, 0])
    valid = np.empty(shape, dtype=np.bool_)
    sv, sl = np.empty(valid.size), np.empty(valid.size)
    cnt = select_pack_kernel(
        length, _c(pe.jac), _c(pe.sure), _c(pe.loose), _IS_DIFF,
        _c(np.broadcast_to(pos_cov, (n, h, 3, 3))), _c(links.var[:, 0]), snr, sc, use_snr,
        np.array([np.log(SNR_SIGMA_DB), 0.5 * _LOG2PI]), float(-np.log(SNR_SPAN_DB)),
        valid, sv, sl)
    w_link = link_weights(links, config, use_snr, n, h)
    slot, best = np.empty((n, h, m), dtype=np.int64), np.empty((n, h, m), dtype=np.int64)
    base, nis, extra = np.empty((n, h, m)), np.empty((n, h, m)), np.empty((n, h, m))
    ex = np.empty(cnt)
    select_best_kernel(length, valid, rho, mask, snr, use_snr, sv, sl, np.log(sv[:cnt]),
                       np.array([_LOG2PI, 0.0, 0.0]), w_link, _LOG_N, ex, best, base, slot, nis,
                       np.zeros(n, np.bool_), np.empty((1, 1, 1), np.int64))
    np.exp(ex, out=ex)
    mix = np.empty((n, h, m))
    select_mix_kernel(length, valid, slot, best, ex, extra, mix)
    log_w = np.where(slot >= 0, base + np.log(mix), base)
    return Selection(slot=slot, log_weight=log_w, nis=nis, extra_var=extra)


def _iekf_before(x_prior, p_prior, links, floor, sel, building, config, level, prior_info):
    """``tracking_model.iekf`` as it was before the shared inputs (verbatim)."""
    y, logdet_y = prior_information(p_prior) if prior_info is None else prior_info
    n, h = x_prior.shape[:2]
    m = sel.slot.shape[-1]
    lo, hi = _box(x_prior, floor, building, config.z_margin_m)
    z_nom, wh, h_const = _height_prior(x_prior, floor, building, config, level)
    fl = np.empty((n, h))
    fl[...] = np.broadcast_to(np.asarray(floor), (n, h))
    x, p = np.empty((n, h, 6)), np.empty((n, h, 6, 6))
    log_ev, residual = np.empty((n, h)), np.empty((n, h, m))
    f8 = np.float64
    iekf_kernel(_c(x_prior, dtype=f8), _c(np.broadcast_to(y, (n, h, 6, 6)), dtype=f8),
                _c(np.broadcast_to(logdet_y, (n, h)), dtype=f8),
                _c(np.broadcast_to(lo, (n, h, 3)), dtype=f8),
                _c(np.broadcast_to(hi, (n, h, 3)), dtype=f8), z_nom, wh, h_const,
                _c(links.anchors[:, 0], dtype=f8), fl, _c(sel.slot, dtype=np.int64),
                _c(np.broadcast_to(sel.extra_var, (n, h, m)), dtype=f8),
                _c(np.broadcast_to(sel.log_weight, (n, h, m)), dtype=f8),
                _c(links.rho[:, 0], dtype=f8), _c(links.var[:, 0], dtype=f8),
                _c(links.mask[:, 0]), int(config.gn_iterations),
                float(1.0 / config.box_sigma_m**2), _LOG2PI, *building_planes(building),
                x, p, log_ev, residual)
    return x, p, log_ev, residual


def _reference_update(x_prior, p_prior, links, floor, b, cfg, level):
    """:func:`measurement_update` (without an SNR cache) as it was: every pass' ``select``
    and ``iekf`` making their own inputs (their bodies of before, verbatim)."""
    x = x_prior
    xc = clamp_to_floor(x[..., :3], floor, b, cfg.z_margin_m)
    moved = np.flatnonzero(np.any(xc != x[..., :3], axis=(-2, -1)))
    relax = existence_margin(p_prior, cfg)
    pe0 = all_paths(xc, links, floor, b, relax)
    snr_c = snr_cost_near(xc, links, floor, b, relax, pe0)
    info = prior_information(p_prior)
    p = p_prior
    for k in range(cfg.select_passes):
        if k > 0:
            relax = existence_margin(p, cfg)
        if k == 0:
            pe = _paths_at(pe0, moved, x[..., :3], links, floor, b, relax)
        else:
            pe = all_paths(x[..., :3], links, floor, b, relax)
        sel = _select_before(p_prior[..., :3, :3], links, pe, cfg, snr_c)
        x, p, log_ev, res = _iekf_before(x_prior, p_prior, links, floor, sel, b, cfg, level,
                                         info)
    return clamp_to_floor(x, floor, b, cfg.z_margin_m), p, log_ev, sel, res


def _bytes(out):
    x, p, ev, sel, res = out
    return [a.tobytes() for a in (x, p, ev, sel.slot, sel.log_weight, sel.nis,
                                  sel.extra_var, res)]


@pytest.mark.parametrize("bi", range(len(_BUILDINGS)))
@pytest.mark.parametrize("h", [1, 3])
def test_measurement_update_with_shared_inputs_is_the_per_pass_one(bi, h):
    """Bit for bit the update whose passes make their own inputs, with SNR and without,
    several hypotheses per node and one, on two other buildings; the cases have priors
    outside their box (their paths evaluated again at the prior) and inliers/outliers."""
    b = _BUILDINGS[bi]
    # the reference applies no SNR cap and no skipped-path term (cap_snr_cost and skip_cost
    # are tested on their own: test_snr_term.py, test_tracking_skip.py)
    cfg = TrackerConfig(snr_reuse_m=0.0, snr_reuse_anchor_m=0.0, snr_cost_cap_nats=0.0,
                        first_arrival_prior=0.0)
    for seed, snr in ((10 * bi + h, True), (10 * bi + h + 5, False)):
        x, p, links, floor, level = _case(b, seed, h=h, snr=snr)
        xc = clamp_to_floor(x[..., :3], floor, b, cfg.z_margin_m)
        assert np.any(xc != x[..., :3]) and np.any(np.all(xc == x[..., :3], axis=-1))
        got = measurement_update(x, p, links, floor, b, cfg, level=level)
        ref = _reference_update(x, p, links, floor, b, cfg, level)
        assert _bytes(got) == _bytes(ref)
        assert np.any(ref[3].slot >= 0) and np.any((ref[3].slot < 0) & links.mask)


def test_shared_inputs_are_read_only_for_the_kernels():
    """``select`` and ``iekf`` given the shared inputs equal the calls that make their own,
    and leave those inputs as they were (two passes may share them)."""
    b = _BUILDINGS[0]
    cfg = TrackerConfig()
    x, p, links, floor, level = _case(b, 41, h=2)
    relax = existence_margin(p, cfg)
    pe = all_paths(clamp_to_floor(x[..., :3], floor, b, cfg.z_margin_m), links, floor, b,
                   relax)
    snr_c = snr_cost_near(x[..., :3], links, floor, b, relax, pe)
    fix_s = _select_fixed(p[..., :3, :3], links, cfg, snr_c, *x.shape[:2])
    info = prior_information(p)
    fix_i = _iekf_fixed(x, p, links, floor, b, cfg, level, info)
    before = [np.array(a, copy=True) for a in (*fix_s, *fix_i[0], *fix_i[1])]
    sel = select(p[..., :3, :3], links, pe, cfg, snr_c, fix_s)
    ref_sel = select(p[..., :3, :3], links, pe, cfg, snr_c)
    for f in ("slot", "log_weight", "nis", "extra_var"):
        assert getattr(sel, f).tobytes() == getattr(ref_sel, f).tobytes(), f
    got = iekf(x, p, links, floor, sel, b, cfg, level, info, fix_i)
    ref = iekf(x, p, links, floor, sel, b, cfg, level, info)
    for g, r in zip(got, ref, strict=True):
        assert g.tobytes() == r.tobytes()
    after = [np.asarray(a) for a in (*fix_s, *fix_i[0], *fix_i[1])]
    for a0, a1 in zip(before, after, strict=True):
        assert a0.tobytes() == a1.tobytes()


def test_cb_is_the_broadcast_copy_without_the_copy():
    """``_cb(a, shape, dtype)`` has the values, dtype, C order and writability of
    ``_c(np.broadcast_to(a, shape), dtype)``; it is ``a`` itself when ``a`` is already such
    an array of the shape, a copy when ``a`` is read-only, strided or of another dtype."""
    rng = np.random.default_rng(5)
    full = rng.normal(size=(4, 3, 2))
    cases = [(full, None), (full[:, :1], None), (2.5, None), (full[:, :, 0:1], None),
             (full.astype(np.float32), np.float64), (np.asarray(full > 0), np.bool_),
             (np.broadcast_to(full[:1], full.shape), None), (full.transpose(0, 1, 2)[::1], None),
             (np.asfortranarray(full), None)]
    for a, dt in cases:
        got = _cb(a, full.shape, dt)
        ref = _c(np.broadcast_to(a, full.shape), dt)
        assert got.shape == ref.shape and got.dtype == ref.dtype
        assert got.flags.c_contiguous and got.flags.writeable
        assert got.tobytes() == ref.tobytes()
    assert _cb(full, full.shape) is full
    ro = full.copy()
    ro.flags.writeable = False
    assert _cb(ro, full.shape) is not ro and _cb(ro, full.shape).flags.writeable
