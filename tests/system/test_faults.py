"""Fault injection on the real multi-process runtime (loopback): what survives each fault.

Every service is a real ``diffpos`` process in its own process group (``services`` fixture,
tests/conftest.py); faults are signals to those groups: SIGKILL (crash), SIGSTOP/SIGCONT
(hang), restart of the same command. The test's own Zenoh client watches liveliness tokens,
estimates, diagnostics and every anchor message (sequence numbers) and times each event on
receipt; the test acts on what it observes, never on sleeps.

Measured figures are printed (``pytest tests/test_faults.py -s``) and reported in
docs/faults.md. Hung anchors are detected through the Zenoh lease of their link: the anchors
here run with ``transport/link/tx/lease`` = 1000 ms (a ``--zenoh-config`` file) instead of
the 10 s default.
"""

from __future__ import annotations

import collections
import contextlib
import itertools
import json
import queue
import signal
import threading
import time
from pathlib import Path

import msgspec
import pytest
import zenoh
from diffpos_services.bus.session import ZenohSettings, open_session
from diffpos_services.processes import free_tcp_port
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key

pytestmark = pytest.mark.slow

PERIOD_NS = 100_000_000
LEASE_MS = 1000
RESULTS: list[dict] = []


def _report(fault: str, **fields) -> None:
    RESULTS.append({"fault": fault, **fields})
    print("\nFAULT", json.dumps({"fault": fault, **fields}))


