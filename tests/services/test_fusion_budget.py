"""Bounded work per live solve step (fusion/tracked.py ``heavy_budget``, fusion/service.py
``StepCost``): a burst of new tracks is initialised over several steps instead of stalling one,
every node-epoch is still published on time, and a replay by the decision record re-issues the
same steps and gets the same estimates bit for bit.

Input made independently of the fusion: the channel emulator ranges from five static UAVs to
eight static nodes on three floors of the default building (first arrivals, seeded), packed
as the AnchorState + RangeBatch messages an anchor publishes. No processes, no bus.
"""

from __future__ import annotations

import collections
import functools
import itertools

import msgspec
import numpy as np
import pytest
from diffpos_services.fusion import tracked
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.core import FusionCore
from diffpos_services.fusion.service import StepCost
from diffpos_services.fusion.tracked import (
    HEAVY_MIN_OPERATIONS,
    HEAVY_WORK_EPOCHS,
    SNAPSHOT_WORK_EPOCHS,
    heavy_budget,
)
from diffpos_services.recording.writer import McapSink
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import quiet_logger
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario

SC = default_scenario()
B = SC.building
KEYS = Keys("b")
PERIOD = 100_000_000
T0 = 1_800_000_000_000_000_000
ANCHORS = {"uav1": [-15.0, -20.0, 1.0], "uav2": [0.0, -15.0, 0.0], "uav3": [0.0, -7.0, 4.0],
           "uav4": [15.0, -20.0, 1.0], "uav5": [-25.0, -12.0, 3.0]}
H = B.nominal_node_height_m
F0, FH = B.first_floor_z_m, B.floor_height_m
NODES = {f"n{i}": [x, y, F0 + f * FH + H] for i, (x, y, f) in enumerate(
    [(-10.0, 3.0, 0), (-4.0, 6.0, 0), (2.0, 4.0, 1), (8.0, 7.0, 1), (12.0, 3.0, 1),
     (-8.0, 5.0, 2), (0.0, 8.0, 2), (6.0, 3.0, 0)])}
EPOCHS = 16


@functools.cache
def _samples(epochs: int = EPOCHS, seed: int = 3) -> tuple:
    """Per epoch, ``(rx_ns, key, payload)`` of every anchor's state and range batch."""
    rng = np.random.default_rng(seed)
    anchors = np.array(list(ANCHORS.values()))
    nodes = np.array(list(NODES.values()))
    ids = list(NODES)
    out = []
    for k in range(epochs):
        fa = first_arrival(emulate_channel(anchors, nodes, building=B, radio=SC.radio),
                           radio=SC.radio, rng=rng)
        t = T0 + k * PERIOD + 20_000_000
        items = []
        for j, a in enumerate(ANCHORS):
            rx = t + 1_000_000 + 100_000 * j
            det = fa.detected[:, j]
            col = lambda v: [float(v[i, j]) if det[i] else None for i in range(len(ids))]  # noqa: E731,B023
            st = M.AnchorState(anchor_id=a, t_ns=t, seq=k, position_m=M.vec3(anchors[j]),
                               velocity_m_s=(0.0, 0.0, 0.0), position_sigma_m=(0.02, 0.02, 0.03),
                               velocity_sigma_m_s=0.05, range_rate_hz=10.0, t_pub_wall_ns=rx)
            batch = M.RangeBatch(anchor_id=a, t_ns=t, seq=k, node_ids=ids,
                                 range_m=col(fa.range_m), sigma_m=col(fa.sigma_m),
                                 snr_db=col(fa.snr_db), t_pub_wall_ns=rx)
            items += [(rx, KEYS.anchor_state(a), M.encode(st)),
                      (rx + 10, KEYS.anchor_range_batch(a), M.encode(batch))]
        out.append(tuple(items))
    return tuple(out)


def _config(**overrides) -> FusionConfig:
    # snapshot_at_start: these tests budget the snapshots of new tracks (a snapshot in the
    # epoch a track starts, as before FusionConfig.snapshot_at_start's default of False)
    overrides.setdefault("snapshot_at_start", True)
    return FusionConfig.from_scenario(SC, site="b", epoch_period_s=0.1, method="mnls",
                                      **overrides)


