"""The live overload policy on its own (:class:`diffpos_services.fusion.overload.OverloadPolicy`):
ready queues of synthetic epochs, no solver. The policy on a real core fed a backlog, with a
replay by the decision record, is in tests/services/test_fusion_budget.py.

References are written from the rule, not from the code: a node's newest epoch kept, counts,
the order of the rounds; infinite settings mean "never" and must not crash the fusion.
"""

from __future__ import annotations

import collections
import json
import math
from types import SimpleNamespace

import msgspec
import pytest
from diffpos_services.fusion.config import (
    DEFAULT_ADMIT_LAG_S,
    DEFAULT_SUPERSEDE_AFTER_S,
    LEGACY_ADMIT_LAG_S,
    FusionConfig,
)
from diffpos_services.fusion.core import FusionCore
from diffpos_services.fusion.overload import BEHIND_KEEP_EPOCHS, OverloadPolicy
from diffpos_services.recording.reader import SideRecords
from diffpos_services.replay.run import replay_settings

from diffpos.alignment import PendingEpoch


def _queue(spec):
    """A ready queue, oldest first: ``spec`` lists (node, epoch)."""
    return collections.deque(PendingEpoch(n, e, 0) for n, e in spec)


class _Policy:
    """An OverloadPolicy with its own counters: ``apply(q, limit)``, ``took(node ids)``."""

    def __init__(self, cfg: FusionConfig, counts: collections.Counter[str]) -> None:
        self.policy, self.counts = OverloadPolicy(cfg), counts

    def apply(self, q, limit):
        return self.policy.apply(q, limit, self.counts)

    def took(self, node_ids):
        self.policy.taken([PendingEpoch(n, 0, 0) for n in node_ids])


def _policy(**overrides):
    cfg = FusionConfig(site="t", method="dnls", epoch_period_s=0.1, **overrides)
    counts: collections.Counter[str] = collections.Counter()
    return _Policy(cfg, counts), counts


def _backlog(nodes, epochs):
    return _queue((n, e) for e in epochs for n in nodes)


def test_a_behind_step_keeps_each_nodes_newest_and_counts_the_rest():
    """Span 0.9 s > 0.5 s: every node keeps its newest epoch; released = kept + superseded."""
    nodes = ["a", "b", "c"]
    pol, counts = _policy(max_backlog_s=2.0)
    q = _backlog(nodes, range(10, 20))
    out = pol.apply(q, limit=5)
    assert sorted((pe.node_id, pe.epoch) for pe in out) == [(n, 19) for n in nodes]
    assert counts["superseded"] + len(out) == len(q) and not counts["overloaded"]
    assert BEHIND_KEEP_EPOCHS == 1  # the reference above keeps one


def test_rounds_serve_the_least_recently_served_node_first():
    """After a step took b then c, a never-served node comes first, then b, then c."""
    pol, _ = _policy(max_backlog_s=2.0, supersede_after_s=0.0)
    pol.took(["b", "c"])
    out = pol.apply(_backlog(["b", "c", "a"], range(3)), limit=1)
    assert [pe.node_id for pe in out] == ["a", "b", "c"]


@pytest.mark.parametrize("spec", [[], [("a", 5)], [("a", 5), ("a", 6)]])
def test_nothing_happens_when_the_step_takes_every_ready_epoch(spec):
    pol, counts = _policy(max_backlog_s=2.0, supersede_after_s=0.0)
    q = _queue(spec)
    assert pol.apply(q, limit=len(q)) is q and pol.apply(q, limit=None) is q
    assert not counts


def test_one_node_alone_keeps_its_newest_epoch():
    pol, counts = _policy(max_backlog_s=2.0)
    out = pol.apply(_queue(("a", e) for e in range(30)), limit=3)
    assert [(pe.node_id, pe.epoch) for pe in out] == [("a", 29)]
    assert counts == {"superseded": 29}


def test_infinite_settings_mean_never_and_do_not_crash_the_core():
    """``--supersede-after-s inf`` / ``--max-backlog-s inf`` (FusionConfig accepts both: ``ge=0``,
    ``gt=0``): the core starts (it raised OverflowError converting inf to epochs) and the
    policy never coalesces, resp. never drops for age."""
    for over in ({"supersede_after_s": math.inf}, {"max_backlog_s": math.inf}):
        FusionCore(FusionConfig(site="t", method="dnls", epoch_period_s=0.1,
                                **{"max_backlog_s": 2.0, **over}))
    q = _backlog(["a", "b"], range(100))  # a 9.9 s span
    pol, counts = _policy(max_backlog_s=2.0, supersede_after_s=math.inf)
    out = pol.apply(q, limit=4)
    assert not counts["superseded"] and counts["overloaded"] == len(q) - len(out)
    assert {pe.epoch for pe in out} == set(range(79, 100))  # the last 2 s: 20 epochs + 1
    pol, counts = _policy(max_backlog_s=math.inf, supersede_after_s=0.0)
    out = pol.apply(q, limit=4)
    assert [(pe.node_id, pe.epoch) for pe in out] == [("a", 99), ("b", 99)]
    assert counts == {"superseded": len(q) - 2}


def _settings_of(recorded: dict, **kw):
    """replay_settings of a recording whose only record is metadata ``fusion_config``."""
    md = SimpleNamespace(name="fusion_config",
                         metadata={k: json.dumps(v) for k, v in recorded.items()})
    return replay_settings(SimpleNamespace(channels={}), side=SideRecords(metadata=[md]),
                           first_state=None, **kw).config


