"""Issue 36 items 1 and 4 without a bus: the supervisor judges progress from heartbeats (a hung
process is a fault, killed and restarted; a fusion that cannot be restarted ends the run), two
publishers under one anchor key are told apart, and "ours" is a MAC under the run's token
bound to the full zenoh id, never an id prefix."""

from __future__ import annotations

import logging
import subprocess
import sys

import pytest
from diffpos_services.bus.integrity import PublisherGuard, Signer, Verifier, run_token
from diffpos_services.emulate.supervise import MAX_RESTARTS, Supervisor, format_faults
from diffpos_services.recorder import Provenance
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key

LOG = logging.getLogger("test")


class _Proc:
    """A stand-in for a Popen that never exits on its own."""

    def __init__(self, pid: int) -> None:
        self.pid, self.returncode = pid, None

    def poll(self):
        return self.returncode

    def wait(self, timeout=None):
        return self.returncode


@pytest.fixture
def pause_proc():
    """A real child in its own process group that waits forever (killed by the test's
    supervisor or at teardown)."""
    p = subprocess.Popen([sys.executable, "-c", "import signal; signal.pause()"],
                         start_new_session=True)
    yield p
    if p.poll() is None:
        p.kill()
        p.wait()


def _supervisor(procs, restarted):
    def restart(name, n):
        restarted.append((name, n))
        return f"restart {n}"
    sup = Supervisor(lambda: procs, restart, LOG, stall_s=5.0)
    sup.t0 = 0.0
    return sup


OTHER = 777_777  # another service whose heartbeats keep coming (the bus works)


def _check(sup, now):
    sup.on_heartbeat(OTHER, int(now * 10), 0, now=now)
    sup.check(now=now)


def test_silent_fusion_is_hung_killed_and_restarted(pause_proc):
    procs = [("fusion", pause_proc)]
    restarted: list = []
    sup = _supervisor(procs, restarted)
    sup.on_heartbeat(pause_proc.pid, 10, 0, now=100.0)
    sup.on_heartbeat(pause_proc.pid, 12, 0, now=100.5)  # progress at 100.5, then silence
    _check(sup, 105.0)
    assert sup.faults == [] and pause_proc.poll() is None  # 4.5 s: not yet
    _check(sup, 105.6)
    (f,) = sup.faults
    assert (f.service, f.kind) == ("fusion", "hung")
    assert f.detected_after_s == pytest.approx(5.1)
    assert pause_proc.wait(timeout=10) == -9 and f.exit_code == -9  # killed
    assert restarted == [("fusion", 1)]
    assert "no progress for 5.1 s" in f.note and "restart 1" in f.note
    _check(sup, 120.0)  # its exit is not a second fault
    assert len(sup.faults) == 1
    assert "hung, found at" in format_faults([f.as_dict()])


def test_stuck_with_work_pending_is_hung_but_idle_is_not(pause_proc):
    procs = [("recorder", pause_proc)]
    sup = _supervisor(procs, [])
    for k in range(20):  # heartbeats keep coming, same progress, nothing pending: idle
        sup.on_heartbeat(pause_proc.pid, 7, 0, now=100.0 + 0.5 * k)
        sup.check(now=100.0 + 0.5 * k)
    assert sup.faults == []
    for k in range(20, 40):  # the same progress with work pending: stuck
        sup.on_heartbeat(pause_proc.pid, 7, 3, now=100.0 + 0.5 * k)
        sup.check(now=100.0 + 0.5 * k)
    (f,) = sup.faults
    assert f.kind == "hung" and "3 items pending" in f.note


def test_no_one_is_hung_while_the_bus_is_silent():
    """The router died (or no heartbeat arrives from anyone): silence is the bus's fault,
    not each process's (before: every service was called hung, fusion and recorder killed)."""
    a, f, router = _Proc(11), _Proc(12), _Proc(13)
    sup = _supervisor([("router", router), ("anchor-uav1", a), ("fusion", f)], [])
    sup.on_heartbeat(a.pid, 1, 0, now=0.0)
    sup.on_heartbeat(f.pid, 1, 0, now=0.0)
    sup.check(now=6.0)  # everyone silent at once
    assert sup.faults == []
    sup.on_heartbeat(f.pid, 2, 0, now=6.5)  # the fusion talks, the anchor does not
    sup.check(now=6.6)
    assert [x.service for x in sup.faults] == ["anchor-uav1"]
    router.returncode = -9
    sup2 = _supervisor([("router", router), ("fusion", f)], [])
    sup2.on_heartbeat(f.pid, 1, 0, now=0.0)
    sup2.on_heartbeat(12_345, 1, 0, now=5.9)
    sup2.check(now=6.0)
    assert [x.service for x in sup2.faults] == ["router"]  # the router's death, only


def test_hung_anchor_reported_left_running_and_resumes():
    anchor = _Proc(999_999)
    sup = _supervisor([("anchor-uav2", anchor)], [])
    sup.on_heartbeat(anchor.pid, 30, 0, now=0.0)
    _check(sup, 6.0)
    (f,) = sup.faults
    assert f.kind == "hung" and f.exit_code is None and "left running" in f.note
    _check(sup, 7.0)
    assert len(sup.faults) == 1  # one fault per hang
    sup.on_heartbeat(anchor.pid, 31, 0, now=12.0)  # SIGCONT: progress again
    _check(sup, 12.1)
    assert "resumed at 12.1 s" in f.note and len(sup.faults) == 1


