"""The SNR kernel's complex fields carried as (re, im) pairs (diffpos.channel.rays_nb)
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

import cmath
import itertools
import math

import numpy as np
from numba import njit

from diffpos.channel.rays_nb import _cmul, _cross, _norm_c, _reflect, _unit, _utd_term_ri
from diffpos.channel.transition_nb import TRANSITION_ASYMPTOTIC_MIN, _utd_term


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


@njit(cache=False)
def _reflect_complex(f0, f1, f2, k0, k1, k2, axis, eta):  # pragma: no cover - compiled
    """The complex ``_reflect`` the pairs replaced (channel_nb at 73c3e34), verbatim."""
    m0 = 1.0 if axis == 0 else 0.0
    m1 = 1.0 if axis == 1 else 0.0
    m2 = 1.0 if axis == 2 else 0.0
    if axis == 0:
        cos_t, o0, o1, o2 = abs(k0), -k0, k1, k2
    elif axis == 1:
        cos_t, o0, o1, o2 = abs(k1), k0, -k1, k2
    else:
        cos_t, o0, o1, o2 = abs(k2), k0, k1, -k2
    c0, c1, c2 = _cross(k0, k1, k2, m0, m1, m2)
    s0, s1, s2, sn = _unit(c0, c1, c2)
    if not sn > 1e-12:
        s0 = 1.0 if (axis + 1) % 3 == 0 else 0.0
        s1 = 1.0 if (axis + 1) % 3 == 1 else 0.0
        s2 = 1.0 if (axis + 1) % 3 == 2 else 0.0
    pi0, pi1, pi2 = _cross(s0, s1, s2, k0, k1, k2)
    po0, po1, po2 = _cross(s0, s1, s2, o0, o1, o2)
    c = min(max(cos_t, 0.0), 1.0)
    root = cmath.sqrt(eta - (1.0 - c * c) + 0j)
    gs = (c - root) / (c + root)
    gp = (eta * c - root) / (eta * c + root)
    es = f0 * s0 + f1 * s1 + f2 * s2
    ep = f0 * pi0 + f1 * pi1 + f2 * pi2
    a = gs * es
    b = gp * ep
    return a * s0 + b * po0, a * s1 + b * po1, a * s2 + b * po2


def test_reflect_pairs_equal_the_complex_reflection():
    """The pair ``_reflect`` against the complex one it replaced (compiled here from the old
    source), fields with random, zero, infinite and NaN parts, every axis, normal incidence
    too: finite results equal (``==``), and the field's norm finite in both or in neither (a
    non-finite field drops the ray either way; the complex product's extra ``x * 0`` terms
    may turn an inf into NaN, nothing else)."""
    rng = np.random.default_rng(5)
    special = [0.0, -0.0, math.inf, -math.inf, math.nan]
    n_special = 0
    for i in range(400):
        f = rng.normal(size=6) * 10.0 ** rng.integers(-6, 6, size=6)
        if i % 2:  # some parts special
            for j in rng.choice(6, size=int(rng.integers(1, 3)), replace=False):
                f[j] = special[int(rng.integers(len(special)))]
            n_special += 1
        k = rng.normal(size=3) if i % 7 else np.array([0.0, 0.0, 1.0])
        k /= np.linalg.norm(k)
        axis = int(rng.integers(3))
        eta = complex(rng.uniform(2.0, 8.0), -rng.uniform(0.0, 1.0))
        ref = _reflect_complex(complex(f[0], f[1]), complex(f[2], f[3]), complex(f[4], f[5]),
                               k[0], k[1], k[2], axis, eta)
        got = _reflect(*f, k[0], k[1], k[2], axis, eta)
        norm_ref = math.sqrt(sum((z * z.conjugate()).real for z in ref))
        assert math.isfinite(_norm_c(*got)) == math.isfinite(norm_ref), (f, k, axis)
        if math.isfinite(norm_ref):
            assert got == tuple(v for z in ref for v in (z.real, z.imag)), (f, k, axis)
    assert n_special == 200
