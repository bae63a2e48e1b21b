"""The window edge's wedge diffraction (``diffpos.channel.wedge``; issue 34 items 3-4).

* Closed-form limits: the perfectly conducting wedge with ``n = 2`` is today's half-plane
  (``gtd_halfplane.utd_coefficients`` / ``field_from_frame``) to 1e-12; the Luebbers form
  with the lit face's Fresnel coefficients is the emulator's dielectric sheet; far from the
  shadow boundaries the conductor's ``n = 1.5`` coefficients are Keller's (GTD) right-angle
  wedge (Keller 1962, the non-uniform cosine form), computed here independently.
* ``slab_reflection``: a thick concrete slab is the half-space (Fresnel) to 1e-6.
* Where Sionna RT is installed: its own diffraction matrix on the facade's lower and upper
  window edges of the paper building (anchors in front and far off to the side, nodes from
  the lit region into the deep shadow): ``wedge_field`` within 0.02 dB (float32 reference),
  where the half-plane is a median 2 dB off in the lower edge's deep shadow.
  ``benchmarks/bench_wedge.py`` checks the same against Sionna's traced path gains.
"""

from __future__ import annotations

import numpy as np
import pytest
from sionna_wedge import sionna_edge_db

from diffpos.channel.gtd_halfplane import (
    edge_frame,
    field_from_frame,
    utd_coefficients,
    wavenumber_rad_m,
)
from diffpos.channel.slots import fresnel_coefficients, itu_permittivity
from diffpos.channel.wedge import slab_reflection, wedge_coefficients, wedge_field

F_HZ = 28e9
ETA = itu_permittivity("concrete", F_HZ)
LAM = 2 * np.pi / float(wavenumber_rad_m(F_HZ))


def _window_links(count: int, seed: int = 3):
    """Anchors outside (y < 0), nodes inside, diffraction points on the lower edge ``z = 1``
    (``e = -x``, wall below: ``t0 = -z``) at the Fermat point in x (the chord's x at the edge)."""
    rng = np.random.default_rng(seed)
    src = np.stack([rng.uniform(-30, 30, count), rng.uniform(-25, -5, count),
                    rng.uniform(-3, 1.5, count)], -1)
    node = np.stack([rng.uniform(-8, 8, count), rng.uniform(0.5, 12, count),
                     rng.uniform(-1.5, 0.9, count)], -1)
    w = np.abs(src[:, 1]) / (np.abs(src[:, 1]) + node[:, 1])
    # the Fermat point on the edge line z = 1, y = 0: equal angles with the edge
    da = np.hypot(src[:, 1], src[:, 2] - 1.0)
    dn = np.hypot(node[:, 1], node[:, 2] - 1.0)
    qx = src[:, 0] + (node[:, 0] - src[:, 0]) * da / (da + dn)
    assert np.all(w > 0)
    q = np.stack([qx, np.zeros(count), np.ones(count)], -1)
    return src, node, q


def test_conductor_half_plane_is_todays_utd() -> None:
    rng = np.random.default_rng(0)
    psi_in = rng.uniform(0.05, np.pi - 0.05, 500)
    psi = rng.uniform(0.01, 2 * np.pi - 0.01, 500)
    gamma = rng.uniform(0.3, np.pi / 2, 500)
    big_l = rng.uniform(0.05, 20, 500)
    ref = utd_coefficients(psi, psi_in, gamma, big_l, frequency_hz=F_HZ)
    for form in ("sionna", "luebbers"):
        got = wedge_coefficients(psi, psi_in, gamma, big_l, frequency_hz=F_HZ, n=2.0, form=form)
        for g, r in zip(got, ref, strict=True):
            np.testing.assert_allclose(g, r, rtol=1e-10, atol=1e-14)
    src, node, q = _window_links(200)
    frame = edge_frame(src, node, q, [-1.0, 0, 0], [0, 0, -1.0])
    e0 = np.array([1.0, 0.0, 0.0])
    np.testing.assert_allclose(wedge_field(frame, e0, frequency_hz=F_HZ),
                               field_from_frame(frame, e0, frequency_hz=F_HZ), rtol=1e-10,
                               atol=1e-16)


