"""The fusion's row-parallel pool (services/diffpos_services/fusion/workers.py) without
processes: the shares (contiguous, cover every row, balanced), the row slicing and its
inverse, and a whole replay (mnls + tracker, synthetic recording) with an in-process stand-in
for the worker pipes (every message pickled both ways, as over a real pipe) that must give
the same estimates, bit for bit, as the plain fusion; a worker that dies or raises loses
nothing (its share is computed locally, the failure counted). The real processes are
tests/system/test_fusion_workers_process.py."""

from __future__ import annotations

import argparse
import collections
import dataclasses
import itertools
import os
import pickle
import time

import msgspec
import numpy as np
import pytest
from diffpos_services.cli import fusion as cmd_fusion
from diffpos_services.cli import replay as cmd_replay
from diffpos_services.errors import ConfigError
from diffpos_services.fusion import rows as R
from diffpos_services.fusion import worker_proc
from diffpos_services.fusion import workers as W
from diffpos_services.fusion.config import DEFAULT_WORKERS, FusionConfig
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_synthetic_recording
from diffpos_services.wire import messages as M

from diffpos.scenario import default_scenario
from diffpos.tracking.state import TrackerState
from diffpos.tracking.tracker import init_state


def test_cli_workers_default_value_and_validation():
    """``diffpos fusion --workers N`` (default 1, in the help, 0 rejected naming the field)
    and ``diffpos replay --workers N`` (an override; default: the recorded setting)."""
    p = argparse.ArgumentParser()
    cmd_fusion.add_arguments(p)
    cfg = lambda *a: cmd_fusion.config_from_args(p.parse_args(list(a)), default_scenario())  # noqa: E731
    assert DEFAULT_WORKERS == 1 == FusionConfig().workers == cfg().workers
    assert cfg("--workers", "2").workers == 2
    assert "--workers" in p.format_help()
    with pytest.raises(ConfigError, match="workers"):
        cfg("--workers", "0")
    r = argparse.ArgumentParser()
    cmd_replay.add_arguments(r)
    assert cmd_replay._overrides(r.parse_args(["x.mcap", "--workers", "3"]))["workers"] == 3
    assert "workers" not in cmd_replay._overrides(r.parse_args(["x.mcap"]))


def test_share_bounds_cover_contiguous_and_balanced():
    """Brute-force properties over random costs: the slices are non-empty, contiguous, in
    order and cover every row; no share costs more than total/n + the largest row cost."""
    rng = np.random.default_rng(0)
    for _ in range(300):
        b = int(rng.integers(1, 40))
        cost = np.where(rng.random(b) < 0.2, W.INIT_COST, 1.0)
        n = int(rng.integers(1, 5))
        sl = R.share_bounds(cost, n)
        assert 1 <= len(sl) <= n
        assert sl[0].start == 0 and sl[-1].stop == b
        assert all(s.stop > s.start for s in sl)
        assert all(a.stop == c.start for a, c in itertools.pairwise(sl))
        assert max(cost[s].sum() for s in sl) <= cost.sum() / n + cost.max() + 1e-9
        w = rng.uniform(0.25, 4.0, n)  # speeds: share k's cost ~ total * w_k / sum(w)
        sl = R.share_bounds(cost, n, w)
        assert sl[0].start == 0 and sl[-1].stop == b
        assert all(a.stop == c.start for a, c in itertools.pairwise(sl))
        ends = np.cumsum(cost)[[s.stop - 1 for s in sl[:-1]]]
        targets = cost.sum() * np.cumsum(w)[:-1] / w.sum()
        # every cut is the first row reaching its target: within one row's cost after it
        assert all(np.any((targets <= e + 1e-9) & (e < targets + cost.max() + 1e-9))
                   for e in ends)


def test_take_and_concat_rows_are_inverse():
    st = init_state(7, default_scenario().building)
    st = dataclasses.replace(st, mean=np.random.default_rng(1).normal(size=st.mean.shape))
    args = (st, np.arange(7.0), None, 3.5)
    parts = [R.take_rows(args, s) for s in R.share_bounds(np.ones(7), 3)]
    back = R.concat_rows(parts)
    assert back[2] is None and back[3] == 3.5
    assert np.array_equal(back[1], args[1])
    for f in TrackerState.__dataclass_fields__:
        assert getattr(back[0], f).tobytes() == getattr(st, f).tobytes(), f


