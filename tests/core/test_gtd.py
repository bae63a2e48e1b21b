"""GTD/UTD half-plane diffraction (diffpos.channel.gtd) against independent references.

References used: direct quadrature of the transition-function integral, the Fresnel-integral
form, its asymptotic series, Sommerfeld's exact half-plane solution (written with Fresnel
integrals), the geometrical-optics field (continuity of GO + diffracted across the shadow
boundaries), the paper's literal sgn/arccos rule and its Table expressions.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import fresnel

from diffpos.channel import gtd, gtd_halfplane
from diffpos.constants import SPEED_OF_LIGHT_M_S
from diffpos.geometry import diffraction_point

F_HZ = 28e9
K = 2 * np.pi * F_HZ / SPEED_OF_LIGHT_M_S


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _dot(a, b):
    return np.einsum("...i,...i->...", a, b)


# ----------------------------------------------------------------------------------------
# transition function F(X)
# ----------------------------------------------------------------------------------------


def _f_quad(x: float) -> complex:
    """F(X) = j sqrt(X) int_0^inf exp(-j t) / sqrt(X + t) dt (tau^2 = X + t), QAWF quadrature."""
    c, _ = quad(lambda t: 1.0 / np.sqrt(x + t), 0.0, np.inf, weight="cos", wvar=1.0)
    s, _ = quad(lambda t: 1.0 / np.sqrt(x + t), 0.0, np.inf, weight="sin", wvar=1.0)
    return 1j * np.sqrt(x) * (c - 1j * s)


def _f_fresnel(x):
    """Textbook form with scipy.special.fresnel (C, S with the pi/2 convention)."""
    u = np.sqrt(x)
    s_v, c_v = fresnel(u * np.sqrt(2 / np.pi))
    tail = np.sqrt(np.pi / 2) * ((0.5 - c_v) - 1j * (0.5 - s_v))
    return 2j * u * np.exp(1j * x) * tail


@pytest.mark.parametrize("x", [1e-3, 0.05, 0.3, 1.0, 2.5, 7.0, 20.0, 60.0])
def test_transition_function_matches_quadrature(x):
    got = gtd_halfplane.transition_function(x)
    ref = _f_quad(x)
    assert abs(got - ref) < 1e-7 * max(1.0, abs(ref))


def test_transition_function_matches_fresnel_form():
    x = np.logspace(-4, 3, 57)
    got = gtd_halfplane.transition_function(x)
    ref = _f_fresnel(x)
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12)


def test_transition_function_small_argument():
    # F(X) = sqrt(pi X) e^{j pi/4} (1 + O(sqrt X)); F(0) = 0.
    x = np.array([1e-12, 1e-9, 1e-6, 1e-4])
    lead = np.sqrt(np.pi * x) * np.exp(0.25j * np.pi)
    rel = np.abs(gtd_halfplane.transition_function(x) / lead - 1)
    assert np.all(rel < 3 * np.sqrt(x))
    assert gtd_halfplane.transition_function(0.0) == 0


def test_transition_function_large_argument():
    # Asymptotic series F ~ sum_n (2n-1)!! (j / (2X))^n (derived in gtd's module docstring;
    # Kouyoumjian-Pathak print 75/16 for the n = 4 coefficient, the correct one is 105/16).
    x = np.array([10.0, 30.0, 1e2, 1e4, 1e8, 1e12, 1e16])
    series = 1 + 1j / (2 * x) - 3 / (4 * x**2) - 15j / (8 * x**3) + 105 / (16 * x**4)
    next_term = 945 / (32 * x**5)
    err = np.abs(gtd_halfplane.transition_function(x) - series)
    assert np.all(err < 2 * next_term + 1e-14)
    assert abs(gtd_halfplane.transition_function(1e16) - 1) < 1e-14


def test_transition_function_rejects_negative():
    with pytest.raises(ValueError, match="X must be >= 0"):
        gtd_halfplane.transition_function([1.0, -0.1])


# ----------------------------------------------------------------------------------------
# ray-fixed / edge-fixed frames
# ----------------------------------------------------------------------------------------


def _random_edge_geometry(rng, n):
    """Random edges (point P0, unit e, face t0 perpendicular to e), sources and observers."""
    e = _unit(rng.normal(size=(n, 3)))
    t = rng.normal(size=(n, 3))
    t = _unit(t - _dot(t, e)[:, None] * e)
    p0 = rng.uniform(-5, 5, size=(n, 3))
    src = p0 + rng.uniform(-30, 30, size=(n, 3))
    obs = p0 + rng.uniform(-30, 30, size=(n, 3))
    dp = diffraction_point(src, obs, p0 - 1e4 * e, p0 + 1e4 * e)
    return src, obs, dp.point_m, e, t


def test_frame_orthonormal_and_law_of_diffraction():
    rng = np.random.default_rng(1)
    src, obs, q, e, t = _random_edge_geometry(rng, 500)
    f = gtd_halfplane.edge_frame(src, obs, q, e, t)
    eye = np.eye(3)
    for triple in (
        (f.s_in, f.beta0_in, f.phi_in),
        (f.s_out, f.beta0_out, f.phi_out),
        (f.t0, f.edge, f.n0),
    ):
        m = np.stack(triple, axis=-1)  # columns
        np.testing.assert_allclose(
            np.einsum("...ji,...jk->...ik", m, m), np.broadcast_to(eye, m.shape), atol=1e-12
        )
    # (s', beta0', phi') and (s, beta0, phi) right-handed: s x beta0 = phi.
    np.testing.assert_allclose(np.cross(f.s_in, f.beta0_in), f.phi_in, atol=1e-12)
    np.testing.assert_allclose(np.cross(f.s_out, f.beta0_out), f.phi_out, atol=1e-12)
    # paper: t0 = n0 x e, n0 faces the source; face direction kept.
    np.testing.assert_allclose(np.cross(f.n0, f.edge), f.t0, atol=1e-12)
    np.testing.assert_allclose(f.t0, t, atol=1e-12)
    assert np.all(_dot(src - q, f.n0) >= 0)
    # law of diffraction at the Fermat point: s'.e = s.e (Definition 1)
    np.testing.assert_allclose(_dot(f.s_in, f.edge), _dot(f.s_out, f.edge), atol=1e-9)
    np.testing.assert_allclose(np.cos(f.gamma0_rad), np.abs(_dot(f.s_out, f.edge)), atol=1e-9)
    np.testing.assert_allclose(f.sin_gamma0, np.sin(f.gamma0_rad), atol=1e-12)
    assert np.all((f.psi_in_rad >= 0) & (f.psi_in_rad <= np.pi))
    assert np.all((f.psi_rad >= 0) & (f.psi_rad < 2 * np.pi))


def test_psi_matches_paper_sgn_arccos_rule():
    rng = np.random.default_rng(2)
    src, obs, q, e, t = _random_edge_geometry(rng, 500)
    f = gtd_halfplane.edge_frame(src, obs, q, e, t)
    # the paper's rule, literally, with the frame's n0/t0
    st_in = _unit(f.s_in - _dot(f.s_in, f.edge)[:, None] * f.edge)
    st_out = _unit(f.s_out - _dot(f.s_out, f.edge)[:, None] * f.edge)
    psi_in = np.pi - (np.pi - np.arccos(np.clip(-_dot(st_in, f.t0), -1, 1))) * np.sign(
        -_dot(st_in, f.n0)
    )
    psi = np.pi - (np.pi - np.arccos(np.clip(_dot(st_out, f.t0), -1, 1))) * np.sign(
        _dot(st_out, f.n0)
    )
    np.testing.assert_allclose(f.psi_in_rad, psi_in, atol=1e-7)
    np.testing.assert_allclose(f.psi_rad, psi, atol=1e-7)
    np.testing.assert_allclose(f.st_in, st_in, atol=1e-12)
    np.testing.assert_allclose(f.st_out, st_out, atol=1e-12)


def test_field_independent_of_edge_sense_and_linear_in_e0():
    rng = np.random.default_rng(3)
    src, obs, q, e, t = _random_edge_geometry(rng, 200)
    e1 = rng.normal(size=(200, 3)) + 1j * rng.normal(size=(200, 3))
    e2 = rng.normal(size=(200, 3))
    kw = {"frequency_hz": F_HZ}
    f_a = gtd_halfplane.diffracted_field(src, obs, q, e, t, e1, **kw)
    f_b = gtd_halfplane.diffracted_field(src, obs, q, -e, t, e1, **kw)
    np.testing.assert_allclose(f_a, f_b, rtol=1e-12, atol=0)
    a, b = 0.3 - 1.2j, 2.0
    lin = gtd_halfplane.diffracted_field(src, obs, q, e, t, a * e1 + b * e2, **kw)
    ref = a * f_a + b * gtd_halfplane.diffracted_field(src, obs, q, e, t, e2, **kw)
    np.testing.assert_allclose(lin, ref, rtol=1e-10, atol=1e-14 * np.abs(ref).max())
    # transverse to the diffracted ray
    s_hat = _unit(obs - q)
    assert np.max(np.abs(_dot(f_a, s_hat))) < 1e-12 * np.abs(f_a).max()


# ----------------------------------------------------------------------------------------
# coefficients: Sommerfeld's exact solution, GTD vs UTD, shadow boundaries
# ----------------------------------------------------------------------------------------


def _sommerfeld_v(k_rho, beta):
    """V(rho, b) = exp(j k rho cos b) (e^{j pi/4}/sqrt(pi)) int_{-inf}^{sqrt(2 k rho) cos(b/2)} exp(-j tau^2) dtau."""
    a = np.sqrt(2 * k_rho) * np.cos(beta / 2)
    s_v, c_v = fresnel(a * np.sqrt(2 / np.pi))  # odd functions
    integral = np.sqrt(np.pi / 2) * ((0.5 + c_v) - 1j * (0.5 + s_v))
    return np.exp(1j * k_rho * np.cos(beta)) * np.exp(0.25j * np.pi) / np.sqrt(np.pi) * integral


def _plane_wave_setup(psi_in, psi, rho):
    """Half-plane: edge = x axis, sheet along t0 = +z (z >= 0, y = 0), n0 = -y side lit.

    Source far away in the direction psi' (normal incidence, sin gamma0 = 1), observer at
    (rho, psi), both angles from the face t0 towards n0.
    """
    e = np.array([1.0, 0.0, 0.0])
    t0 = np.array([0.0, 0.0, 1.0])
    n0 = np.cross(e, t0)  # -y
    far = 1e6
    src = far * (np.cos(psi_in)[..., None] * t0 + np.sin(psi_in)[..., None] * n0)
    obs = rho[..., None] * (np.cos(psi)[..., None] * t0 + np.sin(psi)[..., None] * n0)
    return e, t0, src, obs, far


@pytest.mark.parametrize("k_rho", [3.0, 30.0, 300.0])
@pytest.mark.parametrize("psi_in_deg", [20.0, 75.0, 140.0])
def test_utd_plane_wave_reproduces_sommerfeld_exact(k_rho, psi_in_deg):
    # For a plane wave on a half-plane the UTD diffracted field plus GO equals Sommerfeld's
    # exact total field (n = 2); this checks angles, signs, vector mapping and F together.
    psi_in = np.deg2rad(psi_in_deg)
    psi = np.linspace(0.01, 2 * np.pi - 0.01, 301)
    psi = np.concatenate(
        [psi, np.pi + psi_in + np.array([-1e-3, 1e-3]), np.pi - psi_in + np.array([-1e-3, 1e-3])]
    )
    rho = np.full_like(psi, k_rho / K)
    e, t0, src, obs, far = _plane_wave_setup(np.full_like(psi, psi_in), psi, rho)
    q = np.zeros(3)
    kw = {"frequency_hz": F_HZ, "coefficients": "utd", "spreading": "paper"}
    norm = far * np.exp(1j * K * far)  # divide out the incident field at Q
    # soft: E parallel to the edge; u = E . e
    ed = gtd_halfplane.diffracted_field(src, obs, q, e, t0, e, **kw)
    u_d_soft = _dot(ed, e) * norm
    # hard: E along phi' (H along the edge); u = H_e / H^i_e(Q) = -E^d_phi / E^i_phi'(Q)
    frame = gtd_halfplane.edge_frame(src, obs, q, e, t0)
    ed_h = gtd_halfplane.diffracted_field(src, obs, q, e, t0, frame.phi_in, **kw)
    u_d_hard = -_dot(ed_h, frame.phi_out) * norm
    lit_i = psi < np.pi + psi_in
    lit_r = psi < np.pi - psi_in
    u_i = np.exp(1j * k_rho * np.cos(psi - psi_in))
    u_r = np.exp(1j * k_rho * np.cos(psi + psi_in))
    exact_soft = _sommerfeld_v(k_rho, psi - psi_in) - _sommerfeld_v(k_rho, psi + psi_in)
    exact_hard = _sommerfeld_v(k_rho, psi - psi_in) + _sommerfeld_v(k_rho, psi + psi_in)
    go_soft = lit_i * u_i - lit_r * u_r
    go_hard = lit_i * u_i + lit_r * u_r
    np.testing.assert_allclose(go_soft + u_d_soft, exact_soft, atol=2e-6)
    np.testing.assert_allclose(go_hard + u_d_hard, exact_hard, atol=2e-6)


def test_keller_vs_exact_away_from_boundaries():
    # Keller = UTD with F = 1: away from the shadow boundaries the diffracted field is within
    # |F - 1| ~ 1/(2X) of the exact one. Here X >= 100 => relative error < 1%.
    psi_in = np.deg2rad(60.0)
    psi = np.deg2rad(np.linspace(1, 359, 2000))
    k_rho = 2000.0
    x_min = k_rho * np.minimum(
        2 * np.cos((psi - psi_in) / 2) ** 2, 2 * np.cos((psi + psi_in) / 2) ** 2
    )
    far_from_sb = x_min >= 100
    assert far_from_sb.sum() > 1000
    rho = np.full_like(psi, k_rho / K)
    e, t0, src, obs, far = _plane_wave_setup(np.full_like(psi, psi_in), psi, rho)
    norm = far * np.exp(1j * K * far)
    ek = gtd_halfplane.diffracted_field(
        src, obs, np.zeros(3), e, t0, e, frequency_hz=F_HZ, coefficients="keller", spreading="paper"
    )
    u_k = _dot(ek, e) * norm
    exact = _sommerfeld_v(k_rho, psi - psi_in) - _sommerfeld_v(k_rho, psi + psi_in)
    go = (psi < np.pi + psi_in) * np.exp(1j * k_rho * np.cos(psi - psi_in)) - (
        psi < np.pi - psi_in
    ) * np.exp(1j * k_rho * np.cos(psi + psi_in))
    ud_exact = exact - go
    rel = np.abs(u_k - ud_exact) / np.abs(ud_exact)
    assert np.max(rel[far_from_sb]) < 0.01


def test_utd_tends_to_keller_away_from_boundaries():
    rng = np.random.default_rng(4)
    n = 4000
    psi_in = rng.uniform(0, np.pi, n)
    psi = rng.uniform(0, 2 * np.pi, n)
    gamma0 = rng.uniform(0.2, np.pi / 2, n)
    big_l = rng.uniform(0.01, 20.0, n)
    ds_u, dh_u = gtd_halfplane.utd_coefficients(psi, psi_in, gamma0, big_l, frequency_hz=F_HZ)
    ds_k, dh_k = gtd_halfplane.keller_coefficients(psi, psi_in, gamma0, frequency_hz=F_HZ)
    a_m = 2 * np.cos((psi - psi_in) / 2) ** 2
    a_p = 2 * np.cos((psi + psi_in) / 2) ** 2
    x_min = K * big_l * np.minimum(a_m, a_p)
    pre = 1 / (2 * np.sqrt(2 * np.pi * K) * np.sin(gamma0))
    scale = pre * (1 / np.abs(np.cos((psi - psi_in) / 2)) + 1 / np.abs(np.cos((psi + psi_in) / 2)))
    mask = x_min >= 50
    assert mask.sum() > 1000
    # |F(X) - 1| <= ~1/(2X) <= 1% for X >= 50, term by term
    assert np.max(np.abs(ds_u - ds_k)[mask] / scale[mask]) < 0.0101
    assert np.max(np.abs(dh_u - dh_k)[mask] / scale[mask]) < 0.0101
    # and the bound is not vacuous: closer to the boundaries they differ by more
    near = (x_min < 1.0) & (x_min > 0)
    assert np.max(np.abs(ds_u - ds_k)[near] / scale[near]) > 0.1


def _isb_scan(delta, e0, *, coefficients="utd", gamma_deg=70.0):
    """Observers on the Keller cone at psi = pi + psi' + delta (oblique incidence).

    Returns (diffracted field, GO incident field) at the observers, in V/m.
    """
    e = _unit(np.array([1.0, 0.2, 0.0]))
    t0 = _unit(np.cross(e, np.array([0.0, 0.0, 1.0])))  # horizontal face direction
    t0 = _unit(t0 - _dot(t0, e) * e)
    n0 = np.cross(e, t0)
    q = np.array([0.5, -0.3, 2.0])
    psi_in = np.deg2rad(50.0)
    g = np.deg2rad(gamma_deg)
    s_prime = 7.0
    # incident ray s' makes angle gamma0 with e; source direction (from Q) in the transverse plane at psi'
    dir_to_src = -np.cos(g) * e + np.sin(g) * (np.cos(psi_in) * t0 + np.sin(psi_in) * n0)
    src = q + s_prime * dir_to_src
    s = 3.0
    psi = np.pi + psi_in + np.asarray(delta)
    dir_obs = np.cos(g) * e + np.sin(g) * (np.cos(psi)[:, None] * t0 + np.sin(psi)[:, None] * n0)
    obs = q + s * dir_obs
    ed = gtd_halfplane.diffracted_field(src, obs, q, e, t0, e0, frequency_hz=F_HZ, coefficients=coefficients)
    r_vec = obs - src
    r = np.linalg.norm(r_vec, axis=-1)
    r_hat = r_vec / r[:, None]
    e0_perp = e0 - _dot(e0, r_hat)[:, None] * r_hat
    lit = psi < np.pi + psi_in
    go = lit[:, None] * e0_perp * (np.exp(-1j * K * r) / r)[:, None]
    return ed, go


@pytest.mark.parametrize(
    "e0", [np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.3, 1.0]), np.array([0.2, 1.0 + 0.5j, -0.4])]
)
def test_utd_total_field_continuous_across_incident_shadow_boundary(e0):
    deltas = np.array([1e-5, 1e-4, 1e-3])
    d = np.concatenate([-deltas, deltas])
    ed, go = _isb_scan(d, e0)
    total = ed + go
    n = len(deltas)
    go_mag = np.linalg.norm(go[:n], axis=-1)
    jump_total = np.linalg.norm(total[n:] - total[:n], axis=-1) / go_mag
    jump_diff = np.linalg.norm(ed[n:] - ed[:n], axis=-1) / go_mag
    # the diffracted field alone jumps by the GO field; GO + diffracted is continuous
    assert np.all(np.isfinite(ed))
    np.testing.assert_allclose(jump_diff, 1.0, atol=0.05)
    assert jump_total[0] < 5e-3 and jump_total[1] < 2e-2 and jump_total[2] < 0.2
    assert jump_total[0] < jump_total[1] < jump_total[2]
    # at the boundary the diffracted field is half the GO field (lit side: -GO/2)
    np.testing.assert_allclose(ed[0], -0.5 * go[0], atol=0.01 * go_mag[0])


def test_keller_blows_up_at_shadow_boundary_utd_stays_bounded():
    e0 = np.array([0.3, 1.0, 0.2])
    d = np.array([1e-2, 1e-3, 1e-4, 1e-5])
    ek, _ = _isb_scan(d, e0, coefficients="keller")  # shadow side
    eu, _ = _isb_scan(d, e0, coefficients="utd")
    _, go = _isb_scan(-d, e0)  # GO on the lit side
    mk = np.linalg.norm(ek, axis=-1)
    mu = np.linalg.norm(eu, axis=-1)
    g = np.linalg.norm(go, axis=-1).max()
    # Keller ~ 1/delta; UTD bounded by ~GO/2
    np.testing.assert_allclose(mk[1:] / mk[:-1], 10.0, rtol=0.02)
    assert mk[-1] > 100 * g
    assert np.all(mu < 0.6 * g)


def test_utd_soft_continuous_across_reflection_boundary():
    # Normal incidence, E along the edge: reflected GO = -(image source field) for psi < pi - psi'.
    e = np.array([0.0, 0.0, 1.0])
    t0 = np.array([1.0, 0.0, 0.0])  # sheet: y = 0, x >= 0
    n0 = np.cross(e, t0)  # +y
    psi_in = np.deg2rad(35.0)
    src = 6.0 * (np.cos(psi_in) * t0 + np.sin(psi_in) * n0)
    img = src * np.array([1.0, -1.0, 1.0])
    delta = np.array([-1e-4, 1e-4, -1e-3, 1e-3])
    psi = np.pi - psi_in + delta
    obs = 2.5 * (np.cos(psi)[:, None] * t0 + np.sin(psi)[:, None] * n0)
    ed = gtd_halfplane.diffracted_field(src, obs, np.zeros(3), e, t0, e, frequency_hz=F_HZ)
    u_d = _dot(ed, e)
    r_img = np.linalg.norm(obs - img, axis=-1)
    # the direct GO field is continuous here; only the reflected GO field switches off
    u_refl = -1.0 * (psi < np.pi - psi_in) * np.exp(-1j * K * r_img) / r_img
    tot = u_refl + u_d
    ref = 1 / r_img[0]
    assert abs(tot[1] - tot[0]) < 5e-3 * ref
    assert abs(tot[3] - tot[2]) < 5e-2 * ref
    assert abs(abs(u_d[1] - u_d[0]) - ref) < 0.05 * ref


def test_spreading_paper_vs_spherical_ratio():
    rng = np.random.default_rng(5)
    src, obs, q, e, t = _random_edge_geometry(rng, 100)
    e0 = np.array([0.4, -0.2, 1.0])
    kw = {"frequency_hz": F_HZ, "coefficients": "keller"}
    sph = gtd_halfplane.diffracted_field(src, obs, q, e, t, e0, spreading="spherical", **kw)
    pap = gtd_halfplane.diffracted_field(src, obs, q, e, t, e0, spreading="paper", **kw)
    sp = np.linalg.norm(q - src, axis=-1)
    so = np.linalg.norm(obs - q, axis=-1)
    np.testing.assert_allclose(pap, sph * np.sqrt((sp + so) / sp)[:, None], rtol=1e-10)
    # distance parameters
    fr = gtd_halfplane.edge_frame(src, obs, q, e, t)
    np.testing.assert_allclose(
        gtd_halfplane.distance_parameter_m(sp, so, fr.sin_gamma0), so * sp * fr.sin_gamma0**2 / (so + sp)
    )
    np.testing.assert_allclose(
        gtd_halfplane.distance_parameter_m(sp, so, fr.sin_gamma0, spreading="paper"), so * fr.sin_gamma0**2
    )


# ----------------------------------------------------------------------------------------
# building case: the paper's Tables
# ----------------------------------------------------------------------------------------


def _building_samples(rng, n):
    anchors = np.stack(
        [rng.uniform(-20, 20, n), rng.uniform(-40, -2, n), rng.uniform(0, 10, n)], -1
    )
    nodes = np.stack([rng.uniform(-20, 20, n), rng.uniform(0.5, 30, n), rng.uniform(11, 40, n)], -1)
    w = rng.uniform(0.5, 2.5, n)
    return anchors, nodes, w


def test_building_psi_and_vectors_match_paper_tables():
    rng = np.random.default_rng(6)
    a, nd, w = _building_samples(rng, 400)
    xa, ya, za = a.T
    xn, yn, zn = nd.T
    h = 0.5 * w
    rn = np.sqrt(yn**2 + h**2)
    for edge in ("upper", "lower"):
        f = gtd.window_edge_frame(a, nd, window_height_m=w, edge=edge)
        ze = zn + (h if edge == "upper" else -h)
        dz = ze - za
        r = np.sqrt(ya**2 + dz**2)
        qx = xa + f.s_in_m * f.s_in[:, 0]  # Q_x from the frame's own ray
        dx = qx - xa
        ex = xn - qx
        big_r = np.sqrt(dx**2 + r**2)
        big_rn = np.sqrt(ex**2 + rn**2)
        zero = np.zeros_like(r)
        if edge == "upper":
            psi_in_tab = np.pi - np.arccos(dz / r)
            psi_tab = 2 * np.pi - np.arccos(-h / rn)
            phi_in_tab = np.stack([zero, dz, ya], -1) / r[:, None]
            beta_in_tab = np.stack([r**2, ya * dx, -dx * dz], -1) / (r * big_r)[:, None]
            phi_tab = np.stack([zero, h, yn], -1) / rn[:, None]
            beta_tab = np.stack([-(rn**2), yn * ex, -h * ex], -1) / (rn * big_rn)[:, None]
        else:
            psi_in_tab = np.arccos(dz / r)
            psi_tab = np.pi + np.arccos(h / rn)
            # printed: (dz y - ya z)/r, not orthogonal to s' -> corrected sign of the y term
            phi_in_printed = np.stack([zero, dz, -ya], -1) / r[:, None]
            phi_in_tab = np.stack([zero, -dz, -ya], -1) / r[:, None]
            beta_in_tab = np.stack([-(r**2), -ya * dx, dz * dx], -1) / (r * big_r)[:, None]
            phi_tab = np.stack([zero, h, -yn], -1) / rn[:, None]
            # printed z-component +h(x_n - q_x): not orthogonal to s -> corrected to -h(x_n - q_x)
            beta_printed = np.stack([rn**2, -yn * ex, h * ex], -1) / (rn * big_rn)[:, None]
            beta_tab = np.stack([rn**2, -yn * ex, -h * ex], -1) / (rn * big_rn)[:, None]
            assert np.max(np.abs(_dot(phi_in_printed, f.s_in))) > 0.1
            off = np.abs(ex) > 1.0
            assert np.max(np.abs(_dot(beta_printed, f.s_out))[off]) > 1e-3
        np.testing.assert_allclose(f.psi_in_rad, psi_in_tab, atol=1e-9)
        np.testing.assert_allclose(f.psi_rad, psi_tab, atol=1e-9)
        np.testing.assert_allclose(f.phi_in, phi_in_tab, atol=1e-9)
        np.testing.assert_allclose(f.beta0_in, beta_in_tab, atol=1e-9)
        np.testing.assert_allclose(f.phi_out, phi_tab, atol=1e-9)
        np.testing.assert_allclose(f.beta0_out, beta_tab, atol=1e-9)
        np.testing.assert_allclose(f.n0, np.broadcast_to([0.0, -1.0, 0.0], f.n0.shape))
        # s_t' and s_t of the paper's Table
        st_in_tab = np.stack([zero, -ya, dz], -1) / r[:, None]
        st_tab = np.stack([zero, yn, (-h if edge == "upper" else h)], -1) / rn[:, None]
        np.testing.assert_allclose(f.st_in, st_in_tab, atol=1e-9)
        np.testing.assert_allclose(f.st_out, st_tab, atol=1e-9)


def test_window_edge_fields_match_corollary2_with_paper_spreading():
    # Corollary 2 (with the -D signs of Definition 2 restored): x-polarised, Keller, paper spreading
    rng = np.random.default_rng(7)
    a, nd, w = _building_samples(rng, 200)
    eu, el = gtd.window_edge_fields(
        a, nd, window_height_m=w, coefficients="keller", spreading="paper"
    )
    for edge, got in (("upper", eu), ("lower", el)):
        f = gtd.window_edge_frame(a, nd, window_height_m=w, edge=edge)
        ds, _ = gtd_halfplane.keller_coefficients(f.psi_rad, f.psi_in_rad, f.gamma0_rad, frequency_hz=F_HZ)
        phase = np.exp(-1j * K * (f.s_in_m + f.s_out_m)) / (f.s_in_m * np.sqrt(f.s_out_m))
        ref = -(f.beta0_in[:, 0] * ds * phase)[:, None] * f.beta0_out
        np.testing.assert_allclose(got, ref, rtol=1e-9)


def test_bad_inputs_raise_clear_errors():
    a = np.array([0.0, -10.0, 1.0])
    n = np.array([0.0, 5.0, 10.0])
    with pytest.raises(ValueError, match="anchor_m"):
        gtd.window_edge_fields(np.array([0.0, 1.0, 1.0]), n, window_height_m=1.5)
    with pytest.raises(ValueError, match="node_m"):
        gtd.window_edge_fields(a, np.array([0.0, -1.0, 1.0]), window_height_m=1.5)
    with pytest.raises(ValueError, match="coefficients"):
        gtd.window_edge_fields(a, n, window_height_m=1.5, coefficients="ptd")
    with pytest.raises(ValueError, match="spreading"):
        gtd.window_edge_fields(a, n, window_height_m=1.5, spreading="cylindrical")
    with pytest.raises(ValueError, match="face_dir"):
        gtd_halfplane.edge_frame(a, n, np.zeros(3), [1, 0, 0], [2, 0, 0])
    with pytest.raises(ValueError, match="frequency_hz"):
        gtd_halfplane.keller_coefficients(1.0, 0.5, 1.0, frequency_hz=-1.0)
    with pytest.raises(ValueError, match="edge"):
        gtd.window_edge_frame(a, n, window_height_m=1.5, edge="middle")
