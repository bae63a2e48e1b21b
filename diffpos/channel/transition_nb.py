"""Compiled UTD transition function: the Faddeeva function ``w``, ``F(X)`` and the UTD term
``F(k L a(b)) / cos(b/2)`` (:func:`_utd_term`), scalars only, used by the SNR kernel of
:mod:`diffpos.channel.snr_nb` (through :mod:`diffpos.channel.rays_nb`).

``F(X) = sqrt(pi X) exp(j pi/4) w(exp(j 3 pi/4) sqrt X)``
(``diffpos.channel.gtd.transition_function``) needs the Faddeeva function ``w`` on the ray
``arg z = 3 pi/4``. :func:`faddeeva` is Weideman's rational approximation (J.A.C. Weideman,
SIAM J. Numer. Anal. 31 (1994) 1497-1518) with ``N = 40`` terms, valid in the closed upper
half-plane, coefficients computed once at import (an FFT of the integrand,
:func:`weideman_coefficients`), and its asymptotic series far from the origin. From ``X >=
64`` (most UTD terms of a window edge: ``X = 2 k L cos^2(b/2)`` is ~1e3 at 28 GHz) the
kernel sums ``F``'s own asymptotic series in real arithmetic
(:func:`transition_asymptotic`). Measured against ``scipy.special.wofz``
(tests/core/test_channel_kernel.py, tolerance 5e-14 relative): max relative error 1.3e-14
on the ray for ``t = |z|`` from 0 (the shadow boundaries, ``w = 1``) through the transition
region to 1e9 (the large-argument regime, ``w ~ j / (sqrt(pi) z)``), 1.5e-14 over
``|Re z| <= 20, 0 <= Im z <= 20``, 1.8e-15 on the real axis; ``F`` against
``gtd.transition_function`` 1.3e-14 for ``X`` from 1e-12 to 1e12.

numba keys the cache of :func:`diffpos.channel.snr_nb.channel_snr_kernel` on its own
file: it compiles these functions into itself, so after editing this file update the
dependants' ``CALLEES_SHA256`` stamps (tests/core/test_kernel_stamps.py names the values).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["ASYMPTOTIC_MIN_ABS", "TRANSITION_ASYMPTOTIC_MIN", "WEIDEMAN_N", "faddeeva",
           "faddeeva_kernel", "transition", "transition_asymptotic", "weideman_coefficients"]

#: Terms of Weideman's approximation of the Faddeeva function (accuracy: module docstring).
WEIDEMAN_N = 40


def weideman_coefficients(n_terms: int = WEIDEMAN_N) -> tuple[float, np.ndarray]:
    """``(L, a)`` of Weideman's ``w(z) ~ 2 p(Z) / (L - i z)^2 + 1 / (sqrt(pi) (L - i z))``,
    ``Z = (L + i z) / (L - i z)``, ``p`` the polynomial with coefficients ``a`` (highest
    power first, as ``numpy.polyval``). ``L = sqrt(N / sqrt(2))`` (Weideman's choice)."""
    m = 2 * n_terms
    k = np.arange(-m + 1, m)
    big_l = math.sqrt(n_terms / math.sqrt(2.0))
    t = big_l * np.tan(0.5 * k * np.pi / m)
    f = np.concatenate([[0.0], np.exp(-t * t) * (big_l * big_l + t * t)])
    a = np.real(np.fft.fft(np.fft.fftshift(f))) / (2 * m)
    return big_l, np.ascontiguousarray(a[1:n_terms + 1][::-1])


_W_L, _W_A = weideman_coefficients()
_INV_SQRT_PI = 1.0 / math.sqrt(math.pi)
_SQRT_PI = math.sqrt(math.pi)
_EXP_J_3PI4 = complex(np.exp(0.75j * np.pi))  # as diffpos.channel.gtd computes them
_EXP_J_PI4 = complex(np.exp(0.25j * np.pi))
#: ``X`` from which :func:`transition` sums its asymptotic series (see there).
TRANSITION_ASYMPTOTIC_MIN = 64.0
#: ``|z|`` from which :func:`faddeeva` sums the asymptotic series (see there).
ASYMPTOTIC_MIN_ABS = 8.0
_ASYM_MIN_ABS2 = ASYMPTOTIC_MIN_ABS * ASYMPTOTIC_MIN_ABS
_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}


