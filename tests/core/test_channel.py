"""O2I channel emulator: hand-computable cases, brute-force geometry, detector logic."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.optimize import minimize, minimize_scalar

from diffpos.channel.emulator import MPC_CLASS, emulate_channel, first_arrival, mpc_statistics
from diffpos.channel.slots import fresnel_coefficients, itu_permittivity, slab_loss_db
from diffpos.constants import SPEED_OF_LIGHT_M_S as C
from diffpos.paths.mechanisms import MECHANISMS
from diffpos.scenario import Building, Partition, Radio, default_scenario

SLOT = {m: i for i, m in enumerate(MECHANISMS)}


@pytest.fixture(scope="module")
def small_channel(paper):
    rng = np.random.default_rng(5)
    nodes = paper.node_positions_m()[rng.choice(17600, 300, replace=False)]
    anchors = paper.anchor_positions_m()
    return emulate_channel(anchors, nodes, building=paper.building, radio=paper.radio)


# ------------------------------------------------------------------ materials
def test_fresnel_closed_forms():
    eta = 5.24 - 0.4j
    gs, gp = fresnel_coefficients(1.0, eta)
    n = np.sqrt(eta)
    assert gs == pytest.approx((1 - n) / (1 + n), abs=1e-12)
    # TM and TE agree at normal incidence up to the sign convention
    assert gp == pytest.approx(-gs, abs=1e-12)
    gs0, gp0 = fresnel_coefficients(0.0, eta)  # grazing
    assert gs0 == pytest.approx(-1.0) and gp0 == pytest.approx(-1.0)
    # Brewster angle of a lossless dielectric: TM vanishes at tan(theta) = sqrt(eps)
    th = np.arctan(np.sqrt(4.0))
    assert abs(fresnel_coefficients(np.cos(th), 4.0 + 0j)[1]) < 1e-12


def test_itu_concrete_and_slab_loss_vs_low_loss_formula():
    eta = itu_permittivity("concrete", 28e9)
    sigma = 0.0462 * 28**0.7822
    assert eta.real == pytest.approx(5.24)
    assert eta.imag == pytest.approx(-17.98 * sigma / 28)
    # ITU-R P.2040 low-loss attenuation 1636 sigma / sqrt(eps') dB/m, plus 2 interfaces
    g0 = (1 - np.sqrt(5.24)) / (1 + np.sqrt(5.24))
    iface = -2 * 10 * np.log10(1 - g0**2)
    for d in (0.1, 0.2, 0.3):
        ref = 1636 * sigma / np.sqrt(5.24) * d + iface
        assert slab_loss_db("concrete", d, 28e9) == pytest.approx(ref, rel=0.01)
    assert 4.0 < slab_loss_db("plasterboard", 0.025, 28e9) < 7.0


# ------------------------------------------------------------------ geometry vs brute force
def test_delays_are_lengths_over_c(small_channel):
    ch = small_channel
    v = ch.valid
    np.testing.assert_allclose(ch.delay_s[v] * C, ch.length_m[v], rtol=1e-14)
    assert np.all(np.isnan(ch.delay_s[~v]))
    direct = np.linalg.norm(ch.nodes_m[:, None] - ch.anchors_m[None], axis=-1)
    np.testing.assert_allclose(ch.length_m[..., 0], direct, rtol=1e-12)


def test_diffraction_lengths_are_brute_force_minima(small_channel, paper):
    """The edge paths are the minimum of |A-Q| + |Q-N| over Q on the node floor's edge."""
    ch, b = small_channel, paper.building
    x0, x1 = b.edge_x_m
    rng = np.random.default_rng(1)
    for i, j in zip(rng.integers(0, 300, 25), rng.integers(0, 4, 25), strict=True):
        a, n = ch.anchors_m[j], ch.nodes_m[i]
        lo, hi = b.window_z_m(b.floor_index(n[2]))
        for slot, ze in (("Tx-D(upper)-Rx", hi), ("Tx-D(lower)-Rx", lo)):

            def f(qx, ze=ze, a=a, n=n):
                return np.linalg.norm(a - [qx, 0, ze]) + np.linalg.norm(n - [qx, 0, ze])

            best = minimize_scalar(
                f, bounds=(x0, x1), method="bounded", options={"xatol": 1e-9}
            ).fun
            assert ch.length_m[i, j, SLOT[slot]] == pytest.approx(best, abs=1e-6)
        # diffraction then floor reflection: minimise over the edge point and floor point
        zf = float(b.floor_z_m(b.floor_index(n[2])))

        def g(p, hi=hi, zf=zf, a=a, n=n):
            q = np.array([p[0], 0.0, hi])
            r = np.array([p[1], p[2], zf])
            return np.linalg.norm(a - q) + np.linalg.norm(q - r) + np.linalg.norm(r - n)

        res = minimize(
            g,
            [n[0], n[0], 0.5 * n[1]],
            method="Nelder-Mead",
            options={"xatol": 1e-9, "fatol": 1e-10, "maxiter": 20000},
        )
        k = SLOT["Tx-D(upper)-R(floor)-Rx"]
        if ch.valid[i, j, k]:
            assert ch.length_m[i, j, k] == pytest.approx(res.fun, abs=1e-4)


