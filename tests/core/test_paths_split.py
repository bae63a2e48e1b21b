"""``diffpos.tracking.families.graded_split`` (the tracker's higher-order families' compiled
paths, :func:`diffpos.paths.graded_nb.graded_split_kernel`) against its reference
:func:`diffpos.paths.model.graded_paths`:
the same existence, lengths and Jacobians bit for bit (exact equality, NaN where NaN) on random
geometries of four buildings (some with interior partitions), mechanism sets of order 3 and 4
(with and without partition families), three band widenings, nodes on and off their floors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_paths_kernel import BUILDINGS, _geometries

from diffpos.paths.mechanisms import MECHANISMS, mechanism_set
from diffpos.paths.model import graded_paths
from diffpos.scenario import Partition
from diffpos.tracking.families import graded_split

PARTS = (Partition("x", 2.0, (3.0, 15.0)), Partition("y", 6.0, (-10.0, 20.0)),
         Partition("x", -3.0, (0.0, 9.0)))


def _cases():
    for name in sorted(BUILDINGS):
        for order, parts in ((3, False), (4, False), (3, True)):
            yield name, order, parts


@pytest.mark.parametrize(("name", "order", "parts"), list(_cases()))
def test_graded_split_equals_graded_paths(name: str, order: int, parts: bool) -> None:
    b = BUILDINGS[name]
    if parts:
        b = dataclasses.replace(b, partitions=PARTS)
    mech = mechanism_set(order, partitions=parts)
    nb = len(MECHANISMS)
    rng = np.random.default_rng(sum(map(ord, name)) + 10 * order + int(parts))
    nodes, anchors, floors = _geometries(b, rng, 2000)
    for relax in (0.0, 0.2, 1.5):
        g = graded_paths(nodes, anchors, b, relax_m=relax, floor=floors, mechanisms=mech)
        ok = g.loose & np.isfinite(g.length_m)
        n_before, length, ok_s, jac = graded_split(nodes, anchors, floors, b, order, relax,
                                                   parts)
        np.testing.assert_array_equal(n_before, ok[:, :nb].sum(axis=-1))
        np.testing.assert_array_equal(ok_s, ok[:, nb:])
        np.testing.assert_array_equal(length, g.length_m[:, nb:])  # NaN where NaN
        np.testing.assert_array_equal(jac, g.jacobian[:, nb:])
        # the draws exercise both verdicts of every grade
        assert 0 < ok_s.mean() < 1 and 0 < n_before.mean() < nb
    with pytest.raises(ValueError, match="relax_m"):
        graded_split(nodes, anchors, floors, b, order, -0.1, parts)
