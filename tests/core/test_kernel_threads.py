"""The compiled kernels' row chunks on the thread pool (diffpos._kernels.pool).

The property: every output is bit-identical for 1 and 2 threads (each row's arithmetic is that
of the one-thread call; the rows only move between calls and threads). Checked on the kernels'
wrappers with random inputs on buildings other than the shipped ones (other floor heights and
window sizes, anchors above the windows and beyond the facade ends), with the wrappers' row
thresholds at their defaults and forced down to 1 (many small chunks), and on a small M-NLS
batch and a tracker run (which go through all four split kernels). The references are the
one-thread outputs of the same code; equality is on the raw bytes (NaN and -0.0 included).
Plus the pool's own contract: every row exactly once, small calls on the calling thread, two
threads really used, a chunk's exception raised to the caller.
"""

from __future__ import annotations

import dataclasses
import importlib
import threading

import numpy as np
import pytest

import diffpos.tracking.initialisation as tracking_init
import diffpos.tracking.links as tracking_paths
from diffpos._kernels import pool
from diffpos.channel import snr_nb as channel_nb
from diffpos.channel.emulator import emulate_channel, first_arrival, pair_snr_db
from diffpos.estimators.mnls.solver import mnls
from diffpos.scenario import Building, default_scenario
from diffpos.tracking.initialisation import grid_starts
from diffpos.tracking.links import Links, all_paths
from diffpos.tracking.state import TrackerConfig
from diffpos.tracking.tracker import init_state, update

mnls_mod = importlib.import_module("diffpos.estimators.mnls.solver")  # the package exports mnls()
_RADIO = default_scenario().radio
_BUILDINGS = [
    dataclasses.replace(Building(), n_floors=7, floor_height_m=3.6, first_floor_z_m=3.0,
                        sill_height_m=0.9, window_height_m=2.0, width_m=30.0, depth_m=15.0,
                        partitions=()),
    dataclasses.replace(Building(), floor_height_m=2.7, window_height_m=0.8, sill_height_m=1.2),
]


@pytest.fixture
def restore_threads(monkeypatch):
    """Back to 1 thread afterwards; the back-off rule off (a loaded test machine would turn
    splitting off for a while: the outputs are the same, but the split is what is tested)."""
    monkeypatch.setattr(pool, "BACKOFF_WAIT_SHARE", float("inf"))
    yield
    pool.set_threads(1)
    pool.shutdown()


def _bits(a) -> tuple:
    a = np.asarray(a)
    return a.dtype.str, a.shape, a.tobytes()


def _fields(obj) -> dict:
    return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}


def _assert_same(a, b, where: str = "") -> None:
    """Two results equal bit for bit: arrays by their bytes, dataclasses field by field."""
    if dataclasses.is_dataclass(a):
        fa, fb = _fields(a), _fields(b)
        assert fa.keys() == fb.keys(), where
        for k in fa:
            _assert_same(fa[k], fb[k], f"{where}.{k}")
    elif isinstance(a, np.ndarray):
        assert _bits(a) == _bits(b), where
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, float):
        assert _bits(a) == _bits(b), where
    else:
        assert a == b, where


def _one_vs_two(fn, monkeypatch, *, small_chunks: bool):
    """``fn()`` with 1 thread and with 2 threads (the thresholds forced to 1 rows when
    ``small_chunks``); returns both outputs and the chunk sizes of the 2-thread run."""
    pool.set_threads(1)
    ref = fn()
    chunks: list[int] = []
    real = pool.run_rows

    def spy(f, n_rows, *, min_rows=1):
        def rec(lo, hi):
            chunks.append(hi - lo)
            f(lo, hi)
        return real(rec, n_rows, min_rows=1 if small_chunks else min_rows)

    for mod in (channel_nb, mnls_mod, tracking_paths, tracking_init):
        monkeypatch.setattr(mod, "run_rows", spy)
    pool.set_threads(2)
    got = fn()
    monkeypatch.undo()
    return ref, got, chunks


