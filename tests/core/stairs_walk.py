"""The stairs walk shared by the publication tests (the band bound, the published covariance):
a walker going down the stairs from floor 2 to floor 1 of the default scenario, four UAVs, the
emulator's channel, seed 11."""

from __future__ import annotations

import functools

import numpy as np

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import init_state, update
from diffpos.trajectory import trajectory_from_dict

SC = default_scenario()
B = SC.building


#: the four UAVs' positions [m]
ANCHORS = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0],
                    [15.0, -20.0, 1.0]])


@functools.cache
def arrivals(epochs: int = 57) -> tuple:
    """Per epoch (time [s], the anchors' first arrivals): the walk's channel draws, which do
    not depend on the tracker."""
    walker = trajectory_from_dict({"kind": "waypoints", "speed_m_s": 0.8, "points_m": [
        [-4.0, 4.0, 11.6], [-3.0, 4.0, 11.6], [3.0, 4.0, 8.4], [5.0, 4.0, 8.4]]})
    rng = np.random.default_rng(11)
    out = []
    for k in range(epochs):
        t = k * 0.1
        out.append((t, first_arrival(emulate_channel(ANCHORS, walker.position_m(t)[None],
                                                     building=B, radio=SC.radio),
                                     radio=SC.radio, rng=rng)))
    return ANCHORS, tuple(out)


@functools.cache
def walk(cfg: TrackerConfig, epochs: int = 57):
    """Per epoch the tracker's output and state on the stairs walk (cached: tests share a
    configuration's walk)."""
    anchors, draws = arrivals(epochs)
    st, outs = init_state(1, B), []
    for t, fa in draws:
        st, out = update(st, anchors[None], fa.range_m, fa.sigma_m, fa.detected,
                         round(t * 1e9), B, cfg, snr_db=fa.snr_db, radio=SC.radio)
        outs.append((out, st))
    return outs
