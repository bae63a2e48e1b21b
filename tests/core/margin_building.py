"""The building and anchors of the existence-margin tests (test_tracking_margin,
test_tracking_edge_retry, _prior, test_tracking_mechanism_prior): not a shipped scenario: 4 floors of 3.3 m from 1.0 m, 0.8 m sills,
1.3 m windows, 30 x 16 m, no partitions; four UAVs 0.5-3.5 m high in front of the facade."""

from __future__ import annotations

import dataclasses

import numpy as np

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.tracking.state import TrackerConfig

SCENARIO = default_scenario()
BUILDING = dataclasses.replace(SCENARIO.building, n_floors=4, floor_height_m=3.3,
                               first_floor_z_m=1.0, sill_height_m=0.8, window_height_m=1.3,
                               width_m=30.0, depth_m=16.0, partitions=())
ANCHORS = np.array([[-12.0, -14.0, 1.0], [2.0, -9.0, 3.5], [19.0, -12.0, 0.5],
                    [-3.0, -21.0, 2.0]])

#: the tracker as it was before session 27's defaults (the edge retry and the persistent
#: mechanism prior): the tests of those settings state each of them explicitly
PRE27 = dict(edge_retry_margin_m=0.0, edge_retry_node=False, mechanism_prior_min_links=0,
             mechanism_switch_p=0.0, reseed_outliers=0, cov_published_floors="off")


def pre27_config(**kw) -> TrackerConfig:
    """A tracker configuration without session 27's (and 28's) defaults, ``kw`` on top."""
    return TrackerConfig(**{**PRE27, **kw})


def level_arrivals(rng, n):
    """``n`` level positions on random floors of BUILDING, 1 m inside its facade ends and
    walls, and the emulator's first arrivals there from ANCHORS (floors, nodes, arrivals)."""
    x0, x1 = BUILDING.edge_x_m
    floor = rng.integers(0, BUILDING.n_floors, n)
    nodes = np.stack([rng.uniform(x0 + 1.0, x1 - 1.0, n),
                      rng.uniform(1.0, BUILDING.depth_m - 1.0, n),
                      BUILDING.floor_z_m(floor) + BUILDING.nominal_node_height_m], axis=-1)
    fa = first_arrival(emulate_channel(ANCHORS, nodes, building=BUILDING,
                                       radio=SCENARIO.radio), radio=SCENARIO.radio, rng=rng)
    return floor, nodes, fa
