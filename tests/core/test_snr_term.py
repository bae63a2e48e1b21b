"""The measurement update's compiled SNR term (:func:`diffpos.tracking.model.snr_term`,
:mod:`diffpos.tracking.snr_term_nb`) against its numpy reference: ``cap_snr_cost(
snr_cost_near(...))`` with the same cache, bit for bit, and the cache's contents after every
call equal.

Sequences of updates (the tracker's pairs: one hypothesis per node; and several hypotheses
per node, as the snapshot initialisation's) where some hypotheses keep their point and
anchors, some move within and some beyond the reuse margins (so links are reused, predicted
anew at the cached point and restarted), a fifth of the SNRs unknown in some updates and none
in others, per-hypothesis existence margins wide enough to make holes near the window band;
the default building and a variant with tall floors, short windows and a high sill; with the
cache, with it switched off (both margins 0) and without one; the cap on and off. Fixed
seeds.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import diffpos.tracking.model as tm
from diffpos.scenario import Building, Radio
from diffpos.tracking.links import Links, all_paths
from diffpos.tracking.state import SNR_CACHE_SLOTS, TrackerConfig

BUILDINGS = [
    Building(),
    Building(width_m=30.0, depth_m=15.0, n_floors=4, floor_height_m=3.6, first_floor_z_m=2.5,
             sill_height_m=1.0, window_height_m=1.2),
]
RADIO = Radio()


def _case(b: Building, rng, n: int, h: int, m: int):
    x0, x1 = b.edge_x_m
    w = x1 - x0
    floor = rng.integers(0, b.n_floors, (n, h))
    # heights near the window band's edges as often as elsewhere (holes)
    z_band = b.floor_z_m(floor) + b.sill_height_m + rng.choice(
        [0.0, b.window_height_m], (n, h)) + rng.normal(0.0, 0.15, (n, h))
    z_any = b.floor_z_m(floor) + rng.uniform(0.3, b.floor_height_m - 0.3, (n, h))
    z = np.where(rng.random((n, h)) < 0.5, z_band, z_any)
    pos = np.stack([rng.uniform(x0 + 0.5, x1 - 0.5, (n, h)),
                    rng.uniform(0.5, b.depth_m - 0.5, (n, h)), z], axis=-1)
    pos[..., 2] = np.clip(pos[..., 2], b.floor_z_m(floor) + 0.05,
                          b.floor_z_m(floor) + b.floor_height_m - 0.05)
    anchors = np.stack([rng.uniform(x0 - 0.4 * w, x1 + 0.4 * w, (n, m)),
                        -rng.uniform(0.5, 35.0, (n, m)),
                        rng.uniform(0.3, b.top_z_m + 15.0, (n, m))], axis=-1)
    return pos, floor, anchors


def _links(anchors, pos, rng, unknown):
    n, m = anchors.shape[:2]
    rho = np.linalg.norm(pos[:, :1, None, :] - anchors[:, None], axis=-1)[:, 0] + 1.0
    snr = np.where(rng.random((n, m)) < unknown, np.nan, rng.uniform(-10.0, 45.0, (n, m)))
    return Links.from_arrays(anchors, rho, np.full((n, m), 0.1), np.ones((n, m), bool), 0.1,
                             snr_db=snr, radio=RADIO)


def _cache(n: int, h: int, c: int) -> tm.SnrCache:
    s = len(SNR_CACHE_SLOTS)
    return tm.SnrCache(np.full((n, h, 3), np.nan), np.full((n, h, c, 3), np.nan, np.float32),
                       np.full((n, h, c, s), np.nan, np.float32))


def _copy(c: tm.SnrCache) -> tm.SnrCache:
    return tm.SnrCache(c.node.copy(), c.anchor.copy(), c.pred.copy())


def _reference(pos, links, floor, b, relax, pe, cfg, cache):
    use = cache is not None and tm.snr_reuse_on(cfg)
    c = tm.snr_cost_near(pos, links, floor, b, relax, pe, cache=cache if use else None,
                         reuse_m=(cfg.snr_reuse_m, cfg.snr_reuse_anchor_m))
    return tm.cap_snr_cost(c, cfg)


#: without the detector's skipped paths (first_arrival_prior: its own reference,
#: test_tracking_skip.py)
_BASE = TrackerConfig(first_arrival_prior=0.0)
CONFIGS = {
    "cache": _BASE,
    "cache off (margins 0)": dataclasses.replace(_BASE, snr_reuse_m=0.0,
                                                 snr_reuse_anchor_m=0.0),
    "no cap": dataclasses.replace(_BASE, snr_cost_cap_nats=0.0),
}


@pytest.mark.parametrize("bi", range(len(BUILDINGS)))
@pytest.mark.parametrize("key", list(CONFIGS))
@pytest.mark.parametrize("h", [1, 3])
def test_snr_term_equals_the_numpy_reference(bi, key, h):
    cfg = CONFIGS[key]
    b = BUILDINGS[bi]
    rng = np.random.default_rng(100 + 10 * bi + h)
    n, m = 12, 6
    pos, floor, anchors = _case(b, rng, n, h, m)
    cache_ref, cache_got = _cache(n, h, m - 1), _cache(n, h, m - 1)
    holes = reused = 0
    for step in range(4):
        if step:
            d = rng.normal(size=pos.shape)
            d *= (rng.choice([0.0, 0.02, 0.3], (n, h)) / np.linalg.norm(d, axis=-1))[..., None]
            pos = pos + d
            anchors = np.where(rng.random((n, 1, 1)) < 0.5, anchors,
                               anchors + 0.03 * rng.normal(size=anchors.shape))
        links = _links(anchors, pos, rng, unknown=0.0 if step == 2 else 0.2)
        relax = rng.choice([0.2, 0.5], (n, h))
        pe = all_paths(pos, links, floor, b, relax)
        before = _copy(cache_ref)
        ref = _reference(pos, links, floor, b, relax, pe, cfg, cache_ref)
        got = tm.snr_term(pos, links, floor, b, relax, pe, cfg, cache_got)
        np.testing.assert_array_equal(got, ref)
        for a, r in ((cache_got.node, cache_ref.node), (cache_got.anchor, cache_ref.anchor),
                     (cache_got.pred, cache_ref.pred)):
            np.testing.assert_array_equal(a, r)
        holes += int(np.sum(~np.isfinite(tm._snr_cost_thr(pos, links, b, pe.sure,
                                                          pe.loose | tm.ALWAYS_PREDICTED)[0])
                            & pe.loose))
        reused += int(np.sum(np.all(cache_ref.node == before.node, axis=-1)))
    # and without any cache object
    ref = _reference(pos, links, floor, b, relax, pe, cfg, None)
    np.testing.assert_array_equal(tm.snr_term(pos, links, floor, b, relax, pe, cfg, None), ref)
    assert holes > 0  # the shifted heights were exercised
    if key == "cache":
        assert reused > 0


def test_snr_term_without_snr_is_none():
    b = BUILDINGS[0]
    rng = np.random.default_rng(5)
    pos, floor, anchors = _case(b, rng, 3, 1, 4)
    links = _links(anchors, pos, rng, 0.0)
    links = Links(links.rho, links.var, links.mask, links.anchors)
    pe = all_paths(pos, links, floor, b, 0.2)
    assert tm.snr_term(pos, links, floor, b, 0.2, pe, TrackerConfig(), None) is None
