"""How long this process has spent loading (or compiling) numba kernels: the kernels' share of a
start-up, apart from the imports and the run (docs/startup.md).

Importing this module registers a listener on numba's compiler lock, which a dispatcher holds
while it loads a signature from the on-disk cache or compiles it (numba's own first-use set-up
included); :func:`kernel_load_s` is the wall time spent inside it since then. Loads before the
import are not counted: a command that reports the figure imports this module before any
kernel module (a kernel module with explicit signatures loads them when it is imported).
"""

from __future__ import annotations

import time
from typing import Any

from numba.core import event as numba_event

__all__ = ["kernel_load_s"]


class _KernelClock(numba_event.Listener):
    """Wall seconds inside numba's compiler lock, nested acquisitions counted once. Every
    thread's are counted (the lock is global: a thread that waits for it is held up too)."""

    def __init__(self) -> None:
        self.depth, self.t0, self.total_s = 0, 0.0, 0.0

    def on_start(self, event: Any) -> None:
        if self.depth == 0:
            self.t0 = time.perf_counter()
        self.depth += 1

    def on_end(self, event: Any) -> None:
        self.depth -= 1
        if self.depth == 0:
            self.total_s += time.perf_counter() - self.t0


_CLOCK = _KernelClock()
numba_event.register("numba:compiler_lock", _CLOCK)


def kernel_load_s() -> float:
    """Wall seconds this process spent loading numba kernels from the on-disk cache (or
    compiling them on a fresh cache) since this module was imported."""
    return _CLOCK.total_s
