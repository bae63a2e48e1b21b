"""The recorder's drain thread at stop (``recorder._Drain``), in-process with a stand-in channel.

After the session closes, the drain thread normally sees ``recv()`` raise once the queued
samples are taken. If the channel stayed open (a sender kept alive: zenoh-c #1240 /
zenoh-pico #1120 describe session drops that do not close at once) ``recv()`` would block
forever and the recorder with it (it joined the thread without a timeout). ``finish`` now
stops waiting once the thread has sat in ``recv()`` with nothing taken for ``idle_s``: the
channel is empty then, so every sample queued before is written and the file is complete;
a sample taken afterwards is counted, not written into the closed file.

A drain thread stalled right after a ``recv()`` (descheduled, or the whole process frozen
for longer than ``idle_s``) looks the same from outside as one idle in ``recv()``: before
giving up, ``finish`` takes and writes what the channel still holds (else the queue behind
the stalled sample was counted late, never written), and a freeze seen on a single look (the
clock jumped) is not idleness.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass

import zenoh
from diffpos_services.recorder import _Drain, _ForeignSink
from diffpos_services.recording.reader import McapScanner
from diffpos_services.recording.writer import McapSink
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

KEY = Keys("drain").anchor_range("a1", "n1")
#: a generous bound on a stop that must not hang (not a speed target) [s]
HANG_S = 20.0


@dataclass
class _Payload:
    data: bytes
    seq: int = -1

    def to_bytes(self) -> bytes:
        return self.data


@dataclass
class _Sample:
    key_expr: str
    payload: _Payload
    kind: zenoh.SampleKind
    timestamp: None = None


class _Channel:
    """A subscriber stand-in: ``recv()`` returns the queued samples, blocks while none is
    queued, and raises ``zenoh.ZError`` (a closed channel) when it takes ``CLOSED``."""

    CLOSED = object()

    def __init__(self, stall_at: int | None = None) -> None:
        self.q: queue.Queue = queue.Queue()
        self.stall_at = stall_at  # recv() holds this sample until ``release`` is set
        self.stalled = threading.Event()
        self.release = threading.Event()

    def recv(self):
        item = self.q.get()
        if item is self.CLOSED:
            self.q.put(item)  # stays closed (try_recv sees it too)
            raise zenoh.ZError("channel closed")
        if self.stall_at is not None and item.payload.seq == self.stall_at:
            self.stalled.set()  # taken from the channel, not yet returned: the thread stalls
            assert self.release.wait(HANG_S)
        return item

    def try_recv(self):
        try:
            item = self.q.get_nowait()
        except queue.Empty:
            return None
        if item is self.CLOSED:
            self.q.put(item)
            raise zenoh.ZError("channel closed")
        return item


def _sample(seq: int) -> _Sample:
    msg = M.RangeMeasurement(anchor_id="a1", node_id="n1", t_ns=1_000 + seq, seq=seq,
                             range_m=20.0, sigma_m=0.2, snr_db=15.0, t_pub_wall_ns=1_000 + seq)
    return _Sample(KEY, _Payload(M.encode(msg), seq), zenoh.SampleKind.PUT)


def _start(tmp_path, n: int, stall_at: int | None = None) -> tuple[_Drain, _Channel, McapSink]:
    sink = McapSink(tmp_path / "drain.mcap")
    chan = _Channel(stall_at)
    for i in range(n):
        chan.q.put(_sample(i))
    drain = _Drain(chan, sink, threading.Event(), None, _ForeignSink(None))
    drain.start()
    return drain, chan, sink


def _finish(drain: _Drain, idle_s: float) -> bool:
    """``drain.finish(idle_s)`` on a helper thread, so a regression fails instead of
    hanging the test run."""
    out: list[bool] = []
    t = threading.Thread(target=lambda: out.append(drain.finish(idle_s)), daemon=True)
    t.start()
    t.join(HANG_S)
    assert not t.is_alive(), "finish() did not return: the stop is unbounded"
    return out[0]


def _recorded_seqs(path) -> list[int]:
    scanner = McapScanner(path)
    seqs = [m.sequence for batch in scanner.iter_batches() for m in batch if m.topic == KEY]
    assert scanner.complete  # footer and index: the file was finalised
    return seqs


def test_channel_left_open_stop_is_bounded_and_keeps_every_queued_sample(tmp_path):
    n = 300
    drain, chan, sink = _start(tmp_path, n)
    assert _finish(drain, idle_s=0.2) is False  # gave up on the open channel
    assert drain.is_alive()  # still blocked in recv()
    stats = sink.close()
    assert stats.received == stats.written == n
    assert _recorded_seqs(sink.path) == list(range(n))
    # a sample the channel hands out after the stop is counted, never written
    chan.q.put(_sample(n))
    chan.q.put(_Channel.CLOSED)
    drain.join(HANG_S)
    assert not drain.is_alive()
    assert drain.late == 1 and drain.taken == n + 1
    assert sink.stats.received == n


def test_channel_closed_after_the_queue_every_sample_written(tmp_path):
    n = 300
    drain, chan, sink = _start(tmp_path, n)
    chan.q.put(_Channel.CLOSED)  # the session closed: recv() raises after the queue
    assert _finish(drain, idle_s=60.0) is True
    assert drain.late == 0
    sink.close()
    assert _recorded_seqs(sink.path) == list(range(n))


def test_drain_stalled_after_recv_the_queue_behind_it_is_still_written(tmp_path):
    """The drain thread takes sample ``k`` and stalls before its next step (so it looks idle
    in recv()) with ``n - k - 1`` samples still queued: ``finish`` gives up (bounded), but
    first writes the queued samples itself. Only the stalled sample is counted late (it is in
    the thread's hands: nothing outside can tell). Before the fix finish gave up with the
    whole queue behind ``k`` unwritten (counted late once the thread went on)."""
    n, k = 300, 100
    drain, chan, sink = _start(tmp_path, n, stall_at=k)
    assert chan.stalled.wait(HANG_S)
    assert _finish(drain, idle_s=0.2) is False
    stats = sink.close()
    chan.release.set()
    chan.q.put(_Channel.CLOSED)
    drain.join(HANG_S)
    assert not drain.is_alive()
    assert _recorded_seqs(sink.path) == [i for i in range(n) if i != k]
    assert stats.written == n - 1 and drain.late == 1


def test_a_freeze_seen_on_one_look_is_not_idleness(tmp_path, monkeypatch):
    """The drain thread stalls briefly (0.3 s, under ``idle_s``) after taking sample ``k``
    while the clock jumps by 10 s (the process was frozen: a paused VM, SIGSTOP): the next
    look sees "nothing taken for 10 s". ``finish`` must wait for real slices of idleness,
    so the thread goes on and every sample is written when the channel closes (before the
    fix it gave up on that one look and the rest was counted late)."""
    n, k = 300, 100
    drain, chan, sink = _start(tmp_path, n, stall_at=k)
    assert chan.stalled.wait(HANG_S)
    real = time.monotonic
    t0 = real()
    jumped = {"done": False}

    def frozen_clock() -> float:
        # the first call (finish's start) reads the true time; every later one is 10 s on
        if not jumped["done"]:
            jumped["done"] = True
            return real()
        return real() + 10.0

    import diffpos_services.recorder as rec
    monkeypatch.setattr(rec, "time", _Clock(frozen_clock))
    threading.Timer(0.3, chan.release.set).start()
    chan.q.put(_Channel.CLOSED)
    assert _finish(drain, idle_s=1.0) is True
    assert real() - t0 < HANG_S
    assert drain.late == 0
    sink.close()
    # every sample once (in order unless the release came more than 4 slices late, when
    # finish wrote the queue itself before the held sample: still nothing lost)
    assert sorted(_recorded_seqs(sink.path)) == list(range(n))


class _Clock:
    """A stand-in for the recorder module's ``time``: ``monotonic`` replaced, the rest
    the real module's."""

    def __init__(self, monotonic) -> None:
        self.monotonic = monotonic

    def __getattr__(self, name: str):
        return getattr(time, name)
