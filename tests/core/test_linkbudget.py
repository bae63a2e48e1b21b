"""Link budget against closed forms computed here from the SI constants."""

from __future__ import annotations

import math

import numpy as np
import pytest

from diffpos.channel.linkbudget import (
    db_to_linear,
    dbm_to_watt,
    free_space_path_gain_db,
    free_space_path_loss_db,
    linear_to_db,
    noise_floor_dbm,
    processing_gain_db,
    ranging_crlb_m,
    ranging_crlb_s,
    snr_db,
    watt_to_dbm,
)

K_B = 1.380649e-23  # J/K (SI exact)
C = 299_792_458.0  # m/s (SI exact)


def test_noise_floor_is_ktb() -> None:
    # the paper's N_0 at B = 400 MHz, T = 300 K: -87.8 dBm (printed as -87 dBm)
    expected = 10 * math.log10(K_B * 300 * 400e6 / 1e-3)
    assert noise_floor_dbm(400e6) == pytest.approx(expected, abs=1e-12)
    assert noise_floor_dbm(400e6) == pytest.approx(-87.807, abs=5e-4)
    # textbook -174 dBm/Hz at 290 K
    assert noise_floor_dbm(1.0, temperature_k=290.0) == pytest.approx(-173.975, abs=1e-3)
    # 10 dB per decade of bandwidth, noise figure adds
    nf = noise_floor_dbm([1e6, 1e7, 1e8], noise_figure_db=7.0)
    np.testing.assert_allclose(np.diff(nf), 10.0, rtol=1e-12)
    assert nf[0] == pytest.approx(noise_floor_dbm(1e6) + 7.0)


def test_snr_includes_processing_gain() -> None:
    n0 = 10 * math.log10(K_B * 300 * 400e6 / 1e-3)
    assert snr_db(-80.0) == pytest.approx(-80.0 + 20.0 - n0, abs=1e-12)
    assert snr_db(-80.0, processing_gain_db=0.0) == pytest.approx(-80.0 - n0, abs=1e-12)
    p = np.array([[-100.0], [-90.0]])
    out = snr_db(p, bandwidth_hz=np.array([100e6, 400e6]))
    assert out.shape == (2, 2)
    assert out[1, 0] - out[1, 1] == pytest.approx(10 * math.log10(4.0), abs=1e-12)
    # 100 samples at 400 MHz integrated coherently -> the paper's 20 dB
    assert processing_gain_db(400e6, 250e-9) == pytest.approx(20.0, abs=1e-12)


def test_ranging_crlb_closed_form() -> None:
    b = 400e6
    snr = 100.0  # 20 dB
    sigma_tau = 1.0 / math.sqrt(8 * math.pi**2 * b**2 * snr)
    assert ranging_crlb_s(snr, b) == pytest.approx(sigma_tau, rel=1e-14)
    assert ranging_crlb_m(snr, b) == pytest.approx(C * sigma_tau, rel=1e-14)
    assert ranging_crlb_m(snr, b) == pytest.approx(8.4346e-3, rel=1e-4)
    # scaling: 10x SNR -> /sqrt(10); 2x bandwidth -> /2; zero SNR -> inf
    s = ranging_crlb_m(np.array([1.0, 10.0]), np.array([[1e8], [2e8]]))
    assert s.shape == (2, 2)
    assert s[0, 0] / s[0, 1] == pytest.approx(math.sqrt(10), rel=1e-14)
    assert s[0, 0] / s[1, 0] == pytest.approx(2.0, rel=1e-14)
    assert np.isinf(ranging_crlb_m(0.0, b))
    # via the link budget: P_rx = N_0 - 20 dB processing gain + 10 dB -> SNR 10 dB
    snr_lin = db_to_linear(snr_db(noise_floor_dbm(b) - 20.0 + 10.0))
    assert snr_lin == pytest.approx(10.0, rel=1e-12)


def test_friis_free_space() -> None:
    f = 28e9
    lam = C / f
    assert free_space_path_gain_db(lam / (4 * math.pi), f) == pytest.approx(0.0, abs=1e-12)
    assert free_space_path_gain_db(1.0, f) == pytest.approx(
        20 * math.log10(lam / (4 * math.pi)), abs=1e-12
    )
    assert free_space_path_gain_db(1.0, f) == pytest.approx(-61.39, abs=5e-3)
    d = np.array([10.0, 20.0, 100.0])
    g = free_space_path_gain_db(d, f)
    assert g[0] - g[1] == pytest.approx(20 * math.log10(2), abs=1e-12)
    np.testing.assert_allclose(free_space_path_loss_db(d, f), -g)


def test_db_helpers_round_trip() -> None:
    x = np.array([1e-6, 0.5, 1.0, 2.0, 1e9])
    np.testing.assert_allclose(db_to_linear(linear_to_db(x)), x, rtol=1e-14)
    assert db_to_linear(3.0) == pytest.approx(1.9953, rel=1e-4)
    assert dbm_to_watt(30.0) == pytest.approx(1.0)
    assert watt_to_dbm(1e-3) == pytest.approx(0.0, abs=1e-12)
    assert linear_to_db(0.0) == -np.inf


def test_bad_bandwidth_and_temperature() -> None:
    with pytest.raises(ValueError, match="bandwidth_hz"):
        noise_floor_dbm(0.0)
    with pytest.raises(ValueError, match="temperature_k"):
        noise_floor_dbm(1e6, temperature_k=-1.0)
