"""The services' heartbeats in a recording: which process stalled, and when.

Every service publishes a :class:`~diffpos_services.wire.messages.Heartbeat` twice a second
(:mod:`diffpos_services.bus.heartbeat`) and the recorder records them. :class:`HeartbeatLog`
reads them back per publisher (a service, or one anchor) and per process start (the
heartbeat's ``instance``): how many beats, how far the progress counter went, the longest
silence (no heartbeat at all: a stopped or frozen process, or the recorder itself not
recording) and the longest stall (heartbeats with the same progress while work was pending:
a stuck process), each with when it began. ``diffpos inspect`` prints them.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from diffpos_services.recording.topics import natural_key
from diffpos_services.wire import messages as M

__all__ = ["HeartbeatLog", "ProcessBeats"]


@dataclass
class ProcessBeats:
    """One process start's heartbeats (receive times [ns] as recorded).

    Attributes
    ----------
    who : str
        ``fusion``, ``recorder``, ``dashboard`` or ``anchor <id>``.
    instance : str
        The process start's nonce.
    pid : int
    beats : int
    first_ns, last_ns : int [ns]
        Receive times of the first and last heartbeat.
    first_progress, last_progress : int
        The progress counter at the first and last heartbeat.
    regressions : int
        Heartbeats whose progress was below the one before (never, for a working service).
    longest_silence_s : float [s]
        Longest time between two heartbeats.
    silence_from_ns : int [ns]
        When that silence began (the heartbeat before it; 0: never more than one beat).
    longest_stall_s : float [s]
        Longest time the progress stayed the same while work was pending.
    stall_from_ns : int [ns]
        When that stall began (0: none).
    """

    who: str
    instance: str
    pid: int
    beats: int = 0
    first_ns: int = 0
    last_ns: int = 0
    first_progress: int = 0
    last_progress: int = 0
    regressions: int = 0
    longest_silence_s: float = 0.0
    silence_from_ns: int = 0
    longest_stall_s: float = 0.0
    stall_from_ns: int = 0
    _advanced_ns: int = 0  # last receive time the progress advanced (or work was none)

    def add(self, hb: M.Heartbeat, log_ns: int) -> None:
        if self.beats == 0:
            self.first_ns = self._advanced_ns = log_ns
            self.first_progress = self.last_progress = hb.progress
        else:
            gap = (log_ns - self.last_ns) / 1e9
            if gap > self.longest_silence_s:
                self.longest_silence_s, self.silence_from_ns = gap, self.last_ns
            if hb.progress < self.last_progress:
                self.regressions += 1
            if hb.progress != self.last_progress or hb.pending == 0:
                self._advanced_ns = log_ns
            else:
                stall = (log_ns - self._advanced_ns) / 1e9
                if stall > self.longest_stall_s:
                    self.longest_stall_s, self.stall_from_ns = stall, self._advanced_ns
            self.last_progress = hb.progress
        self.beats += 1
        self.last_ns = log_ns

    def as_dict(self) -> dict:
        d = asdict(self)
        d.pop("_advanced_ns")
        return d


class HeartbeatLog:
    """Heartbeats of a recording, per publisher and process start (see the module docstring).

    Feed it every heartbeat message (:meth:`add`), then read :meth:`processes`."""

    def __init__(self) -> None:
        self._by: dict[tuple[str, str], ProcessBeats] = {}
        self._decode = M.decoder(M.Heartbeat)
        self.bad = 0

    def add(self, data: bytes, log_ns: int) -> None:
        """One recorded heartbeat payload and its receive time [ns]."""
        try:
            hb = self._decode(data)
        except M.DecodeError:
            self.bad += 1
            return
        who = f"anchor {hb.anchor_id}" if hb.anchor_id else hb.service
        p = self._by.get((who, hb.instance))
        if p is None:
            p = self._by[(who, hb.instance)] = ProcessBeats(who, hb.instance, hb.pid)
        p.add(hb, log_ns)

    def processes(self) -> list[ProcessBeats]:
        """Every process start seen, by publisher, then by first heartbeat."""
        return sorted(self._by.values(), key=lambda p: (natural_key(p.who), p.first_ns))