def _run(limit: int | None, sink: McapSink | None = None, emit=None, *, every: int = 1,
         **overrides):
    """The fusion stepped once after every ``every`` epochs' messages (and after the last) with
    ``limit`` (and ``emit``); returns the core and the estimates of each step (the last step:
    the flush). ``overrides``: FusionConfig fields."""
    core = FusionCore(_config(**overrides), logger=quiet_logger())
    t_alive = T0 - PERIOD
    for a in ANCHORS:
        core.on_liveliness(a, True, t_alive)
        if sink is not None:
            sink.write_liveliness("b", KEYS.alive_anchor(a), True, t_alive)
    steps = []
    rx = t_alive
    for k, items in enumerate(_samples()):
        for rx, key, payload in items:
            core.on_sample(key, payload, rx)
            if sink is not None:
                sink.write(key, payload, rx)
        # after the epoch's last batch: every anchor reported, the epoch is complete
        if (k + 1) % every == 0 or k == EPOCHS - 1:
            steps.append(core.step(rx + 1000, limit=limit, emit=emit))
    steps.append(core.flush(rx + 2000))
    if sink is not None:
        for i, ests in enumerate(steps):
            for e in ests:
                sink.write(KEYS.node_estimate(e.node_id), M.encode(e), e.t_pub_wall_ns + i + 1)
        sink.write(KEYS.fusion_diagnostics(), M.encode(core.diagnostics(rx + 3000)), rx + 3000)
    return core, steps


def test_heavy_budget_is_a_fraction_of_the_epochs_solved():
    assert heavy_budget(None) is None  # replay of unlimited steps, flush: unbounded
    assert HEAVY_MIN_OPERATIONS >= 1
    assert heavy_budget(1) == HEAVY_MIN_OPERATIONS  # a step always makes progress
    assert heavy_budget(HEAVY_WORK_EPOCHS - 1) == HEAVY_MIN_OPERATIONS
    k = HEAVY_MIN_OPERATIONS + 1
    assert heavy_budget(k * HEAVY_WORK_EPOCHS) == k
    assert heavy_budget(k * HEAVY_WORK_EPOCHS + HEAVY_WORK_EPOCHS - 1) == k


def _positioned(ests) -> set[str]:
    return {e.node_id for e in ests if e.position_m is not None}


