"""The in-memory fusion scene shared by test_fusion_logic.py and test_bad_input.py.

Site ``t``, five anchors outside the wall (y < 0), three nodes on floors 1, 3 and 5 of a
building with its first floor at 3 m and 3 m floors, a 1.5 m window and edge x in [-20, 20] m,
epochs of 0.1 s. tests/data/nasty/README.md describes the corpus against this scene.
"""

from __future__ import annotations

import numpy as np
from diffpos_services.config import build_config
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.wire.keys import Keys

W = 1.5  # window height [m]
EDGE = (-20.0, 20.0)  # window edge x range [m]
ANCHORS = {
    "uav1": np.array([-15.0, -20.0, 1.0]),
    "uav2": np.array([0.0, -15.0, 0.0]),
    "uav3": np.array([0.0, -7.0, 4.0]),
    "uav4": np.array([15.0, -20.0, 1.0]),
    "uav5": np.array([-5.0, -12.0, 8.0]),
}
NODES = {
    "n01": np.array([-8.0, 4.0, 3.0 + 0.75 + 0.75]),
    "n02": np.array([3.0, 8.0, 9.0 + 1.5]),
    "n03": np.array([12.0, 2.5, 15.0 + 1.5]),
}
PERIOD_NS = 100_000_000
KEYS = Keys("t")


def fusion_config(**kw) -> FusionConfig:
    """The scene's FusionConfig (validated by ``build_config``); ``kw`` overrides fields."""
    base = dict(site="t", window_height_m=W, edge_x_m=EDGE, epoch_period_s=0.1,
                deadline_s=0.3, first_floor_z_m=3.0, floor_height_m=3.0)
    base.update(kw)
    return build_config(FusionConfig, base)
