"""Multi-process runtime on loopback: router + anchor processes + fusion over Zenoh.

Readiness is observed (liveliness tokens), never slept for; every process is started in its
own process group and reaped by the ``services`` fixture (tests/conftest.py).
"""

from __future__ import annotations

import collections
import queue
import threading
import time

import numpy as np
import pytest
import zenoh
from diffpos_services.bus.session import ZenohSettings
from diffpos_services.scenario_io import load_scenario_option
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key

from diffpos.emulation import emulation_nodes

pytestmark = pytest.mark.slow

PERIOD_NS = 100_000_000


class Bus:
    """The test's own Zenoh client: liveliness, estimates and diagnostics into one queue."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self.s = session
        self.keys = keys
        self.q: queue.Queue = queue.Queue()
        self.alive: set[str] = set()
        self.cv = threading.Condition()
        self._subs = [
            session.liveliness().declare_subscriber(keys.alive_all(), self._on_alive, history=True),
            session.declare_subscriber(keys.estimates(), self._on_data),
            session.declare_subscriber(keys.fusion_diagnostics(), self._on_data),
        ]

    def _on_alive(self, sample: zenoh.Sample) -> None:
        with self.cv:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(str(sample.key_expr))
            else:
                self.alive.discard(str(sample.key_expr))
            self.cv.notify_all()
        self.q.put(("alive", str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT, time.monotonic()))

    def _on_data(self, sample: zenoh.Sample) -> None:
        self.q.put(("data", str(sample.key_expr), sample.payload.to_bytes(), time.monotonic()))

    def wait_alive(self, keys: set[str], services, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        with self.cv:
            while not keys <= self.alive:
                services.check_running()
                assert time.monotonic() < deadline, f"not ready: {sorted(keys - self.alive)}"
                self.cv.wait(0.2)

    def start_run(self, *, speed: float, duration_s: float) -> M.RunControl:
        now = time.time_ns() + 200_000_000
        t0 = -(-now // PERIOD_NS) * PERIOD_NS  # on the epoch grid
        rc = M.RunControl(run_id="test", t0_ns=t0, wall_t0_ns=t0, speed=speed,
                          duration_ns=round(duration_s * 1e9), seed=0)
        self.s.put(self.keys.run_control(), M.encode(rc),
                   congestion_control=zenoh.CongestionControl.BLOCK)
        return rc

    def undeclare(self) -> None:
        for s in self._subs:
            s.undeclare()


def _run_system(services, endpoint, *, scenario, anchors, duration_s, speed, site,
                max_nodes=0, on_estimate=None, extra_timeout_s=30.0):
    """Start router, fusion and anchors; run; return (estimates, diagnostics, rc, events)."""
    keys = Keys(site)
    services.start("router", "router", "--listen", endpoint)
    settings = ZenohSettings(connect=(endpoint,))
    from diffpos_services.bus.session import open_session

    stop = threading.Event()
    session = open_session(settings, stop)
    with session:
        bus = Bus(session, keys)
        # the ideal channel is D-NLS's path model: this pipeline test runs D-NLS (at 4x real
        # time; the default mnls + tracker is covered by tests/system/test_tracking_emulate.py).
        # Every node-epoch must arrive: the live overload policy is off (--max-backlog-s 0:
        # a fusion behind only lags). At 4x, 0.5 s of measurement time is 125 ms of wall time,
        # so a stall of the CI machine made it supersede a block of epochs (2026-11-28: 37-49
        # of several nodes); the policy has its own tests (test_fusion_overload/_budget.py).
        services.start("fusion", "fusion", "--site", site, "--connect", endpoint,
                       "--scenario", scenario, "--method", "dnls", "--max-backlog-s", "0")
        for a in anchors:
            services.start(f"anchor-{a}", "anchor", "--id", a, "--site", site, "--connect", endpoint,
                           "--scenario", scenario, "--wait-start", "--channel", "ideal",
                           "--seed", "5", "--clock-offset-ms", f"{(hash(a) % 300) / 100 - 1.5:.2f}",
                           "--max-nodes", str(max_nodes))
        bus.wait_alive({keys.alive_anchor(a) for a in anchors} | {keys.alive_fusion()}, services)
        # the fusion must not be a truth subscriber: nobody matches a truth publisher
        truth_pub = session.declare_publisher(keys.truth_node("n01"),
                                              congestion_control=zenoh.CongestionControl.BLOCK)
        rc = bus.start_run(speed=speed, duration_s=duration_s)
        end_ns = rc.t0_ns + rc.duration_ns
        estimates: list[tuple[float, M.PositionEstimate]] = []
        diags: list[tuple[float, M.FusionDiagnostics]] = []
        events = []
        dec_e, dec_d = M.estimate_decoder(), M.decoder(M.FusionDiagnostics)  # estimate v1/v2
        deadline = time.monotonic() + duration_s / speed + extra_timeout_s
        while True:
            assert time.monotonic() < deadline, "run did not finish"
            try:
                kind, key, val, t_rx = bus.q.get(timeout=0.5)
            except queue.Empty:
                services.check_running() if not diags else None
                continue
            if kind == "alive":
                events.append((t_rx, key, val))
                continue
            pk = parse_key(key)
            if pk.kind == "estimate":
                est = dec_e(val)
                estimates.append((t_rx, est))
                if on_estimate is not None:
                    on_estimate(est, t_rx)
            else:
                d = dec_d(val)
                diags.append((t_rx, d))
                if d.watermark_ns is not None and d.watermark_ns >= end_ns - PERIOD_NS \
                        and d.pending_epochs == 0:
                    break
        matching = truth_pub.matching_status.matching
        truth_pub.undeclare()
        bus.undeclare()
    return estimates, diags, rc, events, matching


def test_four_anchors_fusion_every_node_every_epoch(services, endpoint):
    scenario = "paper"
    site = "itest"
    anchors = ["uav1", "uav2", "uav3", "uav4"]
    duration_s, speed = 10.0, 4.0
    estimates, diags, rc, _, truth_matched = _run_system(
        services, endpoint, scenario=scenario, anchors=anchors, duration_s=duration_s,
        speed=speed, site=site)
    codes = services.stop(["fusion", *[f"anchor-{a}" for a in anchors], "router"])
    assert all(c == 0 for c in codes.values()), codes
    assert truth_matched is False

    sc = load_scenario_option(scenario)
    nodes = dict(emulation_nodes(sc))
    e0 = rc.t0_ns // PERIOD_NS
    n_epochs = int(duration_s * 1e9) // PERIOD_NS
    got = collections.Counter((est.node_id, est.epoch - e0) for _, est in estimates)
    want = {(n, k) for n in nodes for k in range(n_epochs)}
    rejected = diags[-1][1].rejected if diags else None  # why, if any is missing
    assert set(got) == want, (sorted(want - set(got))[:10], sorted(set(got) - want)[:10],
                              rejected)
    assert max(got.values()) == 1  # exactly one estimate per node and epoch

    ok = [est for _, est in estimates if est.position_m is not None]
    assert len(ok) >= 0.9 * len(estimates), collections.Counter(e.status for _, e in estimates)
    err = np.array([
        np.linalg.norm(np.array(e.position_m) - nodes[e.node_id].position_m((e.t_ns - rc.t0_ns) * 1e-9))
        for e in ok
    ])
    peb = np.array([e.peb_m for e in ok])
    assert np.median(err) <= 2 * np.median(peb), (np.median(err), np.median(peb))
    last = diags[-1][1]
    assert last.rejected.get("late", 0) == 0 and not set(last.rejected) - {"late"}
    # all four were live during the run (they leave on their own at its end)
    assert any(sorted(d.live_anchors) == anchors for _, d in diags)
    assert last.received["range"] == len(anchors) * len(nodes) * n_epochs


def test_killed_anchor_is_marked_lost_and_fixes_continue(services, endpoint):
    """Five anchors; SIGKILL one mid-run: fixes continue, it is marked lost within 1 s."""
    scenario = "large"
    site = "ktest"
    anchors = ["uav1", "uav2", "uav3", "uav4", "uav5"]
    victim = "uav3"
    duration_s, speed = 8.0, 2.0
    killed: dict[str, float] = {}

    def on_estimate(est, t_rx):
        if not killed and est.epoch * PERIOD_NS >= start[0] + 3 * 10**9:
            services.kill(f"anchor-{victim}")
            killed["t"] = time.monotonic()

    start = [0]
    orig = _run_system.__globals__["Bus"].start_run

    def start_run(self, **kw):
        rc = orig(self, **kw)
        start[0] = rc.t0_ns
        return rc

    Bus.start_run = start_run
    try:
        estimates, diags, rc, events, _ = _run_system(
            services, endpoint, scenario=scenario, anchors=anchors, duration_s=duration_s,
            speed=speed, site=site, max_nodes=5, on_estimate=on_estimate)
    finally:
        Bus.start_run = orig
    assert killed, "the victim was never killed"
    t_kill = killed["t"]
    # the liveliness token vanished quickly (SIGKILL: the router notices the closed link)
    gone = [t for t, key, alive in events if key.endswith(f"/alive/anchor/{victim}") and not alive]
    assert gone and gone[0] - t_kill < 1.0
    # the fusion marked it lost within 1 s: diagnostics and the estimates' exclusions
    lost_diag = [t for t, d in diags if victim not in d.live_anchors
                 and any(a.anchor_id == victim and not a.alive for a in d.anchors)]
    assert lost_diag and lost_diag[0] - t_kill < 1.0, (lost_diag[:1], t_kill)
    marked = [t for t, e in estimates if M.Exclusion(victim, "ANCHOR_LOST") in e.excluded]
    assert marked and marked[0] - t_kill < 1.0
    # fixes continue from the other four for every node until the end of the run
    after = [e for t, e in estimates if t > t_kill + 1.0]
    nodes = {e.node_id for _, e in estimates}
    assert {e.node_id for e in after} == nodes
    good_after = [e for e in after if e.position_m is not None]
    assert len(good_after) >= 0.8 * len(after)
    assert all(victim not in e.used_anchors for e in after)
    last_epoch = max(e.epoch for e in after)
    assert last_epoch >= rc.t0_ns // PERIOD_NS + int(duration_s * 10) - 2


def test_emulate_one_command_runs_scores_and_cleans_up(services, tmp_path):
    """`diffpos emulate` (lockstep): all services as processes, summary JSON, recording, no
    leftover processes."""
    import json
    from pathlib import Path

    summary_path = tmp_path / "summary.json"
    mcap = tmp_path / "run.mcap"
    # --speed 0: lockstep, emulated time released epoch by epoch as the estimates come in
    p = services.start("emulate", "emulate", "paper", "--duration", "3", "--speed", "0",
                       "--channel", "ideal", "--method", "dnls",  # PEB: D-NLS's model
                       "--record", str(mcap), "--dashboard", "off",
                       "--json", str(summary_path), "--no-progress",
                       "--log-dir", str(tmp_path / "logs"))
    rc = p.wait(timeout=180)
    assert rc == 0, services.log("emulate")[-3000:]
    s = json.loads(summary_path.read_text())
    assert s["anchors"] == 4 and s["nodes"] == 6
    assert s["estimates"] == 6 * 30 and s["epochs_per_node_min"] == 30
    # OK/OK_UNVERIFIED (snapshot fixes) or the tracker's INITIALISING/TRACKING/COASTING
    assert sum(s["status"].get(k, 0) for k in M.GOOD_STATUSES) >= 0.9 * s["estimates"], s["status"]
    assert s["error_3d_m"]["p50"] <= 2 * s["peb_m"]["p50"]
    assert s["floor_accuracy"] >= 0.9
    assert s["fusion"]["late_ranges"] == 0 and not s["lost"]
    assert mcap.exists() and mcap.stat().st_size > 0
    # every service the orchestrator started is gone (they run in their own sessions)
    left = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            except OSError:
                continue
            if s["endpoint"] in cmd:
                left.append(cmd)
    assert not left, left
