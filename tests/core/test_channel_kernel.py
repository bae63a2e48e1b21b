"""The compiled SNR prediction (diffpos.channel.snr_nb) against the numpy emulator.

:func:`diffpos.channel.emulator.pair_snr_db` runs the numba kernel; the reference is the emulator's own
numpy computation (:func:`diffpos.channel.emulator._pair_snr_db_numpy` = ``_slots`` of
:func:`diffpos.channel.emulator.emulate_channel`). The kernel repeats the reference's geometry with the
same floating-point operations (so existence, i.e. the ``-inf`` pattern, must agree exactly,
also for nodes next to the window band's edges), leaves out phase factors common to all field
components (they cancel in ``|gain|``) and evaluates the Faddeeva function itself.

Tolerances:

* Faddeeva ``w(z)`` vs ``scipy.special.wofz``: 5e-14 relative (measured max 2.3e-14 on the
  sampled upper half-plane, 1.4e-14 on the UTD ray; scipy's own accuracy is ~1e-15 to 1e-14);
  the UTD transition function vs :func:`diffpos.channel.gtd_halfplane.transition_function`: 5e-14 relative.
* SNR: 1e-9 dB. An SNR is ``20 log10 |g|`` + constants, so a relative error ``d`` of ``|g|``
  is ``8.7 d`` dB: the kernel's sources of error are rounding (~1e-16 relative per operation,
  a few hundred operations) and the 5e-14 of ``w``, amplified where the soft/hard coefficient
  is a difference of the two UTD terms; measured max ~1e-12 dB, so 1e-9 dB leaves a factor
  ~1000 for that amplification while still catching any modelling difference (the smallest
  physical term of the model, e.g. a 1 dB partition or a pattern 0.1 deg off, is far larger).
* M-NLS with the kernel vs with the numpy SNR: same floors, positions within 1e-9 m.

Geometries: random (fixed seeds) on the default building and on variants (other floor heights,
window sizes, off-centre facade, glass windows with loss, partitions, wall/slab loss overrides,
antenna patterns on and off, another polarisation), anchors below, at and above the window
bands and beyond the facade ends, nodes anywhere in the floors, within 1e-6 m of the window
band's edges and (estimator hypotheses) outside the building.
"""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest
from scipy.special import wofz

from diffpos.channel import emulator as channel
from diffpos.channel import transition_nb
from diffpos.channel.emulator import _pair_snr_db_numpy, emulate_channel, first_arrival, pair_snr_db
from diffpos.channel.gtd_halfplane import transition_function
from diffpos.estimators.mnls.solver import mnls
from diffpos.scenario import Building, Partition, Radio

RTOL_W = 5e-14
ATOL_DB = 1e-9

_PARTS = (Partition("x", 3.0, (2.0, 15.0)), Partition("y", 6.0, (-10.0, 8.0), loss_db=9.0),
          Partition("x", -7.5, (0.0, 22.5), material="brick", thickness_m=0.1))

BUILDINGS = {
    "default": Building(),
    "tall_glass_parts": Building(width_m=25.0, center_x_m=4.0, depth_m=12.0, n_floors=3,
                                 floor_height_m=4.2, first_floor_z_m=0.5, sill_height_m=1.1,
                                 window_height_m=2.3, windows="glass", glass_loss_db=4.0,
                                 partitions=_PARTS),
    "slit_open": Building(width_m=60.0, center_x_m=-7.5, depth_m=30.0, n_floors=8,
                          floor_height_m=2.8, first_floor_z_m=6.0, sill_height_m=0.3,
                          window_height_m=0.6, windows="open", interior_material="plasterboard",
                          ground_material="brick"),
    "low_overrides": Building(width_m=12.0, center_x_m=-4.0, depth_m=8.0, n_floors=2,
                              floor_height_m=3.5, first_floor_z_m=1.0, sill_height_m=0.9,
                              window_height_m=1.8, wall_loss_db=35.0, slab_loss_db=60.0,
                              glass_loss_db=2.0, partitions=_PARTS[:1]),
}
RADIOS = {
    "isotropic": Radio(),
    "patterns": Radio(tx_hpbw_deg=65.0, rx_hpbw_deg=90.0, tx_peak_deg=100.0, rx_peak_deg=80.0,
                      tx_gain_dbi=5.0, rx_gain_dbi=3.0, noise_figure_db=7.0),
    "z_pol_60ghz": Radio(frequency_hz=60e9, polarization=(0.0, 0.6, 0.8), tx_hpbw_deg=30.0,
                         processing_gain_db=30.0),
}