def test_a_burst_of_new_tracks_is_initialised_over_several_steps():
    """Eight new nodes at once. Unbudgeted (limit None) the first step initialises all of
    them and snapshots every one; budgeted (8 epochs per step: ``b`` = HEAVY_MIN_OPERATIONS
    heavy operations), each step initialises exactly ``b`` more nodes (the rest at the end)
    and does nothing else heavy until all are initialised.
    Every node-epoch is still published in the step that released it (no position while the
    node waits: UNINITIALISED), and the budgeted tracks end as close to the truth as the
    unbudgeted ones."""
    n = len(NODES)
    _, free = _run(None)
    assert _positioned(free[0]) == set(NODES)
    assert sum(e.snapshot is not None for e in free[0]) == n
    limit = 4 * HEAVY_WORK_EPOCHS  # every ready epoch; the 8 solved allow b heavy operations
    b = heavy_budget(n)
    assert b == HEAVY_MIN_OPERATIONS < n
    core, steps = _run(limit)
    # node-epochs that waited: n - b after the first step, n - 2 b after the second, ...
    assert core.bank.deferred == sum(max(0, n - b * (k + 1)) for k in range(n))
    seen: set[str] = set()
    for k, ests in enumerate(steps[:-1]):
        # published on time: every node's epoch k in step k
        assert sorted(e.node_id for e in ests) == sorted(NODES)
        assert {e.epoch for e in ests} == {T0 // PERIOD + k}
        new = _positioned(ests) - seen
        heavy = len(new) + sum(e.snapshot is not None for e in ests)
        assert heavy <= b, (k, new)
        if k * b < n:
            assert len(new) == min(b, n - k * b), (k, new)  # initialisations come first
        waiting = [e for e in ests if e.node_id not in seen | new]
        assert all(e.status == "UNINITIALISED" and e.position_m is None for e in waiting)
        seen |= new
    assert seen == set(NODES)
    # accuracy at the last epoch against the truth (static nodes), budgeted vs unbudgeted
    for run in (free, steps):
        last = {e.node_id: e for e in run[-2]}
        err = [np.linalg.norm(np.subtract(last[i].position_m, p)) for i, p in NODES.items()
               if last[i].position_m is not None]
        assert len(err) >= n - 1 and np.median(err) < 1.0, err


def test_initialisations_and_snapshot_fixes_come_after_the_other_estimates_of_their_step(
        monkeypatch):
    """Budgeted steps of 8 epochs (``b`` initialisations each): with ``emit``, each step
    publishes (emits) the estimates of the nodes it does not initialise before it initialises
    any, and the estimates without a snapshot fix before the step computes its fixes (the
    calls of the M-NLS estimator), those with one after; the estimates are bit for bit those
    of the same steps without ``emit``, in the same order (the same sequence numbers: a
    replay numbers them as the live fusion did)."""
    limit = 4 * HEAVY_WORK_EPOCHS
    n, b = len(NODES), heavy_budget(len(NODES))
    _, plain = _run(limit)
    emitted: list = []
    events: list = []  # per step: "step", then "emit" and "fix" as they happen
    mnls, step = tracked.mnls_solver.mnls, FusionCore.step
    monkeypatch.setattr(tracked.mnls_solver, "mnls", lambda *a, **k: events.append("fix") or mnls(*a, **k))
    monkeypatch.setattr(FusionCore, "step",
                        lambda *a, **k: events.append("step") or step(*a, **k))
    _, late = _run(limit, emit=lambda ests: events.append("emit") or emitted.extend(ests))
    segments = " ".join(events).split("step")[1:]  # the last step's: its flush
    for k, seg in enumerate(segments):  # a step's fixes after its last emission
        if any(e.snapshot is not None for e in late[k]):
            assert seg.rstrip().endswith("fix") and "emit" in seg, (k, seg)
    k_init = -(-n // b)  # the steps with an initialisation
    pub: dict[int, list] = collections.defaultdict(list)  # epoch: (estimate, emitted)
    for e in emitted:
        pub[e.epoch].append((e, True))
    for e in (e for s in late[:-1] for e in s):
        pub[e.epoch].append((e, False))
    seen: set[str] = set()
    snapshots = 0
    for k, epoch in enumerate(sorted(pub)):
        order = [e for e, _ in pub[epoch]]
        assert len(order) == n
        new = {e.node_id for e in order if e.position_m is not None} - seen
        if k < k_init:  # the initialisations: returned, after every emitted estimate
            assert len(new) == min(b, n - k * b)
            assert all(not was for e, was in pub[epoch] if e.node_id in new)
            assert all(was for e, was in pub[epoch] if e.node_id not in new)
        else:
            assert not new
        snap = [i for i, e in enumerate(order) if e.snapshot is not None]
        assert snap == list(range(n - len(snap), n)), (k, snap)  # last
        assert all(not pub[epoch][i][1] for i in snap)  # not emitted: after the fixes
        if snap:  # the others: emitted, before the fixes
            assert all(pub[epoch][i][1] for i in range(n - len(snap)))
        snapshots += len(snap)
        seen |= new
    assert seen == set(NODES) and snapshots >= 1 and emitted
    bare = lambda e: M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0))  # noqa: E731
    in_order = [e for epoch in sorted(pub) for e, _ in pub[epoch]] + late[-1]
    assert list(map(bare, in_order)) == [bare(e) for s in plain for e in s]