class _Pipe:
    """A worker's pipe, in process: the request is pickled, run by the worker's task table
    and the reply pickled back; ``fail``: "died" (EOF on receive) or "error" (an error
    reply, as the worker sends when its task raises)."""

    def __init__(self, model, fail: str | None = None, after: int = 0) -> None:
        self.model, self.fail, self.after, self.n = model, fail, after, 0
        self.replies: collections.deque = collections.deque()  # answered in order
        self.slim = 0
        self.kinds: list[str] = []

    def send(self, msg) -> None:
        kind, args = pickle.loads(pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL))
        self.n += 1
        self.kinds.append(kind)
        if kind == "update":  # how many shares crossed without their SNR cache fields
            self.slim += args[0].snr_node is None
        if self.fail == "error" and self.n > self.after:
            reply = ("err", "Traceback: injected", 0.0)
        else:
            reply = ("ok", worker_proc.TASKS[kind](self.model, *args), 0.001)
        self.replies.append(pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL))

    def send_bytes(self, payload) -> None:  # what RowPool writes: the pickled request
        self.send(pickle.loads(payload))

    def poll(self, timeout=None) -> bool:
        return True

    def recv(self):
        if self.fail == "died" and self.n > self.after:
            raise EOFError
        return pickle.loads(self.replies.popleft())

    def close(self) -> None:
        pass


def _replay(path, monkeypatch, fail=None, after=0, reuse_off=False, prime=None):
    """Replay with a 2-way pool whose worker is a :class:`_Pipe` (``fail="none"``: the plain
    fusion); every call is split (MIN_PARALLEL_COST 0); ``reuse_off``: the tracker's SNR
    reuse margins 0 (the slim state crosses the pipe); ``prime(pool)`` sets what the pool has
    learned before the first call. Returns (estimates as bytes, pool)."""
    pools = []

    def fake_start(core, log=None, **_):
        if reuse_off:
            core.bank.config = dataclasses.replace(core.bank.config, snr_reuse_m=0.0,
                                                   snr_reuse_anchor_m=0.0)
        if fail == "none":
            return None
        pool = W.RowPool(1, (core.building, core.model[1], core.config.window_height_m,
                             core.config.first_floor_z_m))
        pool.pipe = _Pipe(pool.model, fail, after)  # kept: close() forgets the slot's
        pool._slots = [W._Slot(conn=pool.pipe, ready=True, pid=-1)]
        pool._start = lambda s: setattr(s, "conn", None)  # "restart": the slot stays empty
        if prime is not None:
            prime(pool)
        core.bank.pool = pool
        pools.append(pool)
        return pool

    # the replay starts a pool (imports start_workers) only for more than one process
    monkeypatch.setattr(W, "start_workers", fake_start)
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    monkeypatch.setattr(W, "MIN_PARALLEL_COST", 0.0)
    r = replay(path, method="mnls", use_decisions=False, overrides={"workers": 2})
    return [M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0)) for e in r.estimates], \
        (pools[0] if pools else None)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("workers") / "syn.mcap"
    write_synthetic_recording(path, n_anchors=6, n_nodes=6, duration_s=1.5, seed=11)
    return path


@pytest.mark.parametrize("reuse_off", [False, True])
def test_split_replay_equals_plain_bit_for_bit(recording, monkeypatch, reuse_off):
    """Split (every call) = plain, with the default SNR reuse (the whole state crosses) and
    with reuse off (the slim state: the SNR cache fields stay with the caller)."""
    plain, _ = _replay(recording, monkeypatch, fail="none", reuse_off=reuse_off)
    split, pool = _replay(recording, monkeypatch, reuse_off=reuse_off)
    assert len(plain) == 6 * 15
    assert split == plain
    assert pool.calls["split"] > 0 and pool.calls["rows_sent"] > 0 and not pool.failures
    assert (pool.pipe.slim > 0) == reuse_off
    # the snapshot fixes went to the worker, not waited for before the tracker's round
    assert pool.calls["submitted"] > 0 and "mnls" in pool.pipe.kinds
    assert not pool._slots[0].pending  # every reply consumed


