"""Shared-memory transport of the fusion worker pool's big messages
(:mod:`diffpos_services.fusion.workers`).

Why: a 128-row tracker share is ~1.4 MB each way (the tracker state with its SNR caches).
Through the pool's pipe (a Unix socket) one round trip of that size cost the caller ~2.7-3.9
ms of CPU and 4-4.6 ms of wall, through a mapped file 0.7 ms and 1.7 ms (2026-11-27, 2-core
VM, load 1.4-2.3; echo of 1.4 MB of float64 arrays, ``/tmp`` prototype of this module): the
socket copies every byte through the kernel in ~200 KB pieces, each a wake-up of the other
process, and the receiver grows and copies its buffer again before unpickling.

How: each worker has one anonymous file (``memfd_create``: no name in any directory, so
nothing outlives the two processes, even when the caller is SIGKILLed before the worker
mapped it) mapped by both processes, a request region and a reply region of
:data:`REGION_BYTES` each; its descriptor reaches the spawned worker as multiprocessing
passes a pipe's (:class:`PassFd`). A message is pickled with protocol 5: its arrays
(out-of-band buffers) are copied into a region, only the small pickle and the buffers' places
(a :class:`ShmRef`) cross the pipe; the receiver copies the buffers out (its arrays never
alias the region). A region holds one message at a time: the caller writes a request there
only when the worker has nothing pending (every earlier request was answered and its reply
received), and asks for the reply there (``ShmRef.reply``) only then, so a region is never
rewritten before its message was read. Anything else (a second request in flight, a message
larger than a region, no ``memfd_create``, no memory for the regions) crosses the pipe as
before: the numbers are the same either way.

Measured (``python benchmarks/bench_workers.py --rows 64,128,256 --repeat 20``, 2-core VM
shared with another job, load 1.5-2.1, 21:36 UTC, two runs each, before = main at 6ce5935):
the caller's CPU outside its own share per split call (slicing, pickling, transfer,
concatenation) 64 rows 1.15 / 1.40 -> 0.99 / 0.94 ms, 128 rows 1.58 / 1.97 -> 1.50 / 1.57
ms, 256 rows 2.14 / 2.47 -> 1.72 / 1.34 ms. Of the remaining ~1.6 ms at 256 rows (the
128-row share), per call: packing into the region 0.35 ms, copying the reply out 0.29 ms,
concatenating the shares 0.3-0.5 ms, slicing 0.07 ms.
"""

from __future__ import annotations

import contextlib
import dataclasses
import mmap
import os
import pickle
from multiprocessing import reduction
from typing import Any

__all__ = ["REGION_BYTES", "PassFd", "Regions", "ShmRef", "pack", "unpack"]

#: Bytes of each region (request, reply): a 200-row share is ~2.2 MB, a larger message than
#: this (~700 rows) crosses the pipe. The file's pages are reserved when it is made (a
#: write to a sparse page without memory left would kill the process with SIGBUS; no memory
#: for them makes the pool use its pipes): 16 MB of shared memory per worker.
REGION_BYTES = 8 << 20
_ALIGN = 64


@dataclasses.dataclass(frozen=True)
class ShmRef:
    """A message in a region: its protocol-5 pickle and each out-of-band buffer's (offset,
    bytes) in the region; ``reply``: (a request) the worker may answer in its reply region."""

    head: bytes
    spans: tuple[tuple[int, int], ...]
    reply: bool = False


class Regions:
    """One worker's mapped file: ``request`` and ``reply`` memoryviews of
    :data:`REGION_BYTES` each. :meth:`create` (the caller: an anonymous file, its
    descriptor :attr:`fd` open until :meth:`close_fd`, once the worker was started with
    it), :meth:`attach` (the worker: maps the caller's descriptor and closes it)."""

    def __init__(self, fd: int) -> None:
        size = os.fstat(fd).st_size  # (the worker: the caller's size)
        self._mm = mmap.mmap(fd, size)
        self._buf = memoryview(self._mm)
        self.request = self._buf[:size // 2]
        self.reply = self._buf[size // 2:]
        self.fd: int | None = None

    @classmethod
    def create(cls) -> Regions:
        """New regions in an anonymous file whose pages are reserved now (a write to a
        sparse page without memory left would kill the process with SIGBUS); OSError if
        that fails or the platform has no ``memfd_create`` (the pool then uses its pipes)."""
        if not hasattr(os, "memfd_create"):
            raise OSError("no memfd_create")
        fd = os.memfd_create("diffpos-fusion", os.MFD_CLOEXEC)
        try:
            os.ftruncate(fd, 2 * REGION_BYTES)
            if hasattr(os, "posix_fallocate"):
                os.posix_fallocate(fd, 0, 2 * REGION_BYTES)
            self = cls(fd)
        except BaseException:
            os.close(fd)
            raise
        self.fd = fd
        return self

    @classmethod
    def attach(cls, fd: int) -> Regions:
        """The regions of the caller's descriptor ``fd`` (closed here, mapped or not)."""
        try:
            return cls(fd)
        finally:
            os.close(fd)

    def close_fd(self) -> None:
        """Close the creator's descriptor (the mapping stays valid)."""
        if self.fd is not None:
            with contextlib.suppress(OSError):
                os.close(self.fd)
            self.fd = None

    def close(self) -> None:
        self.close_fd()
        for v in (self.request, self.reply, self._buf):
            v.release()
        self._mm.close()


class PassFd:
    """A descriptor given to a process started by multiprocessing's ``spawn`` context (in
    its ``Process`` arguments): pickled at the start, the child receives a copy of it as
    the pipes of :func:`multiprocessing.Pipe` are passed; unpickled there as the plain
    ``int`` descriptor, which the child owns."""

    def __init__(self, fd: int) -> None:
        self.fd = fd

    def __reduce__(self):
        return _received_fd, (reduction.DupFd(self.fd),)


def _received_fd(dup: Any) -> int:
    return dup.detach()


def pack(region: memoryview, obj: Any, *, reply: bool = False) -> ShmRef | None:
    """``obj`` pickled with its buffers copied into ``region``; None if they do not fit
    (send ``obj`` through the pipe instead)."""
    bufs: list[pickle.PickleBuffer] = []
    head = pickle.dumps(obj, protocol=5, buffer_callback=bufs.append)
    spans, off = [], 0
    for b in bufs:
        with b.raw() as m:
            n = m.nbytes
            if off + n > len(region):
                return None
            region[off:off + n] = m
        spans.append((off, n))
        off += -(-n // _ALIGN) * _ALIGN
    return ShmRef(head, tuple(spans), reply)


def unpack(region: memoryview, ref: ShmRef) -> Any:
    """The object of :func:`pack`, its buffers copied out of ``region``."""
    return pickle.loads(ref.head, buffers=[bytearray(region[o:o + n]) for o, n in ref.spans])
