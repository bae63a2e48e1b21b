"""estimates_v2's columnar pieces (fusion/estimates_v2.py, fusion/estimates.py) against the per-range construction they
replace: the links of every used (row, anchor) in anchor order with the mechanism label
(None for -1) and the wire residual (None unless finite), and finite_or_none by columns."""

from __future__ import annotations

import math

import msgspec
import numpy as np
from diffpos_services.fusion.estimates import finite_or_none_all
from diffpos_services.fusion.estimates_v2 import _links
from diffpos_services.wire import messages as M
from diffpos_services.wire.messages import finite_or_none

from diffpos.paths.mechanisms import MECHANISMS


def _random_batch(rng, b, m):
    use = rng.random((b, m)) < 0.7
    use[0] = False  # a row without a used anchor
    mech = rng.integers(-1, len(MECHANISMS), (b, m))
    resid = rng.normal(0.0, 0.3, (b, m))
    resid[rng.random((b, m)) < 0.15] = np.nan
    resid[rng.random((b, m)) < 0.05] = np.inf
    resid[rng.random((b, m)) < 0.05] = -0.0
    return use, mech, resid


def test_links_match_the_per_range_construction():
    rng = np.random.default_rng(7)
    for b, m in ((1, 1), (13, 4), (40, 16)):
        use, mech, resid = _random_batch(rng, b, m)
        names = [f"uav{j}" for j in range(m)]
        links, offs = _links(use, mech, resid, names)
        assert len(offs) == b + 1 and offs[-1] == len(links) == int(use.sum())
        for i in range(b):
            want = [M.AnchorLink(names[j], MECHANISMS[mech[i, j]] if mech[i, j] >= 0 else None,
                                 finite_or_none(resid[i, j].item()))
                    for j in range(m) if use[i, j]]
            got = links[offs[i]:offs[i + 1]]
            # the wire bytes (msgspec encodes -0.0 and 0.0 differently: the sign is kept)
            assert msgspec.json.encode(got) == msgspec.json.encode(want), i


def test_finite_or_none_by_columns():
    a = np.array([1.5, np.nan, -np.inf, np.inf, -0.0, 0.0, 1e-300, -2.25])
    got = finite_or_none_all(a)
    want = [finite_or_none(v) for v in a.tolist()]
    assert got == want
    assert all(type(v) is float for v in got if v is not None)
    assert math.copysign(1.0, got[4]) == -1.0
    assert finite_or_none_all(np.zeros(0)) == []