def test_split_replay_equals_plain_while_a_left_out_worker_is_measured_again(recording,
                                                                             monkeypatch):
    """A pool that starts with a bad sample learned (latency at its cap, speed 1/4: the worker's
    share of every call of the 6-node replay is empty) regresses towards its priors
    (``RowPool._forget``) until the worker gets rows again; whichever split each call had,
    the estimates are those of the plain fusion, bit for bit."""
    def bad_sample(pool):
        pool.latency_s, pool.speed = W.LATENCY_MAX_S, 0.25
        pool._unit_s["update"] = 0.001  # 50 update rows of latency: more than a call has

    plain, _ = _replay(recording, monkeypatch, fail="none")
    split, pool = _replay(recording, monkeypatch, prime=bad_sample)
    assert split == plain
    assert pool.calls["forgot"] > 0 and pool.calls["rows_sent"] > 0 and not pool.failures
    # the worker got update shares again, and the regression stopped once it did
    assert "update" in pool.pipe.kinds and pool.calls["forgot"] < pool.calls["split"]


def test_preloaded_bounds_count_the_work_a_worker_already_has():
    """Brute-force properties over random costs and preloads: exactly one slice per sharer,
    contiguous, in order, covering every row; no sharer's share exceeds its weight's part of
    the total less its preload by more than one row's cost, one whose preload is above its
    part gets no rows; no preload = :func:`share_bounds`' cuts."""
    rng = np.random.default_rng(3)
    for _ in range(300):
        b = int(rng.integers(1, 40))
        cost = np.where(rng.random(b) < 0.2, W.INIT_COST, 1.0)
        n = int(rng.integers(1, 4))
        w = [1.0, *rng.uniform(0.5, 2.0, n - 1)]
        pre = [0.0, *rng.choice([0.0, 5.0, 30.0, 500.0], n - 1)]
        sl = R.preloaded_bounds(cost, w, pre)
        assert len(sl) == n and sl[0].start == 0 and sl[-1].stop == b
        assert all(a.stop == c.start for a, c in itertools.pairwise(sl))
        part = (cost.sum() + sum(pre)) * np.asarray(w) / sum(w)
        for k, s_ in enumerate(sl):  # nobody given more than one row above its part
            assert cost[s_].sum() <= max(part[k] - pre[k], 0.0) + cost.max() + 1e-9
            if pre[k] >= part[k]:
                assert s_.stop == s_.start
        nonempty = [s_ for s_ in R.preloaded_bounds(cost, w, [0.0] * n) if s_.stop > s_.start]
        assert nonempty == R.share_bounds(cost, n, w)


def _echo_pool(monkeypatch) -> W.RowPool:
    """A pool of one in-process worker (a pipe answering in order) whose task ``echo``
    doubles its rows; every call is split (no minimum cost)."""
    model = (default_scenario().building, None, 1.0, 0.0)
    pool = W.RowPool(1, model)
    pool._slots = [W._Slot(conn=_Pipe(model), ready=True, pid=-1)]
    monkeypatch.setitem(worker_proc.TASKS, "echo", lambda m, x: x * 2)
    monkeypatch.setattr(W, "MIN_PARALLEL_COST", 0.0)
    return pool


def test_a_submitted_request_and_a_later_share_are_answered_in_order(monkeypatch):
    """A request submitted (deferred), then a split call: the request goes to the worker
    after the call's share, counted as work the worker already has (its share shrinks);
    the replies land in their own requests, in order."""
    pool = _echo_pool(monkeypatch)
    p = pool.submit("echo", (np.arange(3.0),), 3.0)
    assert not p.done and not p.sent and p.cost == 3.0 and not pool._slots[0].pending
    out = pool.map_rows("echo", (np.arange(10.0),), np.ones(10))
    assert np.array_equal(out, np.arange(10.0) * 2)
    # sent after the share (a big share to a busy worker would block the sender)
    assert p.sent and pool._slots[0].pending[0] is p and pool._slots[0].conn.kinds == [
        "echo", "echo"]
    assert np.array_equal(pool.result(p), np.arange(3.0) * 2) and p.done
    # parts (10 + 3) / 2 = 6.5 each: the caller's cut after the row reaching 6.5 (7 rows),
    # the worker 3 rows on top of its 3 of preload (without the preload: 5)
    assert pool.calls["rows_sent"] == 3 and not pool._slots[0].pending


