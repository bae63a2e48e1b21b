"""Child processes: start them so they die with their parent, stop their groups, free ports.

- :func:`child_env` marks a child's environment with this process's pid
  (:data:`PARENT_PID_ENV`); :func:`die_with_parent` (called by the child, through
  :class:`~diffpos_services.shutdown.Shutdown`) asks the kernel for SIGTERM when that parent dies.
- :func:`stop_process_groups` stops processes started with ``start_new_session=True``
  (SIGTERM, one shared deadline, SIGKILL); :func:`free_tcp_port` finds a port for a router.

Used by the commands that start processes (``diffpos emulate``), tests and benchmarks.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Mapping

__all__ = ["PARENT_PID_ENV", "child_env", "die_with_parent", "free_tcp_port",
           "stop_process_groups"]

#: environment variable naming the parent process a service must not outlive
#: (:func:`child_env` sets it, :class:`~diffpos_services.shutdown.Shutdown` acts on it)
PARENT_PID_ENV = "DIFFPOS_PARENT_PID"
_PR_SET_PDEATHSIG = 1


def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (bind to port 0)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def stop_process_groups(
    procs: list[subprocess.Popen],
    *,
    timeout_s: float,
    on_kill: Callable[[subprocess.Popen], None] | None = None,
) -> list[int]:
    """Stop processes started with ``start_new_session=True``: SIGTERM each process group,
    wait until ``timeout_s`` [s] after that (one shared deadline), SIGKILL the groups still
    running (``on_kill(proc)`` is called first, e.g. to log it). Returns the exit codes.

    Signalling the group, not just the process, also stops its children.
    """
    for p in procs:
        if p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    codes = []
    for p in procs:
        try:
            codes.append(p.wait(max(deadline - time.monotonic(), 0.05)))
        except subprocess.TimeoutExpired:
            if on_kill is not None:
                on_kill(p)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            codes.append(p.wait())
    return codes


def child_env(env: Mapping[str, str] | None = None) -> dict[str, str]:
    """The environment of a child service that must die with this process: ``env`` (default
    ``os.environ``) plus :data:`PARENT_PID_ENV` = this process's pid (see
    :func:`die_with_parent`). Nothing runs between fork and exec (no ``preexec_fn``), so it
    is safe after ``zenoh.open()``."""
    return dict(os.environ if env is None else env, **{PARENT_PID_ENV: str(os.getpid())})


def die_with_parent(sig: int = signal.SIGTERM) -> bool:
    """If :data:`PARENT_PID_ENV` is set: ask the kernel for ``sig`` when the parent dies
    (``prctl(PR_SET_PDEATHSIG)``, Linux; it survives ``exec``), even by SIGKILL. Returns
    False if the parent is already gone (the caller stops at once), else True.

    The signal comes when the *thread* that started this process ends: parents start their
    children from threads that outlive them (``diffpos emulate``: the main thread and the
    supervisor, joined after the children are stopped).
    """
    want = os.environ.get(PARENT_PID_ENV)
    if not want:
        return True
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0)
    # the parent may have died before prctl: then we were re-parented already
    return str(os.getppid()) == want