@pytest.mark.parametrize("limit", [None, 4 * HEAVY_WORK_EPOCHS])
def test_a_nodes_estimates_stay_oldest_first_when_one_waits_for_its_snapshot(limit):
    """A step every 4 epochs (4 epochs of each node in one batch, as after a stall): a node's
    first epoch gets a snapshot fix (it never had one) and is published after the fixes; its
    later epochs of the step wait with it, so in publishing order (the sequence numbers: one
    per estimate, 1, 2, ...; emitted ones in increasing order) every node's estimates are
    oldest first, as the epochs came."""
    emitted: list = []
    _, steps = _run(limit, emit=emitted.extend, every=4)
    seqs = [e.seq for e in emitted]
    assert seqs == sorted(seqs) and (emitted or limit is None)  # budgeted: inits held
    ests = sorted(emitted + [e for s in steps for e in s], key=lambda e: e.seq)
    assert [e.seq for e in ests] == list(range(1, len(NODES) * EPOCHS + 1))
    # the case at hand: a snapshot on a node-epoch with a later epoch of the node in its step
    e0 = min(e.epoch for e in ests)  # steps after epochs e0 + 3, e0 + 7, ...
    assert any(e.snapshot is not None and (e.epoch - e0) % 4 != 3 for e in ests)
    for nid in NODES:
        epochs = [e.epoch for e in ests if e.node_id == nid]
        assert epochs == sorted(set(epochs)) and len(epochs) == EPOCHS, (nid, epochs)


def test_the_latency_record_matches_what_was_published_when_steps_emit_early():
    """The live service's publishing (``stamp_published`` for what a step emits and for what
    it returns, as ``ServiceLoop.turn``) with steps that emit early in every way (several
    epochs per node, batches split by ``max_fixes_per_step``, held initialisations, pending
    snapshot fixes): the core's latency record is exactly the published estimates' latencies,
    in publishing order (each entry replaced once, none left from before the stamping)."""
    from diffpos_services.fusion.service import stamp_published

    core = FusionCore(_config(max_fixes_per_step=12), logger=quiet_logger())
    for a in ANCHORS:
        core.on_liveliness(a, True, T0 - PERIOD)
    published: list = []
    emits = 0

    def emit(ests):
        nonlocal emits
        emits += 1
        stamp_published(core, ests, published.append)

    for k, items in enumerate(_samples()):
        for rx, key, payload in items:
            core.on_sample(key, payload, rx)
        if k % 4 == 3:
            stamp_published(core, core.step(rx + 1000, limit=4 * HEAVY_WORK_EPOCHS, emit=emit),
                            published.append)
    stamp_published(core, core.flush(rx + 2000), published.append)
    assert len(published) == len(NODES) * EPOCHS and emits >= 4
    assert [e.seq for e in published] == list(range(1, len(published) + 1))
    assert list(core.latencies_ns) == [e.t_pub_wall_ns - e.t_input_wall_ns for e in published
                                       if e.t_input_wall_ns > 0]


def test_snapshots_have_a_credit_of_their_own_and_move_no_tracked_estimate(monkeypatch):
    """Budgeted steps of 8 epochs: after any step, the snapshots so far are at most one per
    SNAPSHOT_WORK_EPOCHS epochs solved (the credit), and they do happen (a new node is due at
    once). A snapshot never feeds the tracker: with a credit of one per epoch
    the snapshots differ, every tracked estimate (status, position, covariance) is identical
    bit for bit."""
    limit = 4 * HEAVY_WORK_EPOCHS
    _, steps = _run(limit)
    done = solved = 0
    for ests in steps[:-1]:
        solved += len(ests)
        done += sum(e.snapshot is not None for e in ests)
        assert done <= solved // SNAPSHOT_WORK_EPOCHS, (done, solved)
    assert done >= 1
    monkeypatch.setattr(tracked, "SNAPSHOT_WORK_EPOCHS", 1)
    _, many = _run(limit)
    assert sum(e.snapshot is not None for s in many for e in s) > done

    def tracked_only(run):  # (in publishing order: the rows with a snapshot fix last)
        return sorted(M.encode(msgspec.structs.replace(e, snapshot=None, t_pub_wall_ns=0,
                                                       seq=0)) for s in run for e in s)
    assert tracked_only(many) == tracked_only(steps)