def test_a_replay_of_a_recording_from_before_the_coalescing_does_not_coalesce():
    """A live fusion recorded before ``supersede_after_s`` existed (its ``fusion_config`` has
    ``max_backlog_s`` but no ``supersede_after_s``) only shed by age: a replay by its decision
    record must not coalesce per node (the default 0.5 s would: not the live run's fixes).
    A recording that names the setting, an override, or a fusion without the policy keep
    theirs."""
    old = msgspec.to_builtins(FusionConfig(site="t", method="dnls", max_backlog_s=2.0))
    del old["supersede_after_s"]
    cfg = _settings_of(old)
    assert cfg.max_backlog_s == 2.0
    pol = _Policy(cfg, collections.Counter())
    q = _backlog(["a", "b"], range(10))  # 0.9 s of epochs, a step of 4: the old code shed none
    assert pol.apply(q, limit=4) is q
    new = {**old, "supersede_after_s": 0.3}
    assert _settings_of(new).supersede_after_s == 0.3
    assert _settings_of(old, overrides={"supersede_after_s": 0.2}).supersede_after_s == 0.2
    off = {**old, "max_backlog_s": None}
    assert _settings_of(off).supersede_after_s == DEFAULT_SUPERSEDE_AFTER_S


def test_a_step_that_leaves_more_than_admit_lag_s_is_lagging():
    """``lagging(ready, todo)``: what the step leaves (``ready[todo:]``) spans more than
    ``admit_lag_s`` of measurement time. Two nodes, epochs 10-19 (oldest first), 10 Hz:
    with 0.25 s, leaving epochs 17-19 (0.2 s) is not lagging, 16-19 (0.3 s) is; a step that
    takes everything, or leaves one epoch number, never is; 0 s: any span; the legacy
    setting of a replay (and inf) never."""
    q = _backlog(["a", "b"], range(10, 20))

    def lagging(todo, **kw):  # a policy of a core with a tracker (status_of set)
        pol = OverloadPolicy(FusionConfig(site="t", method="dnls", epoch_period_s=0.1, **kw))
        pol.status_of = lambda ids: [0] * len(ids)
        return pol.lagging(q, todo)
    assert DEFAULT_ADMIT_LAG_S == 0.25  # the reference below
    assert not lagging(14) and lagging(12)  # q[14:]: epochs 17-19; q[12:]: 16-19
    assert not lagging(len(q)) and not lagging(len(q) + 3) and not lagging(18)
    assert lagging(16, admit_lag_s=0.0) and not lagging(18, admit_lag_s=0.0)
    for never in (LEGACY_ADMIT_LAG_S, math.inf):
        assert not lagging(0, admit_lag_s=never)


def test_a_replay_of_a_recording_from_before_admission_admits_as_it_did():
    """A live fusion recorded before ``admit_lag_s`` existed initialised new tracks by the
    epochs a step solved, however far behind: its replay gets the legacy setting (never
    lagging), a recording that names it or an override keeps its own, and settings that
    were not recorded (the defaults of a recording without any) get the default."""
    old = msgspec.to_builtins(FusionConfig(site="t", method="dnls", max_backlog_s=2.0))
    del old["admit_lag_s"]
    assert _settings_of(old).admit_lag_s == LEGACY_ADMIT_LAG_S
    assert _settings_of({**old, "admit_lag_s": 0.4}).admit_lag_s == 0.4
    assert _settings_of(old, overrides={"admit_lag_s": 0.1}).admit_lag_s == 0.1
    assert _settings_of({}).admit_lag_s == DEFAULT_ADMIT_LAG_S


def test_a_node_without_a_confirmed_track_keeps_every_ready_epoch():
    """With a tracker's status (admission on): an UNINITIALISED, LOST or INITIALISING node
    keeps all its ready epochs, oldest first (no track: they cost no update and are
    published without a position; a new track: admission bounds them); a confirmed
    (TRACKING) node keeps its newest; only its are counted. Admission off (the
    legacy setting of a replay of an older recording): every node is coalesced, as before."""
    import numpy as np

    from diffpos.tracking.state import TrackStatus
    status = {"u": TrackStatus.UNINITIALISED, "l": TrackStatus.LOST,
              "i": TrackStatus.INITIALISING, "t": TrackStatus.TRACKING}
    q = _backlog(["u", "l", "i", "t"], range(10, 20))
    for admit, kept in ((DEFAULT_ADMIT_LAG_S, 31), (LEGACY_ADMIT_LAG_S, 4)):
        pol, counts = _policy(max_backlog_s=2.0, admit_lag_s=admit)
        pol.policy.status_of = lambda ids: np.array([int(status[n]) for n in ids], np.int8)
        out = pol.apply(q, limit=5)
        assert len(out) == kept and counts["superseded"] == len(q) - kept
        assert [pe.epoch for pe in out if pe.node_id == "t"] == [19]
        for n in "uli":
            mine = [pe.epoch for pe in out if pe.node_id == n]
            assert mine == (list(range(10, 20)) if kept == 31 else [19]), (admit, n)
    # the unplaced node's old epochs do not make the placed one's backlog stale: its ready
    # epochs span 0.1 s < supersede_after_s, nothing is dropped (admission off: all but the
    # newest of each)
    q2 = _queue([("u", e) for e in range(10, 18)] + [("u", 18), ("t", 18), ("u", 19), ("t", 19)])
    for admit, dropped in ((DEFAULT_ADMIT_LAG_S, 0), (LEGACY_ADMIT_LAG_S, 9 + 1)):
        pol, counts = _policy(max_backlog_s=2.0, admit_lag_s=admit)
        pol.policy.status_of = lambda ids: np.array([int(status[n]) for n in ids], np.int8)
        out = pol.apply(q2, limit=3)
        assert counts["superseded"] == dropped and len(out) == len(q2) - dropped