def test_reflection_images_vs_brute_force(small_channel, paper):
    """Single reflections: length = min over the plane of |A-R| + |R-N|, R on the surface."""
    ch, b = small_channel, paper.building
    checked = 0
    for slot, axis in (("Tx-R(ceiling)-Rx", 2), ("Tx-R(ground)-Rx", 2), ("Tx-R(side x1)-Rx", 0)):
        k = SLOT[slot]
        idx = np.argwhere(ch.valid[..., k])[:10]
        for i, j in idx:
            a, n = ch.anchors_m[j], ch.nodes_m[i]
            fl = b.floor_index(n[2])
            coord = {
                "Tx-R(ceiling)-Rx": float(b.floor_z_m(fl)) + b.floor_height_m,
                "Tx-R(ground)-Rx": 0.0,
                "Tx-R(side x1)-Rx": b.edge_x_m[0],
            }[slot]
            free = [d for d in range(3) if d != axis]

            def f(u, free=free, axis=axis, coord=coord, a=a, n=n):
                r = np.empty(3)
                r[axis] = coord
                r[free] = u
                return np.linalg.norm(a - r) + np.linalg.norm(r - n)

            res = minimize(
                f,
                0.5 * (a[free] + n[free]),
                method="Nelder-Mead",
                options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 20000},
            )
            assert ch.length_m[i, j, k] == pytest.approx(res.fun, abs=1e-5)
            # the specular point: equal angles, i.e. the image distance
            img = a.copy() if slot != "Tx-R(ground)-Rx" else a * [1, 1, -1]
            if slot != "Tx-R(ground)-Rx":
                img = n.copy()
                img[axis] = 2 * coord - n[axis]
                assert ch.length_m[i, j, k] == pytest.approx(np.linalg.norm(a - img), abs=1e-9)
            else:
                assert ch.length_m[i, j, k] == pytest.approx(np.linalg.norm(img - n), abs=1e-9)
            checked += 1
    assert checked >= 20


def test_reflections_need_the_window_opening():
    """A ceiling reflection whose ray would hit the facade wall below the window is invalid."""
    b, r = Building(partitions=()), Radio()
    zf = float(b.floor_z_m(2))
    node = np.array([[0.0, 10.0, zf + 1.5]])
    # the unfolded ray to the ceiling image (z = zf + 4.5) crosses y = 0 at zf + 1.5, i.e.
    # inside the window band [zf + 0.75, zf + 2.25]
    ok = emulate_channel([[0.0, -30.0, zf - 7.5]], node, building=b, radio=r)
    # anchor right below the facade: the line to the ceiling image crosses the wall
    bad = emulate_channel([[0.0, -0.5, 0.5]], node, building=b, radio=r)
    k = SLOT["Tx-R(ceiling)-Rx"]
    assert ok.valid[0, 0, k] and not bad.valid[0, 0, k]


