"""The fusion's worker processes for real (services/diffpos_services/fusion/workers.py):
a replay with ``workers=2`` gives the bytes of ``workers=1``; a worker killed with SIGKILL or
one that raises loses nothing (its share computed by the caller, the failure counted, the
dead one restarted and used again); SIGKILL of the process that owns the pool leaves no
worker behind. Process exits are awaited on pidfds, never slept for."""

from __future__ import annotations

import json
import os
import pickle
import select
import signal
import subprocess
import sys
import textwrap
import time

import msgspec
import numpy as np
import pytest
from diffpos_services.fusion import rows as R
from diffpos_services.fusion import shm
from diffpos_services.fusion import workers as W
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_synthetic_recording
from diffpos_services.wire import messages as M

from diffpos.scenario import default_scenario
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import init_state

pytestmark = pytest.mark.system

SC = default_scenario()
MODEL = (SC.building, SC.radio, SC.building.window_height_m, SC.building.first_floor_z_m)


def _gone(pids: list[int], timeout_s: float) -> list[int]:
    """The processes of ``pids`` still running after ``timeout_s`` [s] (zombies count as
    gone), awaited on their pidfds."""
    fds = {}
    for pid in pids:
        try:
            fds[os.pidfd_open(pid)] = pid
        except ProcessLookupError:
            continue
    poller = select.poll()
    for fd in fds:
        poller.register(fd, select.POLLIN)
    left = dict(fds)
    deadline = time.monotonic() + timeout_s
    while left and time.monotonic() < deadline:  # poll returns as soon as one exits
        for fd, _ in poller.poll(max(deadline - time.monotonic(), 0) * 1000):
            poller.unregister(fd)
            left.pop(fd, None)
    for fd in fds:
        os.close(fd)
    return sorted(left.values())


def _estimates(path, workers, monkeypatch=None, on_split=None):
    pools = []
    if monkeypatch is not None:
        real = W.start_workers

        def start(core, log=None, **kw):
            pool = real(core, log, **kw)
            pools.append(pool)
            if on_split is not None and pool is not None:
                orig = pool.map_rows

                def map_rows(*a, **k):
                    on_split(pool)
                    return orig(*a, **k)

                pool.map_rows = map_rows
            return pool

        monkeypatch.setattr(W, "start_workers", start)
    r = replay(path, method="mnls", overrides={"workers": workers}, use_decisions=False)
    out = [M.encode(msgspec.structs.replace(e, t_pub_wall_ns=0)) for e in r.estimates]
    return out, (pools[0] if pools else None)


def test_replay_two_workers_equals_one_and_a_killed_worker_loses_nothing(tmp_path,
                                                                           monkeypatch):
    path = tmp_path / "syn.mcap"
    write_synthetic_recording(path, n_anchors=6, n_nodes=40, duration_s=1.5, seed=4)
    one, _ = _estimates(path, 1)
    two, pool = _estimates(path, 2, monkeypatch)
    assert len(one) == 40 * 15 and two == one
    assert pool.calls["split"] > 0 and not pool.failures
    # the shares crossed through the worker's mapped file (Linux: memfd_create)
    assert pool.calls["via_shm"] >= pool.calls["split"] or not hasattr(os, "memfd_create")
    calls = []

    def kill_on_third(p):  # SIGKILL the worker before the 3rd call (its pipe then breaks)
        calls.append(1)
        if len(calls) == 3:
            os.kill(p.pids[0], signal.SIGKILL)

    killed, pool = _estimates(path, 2, monkeypatch, kill_on_third)
    assert killed == one
    assert pool.failures["died"] == 1 and pool._slots[0].restarts == 1


def _update_args(n):
    rng = np.random.default_rng(2)
    b = SC.building
    anchors = np.broadcast_to(np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0],
                                        [0.0, -7.0, 4.0], [15.0, -20.0, 1.0]]), (n, 4, 3))
    r = rng.uniform(8, 30, (n, 4))
    return (init_state(n, b), anchors, r, np.full((n, 4), 0.2), np.ones((n, 4), bool),
            np.zeros(n, np.int64), None)