def test_a_request_never_collected_leaves_no_stale_reply(monkeypatch):
    """A submitted request whose result is never asked for (the fusion's step raised after a
    snapshot fix was sent and before it was collected, e.g. a publish of the estimates
    emitted meanwhile failed): later calls still get their own replies; the abandoned reply
    lands in its own request."""
    pool = _echo_pool(monkeypatch)
    lost = pool.submit("echo", (np.arange(3.0),), 3.0)
    pool.map_rows("echo", (np.arange(10.0),), np.ones(10))  # sends it after the share
    assert lost.sent and not lost.done
    p = pool.submit("echo", (np.full(2, 5.0),), 2.0)
    out = pool.map_rows("echo", (np.arange(8.0) + 100,), np.ones(8))
    assert np.array_equal(out, (np.arange(8.0) + 100) * 2)
    assert np.array_equal(pool.result(p), np.full(2, 10.0))
    assert lost.done and np.array_equal(lost.value, np.arange(3.0) * 2)
    assert not pool._slots[0].pending and pool.calls["rows_sent"] > 0


@pytest.mark.parametrize("fail", ["died", "error"])
def test_failed_worker_loses_no_estimate(recording, monkeypatch, fail):
    """The worker fails from its 4th request on: the shares are computed locally, the
    estimates are those of the plain fusion, the failure is counted (a dead worker once:
    its slot is restarted, here left empty; one that raised stays and fails again)."""
    plain, _ = _replay(recording, monkeypatch, fail="none")
    split, pool = _replay(recording, monkeypatch, fail=fail, after=3)
    assert split == plain
    assert pool.failures[fail] >= 1
    if fail == "died":
        assert pool.failures[fail] == 1 and pool._slots[0].restarts == 1


class _QueuedPipe:
    """A worker's pipe that keeps every unread reply in order, as a real pipe does (a reply
    not received by one call is what the next call reads); ``recv`` raises once on
    ``bad_reply`` (the reply read but not decoded)."""

    def __init__(self, model) -> None:
        self.model, self.replies, self.bad_reply = model, [], False

    def send(self, msg) -> None:  # as Connection.send: pickled whole, then written
        self.send_bytes(pickle.dumps(msg))

    def send_bytes(self, payload) -> None:
        kind, args = pickle.loads(payload)
        self.replies.append(pickle.dumps(("ok", worker_proc.TASKS[kind](self.model, *args), 0.001)))

    def poll(self, timeout=None) -> bool:
        return bool(self.replies)

    def recv(self):
        reply = self.replies.pop(0)
        if self.bad_reply:
            self.bad_reply = False
            raise pickle.UnpicklingError("injected")
        return pickle.loads(reply)

    def close(self) -> None:
        pass


def test_unpicklable_share_or_reply_leaves_no_stale_reply(monkeypatch):
    """Three sharers; call 1's last share cannot be pickled (a lambda in an object array),
    call 2's first worker reply cannot be decoded: each such share is computed locally and
    every later call gets its own rows back (before the fix, call 1 raised after the first
    worker had its request, and call 2 read call 1's reply from that worker's pipe)."""
    monkeypatch.setitem(worker_proc.TASKS, "echo", lambda model, x: x)
    pool = W.RowPool(1, (None, None, 3.0, 0.0))
    pipes = [_QueuedPipe(pool.model), _QueuedPipe(pool.model)]
    pool._slots = [W._Slot(conn=p, ready=True, pid=-1) for p in pipes]

    def call(x):
        return pool.map_rows("echo", (x,), np.ones(len(x)), local=lambda a: a.copy())

    x1 = np.arange(30.0).astype(object)
    x1[-1] = lambda: None  # the last share (the second worker's) cannot be pickled
    out = call(x1)
    assert list(out[:-1]) == list(range(29)) and out[-1] is x1[-1]
    assert pool.failures["error"] == 1 and not any(p.replies for p in pipes)
    pipes[0].bad_reply = True
    x2 = np.arange(100.0, 130.0)
    assert np.array_equal(call(x2), x2)
    assert pool.failures["error"] == 2 and not any(p.replies for p in pipes)
    x3 = np.arange(200.0, 230.0)
    assert np.array_equal(call(x3), x3)
    assert pool.failures["error"] == 2 and pool.calls["split"] == 3


