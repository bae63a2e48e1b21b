"""M-NLS's floor posterior with each floor's Laplace mass counted inside the floor's box only
(:class:`diffpos.estimators.mnls.rules.SnrRule` ``floor_box``, session 29): the box mass
against a brute-force grid integration of the Gaussian, and a Sionna RT receiver whose
wrong floor's mode lies against the building's back wall."""

from __future__ import annotations

import sys

import numpy as np

from diffpos.estimators.mnls.rules import SnrRule
from diffpos.estimators.mnls.solver import mnls
from diffpos.scenario import default_scenario

_result = sys.modules["diffpos.estimators.mnls.result"]
_problem = sys.modules["diffpos.estimators.mnls.problem"]


def _grid_mass(mu, h, lo, hi, n: int = 161) -> float:
    """Brute force: the N(mu, h^-1) density summed on an n^3 midpoint grid of the box."""
    axes = [lo[i] + (np.arange(n) + 0.5) * (hi[i] - lo[i]) / n for i in range(3)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3) - mu
    dens = np.exp(-0.5 * np.einsum("ni,ij,nj->n", g, h, g)) * np.sqrt(
        np.linalg.det(h) / (2 * np.pi) ** 3)
    return float(dens.sum() * np.prod((hi - lo) / n))


def test_box_mass_against_grid_integration():
    """The log mass inside the box equals the grid integral of the Gaussian (0.05 nats: the
    Monte Carlo's 8192 fixed draws) for a correlated Gaussian whose mode is on one face (about
    half inside), on an edge and in a corner, where the correlation matters (the product of
    the marginals is 0.2-0.5 nats off there); a mode far from every face keeps all its mass."""
    a = np.array([[1.0, 0.6, 0.2], [0.6, 2.0, -0.3], [0.2, -0.3, 1.5]])
    h = np.linalg.inv(a @ a.T * 0.04)  # sd 0.2-0.45 m, correlated
    sd = np.sqrt(np.diag(np.linalg.inv(h)))
    lo, hi = np.zeros(3), np.full(3, 4.0)
    cases = [(np.array([2.0, 0.0, 2.0]), h),  # on the face y = 0
             (np.array([4.0, 2.0, 2.0]), h),  # on the face x = 4
             (np.array([0.0, 0.0, 2.0]), h),  # on the edge x = y = 0
             (np.array([0.0, 0.0, 4.0]), h),  # in a corner
             (np.array([0.0, 0.0, 4.0]), np.diag(1.0 / sd**2))]  # a corner, axis-aligned
    for mu, hh in cases:
        lo_g = np.maximum(lo, mu - 7 * sd)
        hi_g = np.minimum(hi, mu + 7 * sd)
        ref = np.log(_grid_mass(mu, hh, lo_g, hi_g))
        got = _result._box_log_mass(mu, hh, lo, hi)
        assert abs(got - ref) < 0.05, (mu, got, ref)
        assert got < -0.6  # half or less inside: what the whole-Gaussian term overcounts
    assert abs(_result._box_log_mass(np.full(3, 5.0), h, lo, np.full(3, 10.0))) < 1e-9
    # batched (B, F) as M-NLS calls it: the same values row by row
    mus = np.stack([c[0] for c in cases[:4]]).reshape(2, 2, 3)
    got = _result._box_log_mass(mus, np.broadcast_to(h, (2, 2, 3, 3)), lo, hi)
    for k, (mu, _) in enumerate(cases[:4]):
        assert got.reshape(-1)[k] == _result._box_log_mass(mu, h, lo, hi)


#: Sionna RT's paper building, receiver 157 of the study's 200 (`diffpos raytrace paper
#: --receivers 200 --samples 1000000 --max-depth 4`, the study's first arrivals at seed 0,
#: /work/exp/s26/mnls/rt/paper.npz): floor 3 at (2.75, 21.0, 14.5), anchor 0 not detected.
_R157 = {
    "truth_floor": 3,
    "mask": [False, True, True, True],
    "range": [0.0, 41.65808411138705, 33.08787293070705, 46.457665036996374],
    "sigma": [1.0, 0.14633011545013533, 0.12683046559759373, 0.18980735052720243],
    "snr": [np.nan, -4.2461731192898355, -2.8095886466335855, -6.732608055813273],
}
_SOFT_SHEET = dict(first_arrival_prior=0.8, dielectric_edges=1.0)  # the study's best (s27)


def _r157(rule):
    sc = default_scenario()
    radio = sc.radio
    return mnls(sc.anchor_positions_m(), np.array(_R157["range"]), np.array(_R157["sigma"]),
                mask=np.array(_R157["mask"]), building=sc.building,
                snr_db=np.array(_R157["snr"]), radio=radio, max_order=4,
                bandwidth_hz=radio.bandwidth_hz, error_floor_m=radio.range_error_floor_m,
                snr_rule=rule)


def test_sionna_receiver_wrong_floor_mode_against_the_wall():
    """Receiver 157 (three links, 1.5 m from the back wall): with the whole-Gaussian Laplace
    term M-NLS publishes floor 2, whose mode is on the back wall (y = depth), so half its
    Gaussian lies outside the building; counted inside the box, floor 3 wins."""
    b = default_scenario().building
    f = _R157["truth_floor"]
    off = _r157(SnrRule(**_SOFT_SHEET))
    assert off.floor[0] == f - 1
    assert off.position_m[0, 1] > b.depth_m - 0.01  # the wrong floor's mode: on the wall
    on = _r157(SnrRule(**_SOFT_SHEET, floor_box=True))
    assert on.floor[0] == f
    assert on.floor_probability[0, f] > off.floor_probability[0, f]
    # the modes are the same: only the floor decision changes
    lo, hi, _ = _problem._floor_boxes(b, np.array([f]))
    assert np.all(on.position_m[0] >= lo[0]) and np.all(on.position_m[0] <= hi[0])
    assert np.linalg.norm(on.position_m[0, :2] - np.array([2.75, 21.0])) < 0.5


def test_default_is_the_whole_gaussian():
    """``floor_box`` is off by default and off gives the same posterior bit for bit."""
    assert SnrRule().floor_box is False
    a = _r157(SnrRule(**_SOFT_SHEET))
    b = _r157(SnrRule(**_SOFT_SHEET, floor_box=False))
    np.testing.assert_array_equal(a.floor_probability, b.floor_probability)
    np.testing.assert_array_equal(a.position_m, b.position_m)
