"""Link budget: thermal noise floor, SNR with processing gain, ranging CRLB, free-space gain.

Every function is a numpy ufunc-style expression: scalars and arrays broadcast, and the result
has the broadcast shape (a 0-d array for scalar input, converted with ``float()`` if needed).

Conventions
-----------
- Powers in dBm (``*_dbm``), ratios in dB (``*_db``), linear power ratios without suffix
  (``snr`` linear, ``snr_db`` in dB). All dB quantities are *power* dB (``10 log10``).
- The ranging CRLB follows the paper's eq. (ranging CRB) with ``beta`` taken as the signal
  bandwidth ``B``: ``sigma_tau = 1 / sqrt(8 pi^2 B^2 SNR)`` [s] and ``sigma_m = c sigma_tau``.
  Strictly, ``beta`` in that bound is the effective (RMS) bandwidth of the pulse; using ``B``
  reproduces the paper's numbers.

Paper's numbers
---------------
With ``B = 400 MHz`` and ``T = 300 K`` the thermal noise floor is
``kTB = 1.657e-12 W = -87.8 dBm`` (the paper prints ``-87 dBm``, i.e. truncated; use
``noise_floor_dbm(400e6)`` for the exact value). The paper adds a 20 dB receiver processing
gain to every path's received power before comparing with ``kTB``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.constants import BOLTZMANN_J_K, SPEED_OF_LIGHT_M_S

__all__ = [
    "PAPER_BANDWIDTH_HZ",
    "PAPER_PROCESSING_GAIN_DB",
    "PAPER_TEMPERATURE_K",
    "db_to_linear",
    "dbm_to_watt",
    "free_space_path_gain_db",
    "free_space_path_loss_db",
    "linear_to_db",
    "noise_floor_dbm",
    "processing_gain_db",
    "ranging_crlb_m",
    "ranging_crlb_s",
    "snr_db",
    "watt_to_dbm",
]

FloatArray = NDArray[np.float64]

PAPER_BANDWIDTH_HZ: float = 400e6
"""Signal bandwidth of the paper's simulation (Table: simulation parameters) [Hz]."""

PAPER_TEMPERATURE_K: float = 300.0
"""System noise temperature used for the paper's noise floor [K]."""

PAPER_PROCESSING_GAIN_DB: float = 20.0
"""Receiver processing gain added to every path's power in the paper [dB]."""


def db_to_linear(value_db: ArrayLike) -> FloatArray:
    """Power ratio from dB: ``10 ** (value_db / 10)``.

    Parameters
    ----------
    value_db : array_like [dB]

    Returns
    -------
    ndarray [-]
    """
    return np.power(10.0, np.asarray(value_db, dtype=np.float64) / 10.0)


