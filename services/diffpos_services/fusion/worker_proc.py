"""The worker process of the fusion's row-parallel pool (:mod:`diffpos_services.fusion.workers`,
whose docstring says why and how): the tasks it runs and its request loop.

The tasks' modules (M-NLS, the tracker's rows, the warm-up) are imported where they run, not
at the top: importing the pool (the fusion service does, whatever its method) loads no M-NLS
or tracker kernel module (tests/services/test_startup_loads.py); a worker process imports
them in :func:`worker_main`, before it says ready."""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import signal
import sys
import time
import traceback
from collections.abc import Callable
from multiprocessing.reduction import ForkingPickler
from typing import Any

import numpy as np

from diffpos_services.fusion import shm
from diffpos_services.heap import keep_heap

__all__ = ["TASKS", "worker_main"]

_PR_SET_PDEATHSIG = 1


def _task_update(model: tuple, *args):
    from diffpos_services.fusion.rows import run_update  # imported already: a dict look-up

    return run_update(model[0], *args)


def _task_mnls(model: tuple, apos, rng, sig, mask, snr_db, radio, rule, order=2):
    from diffpos.estimators.mnls import solver as mnls_solver  # as _task_update
    from diffpos.estimators.mnls.rules import SnrRule

    return mnls_solver.mnls(apos, rng, sig, building=model[0], mask=mask, snr_db=snr_db,
                            radio=radio, snr_rule=SnrRule(*rule), max_order=order)


def _task_fail(model: tuple, *args):
    """Fault injection for the tests: the worker raises, the caller computes locally."""
    raise RuntimeError("injected worker failure")


def _task_sleep(model: tuple, seconds: np.ndarray):
    """Fault injection for the tests: a worker that hangs (``seconds[0]``) then answers."""
    time.sleep(float(seconds[0]))
    return seconds


#: what a worker computes (the calling process runs the same functions for its own share)
TASKS: dict[str, Callable[..., Any]] = {"update": _task_update, "mnls": _task_mnls,
                                        "fail": _task_fail, "sleep": _task_sleep}


def _die_with(parent_pid: int) -> None:
    """SIGKILL when the parent dies (Linux), and exit at once if it is gone already."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if os.getppid() != parent_pid:
        os._exit(0)


def worker_main(conn: Any, parent_pid: int, model: tuple, shm_fd: int | None = None) -> None:
    """A worker process: map the caller's regions (descriptor ``shm_fd``, :mod:`.shm`),
    warm up on ``model`` = (building, radio or None, window height, first floor z), say ``("ready",
    pid, regions mapped)``, then answer ``(kind, args)`` requests with ``("ok",
    result, busy_s, t_done_s)`` or ``("err", traceback, 0.0)`` until ``stop`` or EOF (the parent is
    gone); ``busy_s`` [s] is the task's wall time (the caller balances the shares by it),
    ``t_done_s`` the :func:`time.perf_counter` at its end (CLOCK_MONOTONIC on Linux, the
    caller's clock too: it learns the per-request latency from it, :attr:`RowPool.latency_s`)."""
    _die_with(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C: the fusion stops us (or EOF)
    with contextlib.suppress(OSError):
        # a session of its own: Linux's autogroup scheduling (on by default) shares the CPU
        # fairly between sessions, so in the fusion's session the worker would only split
        # the fusion's one share on a busy machine (every anchor and the other jobs run in
        # sessions of their own); the fusion stops it, SIGKILL of the fusion kills it
        # (PDEATHSIG above, EOF on the pipe), not a signal to the fusion's process group
        os.setsid()
    regions = None
    if shm_fd is not None:
        with contextlib.suppress(OSError, ValueError):
            regions = shm.Regions.attach(shm_fd)
    keep_heap()  # as the fusion's process (diffpos_services.heap)
    # the tasks' modules: imported (and their kernels loaded) before the worker says ready
    from diffpos_services.fusion.rows import run_update  # noqa: F401
    from diffpos_services.fusion.warm import warm_model

    warm_model(*model)
    conn.send(("ready", os.getpid(), regions is not None))
    while True:
        reply_shm = False
        try:
            kind, args = conn.recv()
            if isinstance(args, shm.ShmRef):  # the request is in our request region
                reply_shm, args = args.reply, shm.unpack(regions.request, args)
        except (EOFError, OSError):
            return
        except Exception:  # the request was read but not decoded: the caller awaits a reply
            kind, args = "", traceback.format_exc(limit=8)
        if kind == "stop":
            return
        t0 = time.perf_counter()
        try:
            if not kind:
                raise RuntimeError(f"request not decoded: {args}")
            value = TASKS[kind](model, *args)
            t1 = time.perf_counter()
            ref = shm.pack(regions.reply, value) if reply_shm else None
            payload = _dumps(("ok", value if ref is None else ref, t1 - t0, t1))
        except Exception:  # reported to the caller, which computes the share locally
            payload = _dumps(("err", traceback.format_exc(limit=8), 0.0))
        try:
            conn.send_bytes(payload)
        except (OSError, ValueError):
            return


def _dumps(msg: Any) -> memoryview:
    """``msg`` pickled as :meth:`multiprocessing.connection.Connection.send` does: pickled
    whole before any byte is written, so a message that cannot be pickled leaves the pipe
    as it was (the other end reads it with ``recv``)."""
    return ForkingPickler.dumps(msg)
