"""Watching an emulated run: ground truth, the lockstep clock, estimates, progress.

:class:`Monitor` runs on the orchestrator's session once the run has started. Each turn of
its loop publishes the ground truth due on the time base, releases emulated time in
lockstep runs, checks whether the run is over, drains the received estimates, diagnostics
and liveliness events into the :class:`~diffpos_services.emulate.scoring.Scorer`, and
updates the status line.
"""

from __future__ import annotations

import collections
import logging
import queue
import shutil
import sys
import time
from typing import Any

import numpy as np
import zenoh

from diffpos.emulation import TimeBase
from diffpos_services.emulate.scoring import Scorer
from diffpos_services.logs import STATUS, log_event
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys, parse_key

__all__ = ["LOOKAHEAD", "Monitor"]

#: lockstep: emulated time runs this many epochs ahead of the oldest incomplete epoch
LOOKAHEAD = 2
#: lockstep: an incomplete epoch is given up (an estimate lost, e.g. the fusion restarted)
#: 2 s after the last estimate once the fusion's diagnostics show it idle (nothing pending);
#: a fusion that is busy (no diagnostics while it solves: initialising the trackers of 50
#: nodes takes tens of seconds on a loaded 2-core machine) is waited for up to this long [s],
#: so a slow machine changes the run's duration, not its result.
LOCKSTEP_STALL_S = 120.0