@pytest.mark.parametrize("limit", [4 * HEAVY_WORK_EPOCHS, 5])
def test_replay_by_the_decision_record_reproduces_budgeted_steps(tmp_path, limit):
    """The steps' limits are in the decision record, so the replay makes the same budgeted
    decisions: every estimate bit for bit (a replay that solved without the limits would
    initialise every node in the first step). Limit 5 < the 8 nodes: a backlog is carried
    from step to step too."""
    path = tmp_path / "budget.mcap"
    with McapSink(path, library="test") as sink:
        core, _ = _run(limit, sink)
        sink.add_metadata("fusion_config", msgspec.to_builtins(core.config))
    r = replay(path)
    assert r.report["decisions"]["steps"] == EPOCHS
    c = r.report["compare"]
    assert c["only_live"] == c["only_replayed"] == 0 and c["status_agree"] == 1.0
    assert c["identical_positions"] == c["with_positions"] > 0
    bare = lambda e: M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0))  # noqa: E731
    assert sorted(map(bare, r.live_estimates)) == sorted(map(bare, r.estimates))


def test_step_cost_separates_the_fixed_and_the_per_epoch_cost():
    """Steps of varying size that cost exactly 3 ms + 0.7 ms per epoch: the fit finds both,
    and the epochs within a 20 ms budget are (20 - 3) / 0.7; the mean cost per epoch (the
    former rule) would allow only 20 / (3 / n + 0.7) for the usual n."""
    cost = StepCost()
    assert not cost.measured
    for n in [8, 50, 12, 8, 30, 50, 9, 17] * 3:
        cost.add(n, 3e6 + 0.7e6 * n)
    fixed, per = cost.model()
    assert fixed == pytest.approx(3e6, rel=1e-6) and per == pytest.approx(0.7e6, rel=1e-6)
    assert cost.epochs_within(20e6) == int(17 / 0.7)
    # equal sizes leave the split unknown: the mean per epoch, no fixed part (the old rule)
    same = StepCost()
    for _ in range(10):
        same.add(8, 8e6)
    assert same.model() == pytest.approx((0.0, 1e6))
    # noise that would make the per-epoch cost negative is clamped to MIN_SHARE of the mean
    noisy = StepCost()
    for n, t in [(10, 20e6), (40, 5e6), (10, 22e6), (40, 4e6)]:
        noisy.add(n, t)
    _, per = noisy.model()
    total_n, total_t = 100, 51e6
    assert per == pytest.approx(StepCost.MIN_SHARE * total_t / total_n, rel=0.05)


def test_the_loop_sizes_steps_by_the_fitted_cost_and_takes_more_when_behind():
    """ServiceLoop.step_limit: MIN_STEP_EPOCHS before any step was measured; then the epochs
    that fit SOLVE_BUDGET_S by the fitted fixed + per-epoch cost; BEHIND_BUDGET_S while the
    previous step left ready epochs (core.backlog > 0)."""
    import threading

    from diffpos_services.fusion import service as S
    from fusion_scene import fusion_config

    core = FusionCore(fusion_config(), logger=quiet_logger())
    loop = S.ServiceLoop(core, S._Inbox(core.config, threading.Event()), lambda e: None,
                         lambda d: None, quiet_logger())
    assert loop.step_limit() == S.MIN_STEP_EPOCHS
    for n in (8, 50, 12, 30, 20):
        loop.cost.add(n, 3e6 + 0.65e6 * n)
    assert loop.step_limit() == int((S.SOLVE_BUDGET_S * 1e9 - 3e6) / 0.65e6)
    core._ready.append(None)  # a ready epoch left over by the previous step: behind
    assert loop.step_limit() == int((S.BEHIND_BUDGET_S * 1e9 - 3e6) / 0.65e6)
    core._ready.clear()
    fixed = S.SOLVE_BUDGET_S * 1e9 * 1.2
    for _ in range(200):  # a fixed part above the budget: still the minimum step
        loop.cost.add(8, fixed + 1e6 * 8)
        loop.cost.add(16, fixed + 1e6 * 16)
    assert loop.step_limit() == S.MIN_MEASURED_STEP_EPOCHS


