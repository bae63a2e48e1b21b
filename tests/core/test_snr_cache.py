"""The tracker's reuse of predicted SNRs between updates (:class:`diffpos.tracking.model.SnrCache`,
``TrackerConfig.snr_reuse_m`` / ``snr_reuse_anchor_m``).

* With both margins 0, :func:`diffpos.tracking.model.snr_cost_near` with a cache equals it
  without one, bit for bit, over a sequence of updates where some hypotheses keep their point
  and anchors exactly and the others move (random anchor coordinates are not float32 values,
  so the float32 cached anchor is never the same: nothing is reused, and the cached path's
  scoring is the plain one's).
* With margins, :func:`diffpos.tracking.model._snr_cost_cached` against a reference written
  pair by pair: each link's SNRs predicted by ``pair_snr_db`` at the node and anchor the rule
  says (the cached point and anchor when both are within the margins: the cached direct and
  diffraction slots, the window-band slots predicted at the cached point; the cached point
  and the new anchor when only the point is; the new point otherwise; a hypothesis whose
  cached diffraction existence differs from the one at its point afresh), the cost by the
  numpy reference ``_snr_cost_of_numpy``; and the cache's contents after the call.

Geometries: the default building and a variant with tall floors, short windows and a high
sill (not in scenarios/), UAVs in front of, above and beyond the facade, a fifth of the SNRs
unknown; fixed seeds.
"""

from __future__ import annotations

import numpy as np
import pytest

import diffpos.tracking.model as ts
from diffpos.channel.emulator import pair_snr_db
from diffpos.scenario import Building, Radio
from diffpos.tracking.links import K_SLOTS, Links, all_paths
from diffpos.tracking.state import SNR_CACHE_SLOTS

CACHED = np.array(SNR_CACHE_SLOTS)

BUILDINGS = [
    Building(),
    Building(width_m=30.0, depth_m=15.0, n_floors=4, floor_height_m=3.6, first_floor_z_m=2.5,
             sill_height_m=1.0, window_height_m=1.2),
]
RADIO = Radio()


def _case(b: Building, rng, n: int = 10, m: int = 6):
    """One hypothesis per node (the tracker's pairs), its floor, the anchors and SNRs."""
    x0, x1 = b.edge_x_m
    w = x1 - x0
    floor = rng.integers(0, b.n_floors, (n, 1))
    z = b.floor_z_m(floor) + rng.uniform(0.3, b.floor_height_m - 0.3, (n, 1))
    pos = np.stack([rng.uniform(x0 + 0.5, x1 - 0.5, (n, 1)),
                    rng.uniform(0.5, b.depth_m - 0.5, (n, 1)), z], axis=-1)
    anchors = np.stack([rng.uniform(x0 - 0.4 * w, x1 + 0.4 * w, (n, m)),
                        -rng.uniform(0.5, 35.0, (n, m)),
                        rng.uniform(0.3, b.top_z_m + 15.0, (n, m))], axis=-1)
    return pos, floor, anchors


def _links(anchors, pos, rng, unknown=0.2):
    n, m = anchors.shape[:2]
    rho = np.linalg.norm(pos[:, :1, None, :] - anchors[:, None], axis=-1)[:, 0] + 1.0
    snr = np.where(rng.random((n, m)) < unknown, np.nan, rng.uniform(-10.0, 45.0, (n, m)))
    return Links.from_arrays(anchors, rho, np.full((n, m), 0.1), np.ones((n, m), bool), 0.1,
                             snr_db=snr, radio=RADIO)


def _empty_cache(n: int, c: int) -> ts.SnrCache:
    return ts.SnrCache(np.full((n, 1, 3), np.nan), np.full((n, 1, c, 3), np.nan, np.float32),
                       np.full((n, 1, c, len(CACHED)), np.nan, np.float32))