# ------------------------------------------------------------------ hand-computable cases
def test_open_window_level_node_sees_direct_path_first():
    b = Building(windows="open", partitions=())
    r = Radio()
    zf = float(b.floor_z_m(1))
    zc = zf + b.nominal_node_height_m
    anchor = np.array([[3.0, -12.0, zc]])  # level with the window of floor 1
    node = np.array([[-1.0, 6.0, zc]])
    ch = emulate_channel(anchor, node, building=b, radio=r)
    fa = first_arrival(ch, radio=r, rng=None)
    assert fa.slot[0, 0] == SLOT["Tx-Rx"] and fa.mpc_class[0, 0] == 1
    d = np.linalg.norm(anchor[0] - node[0])
    assert fa.true_path_m[0, 0] == pytest.approx(d, abs=1e-12)
    assert fa.range_m[0, 0] == fa.true_path_m[0, 0]  # rng=None: noise-free
    # free-space power: P_tx + 20 log10(lambda / (4 pi d)) (x-dipole field is transverse here
    # up to the direction cosine along x)
    u = (node[0] - anchor[0]) / d
    dip = np.sqrt(1 - u[0] ** 2)
    want = r.tx_power_dbm + 20 * np.log10(dip * r.wavelength_m / (4 * np.pi * d))
    assert ch.power_dbm[0, 0, 0] == pytest.approx(want, abs=1e-9)


def test_deep_node_far_above_x_polarised_anchor_sees_upper_edge_first():
    """Theorem 3: with x polarisation and the anchor far below the floor, the upper-edge
    path dominates; the lower-edge path is *shorter* but more than 15 dB weaker, so the
    detector picks the upper edge. With a 40 dB threshold the shorter lower edge wins."""
    b = Building(partitions=())
    r = Radio(polarization=(1.0, 0.0, 0.0))
    zf = float(b.floor_z_m(4))
    node = np.array([[2.0, 15.0, zf + b.nominal_node_height_m]])
    anchor = np.array([[0.0, -3.0, 0.0]])
    ch = emulate_channel(anchor, node, building=b, radio=r)
    up, lo = SLOT["Tx-D(upper)-Rx"], SLOT["Tx-D(lower)-Rx"]
    assert ch.length_m[0, 0, lo] < ch.length_m[0, 0, up]
    assert ch.snr_db[0, 0, up] - ch.snr_db[0, 0, lo] > 15.0
    fa = first_arrival(ch, radio=r)
    assert fa.slot[0, 0] == up and fa.mpc_class[0, 0] == 3
    fa40 = first_arrival(
        ch, radio=dataclasses.replace(r, fap_threshold_db=40.0, detection_snr_db=-60.0)
    )
    assert fa40.slot[0, 0] == lo


@pytest.mark.parametrize("y_n", [3.0, 8.0, 15.0])
def test_upper_lower_power_ratio_is_the_core_field_model(y_n):
    """The emulator's upper/lower diffraction powers are those of diffpos.channel.gtd's window-edge
    fields (no partitions): x polarisation favours the upper edge (Theorem 3), vertical (z)
    polarisation the lower edge."""
    from diffpos.channel.gtd import power_ratio_exact

    b = Building(partitions=())
    zc = float(b.floor_z_m(3)) + b.nominal_node_height_m
    anchor = np.array([[0.0, -20.0, 1.0]])
    node = np.array([[1.0, y_n, zc]])
    up, lo = SLOT["Tx-D(upper)-Rx"], SLOT["Tx-D(lower)-Rx"]
    for e0 in ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)):
        ch = emulate_channel(anchor, node, building=b, radio=Radio(polarization=e0))
        ratio_db = ch.snr_db[0, 0, up] - ch.snr_db[0, 0, lo]
        ref = 10 * np.log10(power_ratio_exact(anchor[0], node[0], window_height_m=1.5, e0=e0,
                                              edge_x_m=b.edge_x_m))
        assert ratio_db == pytest.approx(ref, abs=1e-9)
        if y_n >= 8.0:  # deep inside; near the window the lower edge's transition zone wins
            assert (ratio_db > 0) == (e0[0] == 1.0)


