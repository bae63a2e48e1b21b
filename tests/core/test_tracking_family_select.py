"""``TrackerConfig.family_select``: the higher-order families are offered to every link a
hypothesis has fitted (not only its misfits), so they compete with the 18 mechanisms in the
link's selection (:func:`diffpos.tracking.tracker._family_gate`).

Why (docs/channel_mix.md "Session 26"): on the emulator at ``channel_max_order`` 4 the true
floor fits many order-3/4 slab-series first arrivals with a WRONG one of the 18 inside
``nis_limit`` (so the misfit gate never offers it the family that is exact), and that wrong
mechanism pulls its position fit. ``family_minority`` still counts the misfits only (a link the
18 fit is no sign of a wrong state).

Reference: the gate's definition on hand-made learned arrays (``nis_limit`` 9, one update with
every link but the last), and the gate with the setting off, unchanged.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import _family_gate

#: two hypotheses of one node, seven link columns (the last absent this epoch); NIS of the
#: last real update per link (inf: called an outlier)
FIT = np.array([[[20.0, np.inf, 1.0, 1.0, 1.0, 1.0, 30.0],
                 [20.0, np.inf, 20.0, 1.0, 1.0, 1.0, 1.0]]])
PRESENT = np.array([[True] * 6 + [False]])
COL = np.arange(7)[None]


def _gate(n_meas, history=None, **kw):
    cfg = dataclasses.replace(TrackerConfig(), max_order=3, family_history=1,
                              family_min_links=4, **{"family_few_links": 0, **kw})
    seen = np.ones(FIT.shape) if history is None else history
    lk = {"link_fit": FIT, "link_all": seen, "link_out": np.zeros(FIT.shape)}
    return _family_gate(lk, COL, np.array([n_meas]), cfg, PRESENT)


def test_off_is_the_misfit_gate():
    """Setting off (the default): only the misfits (NIS above ``nis_limit`` or outliers)."""
    assert not TrackerConfig().family_select
    g = _gate(6, family_minority=False)
    assert g[0, 0].tolist() == [True, True, False, False, False, False, True]
    assert g[0, 1].tolist() == [True, True, True, False, False, False, False]


def test_every_fitted_link_is_offered():
    """On: every link with a fit history, the well-fitted ones too; a link the hypothesis has
    not fitted yet (``link_all`` 0) is not; a node below ``family_min_links`` gets none."""
    g = _gate(6, family_select=True, family_minority=False)
    assert g.all()
    unseen = np.ones(FIT.shape)
    unseen[..., 3] = 0.0
    g = _gate(6, unseen, family_select=True, family_minority=False)
    assert not g[..., 3].any() and g[..., [0, 1, 2, 4, 5, 6]].all()
    assert not _gate(3, family_select=True, family_minority=False).any()


def test_minority_counts_the_misfits_only():
    """With ``family_minority``: hypothesis 0 misfits 2 of its 6 present ranges (fewer than
    half): every fitted link is offered; hypothesis 1 misfits 3 (not fewer): none, as with the
    misfit gate. The links the 18 fit do not count as misfits."""
    g = _gate(6, family_select=True, family_minority=True)
    assert g[0, 0].all()
    assert not g[0, 1].any()
    ref = _gate(6, family_minority=True)
    assert not ref[0, 1].any() and ref[0, 0].sum() == 3


def test_select_min_links_only_with_many_ranges():
    """``family_select_min_links`` (default 0, off): a node with at least that many ranges gets
    every fitted link offered and no minority rule (hypothesis 1 misfits 3 of 6 ranges, which
    the rule would close); a node with fewer keeps the misfit gate and the rule, exactly as
    with the setting off. An unfitted link is still not offered."""
    assert TrackerConfig().family_select_min_links == 0
    g = _gate(6, family_select_min_links=6, family_minority=True)
    assert g.all()
    unseen = np.ones(FIT.shape)
    unseen[..., 3] = 0.0
    g = _gate(6, unseen, family_select_min_links=6, family_minority=True)
    assert not g[..., 3].any() and g[..., [0, 1, 2, 4, 5, 6]].all()
    for minority in (True, False):
        below = _gate(5, family_select_min_links=6, family_minority=minority)
        assert np.array_equal(below, _gate(5, family_minority=minority))
    ref = _gate(5, family_minority=True)  # hypothesis 1: 3 misfits of 5 ranges, closed
    assert ref[0, 0].sum() == 3 and not ref[0, 1].any()
