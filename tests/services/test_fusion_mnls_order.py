"""The fusion's M-NLS fixes (the published snapshots) at a mechanism order (``FusionConfig
.mnls_max_order``, session 28): the snapshot call is M-NLS's own at that order, the default is
the 18 mechanisms as recordings ran, and a family beyond the 18 is published without a label."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.tracked import _mnls_finish, _mnls_start

from diffpos.estimators.mnls.solver import mnls
from diffpos.paths.mechanisms import MECHANISMS
from diffpos.scenario import default_scenario

#: Sionna RT's paper building, two receivers of the study's 200 (`diffpos raytrace paper
#: --receivers 200 --samples 1000000 --max-depth 4`, first arrivals at seed 0;
#: docs/raytrace_study.md "Session 27", tests/core/test_mnls_dielectric_edges.py): 177 on
#: floor 4; four anchors.
_RANGE = [[44.95541043059141, 33.85918019014048, 25.41560904304772, 38.4737623808426]]
_SIGMA = [[0.05047779799574086, 0.06783247207918698, 0.0669822212849008, 0.05316684251262638]]
_SNR = [[21.708172583835164, 5.2965514900851645, 5.5401733162570395, 13.37965085531954]]


def _inputs():
    sc = default_scenario()
    a = np.broadcast_to(np.asarray(sc.anchor_positions_m(), float), (1, 4, 3)).copy()
    prep = SimpleNamespace(safe_apos=a, rng_in=np.array(_RANGE), sig_eff=np.array(_SIGMA))
    batch = SimpleNamespace(use=np.ones((1, 4), dtype=bool), snr=np.array(_SNR))
    return sc, prep, batch


def test_the_default_is_the_18_mechanisms():
    assert FusionConfig().mnls_max_order == 2


def test_the_snapshot_call_is_mnls_at_the_configured_order():
    """``_mnls_start`` (in the process) runs ``mnls(..., max_order=K)`` with the recorded rule:
    the same fix bit for bit; orders 2 and 4 differ on this receiver (its floor posterior)."""
    sc, prep, batch = _inputs()
    rule = (False, 0.0, False, 0.0)
    fixes = {}
    for k in (2, 4):
        _, _, collect = _mnls_start(np.array([0]), prep, batch,
                                       (sc.building, sc.radio, rule, k))
        got = collect(None)
        want = mnls(prep.safe_apos, prep.rng_in, prep.sig_eff, building=sc.building,
                    mask=batch.use, snr_db=batch.snr, radio=sc.radio, max_order=k)
        np.testing.assert_array_equal(got.position_m, want.position_m)
        np.testing.assert_array_equal(got.floor_probability, want.floor_probability)
        fixes[k] = got
    assert np.max(np.abs(fixes[2].floor_probability - fixes[4].floor_probability)) > 0.05


def test_a_family_beyond_the_18_is_published_without_a_label():
    fix = SimpleNamespace(floor=np.array([3]), floor_probability=np.full((1, 5), 0.2),
                          used=np.array([[True, True, False, True]]),
                          mechanism=np.array([[2, len(MECHANISMS) + 3, 5, 17]]))
    res = SimpleNamespace(put=lambda rows, f: None)
    floor, prob, mech = np.full(1, -1), np.zeros((1, 5)), np.zeros((1, 4), dtype=int)
    _mnls_finish((np.array([0]), fix, None), res, floor, prob, mech)
    np.testing.assert_array_equal(mech, [[2, -1, -1, 17]])
    assert floor[0] == 3