class Bus:
    """The test's Zenoh client: everything of the site, timed on receipt (monotonic [s])."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self.s = session
        self.keys = keys
        self.q: queue.Queue = queue.Queue()
        self.alive: set[str] = set()
        self.alive_events: list[tuple[float, str, bool]] = []
        self.estimates: list[tuple[float, M.PositionEstimate]] = []
        self.raw_estimates: dict[tuple[str, int], list[bytes]] = collections.defaultdict(list)
        self.diags: list[tuple[float, M.FusionDiagnostics]] = []
        self.seqs: dict[str, list[tuple[float, int]]] = collections.defaultdict(list)
        self._dec_e = M.estimate_decoder()  # v2 (mnls + tracking, the default) or v1
        self._dec_d = M.decoder(M.FusionDiagnostics)
        self._subs = [
            session.liveliness().declare_subscriber(keys.alive_all(), self._on_alive, history=True),
            session.declare_subscriber(keys.everything(), self._on_data),
        ]
        self.rc: M.RunControl | None = None

    def _on_alive(self, sample: zenoh.Sample) -> None:
        self.q.put(("alive", str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT,
                    time.monotonic()))

    def _on_data(self, sample: zenoh.Sample) -> None:
        self.q.put(("data", str(sample.key_expr), sample.payload.to_bytes(), time.monotonic()))

    def _handle(self, item) -> None:
        kind, key, val, t = item
        if kind == "alive":
            (self.alive.add if val else self.alive.discard)(key)
            self.alive_events.append((t, key, val))
            return
        pk = parse_key(key)
        if pk is None:
            return
        if pk.kind == "estimate":
            est = self._dec_e(val)
            self.estimates.append((t, est))
            self.raw_estimates[(est.node_id, est.epoch)].append(val)
        elif pk.kind == "diagnostics":
            self.diags.append((t, self._dec_d(val)))
        elif pk.kind in ("anchor_state", "range"):
            self.seqs[pk.anchor_id].append((t, msgspec.json.decode(val)["seq"]))

    def pump(self, until, *, timeout_s: float, what: str, services, ignore=()) -> float:
        """Handle messages until ``until()`` holds; return the receive time of the last one."""
        deadline = time.monotonic() + timeout_s
        t_last = time.monotonic()
        while not until():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out after {timeout_s} s waiting for: {what}; "
                                     + self.context())
            try:
                item = self.q.get(timeout=0.2)
            except queue.Empty:
                services.check_running(ignore)
                continue
            self._handle(item)
            t_last = item[3]
        return t_last

    def start_run(self, *, duration_s: float = 600.0) -> M.RunControl:
        """Publish the time base (again, for a restarted anchor: same run, same t0)."""
        if self.rc is None:
            now = time.time_ns() + 200_000_000
            t0 = -(-now // PERIOD_NS) * PERIOD_NS
            self.rc = M.RunControl(run_id="faults", t0_ns=t0, wall_t0_ns=t0, speed=1.0,
                                   duration_ns=round(duration_s * 1e9), seed=0)
        self.s.put(self.keys.run_control(), M.encode(self.rc),
                   congestion_control=zenoh.CongestionControl.BLOCK)
        return self.rc

    # -- queries ------------------------------------------------------------------------
    def diag_alive(self, anchor: str, alive: bool, after: float) -> float | None:
        """Receive time of the first diagnostics after ``after`` with ``anchor`` (not) live."""
        for t, d in self.diags:
            if t >= after and (anchor in d.live_anchors) == alive and any(
                    a.anchor_id == anchor for a in d.anchors):
                return t
        return None

    def first_estimate(self, after: float, pred=lambda e: True) -> float | None:
        for t, e in self.estimates:
            if t >= after and pred(e):
                return t
        return None

    def epochs_after(self, t0: float) -> int:
        eps = [e.epoch for t, e in self.estimates if t >= t0]
        return (max(eps) - min(eps)) if eps else -1

    def context(self, since: float = 0.0) -> str:
        """What the bus saw (for failure messages): liveliness events and the last
        diagnostics."""
        ev = [(round(t - since, 3), k.rsplit("/", 1)[-1], v) for t, k, v in self.alive_events
              if t >= since]
        last = self.diags[-1][1] if self.diags else None
        return (f"liveliness events since t0: {ev[-30:]}; last diagnostics: live="
                f"{last.live_anchors if last else None} rejected={last.rejected if last else None}")

    def undeclare(self) -> None:
        for s in self._subs:
            s.undeclare()


def _lease_config(path: Path, endpoint: str) -> str:
    """A plain client configuration file with a short link lease (hang detection)."""
    path.write_text(json.dumps({
        "mode": "client",
        "connect": {"endpoints": [endpoint], "timeout_ms": -1},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tx": {"lease": LEASE_MS}}},
    }))
    return str(path)


def _start_anchor(services, name, aid, *, site, scenario, zenoh_args, max_nodes):
    return services.start(name, "anchor", "--id", aid, "--site", site, "--scenario", scenario,
                          "--wait-start", "--channel", "ideal", "--seed", "5",
                          "--max-nodes", str(max_nodes), *zenoh_args)


def _no_conflicting_duplicates(bus: Bus) -> int:
    """Assert one content per (node, epoch) (ignoring seq and publish time); return the
    number of exact repeats."""
    repeats = 0
    for key, raws in bus.raw_estimates.items():
        if len(raws) > 1:
            contents = {json.dumps({k: v for k, v in json.loads(r).items()
                                    if k not in ("seq", "t_pub_wall_ns")}, sort_keys=True)
                        for r in raws}
            assert len(contents) == 1, f"estimate {key} published with different content: {contents}"
            repeats += len(raws) - 1
    return repeats


def _missing_epochs(bus: Bus, nodes, t_from: float, t_to: float) -> int:
    """(node, epoch) pairs without an estimate between the last epoch before ``t_from`` and
    the first epoch after ``t_to``."""
    before = [e.epoch for t, e in bus.estimates if t < t_from]
    after = [e.epoch for t, e in bus.estimates if t > t_to]
    if not before or not after:
        return -1
    lo, hi = max(before), min(after)
    got = {(e.node_id, e.epoch) for _, e in bus.estimates if lo <= e.epoch <= hi}
    return sum((n, k) not in got for n in nodes for k in range(lo, hi + 1))


def _seq_gaps(seqs: list[int]) -> list[tuple[int, int]]:
    """(last seq before, first seq after) of every jump in a sequence stream."""
    s = sorted(set(seqs))
    return [(a, b) for a, b in itertools.pairwise(s) if b != a + 1]


@contextlib.contextmanager
def _system(services, endpoint, tmp_path, *, site, scenario, anchors, max_nodes,
            lease_file=False, recorder=None):
    """Router, the test's client, fusion, anchors (and a recorder); run started, warm."""
    keys = Keys(site)
    services.start("router", "router", "--listen", endpoint)
    session = open_session(ZenohSettings(connect=(endpoint,)), threading.Event())
    try:
        bus = Bus(session, keys)
        need = {keys.alive_anchor(a) for a in anchors} | {keys.alive_fusion()}
        if recorder is not None:
            services.start("recorder", "recorder", "--site", site, "--connect", endpoint,
                           "--out", str(recorder), "--flush-interval", "0.1")
            need.add(keys.alive_recorder())
        # ideal-channel anchors (D-NLS's path model): the fault tests run D-NLS
        services.start("fusion", "fusion", "--site", site, "--connect", endpoint,
                       "--scenario", scenario, "--method", "dnls")
        zargs = (["--zenoh-config", _lease_config(tmp_path / "anchor-zenoh.json5", endpoint)]
                 if lease_file else ["--connect", endpoint])
        for a in anchors:
            _start_anchor(services, f"anchor-{a}", a, site=site, scenario=scenario,
                          zenoh_args=zargs, max_nodes=max_nodes)
        bus.zargs = zargs
        bus.pump(lambda: need <= bus.alive, timeout_s=60, what=f"ready: {sorted(need)}",
                 services=services)
        bus.start_run()
        t_run = time.monotonic()
        nodes: set[str] = set()
        bus.nodes = nodes

        def warm() -> bool:
            nodes.update(e.node_id for _, e in bus.estimates[-max_nodes:])
            return len(nodes) == max_nodes and bus.epochs_after(t_run) >= 10

        bus.pump(warm, timeout_s=40, what="estimates for every node", services=services)
        yield bus
    finally:
        with contextlib.suppress(Exception):
            bus.undeclare()
        session.close()


