"""The worker pool's shared-memory transport (services/diffpos_services/fusion/shm.py)
without processes: a tracker share packed into a mapped region and unpacked from a second
mapping of the same (anonymous) file is equal to the original bit for bit (also
non-contiguous arrays, which travel in the pickle), owns its memory (a rewrite of the region
changes nothing unpacked before), and a message larger than the region is refused (None:
the pipe)."""

from __future__ import annotations

import dataclasses
import os
import pickle

import numpy as np
import pytest
from diffpos_services.fusion import shm
from diffpos_services.fusion.rows import take_rows

from diffpos.scenario import default_scenario
from diffpos.tracking.tracker import init_state


def _same(a, b) -> bool:
    """Bit-identical: same types, dtypes, shapes and bytes (NaNs included), field by field."""
    if type(a) is not type(b):
        return False
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, tuple):
        return len(a) == len(b) and all(map(_same, a, b))
    if dataclasses.is_dataclass(a):
        return all(_same(getattr(a, f.name), getattr(b, f.name))
                   for f in dataclasses.fields(a))
    return pickle.dumps(a) == pickle.dumps(b)


needs_memfd = pytest.mark.skipif(not hasattr(os, "memfd_create"), reason="no memfd_create")


@pytest.fixture
def regions(monkeypatch):
    monkeypatch.setattr(shm, "REGION_BYTES", 1 << 20)
    mine = shm.Regions.create()
    theirs = shm.Regions.attach(os.dup(mine.fd))  # as the worker does with its copy
    # anonymous: named in no directory (a SIGKILLed owner leaves nothing behind)
    assert os.readlink(f"/proc/self/fd/{mine.fd}").startswith("/memfd:")
    mine.close_fd()
    yield mine, theirs
    theirs.close()
    mine.close()


@needs_memfd
def test_a_tracker_share_crosses_the_region_bit_for_bit(regions):
    mine, theirs = regions
    rng = np.random.default_rng(3)
    state = init_state(40, default_scenario().building)
    state = dataclasses.replace(state, mean=rng.normal(size=state.mean.shape),
                                cov=np.where(rng.random(state.cov.shape) < 0.1, np.nan,
                                             rng.normal(size=state.cov.shape)))
    share = take_rows(state, slice(5, 30))
    strided = rng.normal(size=(30, 8))[:, ::2]  # not contiguous: pickled in-band
    args = (share, rng.normal(size=(25, 16, 3)), strided, np.int64(7), None, "x")
    ref = shm.pack(mine.request, args, reply=True)
    assert ref is not None and ref.reply and len(ref.spans) >= 10
    assert len(ref.head) < 16_000  # the arrays are in the region, not in the pickle
    got = shm.unpack(theirs.request, ref)
    assert _same(got, args)
    assert got[0].mean.flags.writeable and got[0].mean.flags.owndata is False
    # the unpacked arrays own copies: rewriting the region leaves them as they were
    theirs.request[:] = b"\xff" * len(theirs.request)
    assert _same(got, args)
    back = shm.pack(theirs.reply, got[0])
    assert _same(shm.unpack(mine.reply, back), share)


@needs_memfd
def test_a_message_larger_than_the_region_is_refused(regions):
    mine, _ = regions
    big = np.zeros(len(mine.request) // 8 + 1)
    assert shm.pack(mine.request, (big,)) is None
    fits = np.arange(len(mine.request) // 8 - 64, dtype=np.float64)
    ref = shm.pack(mine.request, (fits,))
    assert ref is not None and np.array_equal(shm.unpack(mine.request, ref)[0], fits)


@needs_memfd
def test_no_memory_for_the_regions_leaves_no_descriptor(monkeypatch):
    """No memory for the regions (posix_fallocate fails as without room for shared memory):
    the error is raised (the pool then uses its pipes), the file's descriptor closed."""
    import errno

    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, "No space left on device")

    made = []
    memfd_create = os.memfd_create
    monkeypatch.setattr(os, "memfd_create", lambda *a: made.append(memfd_create(*a)) or made[-1])
    monkeypatch.setattr(os, "posix_fallocate", full, raising=False)
    with pytest.raises(OSError):
        shm.Regions.create()
    assert len(made) == 1
    with pytest.raises(OSError):
        os.fstat(made[0])