def test_partition_loss_is_added_to_the_diffracted_path():
    part = Partition(axis="x", position_m=0.0, span_m=(0.0, 22.5), loss_db=6.0)
    b0, b1 = Building(partitions=()), Building(partitions=(part,))
    r = Radio()
    zc = float(b0.floor_z_m(2)) + b0.nominal_node_height_m
    anchor = np.array([[-15.0, -20.0, 1.0]])
    nodes = np.array([[5.0, 10.0, zc], [-8.0, 10.0, zc]])  # behind / in front of the wall
    c0 = emulate_channel(anchor, nodes, building=b0, radio=r)
    c1 = emulate_channel(anchor, nodes, building=b1, radio=r)
    up = SLOT["Tx-D(upper)-Rx"]
    assert c0.power_dbm[0, 0, up] - c1.power_dbm[0, 0, up] == pytest.approx(6.0, abs=1e-9)
    assert c0.power_dbm[1, 0, up] == pytest.approx(c1.power_dbm[1, 0, up], abs=1e-12)


def test_through_wall_direct_path_carries_wall_loss():
    b, r = Building(partitions=()), Radio()
    zc = float(b.floor_z_m(2)) + b.nominal_node_height_m
    anchor = np.array([[0.0, -20.0, zc - 4.0]])  # hits the wall below the window
    node = np.array([[0.0, 10.0, zc]])
    ch = emulate_channel(anchor, node, building=b, radio=r)
    d = np.linalg.norm(anchor[0] - node[0])
    free = r.tx_power_dbm + 20 * np.log10(r.wavelength_m / (4 * np.pi * d))
    wall = slab_loss_db(b.wall_material, b.wall_thickness_m, r.frequency_hz)
    assert ch.power_dbm[0, 0, 0] == pytest.approx(free - wall, abs=1e-6)  # x-dipole: u_x = 0
    assert not ch.exists[0, 0, 0]


# ------------------------------------------------------------------ detector and noise
def test_first_arrival_matches_a_per_pair_loop(small_channel, paper):
    ch, r = small_channel, paper.radio
    fa = first_arrival(ch, radio=r)
    n, m, _ = ch.valid.shape
    for i in range(0, n, 7):
        for j in range(m):
            snr = ch.snr_db[i, j]
            ex = [
                k
                for k in range(len(MECHANISMS))
                if ch.valid[i, j, k] and snr[k] >= r.detection_snr_db
            ]
            if not ex:
                assert not fa.detected[i, j]
                continue
            thr = max(max(snr[k] for k in ex) - r.fap_threshold_db, r.detection_snr_db)
            cand = [k for k in ex if snr[k] >= thr]
            k = min(cand, key=lambda k: ch.delay_s[i, j, k])
            assert fa.slot[i, j] == k
            assert fa.mpc_class[i, j] == MPC_CLASS[k]
            assert fa.snr_db[i, j] == snr[k]
            crlb = C / np.sqrt(8 * np.pi**2 * r.bandwidth_hz**2 * 10 ** (snr[k] / 10))
            sigma = np.sqrt(crlb**2 + r.range_error_floor_m**2)  # CRLB + the error floor
            assert fa.sigma_m[i, j] == pytest.approx(sigma, rel=1e-12)


