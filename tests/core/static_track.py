"""A static node of the paper building tracked at 10 Hz from noisy (3 cm) ranges: the fixture
of the tracker's family and link-learning tests (test_tracking_family_gate,
test_tracking_family_learned, test_tracking_family_minority, test_tracking_link_learning).

``NODE`` on floor 2 with four UAVs ``ANCHORS`` outside; :func:`triple_bounce` is the
ceiling-floor-ceiling triple bounce through the window (out of the 18 mechanisms, one of
``max_order`` 3's families; tests/core/test_tracking_families.py checks its length)."""

from __future__ import annotations

import dataclasses

import numpy as np

from diffpos.paths.model import first_arrival_paths
from diffpos.scenario import default_scenario
from diffpos.tracking.tracker import init_state, update

B = default_scenario().building
NODE = np.array([0.0, 12.0, B.floor_z_m(2) + 1.5])
ANCHORS = np.array([[0.0, -7.0, 4.0], [-15.0, -20.0, 1.0], [15.0, -20.0, 1.0],
                    [-8.0, -10.0, 2.0]])
SIGMA = 0.03


def triple_bounce(anchor, node, floor) -> float:
    """The ceiling-floor-ceiling triple bounce's length [m] from ``anchor`` to ``node`` on
    ``floor`` (the image of the anchor in ceiling, floor, ceiling)."""
    zf = B.floor_z_m(floor)
    zc = zf + B.floor_height_m
    z = 2 * zc - (2 * zf - (2 * zc - anchor[2]))
    return float(np.linalg.norm([node[0] - anchor[0], node[1] - anchor[1], node[2] - z]))


def first_arrivals(node, anchors, floor):
    """The first arrival's length [m] among the 18 mechanisms from each anchor to ``node``."""
    n = len(anchors)
    ps = first_arrival_paths(np.broadcast_to(node, (n, 3)), anchors, B, floor=floor)
    rho0 = np.nanmin(np.where(ps.valid, ps.length_m, np.nan), axis=-1)
    assert np.all(np.isfinite(rho0))
    return rho0


def track(config, anchors, rho0, *, epochs, seed, displace=None):
    """Every epoch's state of the static node tracked from ``rho0`` plus noise (seed ``seed``).
    ``displace`` (epoch, floor, offset [m]): at that epoch the floor's tracks (both modes) are
    moved by the offset first: the wrong state of a stale or badly initialised hypothesis."""
    n = len(anchors)
    rng = np.random.default_rng(seed)
    state, states = init_state(1, B), []
    for k in range(epochs):
        if displace is not None and k == displace[0]:
            mean = state.mean.copy()
            mean[0, [displace[1], displace[1] + B.n_floors], :3] += displace[2]
            state = dataclasses.replace(state, mean=mean)
        rho = rho0 + rng.normal(0.0, SIGMA, n)
        state, _ = update(state, anchors[None], rho[None], np.full((1, n), SIGMA),
                          np.ones((1, n), bool), 10**9 + k * 10**8, B, config)
        states.append(state)
    return states


def same(a, b) -> bool:
    """Two states equal bit for bit (floor log-probabilities, means, covariances)."""
    return (np.array_equal(a.log_prob, b.log_prob) and np.array_equal(a.mean, b.mean)
            and np.array_equal(a.cov, b.cov))