def _anchors_nodes(b, seed, n, m):
    rng = np.random.default_rng(seed)
    x0, x1 = b.edge_x_m
    floor = rng.integers(0, b.n_floors, n)
    nodes = np.stack([rng.uniform(x0 + 2, x1 - 2, n), rng.uniform(0.3, b.depth_m - 1, n),
                      b.floor_z_m(floor) + rng.uniform(0.1, b.floor_height_m - 0.1, n)], -1)
    # in front of the facade, above the windows, beyond the facade ends
    anc = np.stack([rng.uniform(x0 - 15, x1 + 15, (n, m)), rng.uniform(-40, -2, (n, m)),
                    rng.uniform(0, b.floor_z_m(b.n_floors - 1) + 8, (n, m))], -1)
    return anc, nodes, floor


# ---------------------------------------------------------------------------- the pool
@pytest.mark.parametrize("n_thr", [1, 2, 3])
def test_run_rows_covers_every_row_once(n_thr, restore_threads):
    """Each row in exactly one chunk, chunks contiguous and >= min_rows; one call on the
    calling thread when there is one thread or fewer than 2 * min_rows rows."""
    pool.set_threads(n_thr)
    me = threading.get_ident()
    for n_rows in (0, 1, 5, 17, 100, 1001):
        for min_rows in (1, 3, 50):
            seen = np.zeros(n_rows, np.int64)
            calls: list[tuple[int, int, int]] = []
            lock = threading.Lock()

            def fn(lo, hi, seen=seen, calls=calls, lock=lock):
                with lock:
                    seen[lo:hi] += 1
                    calls.append((lo, hi, threading.get_ident()))

            pool.run_rows(fn, n_rows, min_rows=min_rows)
            assert np.all(seen == 1)
            if n_thr == 1 or n_rows < 2 * min_rows:
                assert calls == [(0, n_rows, me)]
            else:
                assert len(calls) >= 2
                assert all(hi - lo >= min_rows for lo, hi, _ in calls)


def test_run_rows_stats_count_calls_and_cpu(restore_threads):
    """stats(): every call counted, the split ones apart; the busiest thread's CPU is at most
    the chunks' total (equal for a direct call)."""
    pool.set_threads(2)
    pool.reset_stats()
    work = np.random.default_rng(0).normal(size=(64, 64))

    def fn(lo, hi):
        for _ in range(hi - lo):
            np.linalg.inv(work)

    for n_rows, min_rows in ((40, 1), (40, 100), (3, 1)):
        pool.run_rows(fn, n_rows, min_rows=min_rows)
    st = pool.stats()
    assert st["calls"] == 3 and st["split_calls"] == 2
    assert 0 < st["critical_cpu_s"] <= st["chunk_cpu_s"]
    pool.reset_stats()
    pool.set_threads(1)
    pool.run_rows(fn, 10)
    st = pool.stats()
    assert st["calls"] == 1 and st["split_calls"] == 0
    assert st["critical_cpu_s"] == st["chunk_cpu_s"] > 0


def test_run_rows_backs_off_when_the_caller_waits(restore_threads, monkeypatch):
    """After split calls whose caller mostly waited for its helpers, the next BACKOFF_CALLS
    splittable calls run on the calling thread (one call each), then splitting resumes."""
    monkeypatch.setattr(pool, "BACKOFF_WAIT_SHARE", 0.25)
    monkeypatch.setattr(pool, "BACKOFF_CALLS", 3)
    pool.set_threads(2)
    for _ in range(3):  # the average wait share: 0.1, 0.19, then 0.271 > 0.25
        pool._watch(1.0, 1.0)
    calls = []

    def fn(lo, hi):
        calls.append((lo, hi))

    for _ in range(3):
        calls.clear()
        pool.run_rows(fn, 40, min_rows=1)
        assert calls == [(0, 40)]
    calls.clear()
    pool.run_rows(fn, 40, min_rows=1)
    assert len(calls) >= 2