def test_range_noise_is_the_ranging_crlb(paper):
    nodes = paper.node_positions_m()[::4]
    ch = emulate_channel(
        paper.anchor_positions_m(), nodes, building=paper.building, radio=paper.radio
    )
    fa = first_arrival(ch, radio=paper.radio, rng=np.random.default_rng(123))
    z = ((fa.range_m - fa.true_path_m) / fa.sigma_m)[fa.detected]
    assert z.size > 15000
    assert abs(z.mean()) < 0.03 and abs(z.std() - 1) < 0.02
    fa2 = first_arrival(ch, radio=paper.radio, rng=np.random.default_rng(123))
    np.testing.assert_array_equal(fa.range_m, fa2.range_m)  # seeded


def test_vectorised_equals_one_pair_at_a_time(small_channel, paper):
    ch = small_channel
    for i in (0, 17, 123):
        for j in range(4):
            one = emulate_channel(
                ch.anchors_m[j : j + 1],
                ch.nodes_m[i : i + 1],
                building=paper.building,
                radio=paper.radio,
            )
            np.testing.assert_array_equal(one.valid[0, 0], ch.valid[i, j])
            v = ch.valid[i, j]
            np.testing.assert_allclose(one.length_m[0, 0][v], ch.length_m[i, j][v], rtol=1e-13)
            np.testing.assert_allclose(one.snr_db[0, 0][v], ch.snr_db[i, j][v], rtol=1e-11)


def test_mpc_table_counts(small_channel, paper):
    ch = small_channel
    fa = first_arrival(ch, radio=paper.radio)
    t = mpc_statistics(ch, fa)
    pairs = ch.valid.shape[0] * ch.valid.shape[1]
    for g in (1, 2, 3, 4):
        want = np.mean(np.any(ch.exists[..., MPC_CLASS == g], axis=-1)) * 100
        assert t[f"MPC-{g}"]["P_e"] == pytest.approx(want)
        assert t[f"MPC-{g}"]["P_fap"] <= t[f"MPC-{g}"]["P_e"] + 1e-9
    total = sum(t[f"MPC-{g}"]["P_fap"] for g in (1, 2, 3, 4)) + t["none"]["P_fap"]
    assert total == pytest.approx(100.0)
    assert pairs == 1200
    # the physics the paper relies on: diffraction exists almost everywhere
    assert t["MPC-3"]["P_e"] > 90.0


def test_rejects_bad_positions(paper):
    b, r = paper.building, paper.radio
    with pytest.raises(ValueError, match="outside the building"):
        emulate_channel([[0, 5.0, 1.0]], [[0, 5, 5.5]], building=b, radio=r)
    with pytest.raises(ValueError, match="nodes_m"):
        emulate_channel([[0, -5.0, 1.0]], [[0, 30, 5.5]], building=b, radio=r)


def test_physical_invariants(small_channel):
    """No path is shorter than the straight line; an extra bounce only lengthens a path;
    specular paths carry at most the free-space gain of their unfolded length."""
    ch = small_channel
    d = np.linalg.norm(ch.nodes_m[:, None] - ch.anchors_m[None], axis=-1)
    v = ch.valid
    assert np.all(ch.length_m[v] >= np.broadcast_to(d[..., None], v.shape)[v] - 1e-9)
    for edge in ("upper", "lower"):
        k0 = SLOT[f"Tx-D({edge})-Rx"]
        for then in ("floor", "ceiling"):
            k = SLOT[f"Tx-D({edge})-R({then})-Rx"]
            both = v[..., k] & v[..., k0]
            assert np.all(ch.length_m[..., k][both] >= ch.length_m[..., k0][both])
    lam = C / 28e9
    spec = np.array([not m.count("D(") for m in MECHANISMS])
    fs = lam / (4 * np.pi * ch.length_m[..., spec])
    g = np.abs(ch.gain[..., spec])
    ok = v[..., spec]
    assert np.all(g[ok] <= fs[ok] * (1 + 1e-12))
    fa = first_arrival(ch, radio=default_scenario().radio)
    assert np.all(fa.true_path_m[fa.detected] >= d[fa.detected] - 1e-9)  # NLoS bias >= 0
