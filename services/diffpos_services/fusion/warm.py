"""The fusion's warm-up: first-call costs paid before the service declares itself ready.

:func:`warm_up` runs one tiny problem through every solver the core will call (D-NLS; with the
method ``mnls`` also M-NLS, the compiled SNR prediction and a throw-away tracker), so imports,
numba cache loads and first calls happen before the first real epoch, which is then not late.
The core's own state (tracks, tracker bank, counters) is left untouched.
"""

from __future__ import annotations

from typing import Any

import numpy as np

import diffpos.estimators as est
from diffpos.channel import pair_snr_db
from diffpos.geometry import window_edge_path
from diffpos_services.fusion.tracked import TrackBank

__all__ = ["warm_up"]


def warm_up(core: Any) -> None:
    """Solve one 4-anchor problem with ``core``'s solvers (a :class:`FusionCore
    <diffpos_services.fusion.core.FusionCore>`), changing none of its state."""
    cfg = core.config
    anchors = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0],
                        [15.0, -20.0, 1.0]])
    node = np.array([1.0, 5.0, cfg.first_floor_z_m + 1.5])
    r = window_edge_path(anchors, node, window_height_m=cfg.window_height_m).length_m
    est.dnls(anchors[None], r[None], np.full((1, 4), 0.1), window_height_m=cfg.window_height_m,
             gating=core.gating)
    if core.building is not None:  # a throw-away tracker: the core's state is untouched
        est.mnls(anchors[None], r[None], np.full((1, 4), 0.1), building=core.building)
        if core.model[1] is not None:  # the compiled SNR prediction (loaded from cache)
            pair_snr_db(anchors[None], node[None], building=core.building, radio=core.model[1])
        TrackBank(core.building).update(["warm-up"], anchors[None], r[None],
                                        np.full((1, 4), 0.1), np.ones((1, 4), bool),
                                        np.zeros(1, np.int64))
