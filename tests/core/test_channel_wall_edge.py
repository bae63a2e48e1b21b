"""The vertical window edge's UTD on a dielectric side wall (issue 34 item 4).

* The coefficients against the wedge's four-term Kouyoumjian-Pathak form (``n = 2``, the
  cotangents and ``a+-`` with their integers ``N+-``, computed here independently of the
  module's secant / half-angle algebra) with Luebbers' reflection weights: the lit face's
  Fresnel coefficient on its reflection term ``D4``, ``-1`` on the unlit face's ``D3``.
* The perfect-conductor limit of the soft coefficient is Kouyoumjian-Pathak's, bit for bit.
* The physical difference: behind a perfectly conducting sheet the hard (perpendicular to the
  edge) field grows towards the sheet's shadowed face; behind a concrete one it does not.
* Where Sionna RT is installed: its own diffraction matrix (``RadioMaterial._diffraction_matrix``,
  the independent ray tracer's coefficient) on a concrete side wall, anchor beyond the facade
  end, nodes in the wall's shadow: the dielectric sheet within 0.5 dB (median; 2 dB p90) where
  the perfect conductor is up to 18 dB off.
"""

from __future__ import annotations

import numpy as np
import pytest
from sionna_wedge import sionna_edge_db

from diffpos.channel.gtd_halfplane import (
    diffracted_field,
    edge_frame,
    transition_function,
    utd_coefficients,
    wavenumber_rad_m,
)
from diffpos.channel.slots import fresnel_coefficients, itu_permittivity

F_HZ = 28e9
ETA = itu_permittivity("concrete", F_HZ)


def _wedge_terms(phi, phi_in, kl, n=2.0):
    """D1..D4 / prefactor of the wedge (Kouyoumjian-Pathak 1974), general ``n``."""
    def a_pm(beta, sign):
        big_n = np.round((beta + sign * np.pi) / (2 * n * np.pi))
        return 2 * np.cos((2 * n * np.pi * big_n - beta) / 2) ** 2

    bm, bp = phi - phi_in, phi + phi_in
    cot = lambda x: 1.0 / np.tan(x)  # noqa: E731
    d1 = cot((np.pi + bm) / (2 * n)) * transition_function(kl * a_pm(bm, +1))
    d2 = cot((np.pi - bm) / (2 * n)) * transition_function(kl * a_pm(bm, -1))
    d3 = cot((np.pi + bp) / (2 * n)) * transition_function(kl * a_pm(bp, +1))
    d4 = cot((np.pi - bp) / (2 * n)) * transition_function(kl * a_pm(bp, -1))
    return d1, d2, d3, d4


def test_dielectric_coefficients_match_the_four_term_wedge_form() -> None:
    rng = np.random.default_rng(3)
    phi_in = rng.uniform(0.2, np.pi - 0.2, 400)
    phi = rng.uniform(0.1, 2 * np.pi - 0.1, 400)
    # stay off the shadow and reflection boundaries (the cotangents' poles)
    keep = (np.abs(np.abs(phi - phi_in) - np.pi) > 0.05) & (np.abs(phi + phi_in - np.pi) > 0.05) \
        & (np.abs(phi + phi_in - 3 * np.pi) > 0.05)
    phi, phi_in = phi[keep], phi_in[keep]
    gamma0 = rng.uniform(0.6, np.pi / 2, phi.size)
    big_l = rng.uniform(0.5, 30.0, phi.size)
    r_s, r_h = fresnel_coefficients(rng.uniform(0.0, 1.0, phi.size), ETA)
    d_s, d_h = utd_coefficients(phi, phi_in, gamma0, big_l, frequency_hz=F_HZ,
                                lit_face_reflection=(r_s, r_h))
    k = wavenumber_rad_m(F_HZ)
    d1, d2, d3, d4 = _wedge_terms(phi, phi_in, k * big_l)
    # prefactor of the wedge: -exp(-j pi/4) / (2 n sqrt(2 pi k) sin gamma0), n = 2
    pre = -np.exp(-0.25j * np.pi) / (4 * np.sqrt(2 * np.pi * k) * np.sin(gamma0))
    np.testing.assert_allclose(d_s, pre * (d1 + d2 - d3 + r_s * d4), rtol=1e-9)
    np.testing.assert_allclose(d_h, pre * (d1 + d2 - d3 + r_h * d4), rtol=1e-9)


