"""The tracker's SNR term near a path's existence boundary (diffpos.tracking.model).

Measured on the recorded default run (top-floor walker at the nominal height, 17.5 m): the
ceiling-floor double bounce through the window exists at 17.5 m but not 5-10 cm higher, so a
prior a few cm too high scored that link's strong measured SNR as "no such path" and the
detector threshold against a path that exists only on the far side of a band edge; every
such epoch cost the true floor 1.4-4 nats and the track locked onto the mirror floor below.
The reference here is the emulator's amplitude model itself (diffpos.channel.emulator.pair_snr_db) at
heights where the path surely exists / does not exist.
"""

from __future__ import annotations

import numpy as np

from diffpos.channel.emulator import pair_snr_db
from diffpos.scenario import default_scenario
from diffpos.tracking.links import Links
from diffpos.tracking.model import snr_cost, snr_cost_near
from diffpos.tracking.state import TrackerConfig

SC = default_scenario()
B, RADIO = SC.building, SC.radio
CFG = TrackerConfig()
FLOOR = 4
CEIL_FLOOR = 15  # "Tx-R(ceiling)-R(floor)-Rx"
LOWER_EDGE = 8  # "Tx-D(lower)-Rx"
ANCHOR_LOW = np.array([-15.0, -20.0, 0.93])
ANCHOR_MID = np.array([0.0, -15.0, 0.0])


def _links(anchor, snr_db):
    return Links.from_arrays(anchor[None, None], np.array([[30.0]]), np.array([[0.05]]),
                             np.ones((1, 1), bool), 0.0, snr_db=np.array([[snr_db]]),
                             radio=RADIO)


def _pred(anchor, z):
    return pair_snr_db(anchor[None, None], np.array([[9.0, 6.1, z]]), building=B,
                       radio=RADIO)[0, 0]


def test_slot_beyond_its_band_edge_is_scored_where_it_exists():
    """At 17.6 m the double bounce from the low anchor has no power, 0.2 m lower it has
    (independent check with pair_snr_db); with the measured SNR equal to that power the
    point cost is infinite and the near cost is ~0 (< 0.05 nats: no mismatch at all)."""
    z = 17.6
    p_here, p_low = _pred(ANCHOR_LOW, z), _pred(ANCHOR_LOW, z - CFG.exist_margin_m)
    assert not np.isfinite(p_here[CEIL_FLOOR]) and np.isfinite(p_low[CEIL_FLOOR])
    links = _links(ANCHOR_LOW, float(p_low[CEIL_FLOOR]))
    pos = np.array([[[9.0, 6.1, z]]])
    point = snr_cost(pos, links, B)[0, 0, 0]
    near = snr_cost_near(pos, links, np.array([[FLOOR]]), B, CFG.exist_margin_m)[0, 0, 0]
    assert not np.isfinite(point[CEIL_FLOOR])
    assert near[CEIL_FLOOR] < 0.05


def test_detector_threshold_ignores_a_path_beyond_a_band_edge():
    """From the middle anchor the double bounce exists at 17.6 m (33 dB) but not at 17.5 m:
    it is no sure path, so a weak lower-edge diffraction first arrival measured at its
    predicted SNR is not penalised by the detector rule (< 0.05 nats), while the threshold
    from every path at the point penalises it (> 1 nat)."""
    z = 17.6
    p_here, p_nom = _pred(ANCHOR_MID, z), _pred(ANCHOR_MID, z - 0.1)
    assert np.isfinite(p_here[CEIL_FLOOR]) and not np.isfinite(p_nom[CEIL_FLOOR])
    assert p_here[CEIL_FLOOR] - p_here[LOWER_EDGE] > RADIO.fap_threshold_db + 6.0
    links = _links(ANCHOR_MID, float(p_here[LOWER_EDGE]))
    pos = np.array([[[9.0, 6.1, z]]])
    point = snr_cost(pos, links, B)[0, 0, 0]
    near = snr_cost_near(pos, links, np.array([[FLOOR]]), B, CFG.exist_margin_m)[0, 0, 0]
    assert point[LOWER_EDGE] > 1.0
    assert near[LOWER_EDGE] < 0.05