def test_a_fusion_behind_its_input_keeps_each_nodes_newest_epochs_in_rounds(tmp_path):
    """The live overload policy (max_backlog_s set; fusion.overload) on a real core fed
    a backlog: three epochs of eight nodes arrive between two steps of at most 5 epochs.

    - each step solves only the nodes' newest released epochs (the last BEHIND_KEEP_EPOCHS
      fed; the input's own epoch count is the reference), nothing older;
    - every released node-epoch is published or counted as superseded (none overloaded);
    - rounds: no node is solved twice before every other node with data was solved (between
      two steps that solve a node, the steps in between and those two solve all nodes), and
      per node the counts differ by at most one (queueing the released epochs in their
      release order, i.e. by node id, solved n0 and n1 twice as often);
    - a replay by the decision record gives the same estimates bit for bit.
    The same input stepped once per epoch with a limit of all nodes (a fusion that keeps up)
    supersedes nothing and gives the estimates of a fusion without the setting, bit for bit.
    Admission off (``admit_lag_s`` 1e9): this is the policy for placed nodes; nodes the
    tracker does not place keep every epoch with it on (the test after this one).
    """
    from diffpos_services.fusion.core import BEHIND_KEEP_EPOCHS

    every, limit, n_nodes = 3, 5, len(NODES)
    path = tmp_path / "behind.mcap"
    with McapSink(path, library="test") as sink:
        core, steps = _run(limit, sink, every=every, max_backlog_s=2.0, supersede_after_s=0.0,
                           admit_lag_s=1e9)
        sink.add_metadata("fusion_config", msgspec.to_builtins(core.config))
    live, flushed = steps[:-1], steps[-1]
    e0 = (T0 + 20_000_000) // PERIOD  # the first epoch fed (_samples)
    for i, ests in enumerate(live):
        newest = min(every * (i + 1), EPOCHS) - 1  # epochs fed before this step
        assert len(ests) == limit
        assert {e.epoch - e0 for e in ests} <= set(range(newest - BEHIND_KEEP_EPOCHS + 1,
                                                          newest + 1)), i
        assert len({e.node_id for e in ests}) == len(ests)  # one epoch per node and step
    n_published = sum(map(len, steps))
    assert core.rejected["superseded"] > 0 and not core.rejected.get("overloaded")
    assert n_published + core.rejected["superseded"] == EPOCHS * n_nodes
    solved_in = [{e.node_id for e in ests} for ests in live]
    for node in NODES:
        at = [i for i, s in enumerate(solved_in) if node in s]
        assert at, node
        for a, b in itertools.pairwise(at):
            assert set().union(*solved_in[a:b + 1]) == set(NODES), (node, a, b)
    counts = collections.Counter(e.node_id for ests in live for e in ests)
    assert max(counts.values()) - min(counts.values()) <= 1
    assert len(flushed) <= BEHIND_KEEP_EPOCHS * n_nodes
    r = replay(path)
    assert r.report["decisions"]["steps"] == len(live)
    bare = lambda e: M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0))  # noqa: E731
    assert sorted(map(bare, r.live_estimates)) == sorted(map(bare, r.estimates))
    # a backlog within supersede_after_s (the default 0.5 s): four epochs between steps that
    # take one node-epoch less than that, so the ready epochs span 0.3-0.4 s: worked off
    # without loss; with supersede_after_s 0 the same steps supersede
    lim = 4 * n_nodes - 1
    lossless, steps_l = _run(lim, every=4, max_backlog_s=2.0, admit_lag_s=1e9)
    assert not lossless.rejected.get("superseded") and not lossless.rejected.get("overloaded")
    assert sum(map(len, steps_l)) == EPOCHS * n_nodes
    eager, _ = _run(lim, every=4, max_backlog_s=2.0, supersede_after_s=0.0, admit_lag_s=1e9)
    assert eager.rejected.get("superseded")
    # keeping up: the setting changes nothing
    kept, plain = _run(n_nodes, max_backlog_s=2.0), _run(n_nodes)
    assert not kept[0].rejected.get("superseded") and not kept[0].rejected.get("overloaded")
    assert [list(map(bare, s)) for s in kept[1]] == [list(map(bare, s)) for s in plain[1]]