def linear_to_db(value: ArrayLike) -> FloatArray:
    """Power ratio to dB: ``10 log10(value)``; ``-inf`` for 0, NaN for negative input.

    Parameters
    ----------
    value : array_like [-]

    Returns
    -------
    ndarray [dB]
    """
    v = np.asarray(value, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return 10.0 * np.log10(v)


def dbm_to_watt(power_dbm: ArrayLike) -> FloatArray:
    """Power in watts from dBm.

    Parameters
    ----------
    power_dbm : array_like [dBm]

    Returns
    -------
    ndarray [W]
    """
    return db_to_linear(np.asarray(power_dbm, dtype=np.float64) - 30.0)


def watt_to_dbm(power_w: ArrayLike) -> FloatArray:
    """Power in dBm from watts.

    Parameters
    ----------
    power_w : array_like [W]

    Returns
    -------
    ndarray [dBm]
    """
    return linear_to_db(power_w) + 30.0


def noise_floor_dbm(
    bandwidth_hz: ArrayLike,
    *,
    temperature_k: ArrayLike = PAPER_TEMPERATURE_K,
    noise_figure_db: ArrayLike = 0.0,
) -> FloatArray:
    """Thermal noise power ``k T B`` (plus a receiver noise figure) in dBm.

    Parameters
    ----------
    bandwidth_hz : array_like [Hz]
        Noise bandwidth ``B``; must be positive.
    temperature_k : array_like [K]
        System noise temperature ``T`` (default 300 K, as in the paper).
    noise_figure_db : array_like [dB]
        Receiver noise figure added to ``kTB`` (default 0 dB: the paper's ``N_0 = kTB``).

    Returns
    -------
    ndarray [dBm]
        E.g. ``noise_floor_dbm(400e6) = -87.81 dBm`` (the paper rounds this to -87 dBm).

    Raises
    ------
    ValueError
        If any bandwidth or temperature is not positive.
    """
    b = np.asarray(bandwidth_hz, dtype=np.float64)
    t = np.asarray(temperature_k, dtype=np.float64)
    if np.any(~(b > 0.0)):
        raise ValueError(f"bandwidth_hz must be > 0 Hz, got {b[~(b > 0.0)].ravel()[:3]}")
    if np.any(~(t > 0.0)):
        raise ValueError(f"temperature_k must be > 0 K, got {t[~(t > 0.0)].ravel()[:3]}")
    return watt_to_dbm(BOLTZMANN_J_K * t * b) + np.asarray(noise_figure_db, dtype=np.float64)


def processing_gain_db(bandwidth_hz: ArrayLike, integration_time_s: ArrayLike) -> FloatArray:
    """Coherent processing gain of a matched filter, ``10 log10(B T_int)``.

    The paper simply assumes a fixed 20 dB (:data:`PAPER_PROCESSING_GAIN_DB`), which is e.g.
    ``B = 400 MHz`` integrated over ``T_int = 250 ns`` (100 samples).

    Parameters
    ----------
    bandwidth_hz : array_like [Hz]
    integration_time_s : array_like [s]

    Returns
    -------
    ndarray [dB]
    """
    return linear_to_db(
        np.asarray(bandwidth_hz, dtype=np.float64) * np.asarray(integration_time_s, np.float64)
    )


def snr_db(
    rx_power_dbm: ArrayLike,
    *,
    bandwidth_hz: ArrayLike = PAPER_BANDWIDTH_HZ,
    processing_gain_db: ArrayLike = PAPER_PROCESSING_GAIN_DB,
    temperature_k: ArrayLike = PAPER_TEMPERATURE_K,
    noise_figure_db: ArrayLike = 0.0,
) -> FloatArray:
    """Post-processing SNR of a path: ``P_rx + G_proc - N_0`` with ``N_0 = kTB (+ NF)``.

    Parameters
    ----------
    rx_power_dbm : array_like [dBm]
        Received power of the path (e.g. of the first-arriving diffraction path).
    bandwidth_hz : array_like [Hz]
        Noise bandwidth (default 400 MHz).
    processing_gain_db : array_like [dB]
        Receiver processing gain added to the signal power (default 20 dB).
    temperature_k : array_like [K]
        Noise temperature (default 300 K).
    noise_figure_db : array_like [dB]
        Receiver noise figure (default 0 dB).

    Returns
    -------
    ndarray [dB]
        The SNR in dB; convert with :func:`db_to_linear` for :func:`ranging_crlb_m`.
    """
    n0 = noise_floor_dbm(bandwidth_hz, temperature_k=temperature_k, noise_figure_db=noise_figure_db)
    return (
        np.asarray(rx_power_dbm, dtype=np.float64) + np.asarray(processing_gain_db, np.float64) - n0
    )


def ranging_crlb_s(snr: ArrayLike, bandwidth_hz: ArrayLike) -> FloatArray:
    """CRLB (standard deviation) of the delay of an isolated path, ``1/sqrt(8 pi^2 B^2 SNR)``.

    Parameters
    ----------
    snr : array_like [-]
        *Linear* SNR (not dB). ``0`` gives ``inf``.
    bandwidth_hz : array_like [Hz]

    Returns
    -------
    ndarray [s]
    """
    s = np.asarray(snr, dtype=np.float64)
    b = np.asarray(bandwidth_hz, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return 1.0 / np.sqrt(8.0 * np.pi**2 * b * b * s)


def ranging_crlb_m(snr: ArrayLike, bandwidth_hz: ArrayLike) -> FloatArray:
    """CRLB (standard deviation) of the range, ``c / sqrt(8 pi^2 B^2 SNR)``.

    Parameters
    ----------
    snr : array_like [-]
        *Linear* SNR (not dB).
    bandwidth_hz : array_like [Hz]

    Returns
    -------
    ndarray [m]
        E.g. 400 MHz at 20 dB SNR (100 linear) gives 8.43 mm.
    """
    return SPEED_OF_LIGHT_M_S * ranging_crlb_s(snr, bandwidth_hz)


def free_space_path_gain_db(distance_m: ArrayLike, frequency_hz: ArrayLike) -> FloatArray:
    """Friis free-space path gain between isotropic antennas, ``20 log10(lambda / (4 pi d))``.

    Parameters
    ----------
    distance_m : array_like [m]
        Path length (for a diffracted ray, the unfolded length OPL + IPL).
    frequency_hz : array_like [Hz]

    Returns
    -------
    ndarray [dB]
        Negative for ``d > lambda / (4 pi)``; e.g. -61.4 dB at 1 m and 28 GHz.
    """
    d = np.asarray(distance_m, dtype=np.float64)
    wavelength_m = SPEED_OF_LIGHT_M_S / np.asarray(frequency_hz, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(wavelength_m / (4.0 * np.pi * d))


def free_space_path_loss_db(distance_m: ArrayLike, frequency_hz: ArrayLike) -> FloatArray:
    """Friis free-space path loss, ``-free_space_path_gain_db`` [dB] (positive)."""
    return -free_space_path_gain_db(distance_m, frequency_hz)