@njit(**_OPTS)
def faddeeva(z):
    """Faddeeva function ``w(z) = exp(-z^2) erfc(-j z)`` for ``Im z >= 0`` (accuracy in the
    module docstring). Not valid in the lower half-plane.

    Away from the real axis and far from the origin (``|z| >= ASYMPTOTIC_MIN_ABS``, ``Im z >=
    |Re z| / 2``) the asymptotic series ``w ~ j / (sqrt(pi) z) sum_n (2n-1)!! / (2 z^2)^n``,
    summed until a term is below 1e-17 of the first (at most 16 terms at the threshold, 4-6
    at the typical ``|z| ~ 50`` of a UTD edge): its error is below the first omitted term,
    ``< 1e-16`` there. Elsewhere Weideman's rational approximation (N = 40)."""
    if z.imag >= 0.5 * abs(z.real) and (z.real * z.real + z.imag * z.imag) >= _ASYM_MIN_ABS2:
        q = 1.0 / (2.0 * z * z)
        term = 1.0 + 0j
        total = 1.0 + 0j
        for n in range(1, 40):
            term = term * ((2 * n - 1) * q)
            total = total + term
            if abs(term.real) + abs(term.imag) < 1e-17:
                break
        return (1j * _INV_SQRT_PI) * total / z
    big_l = _W_L
    iz = 1j * z
    den = big_l - iz
    zz = (big_l + iz) / den
    p = 0j
    for i in range(_W_A.shape[0]):
        p = p * zz + _W_A[i]
    return 2.0 * p / (den * den) + _INV_SQRT_PI / den


@njit(**_OPTS)
def faddeeva_kernel(z, out):
    """:func:`faddeeva` of every element of ``z`` (1-D complex) into ``out`` (for tests)."""
    for i in range(z.shape[0]):
        out[i] = faddeeva(z[i])


@njit(**_OPTS)
def transition_asymptotic(x):
    """UTD transition function ``F(X) ~ sum_n (2n-1)!! (j / (2X))^n`` for ``X >=``
    :data:`TRANSITION_ASYMPTOTIC_MIN` (gtd.transition_function's large-argument limit), in
    real arithmetic, summed until a term is below 1e-17: the error of the truncated series is
    below its first omitted term, so < 1e-16 relative for ``X >= 64`` (16 terms there, 5-8
    at the typical ``X ~ 1e3`` of a window edge)."""
    r = 0.5 / x
    term = 1.0
    re = 1.0
    im = 0.0
    for n in range(1, 60):
        term = term * ((2 * n - 1) * r)
        m = n % 4
        if m == 1:
            im += term
        elif m == 2:
            re -= term
        elif m == 3:
            im -= term
        else:
            re += term
        if term < 1e-17:
            break
    return complex(re, im)


@njit(**_OPTS)
def transition(x):
    """UTD transition function ``F(X) = sqrt(pi X) exp(j pi/4) w(exp(j 3 pi/4) sqrt X)``
    (gtd.transition_function) for ``X >= 0``: :func:`transition_asymptotic` from
    :data:`TRANSITION_ASYMPTOTIC_MIN` on, :func:`faddeeva` below."""
    if x >= TRANSITION_ASYMPTOTIC_MIN:
        return transition_asymptotic(x)
    r = math.sqrt(x)
    return _SQRT_PI * r * _EXP_J_PI4 * faddeeva(_EXP_J_3PI4 * r)


@njit(**_OPTS)
def _utd_term(c, kl):
    """gtd_halfplane._utd_term ``F(k L a(b)) / cos(b/2)`` of ``c = cos(b/2)``, ``a = 2 cos^2(b/2)``,
    finite at ``c = 0``: ``sgn sqrt(pi) sqrt(2kL) exp(j pi/4) w(exp(j 3 pi/4) sqrt(2kL) |c|)``,
    the same operations as numpy; from ``X = (sqrt(2kL) |c|)^2 >=``
    :data:`TRANSITION_ASYMPTOTIC_MIN` on, ``sgn F(X) / |c|`` with the asymptotic F (the same
    function: ``sqrt(pi) sqrt(2kL) w = F(X) exp(-j pi/4) / |c|``)."""
    sgn = 1.0 if c >= 0.0 else -1.0
    root = math.sqrt(2.0 * kl)
    t = root * abs(c)
    if t * t >= TRANSITION_ASYMPTOTIC_MIN:
        return sgn * transition_asymptotic(t * t) / abs(c)
    return sgn * _SQRT_PI * root * _EXP_J_PI4 * faddeeva(_EXP_J_3PI4 * root * abs(c))
