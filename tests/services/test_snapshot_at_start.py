"""``FusionConfig.snapshot_at_start`` (issue 37, session 21): by default (False) a node gets no
mnls snapshot in the epoch the tracker starts its track (the grid snapshot places it then);
the start counts as its last check, so its first mnls snapshot comes ``snapshot_period_s``
later unless the track is confident by then; recordings made before the setting replay with
True (a snapshot at the start, as they ran)."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
from diffpos_services.fusion.config import (
    LEGACY_SNAPSHOT_AT_START,
    FusionConfig,
    with_legacy_defaults,
)
from diffpos_services.fusion.tracked import TrackBank, _snapshot_due

from diffpos.scenario import Building
from diffpos.tracking.state import TrackStatus


def _due_times(cfg, sure: bool, seconds=5):
    """Seconds at which a node is due: UNINITIALISED and starting at t = 0, then placed
    (TRACKING; confident when ``sure``, its floor in doubt otherwise)."""
    b = Building()
    bank = TrackBank(b)
    bank.rows_of(["n"])
    p = np.full((1, 2 * b.n_floors), 1e-6)
    p[0, 1], p[0, 2] = (0.999, 1e-6) if sure else (0.6, 0.4)
    p /= p.sum(axis=1, keepdims=True)
    eps = [SimpleNamespace(node_id="n")]
    due = []
    for t_s in range(seconds + 1):
        start = np.array([t_s == 0])
        if t_s == 1:  # the tracker started the track at t = 0
            bank.state = replace(bank.state, log_prob=np.log(p), nis=np.ones(1),
                                 status=np.array([TrackStatus.TRACKING], np.int8))
        if _snapshot_due(bank, eps, np.array([t_s * 10**9]), cfg, starting=start)[0]:
            due.append(t_s)
    return due, bank.snapshot_ns


def test_no_snapshot_in_the_epoch_a_track_starts_by_default():
    assert FusionConfig().snapshot_at_start is False
    due, last = _due_times(FusionConfig(), sure=False)
    assert due == [1, 2, 3, 4, 5]  # a period after the start, then every period
    assert last["n"] == 5 * 10**9
    due, last = _due_times(FusionConfig(), sure=True)
    assert due == []  # confident by then: none (confident_snapshot_period_s None)
    assert last["n"] == 0  # the start counts as its last check


def test_with_the_setting_a_starting_track_gets_one():
    due, _ = _due_times(FusionConfig(snapshot_at_start=True), sure=False)
    assert due == [0, 1, 2, 3, 4, 5]
    due, _ = _due_times(FusionConfig(snapshot_at_start=True), sure=True)
    assert due == [0]


def test_a_node_not_starting_keeps_its_snapshots():
    """Without ``starting`` (or with it False) an unplaced node gets one every epoch."""
    b = Building()
    bank = TrackBank(b)
    bank.rows_of(["n"])
    eps = [SimpleNamespace(node_id="n")]
    for t_s in range(3):
        assert _snapshot_due(bank, eps, np.array([t_s * 10**9]), FusionConfig(),
                             starting=np.array([False]))[0]


def test_recordings_made_before_the_setting_replay_with_a_snapshot_at_start():
    old = with_legacy_defaults({"method": "mnls", "snapshot_period_s": 1.0})
    assert old["snapshot_at_start"] is LEGACY_SNAPSHOT_AT_START is True
    new = with_legacy_defaults({"method": "mnls", "snapshot_at_start": False})
    assert new["snapshot_at_start"] is False
    assert "snapshot_at_start" not in with_legacy_defaults({})  # no settings
