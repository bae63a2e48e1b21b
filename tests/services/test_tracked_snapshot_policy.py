"""The live snapshot policy of the tracked fusion (fusion/tracked.py): a confident confirmed
track (floor probability >= CONFIDENT_FLOOR_PROBABILITY, averaged NIS <= CONFIDENT_NIS) gets
its mnls snapshot every ``confident_snapshot_period_s`` of measurement time (here the legacy
10 s; the default None is in test_snapshot_doubt_policy.py), any other confirmed
track every ``snapshot_period_s`` and so does an unconfirmed track that has a position
(INITIALISING, COASTING); a node without a tracked position (UNINITIALISED, LOST) every epoch
(its snapshot is the only fix of it)."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
from diffpos_services.fusion.config import LEGACY_CONFIDENT_SNAPSHOT_PERIOD_S, FusionConfig
from diffpos_services.fusion.tracked import TrackBank, _snapshot_due

from diffpos.scenario import Building
from diffpos.tracking.state import TrackStatus


def _bank():
    b = Building()
    bank = TrackBank(b)
    ids = ["sure", "floor-doubt", "misfit", "init", "coast", "lost", "uninit"]
    bank.rows_of(ids)
    h = 2 * b.n_floors
    p = np.full((len(ids), h), 1e-6)
    p[:, 1] = 0.995  # floor 1, level mode
    p[:, 1 + b.n_floors] = 0.004  # floor 1, vertical mode: floor 1 at 0.999 over both modes
    p[1, 1], p[1, 2] = 0.6, 0.395  # floor-doubt: floor 1 at 0.604
    p /= p.sum(axis=1, keepdims=True)
    # every unconfirmed track here is as confident as "sure": only its status differs
    status = [TrackStatus.TRACKING] * 3 + [TrackStatus.INITIALISING, TrackStatus.COASTING,
                                           TrackStatus.LOST, TrackStatus.UNINITIALISED]
    bank.state = replace(bank.state, log_prob=np.log(p),
                         nis=np.array([1.0, 1.0, 6.0, 1.0, 1.0, 1.0, 1.0]),
                         status=np.array(status, np.int8))
    return bank, ids


def test_confident_of():
    bank, ids = _bank()
    # confidence is the track's floor and fit only (the status is _snapshot_due's business)
    np.testing.assert_array_equal(bank.confident_of([*ids, "unknown"]),
                                  [True, False, False, True, True, True, True, False])


def test_snapshot_periods():
    bank, ids = _bank()
    cfg = FusionConfig(confident_snapshot_period_s=LEGACY_CONFIDENT_SNAPSHOT_PERIOD_S)
    eps = [SimpleNamespace(node_id=n) for n in ids]
    n_ids = len(ids)
    period_ns = round(cfg.snapshot_period_s * 1e9)
    long_ns = round(cfg.confident_snapshot_period_s * 1e9)
    assert long_ns > period_ns
    due = {}
    for t in range(0, long_ns + 1, period_ns // 2):
        d = _snapshot_due(bank, eps, np.full(n_ids, t), cfg)
        for n, v in zip(ids, d.tolist(), strict=True):
            due.setdefault(n, []).append(t) if v else None
    assert due["sure"] == [0, long_ns]
    for name in ("floor-doubt", "misfit", "init", "coast"):
        assert due[name] == list(range(0, long_ns + 1, period_ns)), name
    for name in ("lost", "uninit"):  # every call
        assert due[name] == list(range(0, long_ns + 1, period_ns // 2)), name