def test_anchor_killed_and_hung_fusion_continues_and_takes_it_back(services, endpoint, tmp_path):
    """SIGKILL one anchor, restart it; SIGSTOP another, SIGCONT it. The fusion keeps fixing
    every node from the rest, marks each lost (killed < 1 s, hung < lease + 1 s) and uses it
    again once it is back."""
    site, scenario = "faults1", "large"
    anchors = ["uav1", "uav2", "uav3", "uav4", "uav5"]
    killed, hung = "uav3", "uav4"
    with _system(services, endpoint, tmp_path, site=site, scenario=scenario, anchors=anchors,
                 max_nodes=4, lease_file=True) as bus:
        ignore = {f"anchor-{killed}"}
        # (a plain --zenoh-config file: the service says it is unauthenticated, once)
        assert services.log("anchor-uav1").count("UNAUTHENTICATED") == 1
        # ---- SIGKILL
        t_kill = time.monotonic()
        services.kill(f"anchor-{killed}")
        # (the token's DELETE and the fusion's diagnostics reach this client on two
        # subscriber threads: either may be handled first)
        bus.pump(lambda: bus.diag_alive(killed, False, t_kill) is not None
                 and bus.keys.alive_anchor(killed) not in bus.alive, timeout_s=10,
                 what="fusion marks the killed anchor lost", services=services, ignore=ignore)
        t_lost = bus.diag_alive(killed, False, t_kill)
        t_token = next(t for t, k, v in bus.alive_events if t >= t_kill and not v
                       and k == bus.keys.alive_anchor(killed))
        bus.pump(lambda: bus.epochs_after(t_lost) >= 15, timeout_s=20,
                 what="1.5 s of fixes without the killed anchor", services=services, ignore=ignore)
        during = [e for t, e in bus.estimates if t > t_lost]
        ctx = bus.context(t_kill)
        assert {e.node_id for e in during} == bus.nodes, ctx
        assert all(killed not in e.used_anchors for e in during), ctx
        assert sum(e.position_m is not None for e in during) >= 0.8 * len(during), (
            collections.Counter(e.status for e in during), ctx)
        assert any(M.Exclusion(killed, "ANCHOR_LOST") in e.excluded for e in during), ctx
        # restart the same command: back in the diagnostics and in the fixes
        t_restart = time.monotonic()
        _start_anchor(services, f"anchor-{killed}-restarted", killed, site=site,
                      scenario=scenario, zenoh_args=bus.zargs, max_nodes=4)
        bus.pump(lambda: bus.keys.alive_anchor(killed) in bus.alive, timeout_s=60,
                 what="restarted anchor's token", services=services, ignore=ignore)
        bus.start_run()  # the restarted anchor waits for the run's time base
        # (the fusion publishes the estimates of a loop iteration before its diagnostics:
        # wait for both)
        bus.pump(lambda: bus.first_estimate(t_restart, lambda e: killed in e.used_anchors)
                 and bus.diag_alive(killed, True, t_restart) is not None,
                 timeout_s=20, what="fixes using the restarted anchor", services=services,
                 ignore=ignore)
        t_back_diag = bus.diag_alive(killed, True, t_restart)
        t_back_fix = bus.first_estimate(t_restart, lambda e: killed in e.used_anchors)
        assert t_back_diag is not None, bus.context(t_kill)
        _report("anchor SIGKILL", detection_s=round(t_lost - t_kill, 3),
                token_gone_s=round(t_token - t_kill, 3),
                fixes_missing=_missing_epochs(bus, bus.nodes, t_kill, t_lost + 0.5),
                restart_to_fix_s=round(t_back_fix - t_restart, 3))
        assert t_lost - t_kill < 1.0, bus.context(t_kill)

        # ---- SIGSTOP (hung process: only the link lease notices)
        late_before = bus.diags[-1][1].late_ranges
        t_stop = time.monotonic()
        services.kill(f"anchor-{hung}", signal.SIGSTOP)
        try:
            bus.pump(lambda: bus.diag_alive(hung, False, t_stop) is not None, timeout_s=15,
                     what="fusion marks the hung anchor lost", services=services, ignore=ignore)
            t_hung_lost = bus.diag_alive(hung, False, t_stop)
            bus.pump(lambda: bus.epochs_after(t_hung_lost) >= 15, timeout_s=20,
                     what="1.5 s of fixes without the hung anchor", services=services,
                     ignore=ignore)
            during = [e for t, e in bus.estimates if t > t_hung_lost]
            ctx = bus.context(t_stop)
            assert {e.node_id for e in during} == bus.nodes, ctx
            assert all(hung not in e.used_anchors for e in during), ctx
            assert sum(e.position_m is not None for e in during) >= 0.8 * len(during), (
                collections.Counter(e.status for e in during), ctx)
        finally:
            t_cont = time.monotonic()
            services.kill(f"anchor-{hung}", signal.SIGCONT)
        bus.pump(lambda: bus.first_estimate(t_cont, lambda e: hung in e.used_anchors)
                 and bus.diag_alive(hung, True, t_cont) is not None, timeout_s=20,
                 what="fixes using the resumed anchor", services=services, ignore=ignore)
        t_hung_back = bus.first_estimate(t_cont, lambda e: hung in e.used_anchors)
        assert bus.diag_alive(hung, True, t_cont) is not None, bus.context(t_stop)
        # while it was hung, fixes waited for its ranges until each epoch's deadline
        stalled = [e for t, e in bus.estimates if t_stop < t < t_hung_lost]
        _report("anchor SIGSTOP", detection_s=round(t_hung_lost - t_stop, 3),
                lease_ms=LEASE_MS,
                fixes_missing=_missing_epochs(bus, bus.nodes, t_stop, t_hung_lost + 0.5),
                fixes_while_undetected=len(stalled),
                cont_to_fix_s=round(t_hung_back - t_cont, 3),
                late_ranges_after_cont=bus.diags[-1][1].late_ranges - late_before,
                other_anchor_losses=sum(
                    1 for t, k, v in bus.alive_events if not v and "/alive/anchor/" in k
                    and k.rsplit("/", 1)[-1] not in (killed, hung)))
        assert t_hung_lost - t_stop < LEASE_MS * 1e-3 + 1.0, bus.context(t_stop)
        _no_conflicting_duplicates(bus)


