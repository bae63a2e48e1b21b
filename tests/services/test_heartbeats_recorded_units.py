"""Heartbeats in recordings, piece by piece (the real run: tests/system/
test_heartbeats_recorded.py): their channels get the heartbeat schema, the recorder keeps only
the run's own (signed with the run token, or from one of its anchors), the summary finds
silences and stalls where they were planted, and the dashboard's heartbeat counts what its
drain loop takes with what waits in its ring as pending work."""

from __future__ import annotations

import threading

import rerun as rr
import zenoh
from diffpos_services.bus.integrity import Signer
from diffpos_services.dashboard.service import DashboardService
from diffpos_services.recorder import Provenance, _Drain, _ForeignSink
from diffpos_services.recording.heartbeats import HeartbeatLog
from diffpos_services.recording.schemas import SchemaRegistry
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

K = Keys("demo")
TOKEN = bytes(range(32))
ZID = "1a2b3c4d5e6f70819a2b3c4d5e6f7081"


class _Bytes:
    def __init__(self, b: bytes) -> None:
        self.b = b

    def to_bytes(self) -> bytes:
        return self.b


class _Sample:
    """A zenoh sample as the recorder sees it (heartbeats are signed, never stamped)."""

    def __init__(self, key: str, payload: bytes, attachment: bytes | None) -> None:
        self.key_expr, self.payload = key, _Bytes(payload)
        self.attachment = None if attachment is None else _Bytes(attachment)
        self.timestamp = None
        self.kind = zenoh.SampleKind.PUT


class _Sink:
    def __init__(self) -> None:
        self.written: list[str] = []

    def write(self, key: str, payload: bytes, rx_ns: int) -> None:
        self.written.append(key)


class _Session:
    def zid(self) -> str:
        return ZID


def _hb(progress: int, pending: int = 0, *, seq: int = 0, instance: str = "a1",
        service: str = "fusion", anchor_id: str | None = None) -> bytes:
    return M.encode(M.Heartbeat(service=service, instance=instance, pid=42, seq=seq,
                                t_wall_ns=1, period_ns=500_000_000, progress=progress,
                                pending=pending, last_epoch=None, published=0,
                                anchor_id=anchor_id))


def test_heartbeat_channels_get_the_heartbeat_schema():
    reg = SchemaRegistry()
    for key in (K.heartbeat("fusion"), K.heartbeat("dashboard"), K.heartbeat("anchor", "uav2")):
        entry = reg.for_key(key)
        assert entry is not None and entry.name == "diffpos.heartbeat.v1", key


def test_recorder_keeps_the_runs_heartbeats_only():
    key = K.heartbeat("fusion")
    data = _hb(5)
    signed = Signer.for_session(_Session(), TOKEN).attachment(key, data)
    prov = Provenance.from_run_config({"fusion": {"anchors": ["uav1"]}}, TOKEN)
    assert not prov.foreign(key, _Sample(key, data, signed))
    assert prov.foreign(key, _Sample(key, data, None))  # unsigned: someone else's
    assert prov.foreign(key, _Sample(key, _hb(6), signed))  # altered
    # without a token (an older run configuration): an anchor outside the run is foreign
    old = Provenance.from_run_config({"fusion": {"anchors": ["uav1"]}})
    assert not old.foreign(K.heartbeat("anchor", "uav1"), _Sample(key, data, None))
    assert old.foreign(K.heartbeat("anchor", "uav9"), _Sample(key, data, None))
    assert not old.foreign(key, _Sample(key, data, None))


def test_summary_finds_the_planted_silence_and_stall():
    """Beats every 0.5 s; a 3 s silence after t = 2 s; then 2.5 s of the same progress with
    work pending from t = 6 s; a restart (another instance) counts apart; idle (nothing
    pending) is no stall."""
    s = 1_000_000_000
    log = HeartbeatLog()
    times = [0.0, 0.5, 1.0, 1.5, 2.0, 5.0, 5.5, 6.0, 6.5, 7.0, 7.5, 8.0, 8.5, 9.0]
    progress = [0, 1, 2, 3, 4, 5, 6, 7, 7, 7, 7, 7, 7, 8]
    pending = [0, 0, 0, 0, 0, 0, 0, 3, 3, 3, 3, 3, 3, 0]
    for k, (t, p, q) in enumerate(zip(times, progress, pending, strict=True)):
        log.add(_hb(p, q, seq=k), round(t * s))
    for k in range(6):  # idle: the same progress, nothing pending
        log.add(_hb(10, 0, seq=k, instance="b2"), round((10 + 0.5 * k) * s))
    log.add(b"{not json", 0)
    first, second = log.processes()
    assert (first.instance, second.instance) == ("a1", "b2")
    assert first.beats == 14 and (first.first_progress, first.last_progress) == (0, 8)
    assert first.longest_silence_s == 3.0 and first.silence_from_ns == 2 * s
    assert first.longest_stall_s == 2.5 and first.stall_from_ns == 6 * s
    assert first.regressions == 0
    assert second.longest_stall_s == 0.0 and second.longest_silence_s == 0.5
    assert log.bad == 1


def test_dashboard_heartbeat_counts_what_the_drain_loop_takes():
    rec = rr.RecordingStream("test-dashboard-heartbeat")  # no sink: logs go nowhere
    svc = DashboardService(None, rec, site="demo")
    assert svc.progress() == (0, 0, None, 0)
    bad = b"{}"  # not an estimate view: taken, counted undecodable
    for _ in range(5):
        svc.ring.append(("estimate", bad, 0))
    assert (svc.progress().progress, svc.progress().pending) == (0, 5)  # stuck so far
    assert svc.drain() == 5
    assert (svc.progress().progress, svc.progress().pending) == (5, 0)


def test_recorder_writes_other_heartbeats_but_not_its_own():
    """Its own heartbeat in its own file could never show its own stall (whatever it writes
    proves it was working): left out; every other heartbeat, another recorder's too, kept."""
    sink = _Sink()
    drain = _Drain(None, sink, threading.Event(), None, _ForeignSink(None),
                   own_heartbeat=(K.heartbeat("recorder"), "me00"))
    mine = _hb(3, service="recorder", instance="me00")
    other = _hb(3, service="recorder", instance="b2b2")
    drain._put(_Sample(K.heartbeat("recorder"), mine, None))
    drain._put(_Sample(K.heartbeat("recorder"), other, None))
    drain._put(_Sample(K.heartbeat("fusion"), _hb(1, instance="me00"), None))
    assert sink.written == [K.heartbeat("recorder"), K.heartbeat("fusion")]
    assert drain.own_heartbeats == 1
