"""``TrackerConfig.edge_retry_prior``: with ``edge_retry_margin_m``, a pair's retry replaces its
first update only where every link it re-fits is fitted with a mechanism that is a candidate at
the pair's prior (clamped into its floor's box) with the ordinary existence margin
(docs/tracking_evidence.md "Session 27: why the edge retry loses on Sionna paper").

Reference, independent of the tracker's selection code: the graded path model
(:func:`diffpos.paths.model.graded_paths`) at the prior clamped with ``np.clip`` into the
floor's box, with the first-arrival rule written out here (a slot may be the first arrival if
it may exist and is no later than the earliest surely existing specular path, a diffraction
slot strictly earlier). Measurements: the emulator's own first arrivals at the true position,
on the building and UAVs of tests/core/test_tracking_margin.py (not a shipped scenario).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from margin_building import ANCHORS, BUILDING, SCENARIO, level_arrivals
from margin_building import pre27_config as _cfg

from diffpos.paths.mechanisms import DEFAULT_ORDER, DIFFRACTION_SLOTS
from diffpos.paths.model import graded_paths
from diffpos.tracking.links import Links
from diffpos.tracking.model import measurement_update
from diffpos.tracking.tracker import _update_at

_B = BUILDING
_P = np.diag([0.01, 0.01, 0.0025, 0.25, 0.25, 0.01])  # level track: margin 0.2 m (2 x 5 cm < 0.2)


def _cases(rng, n):
    """True level positions, the emulator's first arrivals there (all four detected), a prior
    0.15-0.4 m off the truth; floors and links."""
    floor, nodes, fa = level_arrivals(rng, n)
    d = rng.normal(size=(n, 3))
    prior = nodes + d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.15, 0.4, (n, 1))
    keep = np.flatnonzero(fa.detected.all(axis=1))
    links = Links.from_arrays(np.broadcast_to(ANCHORS, (n, 4, 3)), fa.range_m, fa.sigma_m,
                              fa.detected, _cfg().sigma_model_m, snr_db=fa.snr_db,
                              radio=SCENARIO.radio)
    return floor[keep], prior[keep], links.take(keep)


def _reference_candidates(prior, floor, margin_m):
    """(n, M, K) the slots that may be each link's first arrival at the clamped prior."""
    zf = _B.floor_z_m(floor)
    x0, x1 = _B.edge_x_m
    zm = _cfg().z_margin_m
    pc = np.stack([np.clip(prior[:, 0], x0 + zm, x1 - zm), np.clip(prior[:, 1], zm, _B.depth_m - zm),
                   np.clip(prior[:, 2], zf + zm, zf + _B.floor_height_m - zm)], axis=-1)
    g = graded_paths(pc[:, None, :], np.broadcast_to(ANCHORS, (len(pc), 4, 3)), _B,
                     relax_m=margin_m, floor=floor[:, None])
    k = g.length_m.shape[-1]
    diff = np.isin(np.arange(k), DIFFRACTION_SLOTS)
    earliest = np.where(g.sure & ~diff, g.length_m, np.inf).min(axis=-1, keepdims=True)
    return g.loose & np.where(diff, g.length_m < earliest, g.length_m <= earliest)


def _update(prior, floor, links, config):
    n = prior.shape[0]
    x = np.zeros((n, 6))
    x[:, :3] = prior
    return _update_at(x, np.broadcast_to(_P, (n, 6, 6)).copy(), links, np.arange(n), floor,
                      _B.n_floors, _B, config)


def test_retry_kept_only_where_every_refit_is_a_candidate_at_the_prior():
    """Every pair's result is the setting off's (the first update) or the plain retry's, bit
    for bit: the retry's exactly where every link it re-fits has a mechanism that the
    reference calls a candidate at the clamped prior with the ordinary 0.2 m margin. Both
    kinds occur (the plain retry alone would fail the test)."""
    rng = np.random.default_rng(5)
    floor, prior, links = _cases(rng, 8000)
    off = _update(prior, floor, links, _cfg())
    on = _update(prior, floor, links, _cfg(edge_retry_margin_m=0.4))
    test = _update(prior, floor, links, _cfg(edge_retry_margin_m=0.4,
                                                      edge_retry_prior=True))
    cand = _reference_candidates(prior, floor, _cfg().exist_margin_m)
    refit = links.mask[:, 0] & (off[3] < 0) & (on[3] >= 0)
    ok = np.take_along_axis(cand, np.maximum(on[3], 0)[..., None], axis=-1)[..., 0]
    want_on = np.all(~refit | ok, axis=-1)
    changed = np.any(off[3] != on[3], axis=-1) | (off[2] != on[2])
    assert np.sum(changed & want_on) >= 10 and np.sum(changed & ~want_on) >= 5
    for a_off, a_on, a in zip(off, on, test, strict=True):
        np.testing.assert_array_equal(a[want_on], a_on[want_on])
        np.testing.assert_array_equal(a[~want_on], a_off[~want_on])


def test_node_retry_updates_every_level_pair_of_the_node():
    """``edge_retry_node``: each node carries two level pairs (its true floor and the next);
    where one of them qualifies for the retry (an outlier in the first update, every link in
    good standing), both equal the reference: the measurement update with every existence
    margin at least 0.4 m (:func:`diffpos.tracking.model.measurement_update`, ``min_margin``);
    the other nodes' pairs equal the setting off, bit for bit. Some non-qualifying pairs of
    qualifying nodes change (the plain retry alone would fail the test). Families off
    (``max_order`` 2) so that the reference's link weights are the update's."""
    rng = np.random.default_rng(6)
    floor, prior, links = _cases(rng, 3000)
    n = floor.size
    rr = np.repeat(np.arange(n), 2)
    fl = np.stack([floor, (floor + 1) % _B.n_floors], axis=1).ravel()
    x = np.zeros((2 * n, 6))
    x[:, :3] = prior[rr]
    p = np.broadcast_to(_P, (2 * n, 6, 6)).copy()
    args = (x, p, links, rr, fl, _B.n_floors, _B)
    base = _cfg(max_order=DEFAULT_ORDER)  # no family weights: the reference's link
    off = _update_at(*args, base)                  # weights are the default ones
    plain = _update_at(*args, replace(base, edge_retry_margin_m=0.4))
    test = _update_at(*args, replace(base, edge_retry_margin_m=0.4, edge_retry_node=True))
    cfg = replace(base, edge_retry_margin_m=0.4)
    ref = measurement_update(x[:, None], p[:, None], links.take(rr), fl[:, None], _B, cfg,
                             level=np.ones((2 * n, 1), bool), min_margin=0.4)
    ref = (ref[0][:, 0], ref[1][:, 0], ref[2][:, 0], ref[3].slot[:, 0], ref[3].nis[:, 0],
           ref[4][:, 0], ref[3].log_weight[:, 0])
    qualifies = np.any(links.mask[rr, 0] & (off[3] < 0), axis=-1)  # eps 0.02: good standing
    node_q = np.isin(rr, rr[qualifies])
    for a_off, a_ref, a in zip(off, ref, test, strict=True):
        np.testing.assert_array_equal(a[node_q], a_ref[node_q])
        np.testing.assert_array_equal(a[~node_q], a_off[~node_q])
    moved = node_q & ~qualifies & ((test[2] != plain[2]) | np.any(test[3] != plain[3], axis=-1))
    assert moved.sum() >= 10