def _read_mcap(path: Path):
    """(topic, log_time_ns, payload) of every message of a finished recording."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f).iter_messages()]


def _anchor_seqs_in_recording(msgs, site: str) -> dict[str, list[int]]:
    out: dict[str, list[int]] = collections.defaultdict(list)
    for topic, _, data in msgs:
        pk = parse_key(topic)
        if pk is not None and pk.site == site and pk.kind in ("anchor_state", "range"):
            out[pk.anchor_id].append(msgspec.json.decode(data)["seq"])
    return out


def test_fusion_killed_and_restarted_resumes_without_conflicting_estimates(
        services, endpoint, tmp_path):
    """SIGKILL the fusion, restart it: estimates resume within seconds, no (node, epoch) is
    published twice with different content, and the recorder loses nothing meanwhile."""
    site, scenario = "faults2", "paper"
    anchors = ["uav1", "uav2", "uav3", "uav4"]
    rec = tmp_path / "fusion-fault.mcap"
    with _system(services, endpoint, tmp_path, site=site, scenario=scenario, anchors=anchors,
                 max_nodes=3, recorder=rec) as bus:
        ignore = {"fusion"}
        t_kill, w_kill = time.monotonic(), time.time_ns()
        services.kill("fusion")
        bus.pump(lambda: bus.keys.alive_fusion() not in bus.alive, timeout_s=10,
                 what="fusion token gone", services=services, ignore=ignore)
        t_gone = next(t for t, k, v in bus.alive_events
                      if t >= t_kill and not v and k == bus.keys.alive_fusion())
        t_restart, w_restart = time.monotonic(), time.time_ns()
        services.start("fusion-restarted", "fusion", "--site", site, "--connect", endpoint,
                       "--scenario", scenario, "--method", "dnls")

        def new(e: M.PositionEstimate) -> bool:  # published by the restarted process
            return e.t_pub_wall_ns > w_restart

        bus.pump(lambda: bus.first_estimate(t_restart, new) is not None, timeout_s=30,
                 what="estimates from the restarted fusion", services=services, ignore=ignore)
        t_resume, w_resume = bus.first_estimate(t_restart, new), time.time_ns()
        bus.pump(lambda: bus.epochs_after(t_resume) >= 10 and all(
            any(e.node_id == n for t, e in bus.estimates if t >= t_resume) for n in bus.nodes),
            timeout_s=20, what="1 s of estimates after the restart", services=services,
            ignore=ignore)
        repeats = _no_conflicting_duplicates(bus)
        missing = _missing_epochs(bus, bus.nodes, t_kill, t_resume + 0.5)
        codes = services.stop(["recorder"])
        assert codes["recorder"] == 0, services.log("recorder")[-2000:]
    msgs = _read_mcap(rec)
    seqs = _anchor_seqs_in_recording(msgs, site)
    assert set(seqs) == set(anchors)
    for a, s in seqs.items():
        assert _seq_gaps(s) == [], (a, _seq_gaps(s)[:5])  # nothing lost at the recorder
    outage = [m for m in msgs if w_kill < m[1] < w_resume and "/anchor/" in m[0]]
    expected = (w_resume - w_kill) * 1e-9 * 10 * len(anchors) * 4  # state + 3 ranges, 10 Hz
    _report("fusion SIGKILL + restart", token_gone_s=round(t_gone - t_kill, 3),
            restart_to_first_estimate_s=round(t_resume - t_restart, 3),
            outage_s=round(t_resume - t_kill, 3), estimates_missing=missing,
            exact_repeats=repeats, recorder_anchor_msgs_during_outage=len(outage),
            recorder_expected_about=round(expected))
    assert t_resume - t_restart < 10.0
    assert len(outage) >= 0.8 * expected


def test_router_killed_and_restarted_clients_reconnect_nothing_lost_after(
        services, endpoint, tmp_path):
    """SIGKILL the router, restart it on the same port: every client reconnects and
    re-declares (tokens, subscriptions); from each anchor's first message after the
    reconnection no message is lost at the test's subscriber nor at the recorder, and the
    recording shows the gap."""
    site, scenario = "faults3", "paper"
    anchors = ["uav1", "uav2", "uav3", "uav4"]
    rec = tmp_path / "router-fault.mcap"
    with _system(services, endpoint, tmp_path, site=site, scenario=scenario, anchors=anchors,
                 max_nodes=3, recorder=rec) as bus:
        ignore = {"router"}
        everyone = {bus.keys.alive_anchor(a) for a in anchors} | {
            bus.keys.alive_fusion(), bus.keys.alive_recorder()}
        t_kill, _w_kill = time.monotonic(), time.time_ns()
        services.kill("router")
        bus.pump(lambda: not bus.alive, timeout_s=10, what="every token gone with the router",
                 services=services, ignore=ignore)
        t_gone = max(t for t, _, v in bus.alive_events if t >= t_kill and not v)
        t_restart = time.monotonic()
        services.start("router-restarted", "router", "--listen", endpoint)
        bus.pump(lambda: everyone <= bus.alive, timeout_s=30, what="every token back",
                 services=services, ignore=ignore)
        t_back = max(t for t, k, v in bus.alive_events if t >= t_restart and v)
        full = set(anchors)
        bus.pump(lambda: bus.first_estimate(t_restart, lambda e: set(e.used_anchors) == full),
                 timeout_s=30, what="fixes with every anchor after the restart",
                 services=services, ignore=ignore)
        t_fix = bus.first_estimate(t_restart, lambda e: set(e.used_anchors) == full)
        bus.pump(lambda: all(bus.seqs[a][-1][0] > t_restart for a in anchors), timeout_s=20,
                 what="a message from every anchor after the restart", services=services,
                 ignore=ignore)
        n_first = {a: next(i for i, (t, _) in enumerate(bus.seqs[a]) if t > t_restart)
                   for a in anchors}
        bus.pump(lambda: all(len(bus.seqs[a]) - n_first[a] >= 40 for a in anchors),
                 timeout_s=20, what="1 s of anchor messages after the reconnection",
                 services=services, ignore=ignore)
        lost_gap = {}
        for a in anchors:
            s = [q for _, q in bus.seqs[a]]
            gaps = _seq_gaps(s)
            assert len(gaps) <= 1, (a, gaps)  # only the outage
            after = [q for t, q in bus.seqs[a] if t > t_restart]
            assert _seq_gaps(after) == [], (a, _seq_gaps(after))
            lost_gap[a] = sum(b - x - 1 for x, b in gaps)
        _no_conflicting_duplicates(bus)
        missing = _missing_epochs(bus, bus.nodes, t_kill, t_fix + 0.5)
        w_end = time.time_ns()
        codes = services.stop(["recorder"])
        assert codes["recorder"] == 0, services.log("recorder")[-2000:]
    msgs = _read_mcap(rec)
    seqs = _anchor_seqs_in_recording(msgs, site)
    for a, s in seqs.items():
        gaps = _seq_gaps(s)
        assert len(gaps) == 1, (a, gaps)  # the recording shows the outage, nothing else
    anchor_times = sorted(t for topic, t, _ in msgs if "/anchor/" in topic and t <= w_end)
    hole_s = max(b - a for a, b in itertools.pairwise(anchor_times)) * 1e-9
    live = [d for topic, _, d in msgs if topic.endswith("/recorder/liveliness")]
    _report("router SIGKILL + restart", tokens_gone_s=round(t_gone - t_kill, 3),
            restart_to_all_tokens_s=round(t_back - t_restart, 3),
            restart_to_full_fix_s=round(t_fix - t_restart, 3),
            outage_s=round(t_back - t_kill, 3),
            anchor_msgs_lost_in_outage=lost_gap, lost_after_reconnect=0,
            estimates_missing=missing, recording_hole_s=round(hole_s, 3),
            recorder_liveliness_events=len(live))
    assert hole_s >= (t_restart - t_kill) * 0.9
    assert t_back - t_restart < 15.0


# ----------------------------------------------------------------------------- secured bus
REPO = Path(__file__).resolve().parents[2]


def test_secured_emulation_every_service_logs_in(services, tmp_path):
    """`diffpos emulate --security-profile`: router with TLS + passwords + ACL, each service
    with its own identity file; the run scores as usual, no service runs unauthenticated,
    the rendered secrets are removed afterwards."""
    summary_path = tmp_path / "summary.json"
    logs = tmp_path / "logs"
    p = services.start("emulate", "emulate", "paper", "--duration", "2", "--channel", "ideal",
                       "--security-profile", str(REPO / "security" / "profile.dev.toml"),
                       "--record", "off", "--dashboard", "off", "--json", str(summary_path),
                       "--no-progress", "--log-dir", str(logs))
    assert p.wait(timeout=120) == 0, services.log("emulate")[-3000:]
    s = json.loads(summary_path.read_text())
    assert s["secured"] is True and s["endpoint"].startswith("tls/localhost:")
    assert s["estimates"] == 6 * 20 and not s["lost"]
    assert sum(s["status"].get(k, 0) for k in M.GOOD_STATUSES) >= 0.9 * s["estimates"], s
    names = {f.stem for f in logs.iterdir()}
    assert names >= {"router", "fusion", "anchor-uav1", "anchor-uav4"}
    for f in logs.iterdir():
        text = f.read_text(errors="replace")
        assert "UNAUTHENTICATED" not in text, f.name
        assert "login is refused" not in text, f.name
    # the orchestrator's own session is secured too, and the rendered files are gone
    assert "UNAUTHENTICATED" not in services.log("emulate")
    # no process this test started still runs from the (deleted) private config directory
    assert not services.own_processes(b"diffpos-zenoh-")


def test_zenoh_config_option_file_env_override_and_errors(tmp_path, monkeypatch, caplog):
    """--zenoh-config (and its env default) replaces the plain default, an explicit
    --connect replaces the file's endpoints, a missing file is a one-line ConfigError,
    health takes --connect or --zenoh-config, never both."""
    import argparse
    import logging

    from diffpos_services.bus.session import add_zenoh_arguments, service_settings
    from diffpos_services.cli.main import main as health_main
    from diffpos_services.errors import ConfigError

    f = tmp_path / "client.json5"
    f.write_text('// a comment\n{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7999"],'
                 ' timeout_ms: -1 }, transport: { auth: { usrpwd: { user: "u", password: "p" } } } }')
    monkeypatch.setenv("DIFFPOS_ZENOH_CONFIG", str(f))
    ap = argparse.ArgumentParser()
    add_zenoh_arguments(ap)
    log = logging.getLogger("diffpos.test")
    with caplog.at_level(logging.WARNING, logger="diffpos.test"):
        zs = service_settings(ap.parse_args([]), log)
    assert zs.connect == ("tcp/127.0.0.1:7999",) and zs.config is not None
    assert json.loads(zs.to_config().get_json("transport/auth/usrpwd"))["user"] == "u"
    assert [r.levelno for r in caplog.records] == [logging.WARNING]  # plain tcp, loopback
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="diffpos.test"):
        zs = service_settings(ap.parse_args(["--connect", "tcp/10.1.2.3:7447"]), log)
    assert zs.connect == ("tcp/10.1.2.3:7447",)
    assert caplog.records[0].levelno == logging.ERROR
    assert caplog.records[0].getMessage().startswith("NOT loopback")
    monkeypatch.delenv("DIFFPOS_ZENOH_CONFIG")
    ap = argparse.ArgumentParser()
    add_zenoh_arguments(ap, mode="router")
    with pytest.raises(ConfigError, match=r"missing\.json5: file not found"):
        service_settings(ap.parse_args(["--zenoh-config", str(tmp_path / "missing.json5")]))
    zs = service_settings(ap.parse_args(["--listen", "tcp/127.0.0.1:7998"]))
    assert zs.mode == "router" and zs.listen == ("tcp/127.0.0.1:7998",)
    with pytest.raises(SystemExit):
        health_main(["health", "--connect", "tcp/127.0.0.1:1", "--zenoh-config", str(f),
                     "--liveliness", "diffpos/x/alive/fusion"])


def test_open_session_waits_and_says_a_login_may_be_refused():
    """With a user/password and no router the retry loop's message names both causes; the
    stop event ends the wait (what SIGTERM does during start-up)."""
    import logging
    port = free_tcp_port()
    cfg = zenoh.Config.from_json5(json.dumps({
        "mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{port}"], "timeout_ms": -1},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": "fusion", "password": "nope"}}}}))
    stop = threading.Event()
    seen: list[str] = []

    class Stopper(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            seen.append(record.getMessage())
            stop.set()

    log = logging.getLogger("diffpos.test.open")
    log.addHandler(Stopper())
    log.setLevel(logging.INFO)
    t0 = time.monotonic()
    assert open_session(cfg, stop, logger=log, attempt_ms=200) is None
    assert seen == ["waiting for the router or the login is refused: check user/password"]
    assert time.monotonic() - t0 < 8.0  # the first message comes at the 10th attempt (200 ms each)
    # the caller's configuration is not modified (still waits forever)
    assert json.loads(cfg.get_json("connect/timeout_ms")) == -1


def test_security_profile_lease_sets_every_client_link_lease(tmp_path):
    """``lease_ms`` in a security profile (hang detection on the secured bus) goes into every
    client file as transport/link/tx/lease; absent, the files are unchanged; bad values are
    refused naming the field."""
    from diffpos_services.bus.security.configs import client_config, to_zenoh
    from diffpos_services.bus.security.profile import SecurityError, profile_from_dict

    (tmp_path / "creds.txt").write_text("anchor-uav1:a\nfusion:f\n")
    base = {"anchors": ["uav1"], "users": {"fusion": "fusion"}, "dictionary_file": "creds.txt"}
    prof = profile_from_dict({**base, "lease_ms": 2000}, root=tmp_path)
    for user in ("anchor-uav1", "fusion"):
        cfg = client_config(prof, user)
        assert cfg["transport"]["link"]["tx"] == {"lease": 2000}
        assert to_zenoh(cfg).get_json("transport/link/tx/lease") == "2000"  # zenoh takes it
    plain = client_config(profile_from_dict(base, root=tmp_path), "fusion")
    assert "tx" not in plain["transport"]["link"]
    for bad in (0, 50, "1000", True, 1.5):
        with pytest.raises(SecurityError, match="lease_ms"):
            profile_from_dict({**base, "lease_ms": bad}, root=tmp_path)