def test_conductor_limit_of_the_soft_coefficient_is_kouyoumjian_pathak() -> None:
    phi_in = np.linspace(0.3, 2.8, 7)[:, None]
    phi = np.linspace(3.3, 6.2, 9)[None, :]
    args = (phi, phi_in, np.full((7, 9), 1.2), np.full((7, 9), 4.0))
    pec_s, _ = utd_coefficients(*args, frequency_hz=F_HZ)
    diel_s, _ = utd_coefficients(*args, frequency_hz=F_HZ,
                                 lit_face_reflection=(np.full((7, 9), -1.0 + 0j),
                                                      np.full((7, 9), 1.0 + 0j)))
    np.testing.assert_array_equal(diel_s, pec_s)


def _side_wall_links(n_nodes: int = 60):
    """Anchor beyond the facade end x0 = -12.9 (front wall y = 0), nodes inside behind the
    side wall x = x0 (its half-plane runs into the building, +y), the Fermat point on the edge."""
    rng = np.random.default_rng(1)
    a = np.array([-24.61, -8.57, 1.38])
    x0 = -12.9
    nodes = np.stack([rng.uniform(x0 + 0.3, x0 + 20, n_nodes), rng.uniform(0.3, 23, n_nodes),
                      rng.uniform(0.5, 15, n_nodes)], -1)
    da, dn = np.hypot(a[0] - x0, a[1]), np.hypot(nodes[:, 0] - x0, nodes[:, 1])
    q = np.stack([np.full(n_nodes, x0), np.zeros(n_nodes),
                  a[2] + (nodes[:, 2] - a[2]) * da / (da + dn)], -1)
    src = np.broadcast_to(a, nodes.shape).copy()
    fr = edge_frame(src, nodes, q, [0, 0, 1.0], [0, 1.0, 0])
    shadow = fr.psi_rad > np.pi + fr.psi_in_rad + 0.01
    return src[shadow], nodes[shadow], q[shadow]


def test_hard_field_behind_a_concrete_wall_does_not_grow_towards_it() -> None:
    """x polarisation at a vertical edge is the hard one. Deep in the shadow, near the wall's
    inner face, the conductor's hard field stays strong (its reflection terms add) while the
    dielectric's falls away with the soft one's."""
    src, nodes, q = _side_wall_links(400)
    fr = edge_frame(src, nodes, q, [0, 0, 1.0], [0, 1.0, 0])
    e0 = np.array([1.0, 0.0, 0.0])
    pec = np.linalg.norm(diffracted_field(src, nodes, q, [0, 0, 1.0], [0, 1.0, 0], e0,
                                          frequency_hz=F_HZ), axis=-1)
    wall = np.linalg.norm(diffracted_field(src, nodes, q, [0, 0, 1.0], [0, 1.0, 0], e0,
                                           frequency_hz=F_HZ, face_permittivity=ETA), axis=-1)
    deep = fr.psi_rad > np.deg2rad(350.0)
    near_isb = fr.psi_rad < np.pi + fr.psi_in_rad + np.deg2rad(5.0)
    assert deep.sum() > 10 and near_isb.sum() > 3
    assert np.all(20 * np.log10(pec[deep] / wall[deep]) > 10.0)
    # at the shadow boundary the incident-field term dominates: both within 1.5 dB
    assert np.all(np.abs(20 * np.log10(pec[near_isb] / wall[near_isb])) < 1.5)


def test_matches_sionna_diffraction_matrix_on_a_concrete_side_wall() -> None:
    pytest.importorskip("sionna.rt")
    src, nodes, q = _side_wall_links(60)
    e_hat = np.array([0.0, 0.0, 1.0])
    e0 = np.array([1.0, 0.0, 0.0])
    # Sionna's |D e| and the model's spreading (Sionna applies it to the path, not the matrix);
    # n0 = -x: the face the anchor sees
    sionna, norm = sionna_edge_db(src, nodes, q, e_hat, np.array([-1.0, 0.0, 0.0]), ETA,
                                  "concrete", 0.2, wavenumber_rad_m(F_HZ))
    out = {}
    for name, eta_face in (("pec", None), ("wall", ETA)):
        e = diffracted_field(src, nodes, q, e_hat, [0, 1.0, 0], e0, frequency_hz=F_HZ,
                             face_permittivity=eta_face)
        out[name] = 20 * np.log10(np.linalg.norm(e, axis=-1) / norm) - sionna
    assert np.max(np.abs(out["pec"])) > 10.0 and np.median(np.abs(out["pec"])) > 2.0
    # the rest is deep in the shadow (30-60 deg past the boundary): Sionna weights the wedge's
    # first term D1 with the lit face's coefficient too, Luebbers' form does not
    assert np.median(np.abs(out["wall"])) < 0.5
    assert np.percentile(np.abs(out["wall"]), 90) < 2.0
    assert np.max(np.abs(out["wall"])) < 6.0