def _geometries(b: Building, rng: np.random.Generator, n: int, m: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (N, 3) inside the floors (a third within 1e-6 m of a window-band edge) and
    per-node anchors (N, M, 3): below, at and above the window bands, beyond the facade ends."""
    x0, x1 = b.edge_x_m
    w = x1 - x0
    k = rng.integers(0, b.n_floors, n)
    z = b.floor_z_m(k) + rng.uniform(0.02, b.floor_height_m - 0.02, n)
    lo, hi = b.window_z_m(k)
    near = rng.random(n) < 1 / 3
    edge_z = np.where(rng.random(n) < 0.5, lo, hi) + rng.uniform(-1e-6, 1e-6, n)
    z = np.where(near, edge_z, z)
    nodes = np.stack([rng.uniform(x0 + 0.01, x1 - 0.01, n),
                      rng.uniform(0.01, b.depth_m - 0.01, n), z], axis=-1)
    ax = rng.uniform(x0 - 0.4 * w, x1 + 0.4 * w, (n, m))  # beyond the facade ends too
    ay = -rng.uniform(0.5, 35.0, (n, m))
    az = rng.uniform(0.3, b.top_z_m + 15.0, (n, m))  # below, at and above every window band
    return nodes, np.stack([ax, ay, az], axis=-1)


# ------------------------------------------------------------------------------------------
# Faddeeva function and UTD transition function
# ------------------------------------------------------------------------------------------


def _w(z: np.ndarray) -> np.ndarray:
    z = np.ascontiguousarray(z, dtype=np.complex128).ravel()
    out = np.empty_like(z)
    transition_nb.faddeeva_kernel(z, out)
    return out


def _rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a - b) / np.abs(b)


def test_faddeeva_on_the_utd_ray_matches_scipy() -> None:
    """``w(exp(j 3pi/4) t)``, the only argument the UTD needs: t = 0 (shadow boundary, w = 1),
    the small-argument and transition regimes (dense to t = 12, both sides of the switch to the
    asymptotic series at |z| = 8) and the large-argument regime up to t = 1e9."""
    t = np.concatenate([[0.0, 1e-300, 1e-12], np.logspace(-10, -1, 200), np.linspace(0, 12, 6001),
                        transition_nb.ASYMPTOTIC_MIN_ABS * (1 + np.array([-1e-15, 0, 1e-15])),
                        np.logspace(1, 9, 800)])
    z = np.exp(0.75j * np.pi) * t
    w = _w(z)
    assert w[0] == pytest.approx(1.0, abs=1e-15)
    assert np.max(_rel(w, wofz(z))) <= RTOL_W


def test_faddeeva_over_the_upper_half_plane_matches_scipy() -> None:
    """Random z with |Re z| <= 20, 0 <= Im z <= 20 (both branches), the real axis itself and
    large |z| in every direction of the upper half-plane."""
    rng = np.random.default_rng(11)
    z = rng.uniform(-20, 20, 40_000) + 1j * rng.uniform(0, 20, 40_000)
    real_axis = np.linspace(-30, 30, 2001) + 0j
    ang = rng.uniform(0, np.pi, 4000)
    far = np.exp(rng.uniform(np.log(20.0), np.log(1e7), 4000)) * np.exp(1j * ang)
    far = far.real + 1j * np.abs(far.imag)
    for zz in (z, real_axis, far):
        assert np.max(_rel(_w(zz), wofz(zz))) <= RTOL_W


def test_transition_function_matches_gtd() -> None:
    """``F(X)`` of the kernel vs :func:`diffpos.channel.gtd_halfplane.transition_function` (scipy's wofz) from
    X = 0 to 1e12, densely around the switch to the asymptotic series; the limits F(0) = 0,
    F ~ sqrt(pi X) exp(j pi/4) (X -> 0) and F -> 1 + j / (2X) (X -> inf) follow."""
    xmin = transition_nb.TRANSITION_ASYMPTOTIC_MIN
    x = np.concatenate([[0.0], np.logspace(-12, 12, 2000), np.linspace(0, 200, 4001),
                        xmin * (1 + np.array([-2e-16, 0.0, 2e-16]))])
    f = np.array([transition_nb.transition(float(v)) for v in x])
    ref = transition_function(x)
    zero = x == 0
    assert np.all(f[zero] == 0)
    assert np.max(_rel(f[~zero], ref[~zero])) <= RTOL_W
    small = ~zero & (x < 1e-8)  # next term -2jX: relative correction ~ 1.13 sqrt(X)
    lead = np.sqrt(np.pi * x[small]) * np.exp(0.25j * np.pi)
    assert np.all(np.abs(f[small] / lead - 1) <= 1.2 * np.sqrt(x[small]))
    big = x > 1e8
    assert np.allclose(f[big], 1 + 0.5j / x[big], rtol=1e-15, atol=1e-15)


# ------------------------------------------------------------------------------------------
# pair_snr_db: kernel vs numpy emulator
# ------------------------------------------------------------------------------------------


def _compare(b: Building, r: Radio, nodes: np.ndarray, anchors: np.ndarray) -> float:
    ref = _pair_snr_db_numpy(anchors, nodes, building=b, radio=r)
    ker = pair_snr_db(anchors, nodes, building=b, radio=r)
    assert ker.shape == ref.shape == (*anchors.shape[:2], len(channel.MECHANISMS))
    assert not np.isnan(ref).any() and not np.isnan(ker).any()
    fin = np.isfinite(ref)
    np.testing.assert_array_equal(np.isfinite(ker), fin)
    assert np.all(ker[~fin] == -np.inf) and np.all(ref[~fin] == -np.inf)
    err = np.abs(ker[fin] - ref[fin])
    assert err.max(initial=0.0) <= ATOL_DB, f"max {err.max():.3e} dB"
    return float(fin.mean())


@pytest.mark.parametrize("bname", list(BUILDINGS))
def test_kernel_matches_numpy_on_buildings(bname: str) -> None:
    """1,000 nodes x 3 anchors per building, every radio: the -inf pattern exactly, finite SNRs
    to 1e-9 dB; every slot is valid somewhere (the comparison covers all 18 mechanisms)."""
    b = BUILDINGS[bname]
    rng = np.random.default_rng(list(BUILDINGS).index(bname))
    nodes, anchors = _geometries(b, rng, 1000, 3)
    for r in RADIOS.values():
        _compare(b, r, nodes, anchors)
    seen = np.isfinite(pair_snr_db(anchors, nodes, building=b, radio=RADIOS["isotropic"]))
    assert seen.any(axis=(0, 1)).all(), np.flatnonzero(~seen.any(axis=(0, 1)))


def test_kernel_uavs_at_and_above_the_windows_and_beyond_the_ends() -> None:
    """Anchors exactly at window-band heights (edge heights +- 1 mm, mid-band), high above the
    building and far beyond both facade ends; nodes at the window mid-height (Assumption 1)."""
    b = BUILDINGS["default"]
    rng = np.random.default_rng(3)
    x0, x1 = b.edge_x_m
    k = rng.integers(0, b.n_floors, 600)
    nodes = np.stack([rng.uniform(x0 + 0.1, x1 - 0.1, 600), rng.uniform(0.1, 22.0, 600),
                      b.floor_z_m(k) + b.nominal_node_height_m], axis=-1)
    kk = rng.integers(0, b.n_floors, (600, 4))
    alo, ahi = b.window_z_m(kk)
    az = np.stack([alo[:, 0] + 1e-3, ahi[:, 1] - 1e-3, 0.5 * (alo[:, 2] + ahi[:, 2]),
                   np.full(600, b.top_z_m + 30.0)], axis=-1)
    ax = np.stack([rng.uniform(x0 - 30, x0 - 1, 600), rng.uniform(x1 + 1, x1 + 30, 600),
                   rng.uniform(x0, x1, 600), rng.uniform(x0, x1, 600)], axis=-1)
    anchors = np.stack([ax, -rng.uniform(1.0, 30.0, (600, 4)), az], axis=-1)
    for r in RADIOS.values():
        _compare(b, r, nodes, anchors)


def test_kernel_hypotheses_outside_the_building() -> None:
    """Position hypotheses of an estimator or tracker may stray: nodes beyond the facade ends,
    behind the back wall, below the first floor (floor index -1), above the top floor and
    just outside the facade (``y < 0``); still the reference's -inf pattern and values."""
    b = BUILDINGS["tall_glass_parts"]
    rng = np.random.default_rng(6)
    x0, x1 = b.edge_x_m
    n = 1500
    nodes = np.stack([rng.uniform(x0 - 5, x1 + 5, n), rng.uniform(-0.5, b.depth_m + 2, n),
                      rng.uniform(-1.0, b.top_z_m + 4, n)], axis=-1)
    anchors = np.stack([rng.uniform(x0 - 20, x1 + 20, (n, 3)), rng.uniform(-30, -0.6, (n, 3)),
                        rng.uniform(0, 25, (n, 3))], axis=-1)
    with np.errstate(all="ignore"):
        _compare(b, RADIOS["patterns"], nodes, anchors)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # the numpy reference on a NaN node
def test_shared_anchors_and_non_finite_input() -> None:
    """(M, 3) anchors are shared by every node (as emulate_channel pairs them, whose snr_db the
    result equals); a NaN coordinate goes to the numpy reference (same output)."""
    b, r = BUILDINGS["default"], RADIOS["patterns"]
    rng = np.random.default_rng(4)
    nodes, anchors = _geometries(b, rng, 200, 4)
    shared = anchors[0]
    ker = pair_snr_db(shared, nodes, building=b, radio=r)
    ch = emulate_channel(shared, nodes, building=b, radio=r)
    fin = np.isfinite(ch.snr_db)
    np.testing.assert_array_equal(np.isfinite(ker), fin)
    assert np.max(np.abs(ker[fin] - ch.snr_db[fin])) <= ATOL_DB
    bad = nodes.copy()
    bad[5, 2] = np.nan
    out = pair_snr_db(anchors, bad, building=b, radio=r)
    ref = _pair_snr_db_numpy(anchors, bad, building=b, radio=r)
    np.testing.assert_array_equal(out, ref)


def test_unhashable_building_still_uses_the_kernel() -> None:
    """Partitions given as a list (not hashable, so the constants are not cached)."""
    b = dataclasses.replace(BUILDINGS["tall_glass_parts"], partitions=list(_PARTS))
    rng = np.random.default_rng(5)
    nodes, anchors = _geometries(b, rng, 200, 2)
    _compare(b, RADIOS["isotropic"], nodes, anchors)


def test_mnls_fixes_unchanged_with_the_kernel(monkeypatch: pytest.MonkeyPatch) -> None:
    """M-NLS on six emulated fixes (8 anchors, measured SNR and radio, so the SNR cost is on):
    the same floors, mechanisms and positions (1e-9 m) with the kernel and the numpy SNR."""
    b = BUILDINGS["default"]
    r = Radio()
    rng = np.random.default_rng(7)
    anchors = np.array([[-15.0, -10.0, 1.5], [0.0, -20.0, 10.0], [15.0, -12.0, 5.0],
                        [5.0, -30.0, 20.0], [-25.0, -12.0, 8.5], [10.0, -10.0, 14.0],
                        [28.0, -18.0, 5.5], [-30.0, -25.0, 19.0]])
    k = rng.integers(0, b.n_floors, 6)
    nodes = np.stack([rng.uniform(-18, 18, 6), rng.uniform(0.5, 20, 6),
                      b.floor_z_m(k) + rng.uniform(0.3, 2.7, 6)], axis=-1)
    fa = first_arrival(emulate_channel(anchors, nodes, building=b, radio=r), radio=r, rng=rng)
    det = fa.detected

    def fix():
        return mnls(np.broadcast_to(anchors, (6, 8, 3)), np.where(det, fa.range_m, 0.0),
                    np.where(det, fa.sigma_m, 1.0), mask=det, building=b, snr_db=fa.snr_db,
                    radio=r, bandwidth_hz=r.bandwidth_hz, error_floor_m=r.range_error_floor_m)

    with_kernel = fix()
    monkeypatch.setattr(sys.modules["diffpos.channel.emulator"], "pair_snr_db", _pair_snr_db_numpy)
    with_numpy = fix()
    np.testing.assert_array_equal(with_kernel.floor, with_numpy.floor)
    np.testing.assert_array_equal(with_kernel.mechanism, with_numpy.mechanism)
    np.testing.assert_allclose(with_kernel.position_m, with_numpy.position_m, rtol=0, atol=1e-9)
    assert np.isfinite(with_kernel.position_m).all()


# ------------------------------------------------------------------------------------------
# the anchors' compiled first-arrival detector
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("bname", ["default", "tall_glass_parts", "slit_open"])
def test_pair_first_arrival_equals_the_numpy_emulator(bname: str) -> None:
    """:func:`diffpos.channel.emulator.pair_first_arrival` (compiled SNR + compiled path lengths) vs
    :func:`emulate_channel` + :func:`first_arrival` on the same pairs with the same noise
    draws: the same detections and first-arrival choice (true path equal to 1e-9 m: lengths
    agree to rounding, so a different slot would differ by centimetres at least), SNR within
    ``ATOL_DB``, measured ranges within 1e-9 m."""
    b = BUILDINGS[bname]
    r = RADIOS["patterns"] if bname == "tall_glass_parts" else RADIOS["isotropic"]
    rng = np.random.default_rng(11)
    nodes, anchors = _geometries(b, rng, 400, 1)
    anchors = anchors[:, 0]
    got = channel.pair_first_arrival(anchors, nodes, building=b, radio=r,
                                     rng=np.random.default_rng(3))
    # the numpy reference on the diagonals of channels of 20 x 20 pairs: pair p = (node p,
    # anchor p); the diagonals stacked in order, then the detector with the same draws
    diags = []
    for k in range(0, len(nodes), 20):
        ch = emulate_channel(anchors[k:k + 20], nodes[k:k + 20], building=b, radio=r)
        idx = np.arange(len(nodes[k:k + 20]))
        diags.append({f.name: getattr(ch, f.name)[idx, idx][:, None]
                      for f in dataclasses.fields(ch)
                      if isinstance(getattr(ch, f.name), np.ndarray)
                      and getattr(ch, f.name).ndim == 3})
    diag = dataclasses.replace(ch, **{k: np.concatenate([d[k] for d in diags])
                                      for k in diags[0]})
    fa = first_arrival(diag, radio=r, rng=np.random.default_rng(3))
    rng_m, sigma, snr, true_path, det = got
    assert np.array_equal(det, fa.detected[:, 0])
    assert 0.3 < det.mean() <= 1.0  # a realistic mix of detected and undetected links
    np.testing.assert_allclose(true_path, fa.true_path_m[:, 0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(snr[det], fa.snr_db[det, 0], rtol=0, atol=ATOL_DB)
    np.testing.assert_allclose(rng_m, fa.range_m[:, 0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(sigma[det], fa.sigma_m[det, 0], rtol=1e-9)
    with pytest.raises(ValueError, match="outside the building"):
        channel.pair_first_arrival(anchors[:1] * [1, -1, 1], nodes[:1], building=b, radio=r)


def test_anchor_first_arrivals_kernel_equals_numpy() -> None:
    """:func:`diffpos.emulation.first_arrivals` (what an anchor process measures per block of
    epochs) with the compiled detector vs the numpy emulator: same detections, ranges within
    1e-9 m from the same generator state, several epochs per call (the anchor moves)."""
    from diffpos.emulation import first_arrivals
    from diffpos.scenario import default_scenario

    sc = default_scenario()
    rng = np.random.default_rng(2)
    nodes, anchors = _geometries(sc.building, rng, 3 * 40, 1)
    nodes = nodes.reshape(3, 40, 3)
    anchor_m = anchors[:3, 0]
    a = first_arrivals(anchor_m, nodes, sc, rng=np.random.default_rng(9))
    b = first_arrivals(anchor_m, nodes, sc, rng=np.random.default_rng(9), kernel=False)
    assert np.array_equal(a[3], b[3])
    for x, y in zip(a[:3], b[:3], strict=True):
        np.testing.assert_allclose(x[a[3]], y[a[3]], rtol=0, atol=1e-9)
