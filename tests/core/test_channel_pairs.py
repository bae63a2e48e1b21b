"""The SNR kernel's complex fields carried as (re, im) pairs (diffpos._kernels.channel_rays_nb)
against numba's complex arithmetic: equal values (``==``: at most the sign of a zero differs,
which no later step sees), so the SNR kernels' outputs are unchanged by the pairs.

* ``_utd_term_ri`` against ``transition_nb._utd_term`` (the complex UTD term, still the
  reference of gtd_halfplane's numpy code in tests/core/test_channel_kernel.py) over both of
  its branches: the asymptotic series (``X >= 64``) and Weideman's Faddeeva function near the
  shadow boundaries (``c`` -> 0, small ``k L``), both signs of ``c`` and ``c = +-0``.
* ``_cmul`` against Python's complex product (CPython's formula, which numba's is) and
  ``_norm_c`` against ``numpy.linalg.norm`` of the complex vector (to rounding: numpy's norm
  sums in another order).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from diffpos._kernels.channel_rays_nb import _cmul, _norm_c, _utd_term_ri
from diffpos._kernels.transition_nb import TRANSITION_ASYMPTOTIC_MIN, _utd_term


def _cases():
    rng = np.random.default_rng(3)
    c = np.concatenate([np.linspace(-1.0, 1.0, 41), [0.0, -0.0, 1e-300, -1e-300],
                        rng.uniform(-0.05, 0.05, 60), rng.uniform(-1.0, 1.0, 60)])
    kl = np.concatenate([np.logspace(-3, 6, 19), rng.uniform(1.0, 5000.0, 20)])
    return c, kl


def test_utd_term_pairs_equal_complex():
    c, kl = _cases()
    n_asym = n_weid = 0
    for kv in kl:
        for cv in c:
            ref = _utd_term(float(cv), float(kv))
            re, im = _utd_term_ri(float(cv), float(kv))
            assert (re, im) == (ref.real, ref.imag), (cv, kv, (re, im), ref)
            x = 2.0 * kv * cv * cv
            n_asym += x >= TRANSITION_ASYMPTOTIC_MIN
            n_weid += x < TRANSITION_ASYMPTOTIC_MIN
    assert n_asym > 500 and n_weid > 500  # both branches exercised


def test_cmul_and_norm_pairs():
    rng = np.random.default_rng(4)
    for _ in range(200):
        a, b, c, d = rng.normal(size=4) * 10.0 ** rng.integers(-8, 8, size=4)
        assert _cmul(a, b, c, d) == ((complex(a, b) * complex(c, d)).real,
                                     (complex(a, b) * complex(c, d)).imag)
        f = rng.normal(size=6)
        ref = np.linalg.norm(f[0::2] + 1j * f[1::2])
        assert abs(_norm_c(*f) - ref) <= 1e-15 * ref


def _same(a: float, b: float) -> bool:
    return a == b or (math.isnan(a) and math.isnan(b))


def test_pairs_equal_complex_on_zero_inf_nan():
    """Zeros of both signs, infinities, NaN and extremes: the pairs give numba's complex
    values (NaN where it gives NaN), so a non-finite field is classified the same way (the
    ray dropped by the kernels' ``isfinite`` test)."""
    special = [0.0, -0.0, 1e-300, -1e-300, 0.3, -1.0, 1e300, math.inf, -math.inf, math.nan]
    for cv, kv in itertools.product(special, [0.0, 1e-300, 1.0, 1e4, 1e300, math.inf,
                                              math.nan]):
        ref = _utd_term(cv, kv)
        re, im = _utd_term_ri(cv, kv)
        assert _same(re, ref.real) and _same(im, ref.imag), (cv, kv, (re, im), ref)
    for a, b, c, d in itertools.product([0.0, -0.0, 1.0, -2.5, 1e308, math.inf, -math.inf,
                                         math.nan], repeat=4):
        z = complex(a, b) * complex(c, d)
        re, im = _cmul(a, b, c, d)
        assert _same(re, z.real) and _same(im, z.imag), (a, b, c, d)
