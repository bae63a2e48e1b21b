"""``TrackerConfig.edge_retry_margin_m``: a hypothesis in good standing whose prediction
stepped a few decimetres over the existence edge of a link's true first arrival is updated
again with a wider existence margin, so that link is fitted with its mechanism instead of
being called an outlier (the README main command's top-floor walker, docs/tracking_evidence.md
"Session 26: a wider margin at an existence edge").

Reference: the emulator's own first arrivals (:func:`diffpos.channel.emulator.first_arrival`,
its detected mechanism per link) at the true position, on a building and UAV layout that is
not in scenarios/ (the one of tests/core/test_tracking_margin.py).
"""

from __future__ import annotations

import numpy as np
from margin_building import ANCHORS, BUILDING, SCENARIO, level_arrivals
from margin_building import pre27_config as _cfg

from diffpos.paths.mechanisms import SPECULAR_SLOTS
from diffpos.tracking.links import Links, all_paths
from diffpos.tracking.tracker import _update_at

_SC, _B, _ANCHORS = SCENARIO, BUILDING, ANCHORS


def _edge_cases(rng, n):
    """True level-walking positions, the emulator's first arrivals there (all four detected),
    and a prior 0.25-0.35 m off the truth (horizontal and height) at which one detected
    specular first arrival (or more) is not even ``loose`` with the default margin but is with
    0.4 m."""
    floor, nodes, fa = level_arrivals(rng, n)
    d = rng.normal(size=(n, 3))
    prior = nodes + d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.25, 0.35, (n, 1))
    links = Links.from_arrays(np.broadcast_to(_ANCHORS, (n, 4, 3)), fa.range_m, fa.sigma_m,
                              fa.detected, _cfg().sigma_model_m, snr_db=fa.snr_db,
                              radio=_SC.radio)
    slot = np.maximum(fa.slot, 0)[:, None, :, None]
    narrow = np.take_along_axis(all_paths(prior[:, None], links, floor[:, None], _B, 0.2).loose,
                                slot, axis=-1)[:, 0, :, 0]
    wide = np.take_along_axis(all_paths(prior[:, None], links, floor[:, None], _B, 0.4).loose,
                              slot, axis=-1)[:, 0, :, 0]
    edge = fa.detected & np.isin(fa.slot, SPECULAR_SLOTS) & ~narrow & wide
    keep = np.flatnonzero(fa.detected.all(axis=1) & edge.any(axis=1))
    return floor[keep], prior[keep], links.take(keep), fa.slot[keep], edge[keep]


def _update(prior, floor, links, config):
    n = prior.shape[0]
    x = np.zeros((n, 6))
    x[:, :3] = prior
    p = np.broadcast_to(np.diag([0.01, 0.01, 0.0025, 0.25, 0.25, 0.01]), (n, 6, 6)).copy()
    return _update_at(x, p, links, np.arange(n), floor, _B.n_floors, _B, config)


def test_edge_link_fitted_with_its_mechanism_not_an_outlier():
    """Prior 0.25-0.35 m off, over the edge of one link's true first arrival: with the setting
    off, the hypothesis calls that link an outlier in some cases (elsewhere the fit at the
    second selection pass is back within the margin); with 0.4 m it fits it with the
    emulator's mechanism wherever the first update called it an outlier (every present link
    is in good standing: nothing learned, the prior outlier weight 0.02), and its evidence is
    mostly higher there (the outlier's density against the mechanism's, less the prior's cost
    of the fit's move back over the edge)."""
    rng = np.random.default_rng(3)
    floor, prior, links, true_slot, edge = _edge_cases(rng, 12000)
    assert floor.size > 40
    off = _update(prior, floor, links, _cfg())
    on = _update(prior, floor, links, _cfg(edge_retry_margin_m=0.4))
    out_off = (off[3] < 0) & edge
    hit = out_off.any(axis=1)
    assert hit.sum() >= 10
    np.testing.assert_array_equal(on[3][out_off], true_slot[out_off])
    gain = on[2][hit] - off[2][hit]
    assert np.mean(gain > 0.0) >= 0.75 and np.median(gain) > 0.5
    # the pairs that called no link an outlier are untouched, bit for bit
    same = ~np.any(off[3] < 0, axis=1)
    assert same.any()
    for a, b in zip(off, on, strict=True):
        np.testing.assert_array_equal(a[same], b[same])


def test_not_in_good_standing_not_retried():
    """A link already learned to be an outlier often (its weight ``log(1 - eps)`` with eps 0.3
    above ``edge_retry_eps``) leaves the hypothesis out of good standing: no second update,
    the result equal to the setting off, bit for bit."""
    rng = np.random.default_rng(4)
    floor, prior, links, _, _ = _edge_cases(rng, 4000)
    n, m = links.rho.shape[0], links.rho.shape[-1]
    w = np.empty((n, 2 * _B.n_floors, m, 2))
    w[..., 0] = np.log1p(-0.3)
    w[..., 1] = np.log(0.3 / 30.0)
    x = np.zeros((n, 6))
    x[:, :3] = prior
    p = np.broadcast_to(np.diag([0.01, 0.01, 0.0025, 0.25, 0.25, 0.01]), (n, 6, 6)).copy()
    args = (x, p, links, np.arange(n), floor, _B.n_floors, _B)
    off = _update_at(*args, _cfg(), None, w)
    on = _update_at(*args, _cfg(edge_retry_margin_m=0.4), None, w)
    for a, b in zip(off, on, strict=True):
        np.testing.assert_array_equal(a, b)
