"""Which links the tracker offers its higher-order families (``TrackerConfig.family_history``,
``family_min_links``; :func:`diffpos.tracking.tracker._family_gate`).

A link is a misfit of a hypothesis (and offered the families) only once that hypothesis has
fitted it (``family_history`` real updates with it): at a track's start no link is offered
anything beyond the 18 mechanisms. A node with fewer than ``family_min_links`` ranges is
never offered them (three ranges are fitted exactly by a position on any floor, so a family
that explains one of them is not tested by the others). Reference: the same run without the
families (``max_order`` 2), bit for bit where no family may be offered.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from static_track import ANCHORS, NODE, first_arrivals, same, track, triple_bounce

from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import _family_gate


def _run(config, n_links, epochs=12, seed=4):
    """Track the static node over ``epochs`` with its first ``n_links`` ranges, the first
    one the triple bounce: every epoch's state."""
    anchors = ANCHORS[:n_links]
    rho0 = first_arrivals(NODE, anchors, 2)
    rho0[0] = triple_bounce(anchors[0], NODE, 2)
    return track(config, anchors, rho0, epochs=epochs, seed=seed)


def test_a_tracks_first_update_offers_no_family():
    """Four ranges, one of them the triple bounce. With the default gate the run equals the
    run without families (max_order 2) bit for bit up to and including the first update in
    which the hypotheses have fitted the links (``link_fit`` set: before it every link is
    unseen), and differs after it (the misfit link is offered the families). With
    ``family_history=0`` (a link never seen counted as a misfit) and ``family_minority`` off
    it differs already in that first update."""
    cfg = dataclasses.replace(TrackerConfig(), max_order=3, family_min_links=4)
    assert cfg.family_history >= 1
    ref = _run(dataclasses.replace(cfg, max_order=2), 4)
    first = next(k for k, s in enumerate(ref) if np.isfinite(s.link_fit).any())
    got = _run(cfg, 4)
    assert all(same(got[k], ref[k]) for k in range(first + 1)), first
    assert not all(same(g, r) for g, r in zip(got, ref, strict=True))
    # (every link of a new track unseen: a majority, so family_minority alone closes it too)
    eager = _run(dataclasses.replace(cfg, family_history=0, family_minority=False), 4)
    assert not same(eager[first], ref[first])


def test_four_ranges_are_never_offered_a_family_without_the_learned_prior():
    """Four ranges (the triple bounce and three in-model ones): with the default
    ``family_min_links`` (5: a family for one link leaves three, fitted exactly on any floor)
    and without the learned family prior (``family_learned_links`` 0) the run equals the run
    without families bit for bit in every epoch; with 4 it does not."""
    cfg = dataclasses.replace(TrackerConfig(), family_learned_links=0,
                              family_worst_min_links=0)  # the worst-link gate apart
    assert cfg.max_order == 3 and cfg.family_min_links == 5
    ref = _run(dataclasses.replace(cfg, max_order=2), 4)
    got = _run(cfg, 4)
    assert all(same(g, r) for g, r in zip(got, ref, strict=True))
    four = _run(dataclasses.replace(cfg, family_min_links=4), 4)
    assert not all(same(g, r) for g, r in zip(four, ref, strict=True))


def test_three_ranges_are_never_offered_a_family():
    """Three ranges (the triple bounce and two in-model ones): the default run equals the run
    without families bit for bit in every epoch; with ``family_min_links=0`` it does not."""
    cfg = dataclasses.replace(TrackerConfig(), max_order=3, family_few_links=0,
                              family_fit_links=0)  # three-range families apart
    ref = _run(dataclasses.replace(cfg, max_order=2), 3)
    got = _run(cfg, 3)
    assert all(same(g, r) for g, r in zip(got, ref, strict=True))
    loose = _run(dataclasses.replace(cfg, family_min_links=0), 3)
    assert not all(same(g, r) for g, r in zip(loose, ref, strict=True))


def test_gate_counts_real_updates_with_the_link():
    """:func:`_family_gate` on hand-made learned arrays (forgetting 0.95, ``nis_limit`` 9): a
    link fitted badly (NIS 20 or an outlier) is offered the families once its forgotten count
    of updates reaches that of ``family_history`` consecutive ones, not before; a link fitted
    well (NIS 1) or never seen (NaN) never; a node with fewer than ``family_min_links`` ranges
    never."""
    f = TrackerConfig().link_forget
    cfg = dataclasses.replace(TrackerConfig(), max_order=3, family_history=3, family_min_links=4,
                              family_few_links=0, family_fit_links=0)
    need = (1 - f ** 3) / (1 - f)
    fit = np.array([[[20.0, np.inf, 20.0, 1.0, np.nan]]])
    n_all = np.array([[[need, need + 1.0, need - 1e-3, 20.0, 0.0]]])
    lk = {"link_fit": fit, "link_all": n_all, "link_out": np.zeros(fit.shape)}
    col = np.array([[0, 1, 2, 3, 4]])
    g = _family_gate(lk, col, np.array([5]), cfg)
    assert g.tolist() == [[[True, True, False, False, False]]]
    assert not _family_gate(lk, col, np.array([3]), cfg).any()