def test_run_rows_uses_two_threads(restore_threads):
    """With 2 threads two chunks run at the same time (a barrier both must reach)."""
    pool.set_threads(2)
    barrier = threading.Barrier(2, timeout=30)
    idents = set()

    def fn(lo, hi):
        idents.add(threading.get_ident())
        if lo < 2:  # the first two chunks (one per thread) wait for each other
            barrier.wait()

    pool.run_rows(fn, 8, min_rows=1)
    assert len(idents) == 2


def test_run_rows_raises_a_chunks_error(restore_threads):
    """An exception in a chunk reaches the caller; the pool keeps working after it."""
    pool.set_threads(2)

    def bad(lo, hi):
        if lo <= 5 < hi:
            raise ValueError("row 5")

    with pytest.raises(ValueError, match="row 5"):
        pool.run_rows(bad, 40, min_rows=1)
    seen = np.zeros(40, np.int64)
    pool.run_rows(lambda lo, hi: seen.__setitem__(slice(lo, hi), seen[lo:hi] + 1), 40,
                  min_rows=1)
    assert np.all(seen == 1)
    with pytest.raises(ValueError):
        pool.set_threads(0)


# ---------------------------------------------------------------------------- the kernels
@pytest.mark.parametrize("small", [False, True])
@pytest.mark.parametrize("bi", range(len(_BUILDINGS)))
def test_channel_snr_bit_identical(bi, small, monkeypatch, restore_threads):
    """pair_snr_db (channel_snr_kernel): (N, M, 18) SNRs, -inf slots included."""
    b = _BUILDINGS[bi]
    anc, nodes, _ = _anchors_nodes(b, 10 + bi, n=97, m=11)
    ref, got, chunks = _one_vs_two(lambda: pair_snr_db(anc, nodes, building=b, radio=_RADIO),
                                   monkeypatch, small_chunks=small)
    _assert_same(ref, got)
    assert np.isneginf(ref).any() and np.isfinite(ref).any()
    assert sum(chunks) == 97 and len(chunks) >= 2


@pytest.mark.parametrize("small", [False, True])
@pytest.mark.parametrize("bi", range(len(_BUILDINGS)))
def test_all_paths_and_grid_starts_bit_identical(bi, small, monkeypatch, restore_threads):
    """tracking_paths.all_paths (all_paths_kernel) and tracking_init.grid_starts
    (grid_cost_kernel) on random hypotheses and links, missing links included."""
    b = _BUILDINGS[bi]
    rng = np.random.default_rng(20 + bi)
    n, h, m = 41, 5, 9
    anc, nodes, floor = _anchors_nodes(b, 30 + bi, n=n, m=m)
    pos = nodes[:, None, :] + rng.normal(0, 0.5, (n, h, 3))
    fl = np.clip(floor[:, None] + rng.integers(-1, 2, (n, h)), 0, b.n_floors - 1)
    rho = np.linalg.norm(anc - nodes[:, None], axis=-1) + rng.uniform(-0.5, 4.0, (n, m))
    links = Links.from_arrays(anc, rho, rng.uniform(0.02, 0.3, (n, m)),
                              rng.random((n, m)) > 0.15, 0.03)
    relax = rng.uniform(0.0, 0.5, (n, h))
    floors = np.sort(rng.choice(b.n_floors, (n, 2)), axis=1)
    cfg = TrackerConfig()

    def run():
        return all_paths(pos, links, fl, b, relax), grid_starts(links, floors, b, cfg)

    (pe1, gs1), (pe2, gs2), chunks = _one_vs_two(run, monkeypatch, small_chunks=small)
    _assert_same(pe1, pe2)
    _assert_same(gs1, gs2)
    assert len(chunks) >= 4  # both kernels split