class Monitor:
    """One run's monitoring loop (see the module docstring).

    Parameters
    ----------
    emu : Emulation
        The orchestrator: options, scenario, nodes, keys, run id, queue of received
        samples (``emu.q``), stop event; ``emu.diag`` is updated with the fusion's
        diagnostics.
    session : zenoh.Session
    tb : TimeBase
        The run's time base.
    """

    def __init__(self, emu: Any, session: Any, tb: TimeBase) -> None:
        o = emu.o
        self.emu, self.o, self.tb = emu, o, tb
        keys: Keys = emu.keys
        enc, bc = zenoh.Encoding.APPLICATION_JSON, zenoh.CongestionControl.BLOCK
        self.pubs = {("node", nid): session.declare_publisher(keys.truth_node(nid), encoding=enc,
                                                              congestion_control=bc)
                     for nid, _ in emu.nodes}
        self.pubs.update({("anchor", a.id): session.declare_publisher(
            keys.truth_anchor(a.id), encoding=enc, congestion_control=bc)
            for a in emu.scenario.anchors})
        self.end_ns = tb.t0_ns + round(o.duration_s * 1e9)
        self.period_ns = round(1e9 / o.rate_hz)
        self.scorer = Scorer(emu.nodes, emu.scenario.building, tb.t0_ns,
                             period_ns=self.period_ns, end_ns=self.end_ns)
        # estimates v2 (mnls, tracking) or v1 (dnls, lls, ippa)
        self.dec_est, self.dec_diag = M.estimate_decoder(), M.decoder(M.FusionDiagnostics)
        self.k_truth = 0
        # lockstep (speed 0): release emulated time epoch by epoch, LOOKAHEAD epochs ahead of
        # the oldest epoch whose estimates are not all in yet
        self.lockstep = o.speed == 0
        self.e0 = tb.t0_ns // self.period_ns
        self.per_epoch: collections.Counter[int] = collections.Counter()
        self.next_needed = 0
        self.clock_k = -1
        self.clock_wall = time.monotonic()
        self.clock_pub = session.declare_publisher(keys.run_clock(), encoding=enc,
                                                   congestion_control=bc) if self.lockstep else None
        self.last_est_wall = 0.0
        self.last_diag_wall = 0.0  # monotonic time of the last fusion diagnostics
        self.recent: collections.deque[tuple[float, float | None]] = collections.deque()
        self.next_status = 0.0
        self.finish_wall: float | None = None
        self.lost_events: list[str] = []
        self.tty = sys.stderr.isatty()

    # ------------------------------------------------------------------ time
    def release(self, k: int) -> None:
        """Lockstep: let emulated time run to the end of epoch ``k``."""
        self.clock_k = k
        self.clock_wall = time.monotonic()
        self.clock_pub.put(M.encode(M.RunClock(
            run_id=self.emu.run_id, t_ns=self.tb.t0_ns + (k + 1) * self.period_ns - 1)))

    def emu_now(self, wall_ns: int) -> int:
        """Emulated time [ns] now (lockstep: the end of the released epochs)."""
        if self.lockstep:
            return self.tb.t0_ns + (self.clock_k + 1) * self.period_ns
        return self.tb.now_ns(wall_ns)

    def advance_clock(self) -> None:
        """Lockstep: release the next epoch once the oldest one's estimates are all in."""
        n_nodes = len(self.emu.nodes)
        while self.per_epoch[self.next_needed] >= n_nodes:
            self.next_needed += 1
        if self.next_needed + LOOKAHEAD - 1 > self.clock_k:
            self.release(self.next_needed + LOOKAHEAD - 1)
        elif self._stalled():
            # no progress (an estimate lost?): move on rather than deadlock
            self.next_needed += 1
            self.release(self.next_needed + LOOKAHEAD - 1)

    def _stalled(self) -> bool:
        """Lockstep: no estimate for 2 s although the fusion reported itself idle since, or
        none for :data:`LOCKSTEP_STALL_S` at all."""
        since = max(self.clock_wall, self.last_est_wall, self.finish_wall or 0.0)
        quiet = time.monotonic() - since
        diag = self.emu.diag
        idle = self.last_diag_wall > since and diag is not None and diag.pending_epochs == 0
        return (quiet > 2.0 and idle) or quiet > LOCKSTEP_STALL_S

    # ------------------------------------------------------------------ truth
    def publish_truth(self, now_wall: int) -> None:
        """Ground truth of every epoch due on the time base (up to the end of the run)."""
        tb = self.tb
        while tb.t0_ns + self.k_truth * self.period_ns <= min(self.emu_now(now_wall),
                                                               self.end_ns - 1):
            self._truth_epoch(self.k_truth)
            self.k_truth += 1

    def _truth_epoch(self, k: int) -> None:
        emu, tb = self.emu, self.tb
        t_ns = tb.t0_ns + round(k * 1e9 / self.o.rate_hz)
        t_s = (t_ns - tb.t0_ns) * 1e-9
        for nid, tr in emu.nodes:
            p = np.asarray(tr.position_m(t_s), float)
            msg = M.GroundTruth(entity="node", id=nid, t_ns=t_ns, position_m=M.vec3(p),
                                velocity_m_s=M.vec3(tr.velocity_m_s(t_s)),
                                floor_index=int(emu.scenario.building.floor_index(p[2])))
            self.pubs[("node", nid)].put(M.encode(msg))
        for a in emu.scenario.anchors:
            msg = M.GroundTruth(entity="anchor", id=a.id, t_ns=t_ns,
                                position_m=M.vec3(a.trajectory.position_m(t_s)),
                                velocity_m_s=M.vec3(a.trajectory.velocity_m_s(t_s)), floor_index=None)
            self.pubs[("anchor", a.id)].put(M.encode(msg))

    # ------------------------------------------------------------------ end of run
    def finished(self, now_wall: int) -> bool:
        """True once the last epochs are in. Lockstep: every node's estimate of every epoch of
        the run arrived (or the fusion stalled, :meth:`_stalled`). Otherwise: the fusion's
        watermark past the end with nothing pending; or, if the machine cannot keep up, once
        estimates stop coming (none for 3 s after the end of the run)."""
        if self.finish_wall is None and self.emu_now(now_wall) >= self.end_ns:
            self.finish_wall = time.monotonic()
        if self.finish_wall is None:
            return False
        diag = self.emu.diag
        wm = diag.watermark_ns if diag else None
        if self.lockstep:  # every node-epoch in, or the fusion stalled
            n_epochs = -(-(self.end_ns - self.tb.t0_ns) // self.period_ns)
            return bool(self.next_needed >= n_epochs or self._stalled())
        return bool((wm is not None and wm >= self.end_ns - self.period_ns
                     and diag.pending_epochs == 0)
                    or time.monotonic() - max(self.finish_wall, self.last_est_wall) > 3.0)

    # ------------------------------------------------------------------ received
    def drain(self) -> None:
        """Handle what was received (waiting up to 50 ms for the first item)."""
        try:
            item = self.emu.q.get(timeout=0.05)
        except queue.Empty:
            item = None
        while item is not None:
            if item[0] == "data":
                self._on_data(item[1], item[2])
            elif item[0] == "alive" and not item[2] and self.finish_wall is None:
                # (anchors leave on their own at the end of the run: not a loss)
                self.lost_events.append(item[1])
                log_event(self.emu.log, logging.WARNING, "service lost", key=item[1])
            try:
                item = self.emu.q.get_nowait()
            except queue.Empty:
                item = None

    def _on_data(self, key: str, payload: bytes) -> None:
        pk = parse_key(key)
        try:
            if pk is not None and pk.kind == "estimate":
                est = self.dec_est(payload)
                self.last_est_wall = time.monotonic()
                self.per_epoch[est.epoch - self.e0] += 1
                self.recent.append((self.last_est_wall, self.scorer.add(est)))
                if not self.o.progress and len(self.recent) > 10_000:
                    self.recent.popleft()
            elif pk is not None and pk.kind == "diagnostics":
                self.emu.diag = self.dec_diag(payload)
                self.last_diag_wall = time.monotonic()
        except M.DecodeError as exc:
            log_event(self.emu.log, logging.WARNING, "bad message", key=key, error=str(exc)[:200])

    # ------------------------------------------------------------------ status line
    def status_line(self, latency_ms: float | None = None, width: int = 100) -> str:
        """What matters first, within 80 columns for 50 responders on 5 floors: emulated time,
        the responders placed now (newest estimate with a usable position) of all, how many
        on each floor, the least sure of them (lowest probability of its published floor),
        the end-to-end latency, then the median error of the placed responders, e.g.
        ``t 7.3/10s placed 48/50 F0:10 F1:9 F2:11 F3:10 F4:8 unsure n17 62% lat 25ms
        err 0.08m``; the parts that would pass ``width`` columns are left out, last first
        (the status line is then never cut). Lockstep runs show no speed."""
        o, sc = self.o, self.scorer
        el = max(min(self.emu_now(time.time_ns()), self.end_ns) - self.tb.t0_ns, 0) * 1e-9
        placed = sc.placed()
        floors = collections.Counter(f for f, _, _ in placed.values())
        per_floor = " ".join(f"F{f}:{n}" if f >= 0 else f"F?:{n}" for f, n in sorted(floors.items()))
        probs = [(p, nid) for nid, (_, p, _) in placed.items() if p == p]  # not NaN
        parts = [f"t {el:.1f}/{o.duration_s:g}s", f"placed {len(placed)}/{len(self.emu.nodes)}"]
        if per_floor:
            parts.append(per_floor)
        if probs:
            p, nid = min(probs)
            parts.append(f"unsure {nid} {100 * p:.0f}%")
        if latency_ms is not None:
            parts.append(f"lat {latency_ms:.0f}ms")
        errs = [e for _, _, e in placed.values() if e == e]
        if errs:
            parts.append(f"err {np.median(errs):.2f}m")
        while len(parts) > 2 and len(" ".join(parts)) > width - 1:
            parts.pop()
        return " ".join(parts)

    def progress(self) -> None:
        """The status line every 0.5 s (:data:`~diffpos_services.logs.STATUS`: log records
        print above it, cut to the terminal's width): :meth:`status_line` with the median
        end-to-end latency (anchor publish -> estimate received here, solve included) over
        the last 2 s. Not a terminal: logged at INFO every 0.5 s."""
        if not self.o.progress or time.monotonic() < self.next_status:
            return
        self.next_status = time.monotonic() + 0.5
        t_now = time.monotonic()
        recent = self.recent
        while recent and recent[0][0] < t_now - 2.0:
            recent.popleft()
        lat = self.emu.e2e.stats_ms(time.time_ns() - 2_000_000_000)
        line = self.status_line(lat["p50"] if lat["count"] else None,
                                width=shutil.get_terminal_size((100, 24)).columns)
        if self.tty:
            STATUS.show(line)
        else:
            log_event(self.emu.log, logging.INFO, "progress", status=line)

    # ------------------------------------------------------------------ loop
    def run(self) -> None:
        """Monitor until the run is over or stopped (results: :attr:`scorer`,
        :attr:`lost_events`)."""
        if self.lockstep:
            self.release(LOOKAHEAD - 1)
        self.last_est_wall = time.monotonic()
        self.next_status = time.monotonic()
        while True:
            now_wall = time.time_ns()
            self.publish_truth(now_wall)
            if self.emu.stop.is_set() or self.emu.supervisor.fatal is not None:
                break  # stopped, or the run cannot go on (the summary says why)
            if self.lockstep:
                self.advance_clock()
            if self.finished(now_wall):
                break
            self.drain()
            self.progress()
        if self.tty and self.o.progress:
            STATUS.done()
        for p in self.pubs.values():
            p.undeclare()
        if self.clock_pub is not None:
            self.clock_pub.undeclare()