def test_call_without_rows_stays_local(monkeypatch):
    """No rows (even with every call split: MIN_PARALLEL_COST 0): computed here, nothing
    sent (there is no share to give; before, the empty share list raised IndexError)."""
    monkeypatch.setitem(worker_proc.TASKS, "echo", lambda model, x: x)
    monkeypatch.setattr(W, "MIN_PARALLEL_COST", 0.0)
    pool = W.RowPool(1, (None, None, 3.0, 0.0))
    pipe = _QueuedPipe(pool.model)
    pool._slots = [W._Slot(conn=pipe, ready=True, pid=-1)]
    out = pool.map_rows("echo", (np.empty((0, 3)),), np.empty(0), local=lambda a: a + 1.0)
    assert out.shape == (0, 3) and pool.calls["local"] == 1 and not pipe.replies
    two = pool.map_rows("echo", (np.ones((2, 3)),), np.ones(2), local=lambda a: a + 1.0)
    assert np.array_equal(two, np.array([[2.0] * 3, [1.0] * 3]))  # split: row 1 echoed


def test_a_failed_start_stops_the_workers_already_started(monkeypatch):
    """RowPool(3): the second worker cannot be started (e.g. no file descriptor left): the
    first one is stopped before the error reaches the caller (who has no pool to close)."""
    started = []

    class Proc:
        def __init__(self):
            self.killed = False

        def kill(self):
            self.killed = True

        def join(self, timeout=None):
            pass

        def close(self):
            pass

    def start(self, s):
        if started:
            raise OSError(24, "Too many open files")
        started.append(Proc())
        s.proc, s.conn, s.pid = started[-1], _QueuedPipe(None), -1

    monkeypatch.setattr(W.RowPool, "_start", start)
    with pytest.raises(OSError, match="Too many"):
        W.RowPool(3, (None, None, 3.0, 0.0))
    assert len(started) == 1 and started[0].killed


def test_replay_never_starts_more_processes_than_the_machine_has_cores(recording, monkeypatch):
    """A recording made with 64 workers replays with at most ``os.cpu_count()`` processes
    (the estimates are the same for any count); the pool is closed after the replay."""
    made, closed = [], []

    class _Pool:
        building = None  # not the core's: every call computed locally

        def __init__(self, n, model, logger=None) -> None:
            made.append(n)

        def wait_ready(self, timeout_s=300.0) -> int:
            return 0

        def close(self, timeout_s=5.0) -> None:
            closed.append(True)

    monkeypatch.setattr(W, "RowPool", _Pool)
    monkeypatch.setattr(os, "cpu_count", lambda: 3)
    r = replay(recording, method="mnls", use_decisions=False, overrides={"workers": 64})
    assert made == [3] and closed == [True] and len(r.estimates) == 6 * 15


class _LatePipe(_QueuedPipe):
    """A worker's pipe whose replies carry the worker's clock at the task's end as a real
    worker's do: ``late_s`` after the request was written (a worker that needs that long
    beyond its task: transfer, wake-up), task time ``busy_s``."""

    def __init__(self, model, late_s: float, busy_s: float) -> None:
        super().__init__(model)
        self.late_s, self.busy_s, self.rows = late_s, busy_s, []

    def send_bytes(self, payload) -> None:
        kind, args = pickle.loads(payload)
        self.rows.append(len(args[0]))
        done = time.perf_counter() + self.late_s + self.busy_s
        self.replies.append(pickle.dumps(("ok", worker_proc.TASKS[kind](self.model, *args), self.busy_s,
                                          done)))