def test_mnls_batch_bit_identical(monkeypatch, restore_threads):
    """A small M-NLS batch with the measured SNR (lm_kernel, and channel_snr_kernel in the
    SNR terms): every result field equal bit for bit."""
    b = _BUILDINGS[0]
    anc, nodes, _ = _anchors_nodes(b, 40, n=24, m=6)
    rng = np.random.default_rng(41)
    rows = [first_arrival(emulate_channel(anc[i], nodes[i:i + 1], building=b, radio=_RADIO),
                          radio=_RADIO, rng=rng) for i in range(24)]
    r = np.concatenate([fa.range_m for fa in rows])  # (N, M): one node per call
    s = np.concatenate([fa.sigma_m for fa in rows])
    det = np.concatenate([fa.detected for fa in rows])
    snr = np.concatenate([fa.snr_db for fa in rows])
    assert det.sum() > 24 * 3

    def run():
        return mnls(anc, np.where(det, r, 0.0), np.where(det, s, 1.0), building=b, mask=det,
                    snr_db=snr, radio=_RADIO, chunk_size=12)

    ref, got, chunks = _one_vs_two(run, monkeypatch, small_chunks=True)
    _assert_same(ref, got)
    assert np.isfinite(ref.position_m).any() and len(chunks) > 2


def test_tracker_run_bit_identical(monkeypatch, restore_threads):
    """Ten epochs of the tracker on emulated ranges (initialisation grid search, all paths,
    SNR prediction): every output of every epoch and the final state equal bit for bit."""
    b = _BUILDINGS[1]
    anc, nodes, _ = _anchors_nodes(b, 50, n=6, m=7)
    anc = np.broadcast_to(anc[0], (6, 7, 3)).copy()
    rng = np.random.default_rng(51)
    epochs = []
    for k in range(10):
        p = nodes + np.array([0.1 * k, 0.05 * k, 0.0])
        fa = first_arrival(emulate_channel(anc[0], p, building=b, radio=_RADIO), radio=_RADIO,
                           rng=rng)
        epochs.append((round(k * 1e8), fa.range_m, fa.sigma_m, fa.detected, fa.snr_db))
    cfg = TrackerConfig()

    def run():
        state, outs = init_state(6, b), []
        for t_ns, r, s, det, snr in epochs:
            state, out = update(state, anc, np.where(det, r, 0.0), np.where(det, s, 1.0), det,
                                t_ns, b, cfg, snr_db=snr, radio=_RADIO)
            outs.append(out)
        return state, outs

    (st1, o1), (st2, o2), chunks = _one_vs_two(run, monkeypatch, small_chunks=True)
    for a, c in zip(o1, o2, strict=True):
        _assert_same(a, c)
    _assert_same(st1, st2)
    assert np.isfinite(o1[-1].position_m).any() and len(chunks) > 10


def test_run_rows_with_a_pool_shut_down_meanwhile(restore_threads):
    """A split call whose pool was shut down after its look-up (another thread's shutdown or
    set_threads, or interpreter exit: ThreadPoolExecutor.submit raises RuntimeError) runs
    every chunk on the calling thread, each row once, and counts it."""
    pool.set_threads(2)
    pool._executor(1).shutdown(wait=True)  # the pool the call will find, already shut down
    pool.reset_stats()
    me = threading.get_ident()
    seen = np.zeros(40, np.int64)
    idents = set()

    def fn(lo, hi):
        seen[lo:hi] += 1
        idents.add(threading.get_ident())

    pool.run_rows(fn, 40, min_rows=1)
    assert np.all(seen == 1) and idents == {me}
    assert pool.stats()["refused"] == 1 and pool.stats()["split_calls"] == 1
    pool.shutdown()  # a fresh pool afterwards splits again
    pool.run_rows(fn, 40, min_rows=1)
    assert np.all(seen == 2) and pool.stats()["refused"] == 1
