"""Diffraction at the window's vertical edges (the facade ends), issue 34 item 2.

The families ``D(vertical x1|x2)`` of :func:`diffpos.paths.mechanisms.mechanism_set` (order >=
3): their geometry is held to the brute-force reference in tests/core/test_paths.py
(``test_higher_order_families_match_brute_force``) and to Sionna's traced paths by
``benchmarks/bench_path_model.py --sionna``; the emulator's compiled kernel to its numpy
reference in tests/core/test_channel_families.py. Here: the physics of the amplitude (the UTD
half-plane of the side wall) against the closed-form property of any half-plane, and the
family names.
"""

from __future__ import annotations

import numpy as np
import pytest

from diffpos.channel.slots import _Ctx, family_slot
from diffpos.paths.mechanisms import VERTICAL_EDGES, Recipe, label_family, mechanism_set
from diffpos.paths.model import first_arrival_paths
from diffpos.scenario import Building, Radio

B = Building()  # the paper's building, no partitions: x0 = -20, x1 = 20


def _shadow_boundary_pair(edge: str, depth_in: float, turn_deg: float = 0.0):
    """(anchor, node) with the node ``depth_in`` m beyond the edge point, along the incident
    ray turned by ``turn_deg`` about the edge (0: on the incident shadow boundary, > 0: into
    the shadow, away from the facade)."""
    lo, hi = B.window_z_m(1)
    z = 0.5 * (lo + hi)
    x0, x1 = B.edge_x_m
    if edge in VERTICAL_EDGES:
        sx = -1.0 if edge == "vertical x1" else 1.0  # the anchor beyond that facade end
        q = np.array([x0 if sx < 0 else x1, 0.0, z])
        a = q + np.array([10.0 * sx, -10.0, 0.0])
        th = np.deg2rad(45.0 + turn_deg)  # incident direction in the xy plane, then turned
        d = np.array([-sx * np.cos(th), np.sin(th), 0.0])
    else:  # the upper edge, anchor above it: the wall above the window shadows upwards
        q = np.array([0.0, 0.0, hi])
        a = q + np.array([0.0, -10.0, 6.0])
        u = (q - a) / np.linalg.norm(q - a)
        th = np.arctan2(u[2], u[1]) + np.deg2rad(turn_deg)
        d = np.array([0.0, np.cos(th), np.sin(th)])
    return a, q + depth_in * d


@pytest.mark.parametrize("edge", [*VERTICAL_EDGES, "upper"])
def test_half_plane_field_is_half_the_incident_on_the_shadow_boundary(edge: str) -> None:
    """On the incident shadow boundary a half-plane's UTD field is half the incident field
    (-6.02 dB of free space over the unfolded length), up to the reflection-boundary term
    (small: the reflection boundary is far); into the shadow it falls monotonically, up to 5 deg
    from the sheet (a vertical edge's sheet is the concrete side wall: on its face the field of a
    dielectric sheet flattens out, tests/core/test_channel_wall_edge.py; 45 deg would put the
    node on the wall for the vertical edges)."""
    radio = Radio()  # isotropic, x polarisation
    rec = Recipe("diff", edge=edge)
    out = []
    for turn in (0.0, 10.0, 25.0, 40.0):
        a, n = _shadow_boundary_pair(edge, 3.0, turn)
        ctx = _Ctx(B, radio, n[None], a[None])
        length, gain, _, _, valid = family_slot(ctx, rec)
        assert valid[0, 0], (edge, turn)
        if turn == 0:  # the straight line through the edge point
            assert length[0, 0] == pytest.approx(np.linalg.norm(n - a), rel=1e-12)
        u = (n - a) / np.linalg.norm(n - a)
        e0 = np.asarray(radio.polarization)
        e_inc = np.linalg.norm(e0 - np.dot(e0, u) * u)  # transverse field at the edge
        free = e_inc * radio.wavelength_m / (4 * np.pi * length[0, 0])
        out.append(20 * np.log10(abs(gain[0, 0]) / free))
    assert out[0] == pytest.approx(-6.02, abs=1.0), out
    assert all(np.diff(out) < 0), out


def test_vertical_edge_is_the_first_arrival_beyond_a_facade_end() -> None:
    """An anchor beyond the facade end, level with the window band, sees a node just inside the
    end wall only round the vertical edge: the model has that family (and neither horizontal
    edge: those need a Fermat point beyond an edge end) and its length is the Fermat length through the edge point."""
    mech = mechanism_set(3)
    a, n = _shadow_boundary_pair("vertical x1", 6.0, 20.0)
    ps = first_arrival_paths(n, a, B, mechanisms=mech)
    s = mech.labels.index("Tx-D(vertical x1)-Rx")
    assert ps.valid[s]
    q = np.array([B.edge_x_m[0], 0.0, a[2]])  # a and n level: the Fermat point is level too
    assert ps.length_m[s] == pytest.approx(np.linalg.norm(q - a) + np.linalg.norm(n - q),
                                           rel=1e-12)
    for lab in ("Tx-D(upper)-Rx", "Tx-D(lower)-Rx"):
        assert not ps.valid[mech.labels.index(lab)], lab
    np.testing.assert_allclose(ps.jacobian[s], (n - q) / np.linalg.norm(n - q), atol=1e-12)


def test_vertical_families_come_after_the_earlier_ones() -> None:
    """The vertical-edge families are appended: every earlier family keeps its slot."""
    for order in (3, 4):
        labels = mechanism_set(order).labels
        first = min(i for i, lab in enumerate(labels) if "vertical" in lab)
        assert all("vertical" in lab for lab in labels[first:])
        assert first == {3: 65, 4: 88}[order]
    assert label_family("Tx-R(ground)-D(vertical x1)-R(ceiling)-Rx") == "vertical D"