def test_dead_worker_restarted_and_raising_worker_kept():
    cfg = TrackerConfig()
    args = _update_args(40)
    ref = R.run_update(SC.building, *args, cfg, None)
    with W.RowPool(2, MODEL) as pool:
        assert pool.wait_ready(120) == 1
        old = pool.pids[0]
        fds = sorted(os.listdir("/proc/self/fd"))
        os.kill(old, signal.SIGKILL)
        assert _gone([old], 10) == []
        got = pool.map_rows("update", args, np.ones(40), shared=(cfg, None))
        assert pool.failures["died"] == 1
        assert pool.wait_ready(120) == 1 and pool.pids[0] != old  # restarted, warmed up
        assert len(os.listdir("/proc/self/fd")) == len(fds)  # no descriptor leaked
        again = pool.map_rows("update", args, np.ones(40), shared=(cfg, None))
        assert pool.calls["split"] == 2 and pool.failures["died"] == 1
        for out in (got, again):
            for f in ref[1].__dataclass_fields__:
                assert getattr(out[1], f).tobytes() == getattr(ref[1], f).tobytes(), f
        # a task that raises in the worker: the caller computes the share, the worker stays
        pid = pool.pids[0]
        here = pool.map_rows("fail", (np.arange(40),), np.ones(40), local=lambda a: a * 2)
        assert np.array_equal(here, np.arange(40) * 2)
        assert pool.failures["error"] == 1 and pool.pids == [pid]


def test_sigkill_of_the_owner_leaves_no_worker(tmp_path):
    script = tmp_path / "owner.py"
    script.write_text(textwrap.dedent("""
        import json, sys, threading
        from diffpos.scenario import default_scenario
        from diffpos_services.fusion.workers import RowPool

        if __name__ == "__main__":
            sc = default_scenario()
            b = sc.building
            pool = RowPool(3, (b, sc.radio, b.window_height_m, b.first_floor_z_m))
            print(json.dumps({"ready": pool.wait_ready(120), "pids": pool.pids}), flush=True)
            threading.Event().wait()
    """))
    p = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        info = json.loads(p.stdout.readline())
        assert info["ready"] == 2 and len(info["pids"]) == 2
        kids = [int(c) for t in os.listdir(f"/proc/{p.pid}/task")
                for c in open(f"/proc/{p.pid}/task/{t}/children").read().split()]
        assert set(info["pids"]) <= set(kids)
        os.kill(p.pid, signal.SIGKILL)
        p.wait(10)
        assert _gone(kids, 10) == [], "workers (or multiprocessing's tracker) outlived"
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(10)


def _shm_names() -> set[str]:
    return set(os.listdir("/dev/shm")) if os.path.isdir("/dev/shm") else set()


def test_sigkill_of_the_owner_before_its_workers_started_leaves_no_shared_memory(tmp_path):
    """The owner SIGKILLed right after making its pool (its workers still importing, their
    regions not mapped yet): nothing of it is left in /dev/shm (a named file there would
    hold its 2 x 8 MB of RAM until reboot) and its workers are gone."""
    script = tmp_path / "owner.py"
    script.write_text(textwrap.dedent("""
        import json, os, signal
        from diffpos.scenario import default_scenario
        from diffpos_services.fusion.workers import RowPool

        if __name__ == "__main__":
            sc = default_scenario()
            b = sc.building
            pool = RowPool(3, (b, sc.radio, b.window_height_m, b.first_floor_z_m))
            print(json.dumps({"pids": pool.pids, "shm": [s.shm is not None
                                                        for s in pool._slots]}), flush=True)
            os.kill(os.getpid(), signal.SIGKILL)
    """))
    before = _shm_names()
    p = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True,
                         start_new_session=True)
    try:
        info = json.loads(p.stdout.readline())
        p.wait(30)
        assert p.returncode == -signal.SIGKILL
        assert _gone(info["pids"], 10) == []
        assert info["shm"] == [True, True] or not sys.platform.startswith("linux")
        left = sorted(n for n in _shm_names() - before if "diffpos" in n)
        assert left == [], f"left in /dev/shm: {left}"
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait(10)


