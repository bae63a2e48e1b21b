"""M-NLS's boundary starts (:class:`diffpos.estimators.mnls.rules.SnrRule` ``shadow_starts``,
session 30): the lit counterpart of every slot against a reference built from the labels, and
a Sionna RT receiver whose true floor's mode sat on the shadow side of the window's lower edge,
against the search's upper bound (a start at the truth)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from diffpos.estimators.mnls.rules import SnrRule
from diffpos.estimators.mnls.solver import mnls
from diffpos.paths.mechanisms import mechanism_set
from diffpos.scenario import default_scenario


@pytest.mark.parametrize("order", [2, 3, 4])
def test_lit_counterpart_against_the_labels(order):
    """``MechanismSet.lit`` equals the slot whose label is the diffracted slot's label with its
    ``D(upper)`` / ``D(lower)`` removed (-1 where that label is not in the set, and for every
    slot without a horizontal window-edge diffraction); built from the label strings, not the
    recipes."""
    for partitions in (False, True):
        m = mechanism_set(order, partitions=partitions)
        ref = []
        for label in m.labels:
            stripped = re.sub(r"-D\((lower|upper)\)", "", label)
            ref.append(m.labels.index(stripped) if stripped != label and stripped in m.labels
                       else -1)
        assert m.lit == tuple(ref)
        assert sum(k >= 0 for k in m.lit) >= 7  # at least the 18's seven window-edge slots


#: Sionna RT's paper building, receiver 138 of the study's 200 (`diffpos raytrace paper
#: --receivers 200 --samples 1000000 --max-depth 4`, the study's first arrivals at seed 0,
#: /work/exp/s26/mnls/rt/paper.npz): floor 3 at (2.25, 10.5, 14.5), four links; the first
#: arrivals of links 0 and 3 are `R(ceiling)-R(floor)` (strong: 29 and 36 dB).
_R138 = {
    "truth": [2.25, 10.5, 14.5],
    "range": [40.06471315750436, 34.801505142494555, 22.609033429124967, 38.2818293106495],
    "sigma": [0.05008831680540739, 0.05009382026009081, 0.06104630282627774,
              0.050019706767422324],
    "snr": [29.057049536960164, 28.794277930514852, 7.6341064217257895, 35.57430722738985],
}
_SOFT_SHEET = dict(first_arrival_prior=0.8, dielectric_edges=1.0)  # the study's best (s27)


def _r138(rule, x0=None):
    sc = default_scenario()
    radio = sc.radio
    return mnls(sc.anchor_positions_m(), np.array(_R138["range"]), np.array(_R138["sigma"]),
                building=sc.building, snr_db=np.array(_R138["snr"]), radio=radio,
                max_order=4, bandwidth_hz=radio.bandwidth_hz,
                error_floor_m=radio.range_error_floor_m, snr_rule=rule, x0_m=x0)


def test_sionna_receiver_on_the_shadow_side():
    """Receiver 138: without the boundary starts the true floor's mode explains links 0 and 3
    by `D(lower)-R(ceiling)-R(floor)` (the specular `R(ceiling)-R(floor)` does not exist there:
    the mode is 4-6 cm on the lower edge's shadow side) and floor 4 wins; with them the search
    crosses the boundary into the basin a start at the truth finds (the search's upper bound:
    the same mechanisms, within 5 cm, at a cost no higher), and floor 3 wins."""
    labels = mechanism_set(4, partitions=True).labels
    spec = labels.index("Tx-R(ceiling)-R(floor)-Rx")
    off = _r138(SnrRule(**_SOFT_SHEET))
    assert off.floor[0] == 4
    on = _r138(SnrRule(**_SOFT_SHEET, shadow_starts=0.1))
    assert on.floor[0] == 3
    assert on.floor_probability[0, 3] > 0.5 > off.floor_probability[0, 3]
    oracle = _r138(SnrRule(**_SOFT_SHEET), x0=np.array(_R138["truth"]))
    assert oracle.floor[0] == 3
    assert np.linalg.norm(on.position_m[0] - oracle.position_m[0]) < 0.05
    assert on.mechanism[0, 0] == on.mechanism[0, 3] == spec
    np.testing.assert_array_equal(on.mechanism[0], oracle.mechanism[0])
    assert on.cost[0] <= oracle.cost[0] + 1e-6


def test_batched_equals_one_by_one():
    """In a batch the boundary starts go to each fix's own rows: receiver 138 after two other
    fixes (the same links without the weakest one, and the links in reverse order) gives
    the answer it gives alone, bit for bit, and so do the others."""
    sc = default_scenario()
    radio = sc.radio
    rule = SnrRule(**_SOFT_SHEET, shadow_starts=0.1)
    r, s, q = (np.array(_R138[k]) for k in ("range", "sigma", "snr"))
    a = sc.anchor_positions_m()
    rows = [(a, r, s, q, np.array([True, True, False, True])), (a[::-1], r[::-1], s[::-1],
            q[::-1], np.ones(4, bool)), (a, r, s, q, np.ones(4, bool))]
    kw = dict(building=sc.building, radio=radio, max_order=4, bandwidth_hz=radio.bandwidth_hz,
              error_floor_m=radio.range_error_floor_m, snr_rule=rule)
    batch = mnls(np.stack([x[0] for x in rows]), np.stack([x[1] for x in rows]),
                 np.stack([x[2] for x in rows]), mask=np.stack([x[4] for x in rows]),
                 snr_db=np.stack([x[3] for x in rows]), **kw)
    for i, (ai, ri, si, qi, mi) in enumerate(rows):
        one = mnls(ai, ri, si, mask=mi, snr_db=qi, **kw)
        np.testing.assert_array_equal(batch.position_m[i], one.position_m[0])
        np.testing.assert_array_equal(batch.floor_probability[i], one.floor_probability[0])
    assert batch.floor[2] == 3


def test_default_is_no_boundary_starts():
    """``shadow_starts`` is 0 by default and 0 gives the same answer bit for bit; negative
    displacements are refused."""
    assert SnrRule().shadow_starts == 0.0
    a = _r138(SnrRule(**_SOFT_SHEET))
    b = _r138(SnrRule(**_SOFT_SHEET, shadow_starts=0.0))
    np.testing.assert_array_equal(a.floor_probability, b.floor_probability)
    np.testing.assert_array_equal(a.position_m, b.position_m)
    with pytest.raises(ValueError):
        SnrRule(shadow_starts=-0.1)