def test_a_step_behind_its_input_gives_no_snapshot_fix_to_a_placed_node(monkeypatch):
    """Budgeted steps that leave ready epochs (2 epochs of 8 nodes more per step, at most 5
    solved: behind; a snapshot credit of one per epoch solved) give no M-NLS snapshot fix to a node the tracker places (the fixes were ~18 % of
    an overloaded fusion's CPU; a node without a tracked position is not concerned: the fix
    is its only one). The tracked estimates are those of the same steps under the usual
    policy (a fix never feeds the tracker), which does give placed nodes fixes here."""
    monkeypatch.setattr(tracked, "SNAPSHOT_WORK_EPOCHS", 1)  # credit for a fix per epoch
    limit = 5
    _, steps = _run(limit, every=2)
    budgeted = [e for s in steps[:-1] for e in s]  # (the last: the unbudgeted flush)
    assert not [e for e in budgeted if e.position_m is not None and e.snapshot is not None]
    usual = tracked._snapshot_due
    monkeypatch.setattr(tracked, "_snapshot_due",
                        lambda *a: usual(*a[:5]))  # behind ignored: the usual policy
    _, ref = _run(limit, every=2)
    assert [e for s in ref[:-1] for e in s if e.position_m is not None and e.snapshot]

    def tracked_only(run):
        return sorted(M.encode(msgspec.structs.replace(e, snapshot=None, t_pub_wall_ns=0,
                                                       seq=0)) for s in run for e in s)
    assert tracked_only(steps) == tracked_only(ref)


@pytest.mark.parametrize("admit_lag_s", [0.25, 1e9])
def test_a_lagging_step_starts_only_the_minimum_of_new_tracks(tmp_path, admit_lag_s):
    """Eight epochs of the eight new nodes arrive between two steps of at most 30 epochs
    (``heavy_budget(30)`` = 3 > HEAVY_MIN_OPERATIONS): each step leaves 0.4 s or more of ready
    epochs. With ``admit_lag_s`` 0.25 s (the default) the step is lagging and initialises
    exactly HEAVY_MIN_OPERATIONS tracks, each from its node's newest epoch in the step (its
    older ones published without a position); with admission off (1e9 s) its share of the
    epochs, 3, each from the node's oldest epoch in the step (positions from then on). Either
    way every node-epoch is published (no policy drops here) and a replay by the decision
    record gives the same estimates bit for bit."""
    every, limit = 8, 30
    assert heavy_budget(limit) == 3 > HEAVY_MIN_OPERATIONS
    path = tmp_path / "admit.mcap"
    with McapSink(path, library="test") as sink:
        core, steps = _run(limit, sink, every=every, admit_lag_s=admit_lag_s)
        sink.add_metadata("fusion_config", msgspec.to_builtins(core.config))
    live = steps[:-1]  # (the last: the unbudgeted flush)
    assert [len(s) for s in live] == [limit] * (EPOCHS // every)
    expect = HEAVY_MIN_OPERATIONS if admit_lag_s < 1 else heavy_budget(limit)
    seen: set[str] = set()
    for k, ests in enumerate(live):
        new = _positioned(ests) - seen
        assert len(new) == expect, (k, new)
        for node in new:
            mine = sorted((e.epoch, e.position_m is not None) for e in ests if e.node_id == node)
            assert len(mine) > 1 and [p for _, p in mine] == (
                [False] * (len(mine) - 1) + [True] if admit_lag_s < 1 else [True] * len(mine))
        seen |= new
    assert sum(map(len, steps)) == EPOCHS * len(NODES)
    r = replay(path)
    bare = lambda e: M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0))  # noqa: E731
    assert sorted(map(bare, r.live_estimates)) == sorted(map(bare, r.estimates))


