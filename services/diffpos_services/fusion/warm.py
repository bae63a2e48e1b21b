"""The fusion's warm-up: first-call costs paid before the service declares itself ready.

:func:`warm_up` runs one tiny problem through every solver the core will call (D-NLS with the
method ``dnls``; with ``mnls`` M-NLS, the compiled SNR prediction and a throw-away tracker), so imports,
numba cache loads and first calls happen before the first real epoch, which is then not late.
The core's own state (tracks, tracker bank, counters) is left untouched. :func:`warm_model`
is the mnls + tracker part, also run by each worker process of
:mod:`diffpos_services.fusion.workers` before it says ready.

Only what the run calls is loaded: a fusion without its tracker (``tracking`` off) warms no
tracker, and the throw-away tracker runs with the run's tracker settings. The seconds the
kernels' loads take: :func:`diffpos._kernels.clock.kernel_load_s` (docs/startup.md).
M-NLS, the SNR prediction and the tracker are imported inside the functions that call them: a
D-NLS process (fusion, replay) never imports their modules (the D-NLS solver's own kernels
are imported when it first solves).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from diffpos.estimators.dnls import solver as dnls_solver
from diffpos.geometry import window_edge_path
from diffpos.tracking.state import TrackerConfig

__all__ = ["warm_model", "warm_up"]


_ANCHORS = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0],
                     [15.0, -20.0, 1.0]])


def _problem(window_height_m: float, first_floor_z_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A node on the first floor and its four window-edge ranges [m]."""
    node = np.array([1.0, 5.0, first_floor_z_m + 1.5])
    return node, window_edge_path(_ANCHORS, node, window_height_m=window_height_m).length_m


def warm_model(building: Any, radio: Any, window_height_m: float, first_floor_z_m: float,
               *, tracking: bool = True,
               tracker_config: TrackerConfig | None = None) -> None:
    """M-NLS, the SNR prediction (with ``radio``) and, with ``tracking``, a throw-away tracker
    (an initialisation and a tracked update, without and with the SNR; ``tracker_config``: the
    run's :class:`~diffpos.tracking.state.TrackerConfig`, default its defaults) on one tiny
    problem in ``building``: every compiled kernel these calls use is loaded
    (tests/system/test_fusion_workers_process.py)."""
    # here, not at the top: a D-NLS process imports no M-NLS, SNR or tracker module
    # (tests/services/test_startup_loads.py)
    from diffpos.channel.emulator import pair_snr_db
    from diffpos.estimators.mnls import solver as mnls_solver

    node, r = _problem(window_height_m, first_floor_z_m)
    sig, mask = np.full((1, 4), 0.1), np.ones((1, 4), bool)
    mnls_solver.mnls(_ANCHORS[None], r[None], sig, building=building)
    snr = None
    if radio is not None:  # the compiled SNR prediction (loaded from cache)
        snr = pair_snr_db(_ANCHORS[None], node[None], building=building, radio=radio)
        snr = snr.max(axis=-1)  # (1, 4): the strongest mechanism as the "measured" SNR
    if tracking:
        _warm_tracker(building, radio, node, r, sig, mask, snr, tracker_config)


def _warm_tracker(building: Any, radio: Any, node: np.ndarray, r: np.ndarray, sig: np.ndarray,
                  mask: np.ndarray, snr: np.ndarray | None,
                  tracker_config: TrackerConfig | None) -> None:
    """A throw-away tracker's initialisation and tracked update, without and with ``snr``;
    and the extra families' compiled paths (``max_order`` > 2), which its links do not reach
    (a link gets them after a history of misfits: the first real ones did load them)."""
    from diffpos.tracking.families import extra_families, graded_split  # as below
    from diffpos.tracking.tracker import init_state, update  # an untracked run: never loaded

    config = TrackerConfig() if tracker_config is None else tracker_config
    if extra_families(config.max_order) is not None:
        graded_split(node[None], _ANCHORS[:1], np.zeros(1), building, config.max_order,
                     config.exist_margin_m)
    for snr_db in (None,) if snr is None else (None, snr):
        # an initialisation, then a tracked update of it (the IEKF from a prior and, with the
        # SNR, the prediction cache's kernels: loaded now, not in the first real call)
        st = init_state(1, building)
        for k in range(2):
            st, _ = update(st, _ANCHORS[None], r[None], sig, mask, np.full(1, k * 100_000_000),
                           building, config, snr_db=snr_db,
                           radio=None if snr_db is None else radio)


def warm_up(core: Any) -> None:
    """Solve one 4-anchor problem with ``core``'s solvers (a :class:`FusionCore
    <diffpos_services.fusion.core.FusionCore>`), changing none of its state: D-NLS for the
    method ``dnls`` only (the other methods do not call it)."""
    cfg = core.config
    _, r = _problem(cfg.window_height_m, cfg.first_floor_z_m)
    if cfg.method == "dnls":
        dnls_solver.dnls(_ANCHORS[None], r[None], np.full((1, 4), 0.1),
                         window_height_m=cfg.window_height_m, gating=core.gating)
    if core.building is not None:  # a throw-away tracker: the core's state is untouched
        warm_model(core.building, core.model[1], cfg.window_height_m, cfg.first_floor_z_m,
                   tracking=core.bank is not None,
                   tracker_config=None if core.bank is None else cfg.tracker_config())
