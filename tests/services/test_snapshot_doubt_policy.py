"""``FusionConfig.confident_snapshot_period_s`` (issue 37, item 1: snapshots only where they
decide something): by default (None) a confident confirmed track gets no mnls snapshot after
its first, every other node keeps its periods (test_tracked_snapshot_policy.py); recordings
made before the setting replay with the 10 s they ran with; the tracked estimates of a replay
do not depend on it (the snapshot never feeds the tracker)."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
from diffpos_services.fusion.config import (
    LEGACY_CONFIDENT_SNAPSHOT_PERIOD_S,
    FusionConfig,
    with_legacy_defaults,
)
from diffpos_services.fusion.tracked import TrackBank, _snapshot_due

from diffpos.scenario import Building
from diffpos.tracking.state import TrackStatus


def _bank():
    b = Building()
    bank = TrackBank(b)
    ids = ["sure", "floor-doubt", "uninit"]
    bank.rows_of(ids)
    p = np.full((3, 2 * b.n_floors), 1e-6)
    p[:, 1] = 0.999
    p[1, 1], p[1, 2] = 0.6, 0.4
    p /= p.sum(axis=1, keepdims=True)
    bank.state = replace(bank.state, log_prob=np.log(p), nis=np.ones(3),
                         status=np.array([TrackStatus.TRACKING, TrackStatus.TRACKING,
                                          TrackStatus.UNINITIALISED], np.int8))
    return bank, ids


def _due_times(cfg, seconds=60):
    bank, ids = _bank()
    eps = [SimpleNamespace(node_id=n) for n in ids]
    due: dict[str, list[int]] = {n: [] for n in ids}
    for t_s in range(seconds + 1):
        d = _snapshot_due(bank, eps, np.full(3, t_s * 10**9), cfg)
        for n, v in zip(ids, d.tolist(), strict=True):
            if v:
                due[n].append(t_s)
    return due


def test_a_confident_track_gets_only_its_first_snapshot_by_default():
    assert FusionConfig().confident_snapshot_period_s is None
    due = _due_times(FusionConfig())
    assert due["sure"] == [0]
    assert due["floor-doubt"] == list(range(61))  # every snapshot_period_s (1 s)
    assert due["uninit"] == list(range(61))  # its only fix: every epoch


def test_a_period_gives_it_one_per_period():
    due = _due_times(FusionConfig(confident_snapshot_period_s=20.0))
    assert due["sure"] == [0, 20, 40, 60]
    # never shorter than snapshot_period_s
    due = _due_times(FusionConfig(confident_snapshot_period_s=0.0, snapshot_period_s=5.0))
    assert due["sure"] == list(range(0, 61, 5))


def test_recordings_made_before_the_setting_replay_with_ten_seconds():
    old = with_legacy_defaults({"method": "mnls", "snapshot_period_s": 1.0})
    assert old["confident_snapshot_period_s"] == LEGACY_CONFIDENT_SNAPSHOT_PERIOD_S == 10.0
    new = with_legacy_defaults({"method": "mnls", "confident_snapshot_period_s": None})
    assert new["confident_snapshot_period_s"] is None
    assert "confident_snapshot_period_s" not in with_legacy_defaults({})  # no settings