def test_worker_latency_is_learned_and_moves_rows_to_the_caller(monkeypatch):
    """A worker whose shares end 20 ms after the caller's own share starts, beyond a 1 ms
    task: the learned latency converges to ~19 ms (EWMA from 0: within 1 ms after 30 calls),
    each share is the one :func:`preloaded_bounds` gives with that latency as the worker's
    preload (in its update rows: 1 ms each), and the rows come back in order; replies without
    the clock (older workers) leave the latency at 0 and the split as before."""
    monkeypatch.setitem(worker_proc.TASKS, "echo", lambda model, x: x)
    monkeypatch.setattr(W, "MIN_PARALLEL_COST", 0.0)
    monkeypatch.setattr(W.RowPool, "_learn", lambda self, *a: None)  # speed stays 1
    pool = W.RowPool(1, (None, None, 3.0, 0.0))
    pipe = _LatePipe(pool.model, 0.020, 0.001)
    pool._slots = [W._Slot(conn=pipe, ready=True, pid=-1)]
    pool._unit_s["update"] = 0.001
    x = np.arange(200.0)
    for _ in range(30):
        expect = R.preloaded_bounds(np.ones(x.size), [1.0, 1.0], [0.0, pool.latency_cost()])
        assert np.array_equal(pool.map_rows("echo", (x,), np.ones(x.size),
                                            local=lambda a: a.copy()), x)
        assert pipe.rows[-1] == expect[1].stop - expect[1].start
    assert pool.latency_s == pytest.approx(0.019, abs=0.001)
    assert pipe.rows[0] == 100 and pipe.rows[-1] == pytest.approx((200 - 19) / 2, abs=1.5)
    assert pool.calls["latency_n"] == 30
    plain = _echo_pool(monkeypatch)  # 3-field replies: no clock, no latency
    plain.map_rows("echo", (x,), np.ones(x.size))
    assert plain.latency_s == 0.0 and plain.calls["rows_sent"] == 100


def test_a_worker_left_out_by_a_bad_sample_is_measured_again(monkeypatch):
    """A pool that learned in a bad moment (latency at its cap, speed 1/4) and now gets
    40-row calls: by those estimates the idle worker's share is empty (40 x 1/4 < 50 rows of
    latency), and the estimates came only from shares, so before ``_forget`` it got no row
    again for the rest of the run. Now each such call moves both one EWMA step towards the
    priors: a fast worker (no latency) gets rows again within a few calls and the learned
    latency converges back to ~0; a worker that really is 30 ms late keeps a latency of that
    order (its samples pull it back up) and gets only the small shares that balance it."""
    monkeypatch.setitem(worker_proc.TASKS, "echo", lambda model, x: x)
    monkeypatch.setattr(W, "MIN_PARALLEL_COST", 0.0)
    monkeypatch.setattr(W.RowPool, "_learn", lambda self, *a: None)  # speed: only _forget
    x = np.arange(40.0)
    for late_s in (0.0, 0.030):
        pool = W.RowPool(1, (None, None, 3.0, 0.0))
        pipe = _LatePipe(pool.model, late_s, 0.001)
        pool._slots = [W._Slot(conn=pipe, ready=True, pid=-1)]
        pool._unit_s["update"] = 0.001
        pool.latency_s, pool.speed = W.LATENCY_MAX_S, 0.25
        assert R.preloaded_bounds(np.ones(x.size), [1.0, 0.25], [0.0, 50.0])[1] == slice(40, 40)
        sent = []
        for _ in range(60):
            expect = R.preloaded_bounds(np.ones(x.size), [1.0, pool.speed],
                                        [0.0, pool.latency_cost()])[1]
            assert np.array_equal(pool.map_rows("echo", (x,), np.ones(x.size),
                                                local=lambda a: a.copy()), x)
            sent.append(pool.calls["rows_sent"])
            assert sent[-1] - (sent[-2] if len(sent) > 1 else 0) == expect.stop - expect.start
        if late_s == 0.0:  # (speed is learned from shares; _learn is off here)
            assert sent.index(next(v for v in sent if v > 0)) <= 10
            assert pool.latency_s < 0.002 and pipe.rows[-1] >= 10
        else:
            assert 0.005 < pool.latency_s <= W.LATENCY_MAX_S
            assert pipe.rows and max(pipe.rows) <= 10  # balanced against ~30 rows of delay
        assert pool.calls["forgot"] > 0