def _region_bytes(obj) -> int:
    """Bytes a region needs for ``obj`` (its protocol-5 buffers, each 64-byte aligned)."""
    bufs = []
    pickle.dumps(obj, protocol=5, buffer_callback=bufs.append)
    return sum(-(-b.raw().nbytes // 64) * 64 for b in bufs)


def _fields_bytes(x) -> list:
    return [None if getattr(x, f) is None else np.asarray(getattr(x, f)).tobytes()
            for f in x.__dataclass_fields__]


def test_messages_larger_than_a_region_cross_the_pipe_with_the_same_numbers(monkeypatch):
    """A 40-row update sent whole to a worker (submit / result) with regions that hold the
    request and the reply, the request only, or neither: the request goes through the region
    only when it fits, the reply too (read from the region by the caller) else through the
    pipe, and the numbers are those computed here, bit for bit, with no failure."""
    cfg = TrackerConfig()
    args = _update_args(40)
    ref = R.run_update(SC.building, *args, cfg, None)
    req, rep = _region_bytes((*args, cfg, None)), _region_bytes(ref)
    assert rep - 64 > req  # (the reply carries the estimates besides the state)
    read = []
    unpack = shm.unpack
    monkeypatch.setattr(shm, "unpack", lambda region, ref: read.append(1) or unpack(region, ref))
    for region_bytes, via_shm, reply_read in ((rep + 64, 1, 1), (req, 1, 0), (req - 4096, 0, 0)):
        monkeypatch.setattr(shm, "REGION_BYTES", region_bytes)
        read.clear()
        with W.RowPool(2, MODEL) as pool:
            assert pool.wait_ready(120) == 1 and pool._slots[0].shm is not None
            p = pool.submit("update", args, 40.0, shared=(cfg, None))
            out = pool.result(p, shared=(cfg, None))
            assert p.ok and not pool.failures, region_bytes
            assert (pool.calls["via_shm"], len(read)) == (via_shm, reply_read), region_bytes
        assert _fields_bytes(out[0]) == _fields_bytes(ref[0])
        assert _fields_bytes(out[1]) == _fields_bytes(ref[1])


def test_hung_worker_times_out_is_killed_and_restarted(monkeypatch):
    """A worker that does not answer within the timeout (here 0.5 s; live 30 s + 0.1 s per
    cost unit) is killed, its share computed by the caller, a new worker started and used."""
    monkeypatch.setattr(W, "TIMEOUT_BASE_S", 0.5)
    monkeypatch.setattr(W, "TIMEOUT_PER_COST_S", 0.0)
    with W.RowPool(2, MODEL) as pool:
        assert pool.wait_ready(120) == 1
        old = pool.pids[0]
        x = np.full(40, 60.0)  # the worker's share would sleep a minute
        got = pool.map_rows("sleep", (x,), np.ones(40), local=lambda a: a + 1)
        assert np.array_equal(got, x + 1)
        assert pool.failures["timeout"] == 1
        assert _gone([old], 10) == []  # killed
        assert pool.wait_ready(120) == 1 and pool.pids[0] != old
        # the new worker (its request region had the hung request: it has new regions)
        # answers through its regions with the numbers computed here
        cfg, args = TrackerConfig(), _update_args(40)
        ref = R.run_update(SC.building, *args, cfg, None)
        sent = pool.calls["via_shm"]
        again = pool.map_rows("update", args, np.ones(40), shared=(cfg, None))
        assert pool.calls["via_shm"] == sent + 1 and pool.failures["timeout"] == 1
        assert _fields_bytes(again[0]) == _fields_bytes(ref[0])
        assert _fields_bytes(again[1]) == _fields_bytes(ref[1])


_WARM_CHECK = """
import json, sys
import numpy as np
from numba.core.registry import CPUDispatcher
from diffpos.estimators.mnls import solver as est
from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.scenario import default_scenario
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import init_state, update
from diffpos_services.fusion.warm import warm_model

def loaded():
    return {f"{n}.{k}": len(v.signatures) for n, m in list(sys.modules.items())
            if n.startswith("diffpos.") and n.endswith("_nb") for k, v in vars(m).items()
            if isinstance(v, CPUDispatcher)}

sc = default_scenario()
b = sc.building
warm_model(b, sc.radio, b.window_height_m, b.first_floor_z_m)
before = loaded()
anchors = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0],
                    [15.0, -20.0, 1.0], [-25.0, -12.0, 3.0], [25.0, -12.0, 3.0]])
nodes = np.array([[-4.0, 3.0, 4.5], [2.0, 6.0, 7.5], [6.0, 2.5, 10.5]])
rng = np.random.default_rng(1)
st = init_state(3, b)
a = np.broadcast_to(anchors, (3, *anchors.shape))
for k in range(4):
    fa = first_arrival(emulate_channel(anchors, nodes, building=b, radio=sc.radio),
                       radio=sc.radio, rng=rng)
    st, _ = update(st, a, fa.range_m, fa.sigma_m, fa.detected, np.full(3, k * 100_000_000), b,
                   TrackerConfig(), snr_db=fa.snr_db, radio=sc.radio)
    est.mnls(a, fa.range_m, fa.sigma_m, building=b, mask=fa.detected, snr_db=fa.snr_db,
             radio=sc.radio)
print(json.dumps({k: [before.get(k, 0), v] for k, v in loaded().items()
                  if v != before.get(k, 0)}))
"""


def test_warm_model_loads_every_kernel_the_real_calls_use():
    """A worker says ready after :func:`warm_model`: in a fresh process, tracked updates (with
    the SNR) and M-NLS fixes afterwards load or compile no further kernel (before, the SNR
    cache's two kernels were loaded by the first real tracked update, in the hot path)."""
    out = subprocess.run([sys.executable, "-c", _WARM_CHECK], capture_output=True, text=True,
                         timeout=600, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == {}
