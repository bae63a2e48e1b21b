"""The building and anchors of the existence-margin tests (test_tracking_margin,
test_tracking_edge_retry): not a shipped scenario: 4 floors of 3.3 m from 1.0 m, 0.8 m sills,
1.3 m windows, 30 x 16 m, no partitions; four UAVs 0.5-3.5 m high in front of the facade."""

from __future__ import annotations

import dataclasses

import numpy as np

from diffpos.scenario import default_scenario

SCENARIO = default_scenario()
BUILDING = dataclasses.replace(SCENARIO.building, n_floors=4, floor_height_m=3.3,
                               first_floor_z_m=1.0, sill_height_m=0.8, window_height_m=1.3,
                               width_m=30.0, depth_m=16.0, partitions=())
ANCHORS = np.array([[-12.0, -14.0, 1.0], [2.0, -9.0, 3.5], [19.0, -12.0, 0.5],
                    [-3.0, -21.0, 2.0]])
