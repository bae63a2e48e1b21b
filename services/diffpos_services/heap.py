"""Keep freed memory in the process' heap (glibc ``mallopt``): no page faults per update.

The tracker's update allocates its (N, H, M, K) temporaries afresh every call (paths,
Jacobians, SNR predictions, selections: ~1-5 MB for a 100-node batch). With glibc's default
allocator settings these come from ``mmap`` or from a heap top that is trimmed back to the
kernel when freed, so every call touches fresh pages and pays a minor page fault (and the
kernel's zeroing) per 4 KB page. :func:`keep_heap` raises the mmap threshold (arrays up to
it come from the heap) and the trim threshold (freed heap memory stays mapped), so the pages
are reused from one call to the next. The numbers computed do not change (the same
operations on the same values; the large and soak replays' estimate hashes are unchanged).

Measured (2-core shared VM; ``tracking.update`` on four batches of 58-91 nodes captured from
the 16 x 200 soak's schedule, 20 repetitions each, the best): default 103-106 ms CPU, system
time 0.41-0.51 s, 185,000 minor faults; with the heap kept 85-93 ms, 0.10-0.12 s, 25,000
(the environment's ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` give the same).
The whole in-process fusion on the soak's schedule (``benchmarks/bench_fusion_cost.py
--schedule soak16x200.mcap``, load 1.5-3, three runs each, alternated): 0.434-0.455 ms CPU
per node-epoch without, 0.390-0.402 with (the code before this session's tracker changes:
0.472-0.505); system time 3.60 -> 0.69 s, minor faults 1,356,000 -> 65,000, peak RSS 343.5
-> 346.2 MB (user time 27.8 -> 27.3 s: the saving is the kernel's page faults). The cost: the
process keeps its peak heap (plus fragmentation) instead of returning it; a process should
call this once at start, before its working set is built (``mallopt`` applies to later
allocations).

Process-wide and not part of any computation, so it lives in the services, not the pure
core: the fusion's process (``fusion.service.run_fusion``), its worker processes
(``fusion.worker_proc.worker_main``), ``diffpos replay`` and the benchmarks that stand for
them (``bench_fusion_cost.py``, ``bench_replay.py``) call it at start. Not glibc (musl,
macOS): nothing is changed and False is returned.
"""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["MMAP_THRESHOLD_BYTES", "TRIM_THRESHOLD_BYTES", "keep_heap"]

#: glibc's ``mallopt`` parameter numbers (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: Allocations below this come from the heap, not a fresh ``mmap`` (32 MiB: the maximum
#: of glibc's own dynamic threshold on 64-bit; a 1,000-node batch's largest temporary,
#: the (N, H, M, K, 3) Jacobians of ~4 hypotheses x 16 anchors x 18 slots, is 28 MB).
MMAP_THRESHOLD_BYTES = 32 * 2**20
#: Freed memory at the heap's top is returned to the kernel only beyond this.
TRIM_THRESHOLD_BYTES = 256 * 2**20


def keep_heap(mmap_threshold_bytes: int = MMAP_THRESHOLD_BYTES,
              trim_threshold_bytes: int = TRIM_THRESHOLD_BYTES) -> bool:
    """Set glibc's mmap and trim thresholds for this process (module docstring); True if
    both were set, False where the C library is not glibc (nothing changed)."""
    if min(mmap_threshold_bytes, trim_threshold_bytes) <= 0:
        raise ValueError("thresholds must be > 0 bytes")
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold_bytes)) == 1
    return mallopt(_M_TRIM_THRESHOLD, int(trim_threshold_bytes)) == 1 and ok