def test_luebbers_form_is_the_emulators_dielectric_sheet() -> None:
    rng = np.random.default_rng(1)
    psi_in = rng.uniform(0.05, np.pi - 0.05, 400)
    psi = rng.uniform(0.01, 2 * np.pi - 0.01, 400)
    gamma = rng.uniform(0.3, np.pi / 2, 400)
    big_l = rng.uniform(0.05, 20, 400)
    lit = fresnel_coefficients(np.abs(np.sin(psi_in)), ETA)
    ref = utd_coefficients(psi, psi_in, gamma, big_l, frequency_hz=F_HZ, lit_face_reflection=lit)
    got = wedge_coefficients(psi, psi_in, gamma, big_l, frequency_hz=F_HZ, n=2.0, face0=lit,
                             facen=(-1.0, -1.0), form="luebbers")
    for g, r in zip(got, ref, strict=True):
        np.testing.assert_allclose(g, r, rtol=1e-10, atol=1e-14)


def test_right_angle_conductor_tends_to_kellers_wedge() -> None:
    n = 1.5
    phi_in = np.linspace(0.2, 1.2, 6)[:, None]
    phi = np.linspace(0.2, n * np.pi - 0.2, 41)[None, :]
    phi_in, phi = np.broadcast_arrays(phi_in, phi)
    far = ((np.abs(np.cos((phi - phi_in) / 2)) > 0.3) & (np.abs(np.cos((phi + phi_in) / 2)) > 0.3)
           & (np.abs(np.sin((phi + phi_in) / 2 - n * np.pi / 2)) > 0.3))
    k = float(wavenumber_rad_m(F_HZ))
    big_l = np.full(phi.shape, 50.0)  # k L ~ 3e4: UTD -> GTD
    got_s, got_h = wedge_coefficients(phi, phi_in, np.pi / 2, big_l, frequency_hz=F_HZ, n=n)
    pre = np.exp(-0.25j * np.pi) * np.sin(np.pi / n) / (n * np.sqrt(2 * np.pi * k))
    t1 = 1 / (np.cos(np.pi / n) - np.cos((phi - phi_in) / n))
    t2 = 1 / (np.cos(np.pi / n) - np.cos((phi + phi_in) / n))
    assert far.sum() > 100
    np.testing.assert_allclose(got_s[far], (pre * (t1 - t2))[far], rtol=2e-3)
    np.testing.assert_allclose(got_h[far], (pre * (t1 + t2))[far], rtol=2e-3)


def test_thick_slab_reflection_is_the_half_space() -> None:
    c = np.linspace(0.0, 1.0, 101)
    got = slab_reflection(c, ETA, 0.2, LAM)
    ref = fresnel_coefficients(c, ETA)
    for g, r in zip(got, ref, strict=True):
        np.testing.assert_allclose(g, r, atol=1e-6)
    thin = slab_reflection(c, ETA, 0.002, LAM)  # a thin slab is not
    assert np.max(np.abs(thin[0] - ref[0])) > 0.05


@pytest.mark.parametrize("edge", ["lower", "upper"])
def test_matches_sionna_diffraction_matrix_on_a_window_edge(edge: str) -> None:
    pytest.importorskip("sionna.rt")
    src, node, q = _window_links(300, seed=5 if edge == "lower" else 6)
    if edge == "upper":  # mirror in z = 1: the wall above the window
        src, node = src * [1, 1, -1] + [0, 0, 2], node * [1, 1, -1] + [0, 0, 2]
    e_dir, face = ([-1.0, 0, 0], [0, 0, -1.0]) if edge == "lower" else ([1.0, 0, 0], [0, 0, 1.0])
    frame = edge_frame(src, node, q, e_dir, face)
    e0 = np.array([1.0, 0.0, 0.0])
    # Sionna's edge: n0 x e = t0 (its face); n0 = -y, the face the anchors see
    sionna, norm = sionna_edge_db(src, node, q, frame.edge[0], np.array([0.0, -1.0, 0.0]), ETA,
                                  "concrete", 0.2, wavenumber_rad_m(F_HZ))
    field = wedge_field(frame, e0, frequency_hz=F_HZ, permittivity=ETA, thickness_m=0.2)
    got = 20 * np.log10(np.linalg.norm(field, axis=-1) / norm)
    ok = np.isfinite(sionna)
    assert ok.sum() > 250
    assert np.max(np.abs(got - sionna)[ok]) < 0.02
    pec = 20 * np.log10(np.linalg.norm(field_from_frame(frame, e0, frequency_hz=F_HZ), axis=-1)
                        / norm)
    loss = 20 * np.log10(LAM / (4 * np.pi * (frame.s_in_m + frame.s_out_m))) \
        - 20 * np.log10(np.linalg.norm(field_from_frame(frame, e0, frequency_hz=F_HZ), axis=-1)
                        * LAM / (4 * np.pi))
    if edge == "lower":  # the conductor is too weak deep in the shadow
        deep = ok & (loss > 40)
        assert deep.sum() > 10 and np.median((sionna - pec)[deep]) > 1.5
