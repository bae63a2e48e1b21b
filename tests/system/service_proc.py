"""A ``diffpos`` service started as a child for a system test: its own process group, its
JSON status lines collected from stdout by a thread, waits on those lines (readiness), never
on sleeps."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import threading

import pytest


class ServiceProc:
    """A child in its own process group; stdout JSON lines collected by a thread."""

    def __init__(self, argv: list[str], *, timeout_s: float) -> None:
        env = dict(os.environ, DIFFPOS_LOG_FORMAT="json", DIFFPOS_LOG_LEVEL="warning")
        env.pop("DIFFPOS_ZENOH_CONFIG", None)  # the test's own bus, not a user's config
        self.timeout_s = timeout_s
        self.p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True, start_new_session=True, env=env)
        self.lines: queue.Queue = queue.Queue()
        self.stderr: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()
        self._err = threading.Thread(target=lambda: self.stderr.extend(self.p.stderr),
                                     daemon=True)
        self._err.start()

    def _read(self) -> None:
        for line in self.p.stdout:
            try:
                self.lines.put(json.loads(line))
            except ValueError:
                self.lines.put({"event": "text", "line": line})
        self.lines.put(None)

    def wait_event(self, pred) -> dict:
        """Block until a status line satisfies ``pred`` (fails if the process exits first)."""
        last = None
        while True:
            try:
                ev = self.lines.get(timeout=self.timeout_s)
            except queue.Empty:
                pytest.fail(f"no matching status line within {self.timeout_s} s; last: {last}; "
                            "stderr: " + "".join(self.stderr)[-2000:])
            if ev is None:
                pytest.fail("process exited; stderr: " + "".join(self.stderr)[-2000:])
            if pred(ev):
                return ev
            last = ev

    def stderr_events(self) -> list[dict]:
        """The JSON log lines of stderr once the process closed it (call after it exited;
        fails if it did not close stderr within the timeout)."""
        self._err.join(self.timeout_s)
        if self._err.is_alive():
            pytest.fail("stderr still open after the process exited")
        out = []
        for line in self.stderr:
            try:
                out.append(json.loads(line))
            except ValueError:
                continue
        return out

    def kill(self) -> None:
        if self.p.poll() is None:
            try:
                os.killpg(self.p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self.p.wait(timeout=self.timeout_s)
