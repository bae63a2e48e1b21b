"""M-NLS's floor posterior with each floor's Laplace mass counted inside its box AND where the
mode's mechanisms exist (:class:`diffpos.estimators.mnls.rules.SnrRule` ``path_region``,
session 31): the region mass against independent draws of the Gaussian with the numpy
reference path model, and a Sionna RT receiver whose wrong floor's mode is a specular hypothesis whose
paths vanish over a third of its Gaussian."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from diffpos.estimators.mnls.rules import SnrRule
from diffpos.estimators.mnls.solver import mnls
from diffpos.paths.mechanisms import mechanism_set
from diffpos.paths.model import _first_arrival_paths_numpy
from diffpos.scenario import default_scenario

_solver = sys.modules["diffpos.estimators.mnls.solver"]
_result = sys.modules["diffpos.estimators.mnls.result"]
_problem = sys.modules["diffpos.estimators.mnls.problem"]

#: Sionna RT's paper building, receiver 18 of the study's 200 (`diffpos raytrace paper
#: --receivers 200 --samples 1000000 --max-depth 4`, the study's first arrivals at seed 0,
#: /work/exp/s31/study/rt/paper.npz): floor 0 at mid-floor height, four links.
_R18 = {
    "truth_floor": 0,
    "range": [43.9012558646199, 30.964919264964955, 23.590956863837903, 30.884885704694724],
    "sigma": [0.05079566775440823, 0.05001371319557662, 0.05010024696636401,
              0.05008281607519463],
    "snr": [19.479580664889852, 37.149334693210164, 28.506253028171102, 29.336575293796102],
}
#: Its floor-1 mode (soft + sheet + box, K 4): the mode, the Gauss-Newton information and the
#: chosen mechanisms (Tx-R(ground)-R(ceiling)-Rx, Tx-R(ceiling)-Rx twice,
#: Tx-D(upper)-R(ceiling)-Rx).
_F1_MODE = np.array([15.405344651667411, 8.559004693511453, 7.212109526825048])
_F1_H = np.array([[454.84206279511847, 502.60477727673174, -265.3539011892888],
                  [502.6047772767316, 909.9110725755344, -443.39018818364866],
                  [-265.3539011892888, -443.39018818364855, 221.0380486883755]])
_F1_SLOTS = np.array([14, 3, 3, 10])
_SOFT_SHEET_BOX = dict(first_arrival_prior=0.8, dielectric_edges=1.0, floor_box=True)


def _reference_mass(mu, h, lo, hi, anchors, building, floor, slots, mech, n: int = 16384):
    """Reference: the Gaussian's mass where the node is in the box and every chosen path
    exists, by 16,384 independent draws (another generator than the estimator's 512 fixed
    ones: standard error about 0.01 nats here), existence from the numpy reference path
    model (independent of the compiled kernel)."""
    u = np.random.default_rng(7).standard_normal((n, 3))
    ev, v = np.linalg.eigh(np.linalg.inv(h))
    pts = mu + u @ (v * np.sqrt(ev)).T
    ok = np.all((pts >= lo) & (pts <= hi), axis=-1)
    if len(slots):
        uniq = np.unique(slots)
        ps = _first_arrival_paths_numpy(pts[:, None, :], anchors[None], building,
                                        floor=np.full((len(pts), 1), floor), slots=uniq,
                                        mechanisms=mech)
        ok &= np.all(ps.valid[:, np.arange(len(slots)), np.searchsorted(uniq, slots)], axis=-1)
    return float(np.log(np.mean(ok)))


def test_region_mass_against_reference():
    """Receiver 18's floor-1 mode: the share of its Gaussian inside the floor's box where its
    four paths exist, against 16,384 independent draws with the numpy reference path model
    (0.15 nats: about 2.5 standard errors of the estimator's 512 fixed draws); well below the box mass alone (what
    ``floor_box`` counts), so the test fails if the paths' existence is not counted."""
    sc = default_scenario()
    b = sc.building
    mech = mechanism_set(4, partitions=True)
    a = sc.anchor_positions_m()
    floors = np.array([1])
    p = _problem._problem(a[None], np.array([_R18["range"]]), np.array([_R18["sigma"]]),
                          np.ones((1, 4), bool), floors, b, 0.75, np.zeros((1, 4)), 0.01,
                          mech, SnrRule(**_SOFT_SHEET_BOX, path_region=True))
    t = {"slot": _F1_SLOTS[None], "tail": np.zeros((1, 4), bool),
         "none": np.zeros((1, 4), bool)}
    box = _result._box_log_mass(_F1_MODE, _F1_H, p.lo[0], p.hi[0])
    got = _solver._region_log_mass(p, np.array([0]), _F1_MODE[None, None], _F1_H[None, None],
                                   t, np.zeros((1, 1)), np.full((1, 1), box), b)[0, 0]
    ref = _reference_mass(_F1_MODE, _F1_H, p.lo[0], p.hi[0], a, b, 1, _F1_SLOTS, mech)
    box_ref = _reference_mass(_F1_MODE, _F1_H, p.lo[0], p.hi[0], a, b, 1, np.zeros(0, int), mech)
    assert abs(got - ref) < 0.15, (got, ref)
    assert abs(box - box_ref) < 0.1, (box, box_ref)
    assert got < box - 0.3  # the paths vanish over part of the Gaussian inside the box
    # a floor far below the fix's best keeps its box mass (REGION_NATS)
    far = _solver._region_log_mass(p, np.array([0]), _F1_MODE[None, None], _F1_H[None, None],
                                   t, np.full((1, 1), np.inf), np.full((1, 1), box), b)
    assert far[0, 0] == box


def _r18(rule):
    sc = default_scenario()
    radio = sc.radio
    return mnls(sc.anchor_positions_m(), np.array(_R18["range"]), np.array(_R18["sigma"]),
                building=sc.building, snr_db=np.array(_R18["snr"]), radio=radio, max_order=4,
                bandwidth_hz=radio.bandwidth_hz, error_floor_m=radio.range_error_floor_m,
                snr_rule=rule)


def test_sionna_receiver_specular_mode_out_of_its_region():
    """Receiver 18 (floor 0): with the box mass M-NLS publishes floor 1 (p 0.61), whose mode
    explains three links by ceiling reflections that stop existing over a third of its
    Gaussian; counted where its paths exist, floor 0 wins. The modes do not change."""
    f = _R18["truth_floor"]
    off = _r18(SnrRule(**_SOFT_SHEET_BOX))
    assert off.floor[0] == f + 1
    on = _r18(SnrRule(**_SOFT_SHEET_BOX, path_region=True))
    assert on.floor[0] == f
    assert on.floor_probability[0, f] > off.floor_probability[0, f]
    assert on.floor_probability[0, f + 1] < off.floor_probability[0, f + 1]


def test_default_off_and_needs_the_box():
    """``path_region`` is off by default, off gives the box posterior bit for bit, and it
    needs ``floor_box`` (the mass inside the box)."""
    assert SnrRule().path_region is False
    a = _r18(SnrRule(**_SOFT_SHEET_BOX))
    b = _r18(SnrRule(**_SOFT_SHEET_BOX, path_region=False))
    np.testing.assert_array_equal(a.floor_probability, b.floor_probability)
    np.testing.assert_array_equal(a.position_m, b.position_m)
    with pytest.raises(ValueError):
        SnrRule(first_arrival_prior=0.8, path_region=True)
