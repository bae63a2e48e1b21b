"""``prepare_kernels(skip_cached=True)`` (``diffpos replay``): no worker processes when the
stamp says numba's cache holds the run's groups for the current sources; workers again as
soon as a source, a ``NUMBA_*`` setting or a cache file changes (issue 37, item 3).

The workers run cheap stand-in groups (stdlib imports) on a fake core package in a temporary
folder (its sources and numba cache files); nothing here compiles.
"""

from __future__ import annotations

import json
import os

import pytest
from diffpos_services.fusion import prepare
from diffpos_services.fusion.prepare import Group, cached_groups, prepare_kernels


@pytest.fixture
def fake_core(tmp_path, monkeypatch):
    """A core package with one source and one cached kernel; numba's cache in ``cache/``."""
    core = tmp_path / "core"
    (core / "sub").mkdir(parents=True)
    (core / "sub" / "k_nb.py").write_text("x = 1\n")
    cache = tmp_path / "cache"
    (cache / "sub").mkdir(parents=True)
    for name in ("k_nb.f-1.py311.nbi", "k_nb.f-1.py311.1.nbc"):
        (cache / "sub" / name).write_bytes(b"0")
    monkeypatch.setattr(prepare, "_CORE", core)
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    monkeypatch.setattr(prepare, "GROUPS", {"a": Group("part A", 1.0, ("json",)),
                                            "b": Group("part B", 1.0, ("decimal",))})
    return core, cache


def test_a_stamped_group_starts_no_worker(fake_core):
    first = prepare_kernels(["a"], workers=1, interval_s=0.05, skip_cached=True)
    assert not first.cached and len(first.worker_cpu_s) == 1  # no stamp yet: a worker
    assert cached_groups() == {"a"}
    again = prepare_kernels(["a"], workers=1, interval_s=0.05, skip_cached=True)
    assert again.cached and again.worker_cpu_s == ()
    # without skip_cached (emulate): the workers as before
    assert not prepare_kernels(["a"], workers=1, interval_s=0.05).cached
    # a group never prepared: workers (for the run's groups), then both are stamped
    assert not prepare_kernels(["a", "b"], workers=1, interval_s=0.05, skip_cached=True).cached
    assert cached_groups() == {"a", "b"}
    assert prepare_kernels(["b"], workers=1, interval_s=0.05, skip_cached=True).cached


def test_a_changed_source_setting_or_cache_file_means_workers_again(fake_core, monkeypatch):
    core, cache = fake_core
    prepare_kernels(["a"], workers=1, interval_s=0.05)
    assert cached_groups() == {"a"}
    src = core / "sub" / "k_nb.py"
    src.write_text("x = 22\n")  # an edited kernel source (size and mtime)
    assert cached_groups() == set()
    prepare_kernels(["a"], workers=1, interval_s=0.05)
    assert cached_groups() == {"a"}
    monkeypatch.setenv("NUMBA_OPT", "0")  # a numba setting: another compilation
    assert cached_groups() == set()
    monkeypatch.delenv("NUMBA_OPT")
    assert cached_groups() == {"a"}
    (cache / "sub" / "k_nb.f-1.py311.1.nbc").unlink()  # the cache cleared
    assert cached_groups() == set()
    assert not prepare_kernels(["a"], workers=1, interval_s=0.05, skip_cached=True).cached


def test_a_failed_preparation_stamps_nothing(fake_core, monkeypatch):
    monkeypatch.setitem(prepare.GROUPS, "bad", Group("broken", 1.0, ("no_such_module_here",)))
    with pytest.raises(prepare.KernelError):
        prepare_kernels(["a", "bad"], workers=1, interval_s=0.05)
    assert cached_groups() == set()
    stamp = os.path.join(os.environ["NUMBA_CACHE_DIR"], prepare.STAMP_NAME)
    assert not os.path.exists(stamp)


def test_an_unreadable_stamp_is_no_stamp(fake_core):
    _, cache = fake_core
    (cache / prepare.STAMP_NAME).write_text("{not json")
    assert cached_groups() == set()
    prepare_kernels(["a"], workers=1, interval_s=0.05)
    assert json.loads((cache / prepare.STAMP_NAME).read_text())["groups"].keys() == {"a"}


def test_a_source_edited_while_the_workers_ran_is_not_stamped(fake_core, monkeypatch):
    core, _ = fake_core
    real = prepare._Worker

    class EditsMeanwhile(real):
        def __init__(self, groups):
            super().__init__(groups)
            (core / "sub" / "k_nb.py").write_text("x = 333\n")

    monkeypatch.setattr(prepare, "_Worker", EditsMeanwhile)
    prepare_kernels(["a"], workers=1, interval_s=0.05)
    assert cached_groups() == set()


def test_a_file_rewritten_with_the_same_content_keeps_the_stamp(fake_core):
    """A merge or checkout rewrites files (new mtimes) whose content may not change: the stamp
    holds while every source's content is the same and no file that can define a kernel (one
    naming numba, whose mtime numba's own cache index checks) was touched."""
    core, _ = fake_core
    plain = core / "sub" / "geometry.py"
    plain.write_text("Y = 2.0\n")
    kernel = core / "sub" / "f_nb.py"
    kernel.write_text("from numba import njit\n")
    prepare_kernels(["a"], workers=1, interval_s=0.05)
    assert cached_groups() == {"a"}
    st = plain.stat()
    plain.write_text("Y = 2.0\n")  # the same bytes written again
    os.utime(plain, ns=(st.st_atime_ns, st.st_mtime_ns + 5_000_000_000))  # a later mtime
    assert cached_groups() == {"a"}
    plain.write_text("Y = 3.0\n")  # the same size, another content
    os.utime(plain, ns=(st.st_atime_ns, st.st_mtime_ns))  # and the old mtime
    assert cached_groups() == set()
    plain.write_text("Y = 2.0\n")
    assert cached_groups() == {"a"}  # the content stamped again: no worker needed
    kst = kernel.stat()
    os.utime(kernel, ns=(kst.st_atime_ns, kst.st_mtime_ns + 5_000_000_000))
    assert cached_groups() == set()  # numba's index of that file is stale: workers again
