"""Live dashboard service over real Zenoh sessions (no viewer is ever spawned).

Synchronisation uses events set from the subscriber callbacks and publisher matching
listeners, never sleeps. The tests' publishers use congestion control BLOCK: Zenoh's default
(DROP) lost messages under CPU load (received 245 of 264). Output goes to an .rrd (save) or a
gRPC/web server on free ports.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np
import pytest
import rerun as rr
import zenoh
from diffpos_services.bus.session import ZenohSettings, wait_matching
from diffpos_services.dashboard.building import BuildingOutline
from diffpos_services.dashboard.convert import rrd_rows
from diffpos_services.dashboard.service import (
    DashboardService,
    RerunTarget,
    describe_target,
    display_available,
    open_rerun,
)
from diffpos_services.processes import free_tcp_port
from diffpos_services.replay.synthetic import display_run
from diffpos_services.wire import messages as m
from diffpos_services.wire.keys import Keys


def synthetic_run(**kw):
    """The dashboard's synthetic run (``replay.synthetic.display_run``), its building as
    the outline the dashboard draws."""
    building, msgs = display_run(**kw)
    return BuildingOutline.from_object(building), msgs


TIMEOUT_S = 60.0  # generous under CPU load, but bounded


@pytest.fixture
def sessions(endpoint):
    """Two peer sessions on loopback: ``pub`` listens, ``sub`` connects to it."""
    ep = endpoint
    pub = zenoh.open(ZenohSettings(mode="peer", connect=(), listen=(ep,)).to_config())
    sub = zenoh.open(ZenohSettings(mode="peer", connect=(ep,)).to_config())
    yield pub, sub
    sub.close()
    pub.close()


class CountingService(DashboardService):
    """Sets ``done`` once ``expected`` data messages and ``expected_live`` liveliness
    changes have arrived (called from the Zenoh callback threads)."""

    expected = 0
    expected_live = 0

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.done = threading.Event()
        self.joined = threading.Event()  # a liveliness PUT arrived: the subscriber is known
        self.n_live = 0

    def _check(self):
        if self.stats.received >= self.expected and self.n_live >= self.expected_live:
            self.done.set()

    def _on_sample(self, sample):
        super()._on_sample(sample)
        self._check()

    def _on_liveliness(self, sample):
        super()._on_liveliness(sample)
        self.n_live += 1
        if sample.kind == zenoh.SampleKind.PUT:
            self.joined.set()
        self._check()


def publishers_matched(session, keys):
    """Declare one publisher per key (congestion control BLOCK: every message must arrive)
    and wait until each has a matching subscriber."""
    block = zenoh.CongestionControl.BLOCK
    pubs = {key: session.declare_publisher(key, congestion_control=block)
            for key in sorted(set(keys))}
    for key, pub in pubs.items():
        assert wait_matching(pub, timeout_s=TIMEOUT_S), f"no subscriber matched {key}"
    return pubs


def test_live_service_draws_what_fusion_published(sessions, tmp_path):
    pub_s, sub_s = sessions
    building, msgs = synthetic_run(n_anchors=3, n_nodes=3, duration_s=3.0, seed=5)
    site = "live1"
    path = tmp_path / "live.rrd"
    rec, how = open_rerun(RerunTarget(mode="save", path=str(path)), recording_id="live1")
    assert str(path) in how
    svc = CountingService(sub_s, rec, site=site, building=building, drain_period_s=0.05)
    svc.expected = len(msgs) + 1
    svc.expected_live = 2
    svc.start()
    keys = [Keys(site).of(x) for x in msgs]
    pubs = publishers_matched(pub_s, keys)
    token = pub_s.liveliness().declare_token(Keys(site).alive_anchor("uav1"))
    # readiness of the liveliness subscriber: its interest may still be in flight when the
    # data subscribers match; a token undeclared before it arrives is never seen (no PUT, no
    # DELETE). Once the PUT is in, the DELETE will follow.
    assert svc.joined.wait(TIMEOUT_S), "the dashboard never saw the anchor's token"
    for key, x in zip(keys, msgs, strict=True):
        pubs[key].put(m.encode(x))
    pubs[keys[-1]].put(b'{"schema": "diffpos.estimate.v1", "node_id": 7}')  # garbage
    token.undeclare()
    assert svc.done.wait(TIMEOUT_S), (svc.stats, svc.n_live)
    svc.close()
    rec.disconnect()
    assert svc.stats.dropped == 0 and svc.stats.undecodable == 1
    assert svc.stats.drawn == len(msgs)

    rows = rrd_rows(path)
    ests = [x for x in msgs if isinstance(x, m.PositionEstimate)]
    for e in ests:
        row = dict(rows[f"/world/nodes/{e.node_id}/estimate"])[e.t_ns]
        if e.position_m is not None:
            np.testing.assert_allclose(row["Points3D:positions"][0], e.position_m, atol=1e-4)
    assert sum(len(rows[f"/world/nodes/{n}/estimate"]) for n in ("n00", "n01", "n02")) == len(ests)
    # errors use the truth of the same time (estimates wait for their truth)
    truth = {(t.id, t.t_ns): np.array(t.position_m) for t in msgs if isinstance(t, m.GroundTruth)}
    err = dict(rows["/metrics/error_3d_m/n02"])
    for e in ests:
        if e.node_id == "n02" and e.position_m is not None:
            want = np.linalg.norm(np.array(e.position_m) - truth[("n02", e.t_ns)])
            assert err[e.t_ns]["Scalars:scalars"][0] == pytest.approx(want, abs=1e-9)
    texts = [t for _, r in rows["/events"] for t in r["TextLog:text"]]
    # an anchor the fusion stops seeing is a DEBUG row: the liveliness events tell a lost
    # anchor from the end of a run (docs/dashboard.md, events)
    # (either row may come first: the liveliness DELETE or the fusion's next diagnostics)
    assert "anchor uav1 joined" in texts
    assert any(x.startswith("anchor uav1 left") or x == "fusion no longer sees anchor uav1"
               for x in texts), texts
    assert {"/world/building/floors", "/floors", "/metrics/residual_m/uav2"} <= set(rows)


def test_ring_buffer_drops_the_oldest_and_never_blocks_the_publisher(sessions, tmp_path):
    pub_s, sub_s = sessions
    _, msgs = synthetic_run(n_anchors=3, n_nodes=1, duration_s=20.0, seed=2)
    ests = [x for x in msgs if isinstance(x, m.PositionEstimate)][:200]
    site = "ring"
    path = tmp_path / "ring.rrd"
    rec, _ = open_rerun(RerunTarget(mode="save", path=str(path)))
    svc = CountingService(sub_s, rec, site=site, ring_size=20)
    svc.expected = len(ests)
    svc.start()  # subscribed, but nothing drains: the "viewer" is stuck
    pubs = publishers_matched(pub_s, [Keys(site).of(ests[0])])
    pub = next(iter(pubs.values()))
    for e in ests:
        pub.put(m.encode(e))  # BLOCK: waits for the link, never for the ring (callback is O(1))
    assert svc.done.wait(TIMEOUT_S), svc.stats
    assert svc.stats.received == 200 and svc.stats.dropped == 180 and len(svc.ring) == 20
    svc.close()
    rec.disconnect()
    rows = rrd_rows(path)
    assert [t for t, _ in rows["/world/nodes/n00/estimate"]] == [e.t_ns for e in ests[-20:]]


def test_serve_mode_serves_the_web_viewer_and_auto_never_spawns_headless(monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    if sys.platform.startswith("linux"):
        assert not display_available()
        with pytest.raises(RuntimeError, match="needs a display"):
            open_rerun(RerunTarget(mode="spawn"))
    web = free_tcp_port()
    target = RerunTarget(mode="auto", grpc_port=free_tcp_port(), web_port=web)
    rec, how = open_rerun(target)
    try:
        assert how == describe_target(target), "emulate can print the same sentence"
        assert f"http://127.0.0.1:{web}/?url=rerun%2Bhttp" in how
        page = urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=10).read()
        assert b"<html" in page.lower() or b"<!doctype" in page.lower()
        rec.log("probe", rr.Points3D([[0.0, 0.0, 0.0]]))
    finally:
        rec.disconnect()


def test_bad_rerun_targets_are_clear_errors():
    with pytest.raises(ValueError, match="needs a PATH"):
        RerunTarget(mode="save")
    with pytest.raises(ValueError, match="spawn, serve, save PATH or off"):
        RerunTarget(mode="window")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="grpc_port"):
        RerunTarget(mode="serve", grpc_port=70000)


@pytest.mark.slow
def test_dashboard_cli_process_end_to_end(tmp_path, endpoint):
    """diffpos router + diffpos dashboard --rerun save as processes; SIGTERM closes the file."""
    ep = endpoint
    exe = [sys.executable, "-m", "diffpos_services.cli.main"]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    env.pop("DISPLAY", None)
    out = tmp_path / "cli.rrd"
    router = subprocess.Popen([*exe, "router", "--listen", ep], env=env, stderr=subprocess.DEVNULL)
    dash = subprocess.Popen(
        [*exe, "dashboard", "--connect", ep, "--site", "cli", "--rerun", "save", str(out),
         "--drain-period", "0.05", "--report-every", "0.1"],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    status: queue.Queue = queue.Queue()  # the dashboard's structured log lines, as they come
    err_lines: list[str] = []

    def read_stderr() -> None:
        for line in dash.stderr:
            err_lines.append(line)
            if '"dashboard running"' in line:
                status.put(json.loads(line))

    reader = threading.Thread(target=read_stderr, daemon=True)
    reader.start()
    try:
        _, msgs = synthetic_run(n_anchors=2, n_nodes=2, duration_s=2.0, seed=9)
        ests = [x for x in msgs if isinstance(x, m.PositionEstimate)]
        with zenoh.open(ZenohSettings(mode="client", connect=(ep,)).to_config()) as s:
            keys = [Keys("cli").of(x) for x in msgs]
            pubs = publishers_matched(s, keys)  # the dashboard process has subscribed
            for key, x in zip(keys, msgs, strict=True):
                pubs[key].put(m.encode(x))
            # readiness: the dashboard's own status says it received every message (only
            # then SIGTERM; before, a stop could overtake messages still in flight)
            received = 0
            while received < len(msgs):
                received = status.get(timeout=60)["received"]
        dash.send_signal(signal.SIGTERM)
        stdout = dash.stdout.read()
        dash.wait(timeout=60)
        reader.join(timeout=60)
        stderr = "".join(err_lines)
        assert dash.returncode == 0, stderr
        assert "saved to" in stdout
        final = [json.loads(line) for line in stderr.splitlines() if '"dashboard stopped"' in line]
        assert final and final[-1]["dropped"] == 0
        rows = rrd_rows(out)  # footer written: the file is complete
        drawn = {(p.split("/")[3], t): r for p in rows if p.endswith("/estimate")
                 for t, r in rows[p]}  # fmt: skip
        assert len(drawn) >= 1
        for e in ests:
            row = drawn.get((e.node_id, e.t_ns))
            if row is not None and e.position_m is not None:
                np.testing.assert_allclose(row["Points3D:positions"][0], e.position_m, atol=1e-4)
    finally:
        for p in (dash, router):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    p.kill()


def test_wait_received_returns_once_everything_arrived(sessions, tmp_path):
    """``DashboardService.wait_received(n)`` wakes up when the n-th sample arrives (what a
    caller waits on before stopping the service) and says False on a timeout."""
    pub_s, sub_s = sessions
    _, msgs = synthetic_run(n_anchors=2, n_nodes=2, duration_s=1.0, seed=3)
    rec, _ = open_rerun(RerunTarget(mode="save", path=str(tmp_path / "w.rrd")))
    svc = DashboardService(sub_s, rec, site="wait1")
    svc.start()
    keys = [Keys("wait1").of(x) for x in msgs]
    pubs = publishers_matched(pub_s, keys)
    done = threading.Event()
    waiter = threading.Thread(
        target=lambda: done.set() if svc.wait_received(len(msgs), timeout_s=TIMEOUT_S) else None)
    waiter.start()
    for key, x in zip(keys, msgs, strict=True):
        pubs[key].put(m.encode(x))
    t0 = time.monotonic()
    waiter.join(TIMEOUT_S)
    # woken by the last sample, not by its timeout
    assert done.is_set() and time.monotonic() - t0 < 0.5 * TIMEOUT_S
    assert svc.stats.received == len(msgs)
    assert not svc.wait_received(len(msgs) + 1, timeout_s=0.05)  # nothing more comes
    svc.close()
    rec.disconnect()