def _moves(rng, n, scale):
    """Displacements: a third zero, a third small, a third ``scale``-sized."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    size = rng.choice([0.0, 0.3, 3.0], n) * scale
    return d * size[:, None]


@pytest.mark.parametrize("bi", range(len(BUILDINGS)))
def test_zero_margins_equal_no_cache(bi):
    """Margins 0: the same costs as predicting every time, bit for bit, over 4 updates; the
    cache holds the last points and anchors."""
    b = BUILDINGS[bi]
    rng = np.random.default_rng(10 + bi)
    pos, floor, anchors = _case(b, rng)
    n = anchors.shape[0]
    cache = _empty_cache(n, 4)  # fewer cached columns than links: the rest never cached
    hits = 0
    for step in range(4):
        if step:
            keep = rng.random(n) < 0.5  # these keep point and anchors exactly
            pos = np.where(keep[:, None, None], pos, pos + _moves(rng, n, 0.1)[:, None])
            anchors = np.where(keep[:, None, None], anchors,
                               anchors + 0.05 * rng.normal(size=anchors.shape))
            hits += int(keep.sum())
        links = _links(anchors, pos, rng)
        pe = all_paths(pos, links, floor, b, 0.3)
        ref = ts.snr_cost_near(pos, links, floor, b, 0.3, pe)
        got = ts.snr_cost_near(pos, links, floor, b, 0.3, pe, cache=cache, reuse_m=(0.0, 0.0))
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_array_equal(cache.node, pos)
    assert hits > 0


def _reference(pos, links, b, pe, cache0, reuse_m):
    """:func:`_snr_cost_cached` pair by pair: (costs, thresholds, node, anchors, preds)."""
    n, m = links.rho.shape[0], links.rho.shape[-1]
    c_n = cache0.pred.shape[2]
    need = pe.loose | ts.ALWAYS_PREDICTED
    cost, thr = np.zeros((n, 1, m, K_SLOTS)), np.full((n, 1, m), np.nan)
    node, anc_c, pred_c = cache0.node.copy(), cache0.anchor.copy(), cache0.pred.copy()
    for i in range(n):
        p = pos[i, 0]
        near = np.linalg.norm(p - cache0.node[i, 0]) <= reuse_m[0]
        kept = [j < c_n and np.linalg.norm(links.anchors[i, 0, j] - cache0.anchor[i, 0, j])
                <= reuse_m[1] for j in range(m)]
        for j in range(min(m, c_n)):
            if kept[j] and np.any(np.isfinite(cache0.pred[i, 0, j, 1:])
                                  != pe.strict[i, 0, j, CACHED[1:]]):
                near = False  # the cached diffraction existence is not the point's
        at = cache0.node[i, 0] if near else p
        if not near:
            node[i, 0] = p
            anc_c[i, 0], pred_c[i, 0] = np.nan, np.nan
        for j in range(m):
            meas = links.snr[i, 0, j]
            if not np.isfinite(meas):
                continue
            full = pair_snr_db(links.anchors[i, :, j][:, None, :], at[None], building=b,
                               radio=RADIO)[0, 0]
            pred = np.where(need[i, 0, j], full, -np.inf)
            if near and kept[j]:
                pred[CACHED] = np.where(need[i, 0, j, CACHED],
                                        cache0.pred[i, 0, j].astype(np.float64), -np.inf)
            elif j < c_n:
                anc_c[i, 0, j], pred_c[i, 0, j] = links.anchors[i, 0, j], pred[CACHED]
            c, t = ts._snr_cost_of_numpy(pred[None], np.array([meas]), RADIO,
                                         pe.sure[i, 0, j][None])
            cost[i, 0, j], thr[i, 0, j] = c[0], t[0]
    return cost, thr, node, anc_c, pred_c


@pytest.mark.parametrize("bi", range(len(BUILDINGS)))
def test_margins_reuse_as_the_rule_says(bi):
    """With margins (0.05 m, 0.1 m): costs, thresholds and the cache's contents equal the
    pair-by-pair reference over 3 updates with points and anchors moved by 0, a fraction of
    and several times the margins; the updates reuse links, predict some anew at the cached
    point and restart some hypotheses (non-vacuous)."""
    b = BUILDINGS[bi]
    rng = np.random.default_rng(20 + bi)
    pos, floor, anchors = _case(b, rng, n=14)
    n, m = anchors.shape[:2]
    reuse = (0.05, 0.1)
    cache = _empty_cache(n, m - 1)
    n_reused = n_restarted = 0
    for step in range(3):
        if step:
            pos = pos + _moves(rng, n, reuse[0])[:, None]
            anchors = anchors + _moves(rng, n * m, reuse[1]).reshape(n, m, 3)
        links = _links(anchors, pos, rng, unknown=0.0 if step == 1 else 0.2)  # both paths
        pe = all_paths(pos, links, floor, b, 0.3)
        cache0 = ts.SnrCache(cache.node.copy(), cache.anchor.copy(), cache.pred.copy())
        ref = _reference(pos, links, b, pe, cache0, reuse)
        got = ts._snr_cost_cached(pos, links, b, pe.sure, pe.loose | ts.ALWAYS_PREDICTED,
                                  pe.strict, cache, reuse)
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])
        np.testing.assert_array_equal(cache.node, ref[2])
        np.testing.assert_array_equal(cache.anchor, ref[3])
        np.testing.assert_array_equal(cache.pred, ref[4])
        if step:
            same = np.all(cache.node == cache0.node, axis=-1)
            n_reused += int(np.sum(same & np.any(cache.anchor == cache0.anchor, axis=-1)))
            n_restarted += int(np.sum(~same))
    assert n_reused > 0 and n_restarted > 0


def test_cached_diffraction_existence_must_match():
    """A hypothesis whose cached diffraction slots exist where its point's do not (or the
    reverse) is predicted afresh at its point, even at the same point and anchors."""
    b = BUILDINGS[0]
    rng = np.random.default_rng(31)
    pos, floor, anchors = _case(b, rng, n=6)
    links = _links(anchors, pos, rng, unknown=0.0)
    pe = all_paths(pos, links, floor, b, 0.3)
    need = pe.loose | ts.ALWAYS_PREDICTED
    cache = _empty_cache(6, anchors.shape[1])
    first = ts._snr_cost_cached(pos, links, b, pe.sure, need, pe.strict, cache, (0.05, 0.1))
    fresh = cache.pred.copy()
    assert pe.strict[0, 0, 0, CACHED[1:]].any()
    cache.node[0] += 0.01  # within the margin: reused, but for the existence
    cache.pred[0, 0, 0, 1:] = np.where(np.isfinite(fresh[0, 0, 0, 1:]), -np.inf, 20.0)
    cache.pred[1, 0, 0, 1] = cache.pred[1, 0, 0, 1] + 1.0  # existence unchanged
    again = ts._snr_cost_cached(pos, links, b, pe.sure, need, pe.strict, cache, (0.05, 0.1))
    np.testing.assert_array_equal(again[0][0], first[0][0])  # afresh at the point itself
    np.testing.assert_array_equal(cache.node[0], pos[0])
    np.testing.assert_array_equal(cache.pred[0], fresh[0])
    assert np.any(again[0][1, 0, 0] != first[0][1, 0, 0])  # pair 1 reused its cached values


def test_anchor_columns_may_change_between_updates():
    """The cache is matched by anchor position, not by column: between two updates the
    anchors are permuted across the columns, one disappears and a new one (far from every
    cached anchor) takes a column; the hypotheses move by less than the margin. Every link is
    then scored as if predicted at the cached point (where the cache says it kept it) with
    its own anchor: the float64 prediction there, equal up to the float32 rounding of the
    reused values. A cache that matched columns would score links with another anchor's SNRs
    (tens of dB apart)."""
    b = BUILDINGS[1]
    rng = np.random.default_rng(41)
    pos, floor, anchors = _case(b, rng, n=8, m=6)
    n, m = anchors.shape[:2]
    reuse = (0.05, 0.1)
    cache = _empty_cache(n, m)
    links = _links(anchors, pos, rng, unknown=0.0)
    pe = all_paths(pos, links, floor, b, 0.3)
    ts._snr_cost_cached(pos, links, b, pe.sure, pe.loose | ts.ALWAYS_PREDICTED, pe.strict,
                        cache, reuse)
    old_node = cache.node.copy()
    perm = np.array([3, 0, 5, 1, 2])  # column 4 disappears, the rest move
    moved = anchors[:, perm].copy()
    moved[:, 2] = [b.edge_x_m[1] + 30.0, -60.0, 40.0]  # a new anchor where anchor 5 was
    pos2 = pos + 0.02 * rng.normal(size=pos.shape) / np.sqrt(3)
    links2 = _links(moved, pos2, rng, unknown=0.0)
    pe2 = all_paths(pos2, links2, floor, b, 0.3)
    need = pe2.loose | ts.ALWAYS_PREDICTED
    got = ts._snr_cost_cached(pos2, links2, b, pe2.sure, need, pe2.strict, cache, reuse)
    kept = np.all(cache.node == old_node, axis=-1)[:, 0]
    assert kept.sum() >= n // 2  # most hypotheses reused their point (non-vacuous)
    for i in range(n):
        one = links2.take(np.array([i]))
        ref = ts._snr_cost_thr(cache.node[i:i + 1], one, b, trust=pe2.sure[i:i + 1],
                               need=need[i:i + 1])
        for g, r in zip((got[0][i], got[1][i]), (ref[0][0], ref[1][0]), strict=True):
            np.testing.assert_array_equal(np.isfinite(g), np.isfinite(r))
            np.testing.assert_allclose(g[np.isfinite(g)], r[np.isfinite(r)], rtol=1e-5,
                                       atol=1e-5)