def test_fusion_that_cannot_be_restarted_ends_the_run():
    procs = []
    restarted: list = []
    sup = _supervisor(procs, restarted)
    for k in range(MAX_RESTARTS + 1):
        p = _Proc(1000 + k)
        p.returncode = -9
        procs.append(("fusion", p))
        sup.check(now=float(k))
    assert len(sup.faults) == MAX_RESTARTS + 1
    assert sup.fatal is not None and "the fusion is gone" in sup.fatal
    assert "died 4 times" in sup.faults[-1].note
    # a recorder that cannot be restarted does not end the run
    sup2 = _supervisor([], [])
    sup2.restarts["recorder"] = MAX_RESTARTS
    sup2._fault("recorder", -9)
    assert sup2.fatal is None


def test_guard_two_nonces_contested_until_one_remains():
    g = PublisherGuard(window_s=2.0)
    s = 1_000_000_000
    assert g.check("uav1", b"A", 1, 0) == (True, None)
    assert g.check("uav1", b"A", 2, s // 10) == (True, None)
    assert g.check("uav1", b"B", 2, s // 5) == (False, "contested")  # a second process
    assert g.check("uav1", b"A", 3, s // 2) == (False, None)
    assert g.contested() == ["uav1"] and g.detections() == {"uav1": 1}
    # B stops: A alone for more than the window -> trusted again
    assert g.check("uav1", b"A", 4, s // 2 + 2 * s + 1)[0] is True
    assert g.contested() == []
    assert g.check("uav2", b"C", 1, 0) == (True, None)  # other anchors unaffected


def test_guard_copier_of_nonce_caught_by_sequence_and_restart_is_not_a_second():
    g = PublisherGuard()
    assert g.check("uav1", b"A", 10, 0)[0]
    assert g.check("uav1", b"A", 10, 1) == (False, "contested")  # same nonce, same seq
    g.forget("uav1")  # its token went away
    assert g.check("uav1", b"NEW", 1, 2) == (True, None)


class _Bytes:
    def __init__(self, b: bytes) -> None:
        self.b = b

    def to_bytes(self) -> bytes:
        return self.b


class _Ts:
    def __init__(self, zid: str) -> None:
        self.zid = zid

    def get_id(self) -> str:
        return self.zid


class _Sample:
    def __init__(self, key, payload, attachment, zid) -> None:
        self.key_expr, self.payload = key, _Bytes(payload)
        self.attachment = None if attachment is None else _Bytes(attachment)
        self.timestamp = None if zid is None else _Ts(zid)


class _Session:
    def __init__(self, zid: str) -> None:
        self._zid = zid

    def zid(self) -> str:
        return self._zid


FUSION_ZID = "1a2b3c4d5e6f70819a2b3c4d5e6f7081"
FORGER_ZID = "1a2b3c4d5e6f7081ffffffffffffffff"  # the same 16-digit prefix


def test_signed_only_with_token_full_id_and_unchanged_payload():
    token = bytes(range(32))
    key = Keys("demo").node_estimate("n01")
    payload = b'{"schema":"diffpos.estimate.v2"}'
    att = Signer.for_session(_Session(FUSION_ZID), token).attachment(key, payload)
    v = Verifier(token)
    assert v.ours(_Sample(key, payload, att, FUSION_ZID))
    assert not v.ours(_Sample(key, payload + b" ", att, FUSION_ZID))  # altered
    assert not v.ours(_Sample(key, payload, att, FORGER_ZID))  # a copy from another id
    assert not v.ours(_Sample(key, payload, None, FUSION_ZID))  # unsigned
    assert not v.ours(_Sample(key.replace("n01", "n02"), payload, att, FUSION_ZID))
    assert not Verifier(bytes(32)).ours(_Sample(key, payload, att, FUSION_ZID))  # other run
    assert Signer.for_session(_Session(FUSION_ZID), b"").attachment(key, payload) is None
    assert run_token({"DIFFPOS_RUN_TOKEN": "00ff"}) == b"\x00\xff"
    assert run_token({}) is None


def test_recorder_needs_the_mac_not_the_prefix():
    """Issue 36: 716 forged estimates under the fusion's id prefix were recorded as live."""
    token = bytes(range(32))
    key = Keys("demo").node_estimate("n01")
    payload = b"{}"
    cfg = {"emulate": {"fusion_id_prefix": FUSION_ZID[:16]}, "fusion": {"anchors": ["uav1"]}}
    prov = Provenance.from_run_config(cfg, token)
    forged = _Sample(key, payload, None, FORGER_ZID)
    assert prov.foreign(key, forged)  # the prefix matches, but no MAC
    att = Signer.for_session(_Session(FUSION_ZID), token).attachment(key, payload)
    assert not prov.foreign(key, _Sample(key, payload, att, FUSION_ZID))
    # without a token (an old run configuration): the prefix, as before
    assert not Provenance.from_run_config(cfg).foreign(key, forged)


def test_heartbeat_keys_and_message():
    k = Keys("demo")
    assert parse_key(k.heartbeat("fusion")).service == "fusion"
    pk = parse_key(k.heartbeat("anchor", "uav3"))
    assert (pk.kind, pk.service, pk.anchor_id) == ("heartbeat", "anchor", "uav3")
    assert parse_key("diffpos/demo/heartbeat/intruder") is None
    with pytest.raises(ValueError):
        k.heartbeat("intruder")
    hb = M.Heartbeat(service="recorder", instance="ab", pid=3, seq=0, t_wall_ns=1,
                     period_ns=5, progress=2, pending=0, last_epoch=None, published=2)
    assert k.of(hb) == k.heartbeat("recorder")
    assert M.decoder(M.Heartbeat)(M.encode(hb)) == hb