def test_a_behind_fusion_supersedes_no_epoch_of_a_node_without_a_confirmed_track(tmp_path):
    """Admission on (the default ``admit_lag_s``), the backlog of the test before (three
    epochs of the eight new nodes between steps of at most 5, ``supersede_after_s`` 0): a
    node's epochs up to its track's confirmation (first TRACKING) are all published (no
    track: they cost no update, published without a position; a new track: admission
    bounds them), and only confirmed tracks' older epochs are superseded; every released
    node-epoch is published or superseded; a replay by the decision record gives the same
    estimates bit for bit."""
    every, limit = 3, 5
    path = tmp_path / "unplaced.mcap"
    with McapSink(path, library="test") as sink:
        core, steps = _run(limit, sink, every=every, max_backlog_s=2.0, supersede_after_s=0.0)
        sink.add_metadata("fusion_config", msgspec.to_builtins(core.config))
    e0 = (T0 + 20_000_000) // PERIOD
    by_node = collections.defaultdict(list)
    for e in (e for s in steps for e in s):
        by_node[e.node_id].append((e.epoch - e0, e.status == "TRACKING"))
    for node, got in by_node.items():
        first = min((k for k, confirmed in got if confirmed), default=EPOCHS)
        assert {k for k, _ in got if k <= first} == set(range(min(first, EPOCHS - 1) + 1)), node
    assert not core.rejected.get("overloaded")  # (the confirmed tracks': the rule's tests)
    assert sum(map(len, steps)) + core.rejected.get("superseded", 0) == EPOCHS * len(NODES)
    assert any(c for got in by_node.values() for _, c in got)  # some tracks were confirmed
    r = replay(path)
    bare = lambda e: M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0))  # noqa: E731
    assert sorted(map(bare, r.live_estimates)) == sorted(map(bare, r.estimates))


def test_a_lagging_step_holds_the_newest_epoch_it_can_initialise_from():
    """``hold_inits(newest=True)`` chooses the nodes to start by the epoch the track will
    start from (the newest): node a, first in row order, has enough ranges only in its older
    epoch, so b (enough in its newest) is held instead; without ``newest`` a is held with
    both its epochs. (The ranges' values are not read: only how many there are.)"""
    from diffpos.alignment import PendingEpoch
    from diffpos.tracking.state import TrackerConfig
    bank = tracked.TrackBank(B)
    k = TrackerConfig().min_ranges_init

    def pe(node, epoch, n):
        return PendingEpoch(node, epoch, 0, {f"uav{j}": None for j in range(n)})
    epochs = [pe("a", 10, k), pe("b", 10, k), pe("a", 11, k - 1), pe("b", 11, k)]
    now, later = bank.hold_inits(epochs, 1, newest=True)
    assert [(e.node_id, e.epoch) for e in later] == [("b", 11)]
    assert [(e.node_id, e.epoch) for e in now] == [("a", 10), ("b", 10), ("a", 11)]
    now, later = bank.hold_inits(epochs, 1)
    assert [(e.node_id, e.epoch) for e in later] == [("a", 10), ("a", 11)]


def _by_node_epoch(steps) -> dict:
    return {(e.node_id, e.epoch): (e.status, e.position_m, e.floor_index)
            for ests in steps for e in ests}


def test_unbounded_steps_make_the_estimates_independent_of_the_step_cadence():
    """FusionConfig.bounded_steps False (lockstep emulate): the service loop asks for every
    ready epoch (limit None) before and after its step cost is measured, and the estimates are
    the same bit for bit whether the fusion steps after every epoch or after every third (a
    loaded machine: more epochs ready per step). With the live bound (a limit per step) the
    same two cadences start tracks at other epochs, i.e. the estimates depend on timing: what
    the setting removes."""
    import threading

    from diffpos_services.fusion import service as S

    core = FusionCore(_config(bounded_steps=False), logger=quiet_logger())
    loop = S.ServiceLoop(core, S._Inbox(core.config, threading.Event()), lambda e: None,
                         lambda d: None, quiet_logger())
    assert loop.step_limit() is None
    for n in (8, 50, 12):
        loop.cost.add(n, 3e6 + 0.65e6 * n)
    assert loop.step_limit() is None
    assert FusionCore(_config(), logger=quiet_logger()).config.bounded_steps  # the default
    one, three = (_by_node_epoch(_run(None, every=k)[1]) for k in (1, 3))
    assert len(one) == len(NODES) * EPOCHS
    assert one == three
    bounded = [_by_node_epoch(_run(2 * HEAVY_WORK_EPOCHS, every=k)[1]) for k in (1, 3)]
    assert bounded[0] != bounded[1]
