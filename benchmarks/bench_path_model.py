"""Speed of the path models: the first-arrival model (numpy reference vs compiled kernel), the
window-edge model and the bounds.

Run:  .venv/bin/python benchmarks/bench_path_model.py [--repeats 7] [--only first-arrival|geometry]
      .venv/bin/python benchmarks/bench_path_model.py --profile-mnls 64   (where M-NLS spends)

One thread (OMP/OPENBLAS/MKL_NUM_THREADS=1, set below); every time is the median of the repeats,
by wall clock and by this thread's CPU time (the figure to compare when other processes share
the cores); inputs are made outside the timed region.

**First-arrival path model** (:func:`diffpos.paths.model.first_arrival_paths`, all 18 slots with
existence, Jacobians, deviation cosines; the inner loop of M-NLS and of the tracker), per
*row* = one (node, anchor, floor hypothesis) evaluation, on the default building, 8 anchors
(the paper's 4 and 4 more: at a window band, above the windows, beyond a facade end, high):

- *batched*: ``--fa-nodes`` nodes x 5 floor hypotheses x 8 anchors in one call;
- *single*: one node x 8 anchors x its floor per call (a live one-fix call);
- reference = the numpy implementation kept as ``diffpos.paths.model._first_arrival_paths_numpy``;
  kernel = ``first_arrival_paths`` (row preparation + numba kernel); kernel alone = the
  compiled loop on prepared rows (what a caller holding flat rows pays); lengths only =
  ``want_jac=False``;
- compile: ``warm_paths()`` in a fresh process with an empty numba cache (first start on a
  machine) and again with that cache (every later start), plus the import of the module
  (numba itself), each by wall clock and process CPU time.

The kernel is checked against the reference (1e-12 relative, existence exactly) before timing.

**Where an M-NLS fix spends** (``--profile-mnls N``: cProfile of one batched ``mnls`` call on
N emulated first arrivals, 8 anchors, with the measured SNR and the radio as live; shares of
the total thread CPU, cumulative; then the top functions by own CPU; ``--numpy-paths`` runs
the estimator on the numpy path model, ``--numpy-snr`` its SNR cost on the numpy emulator
instead of the compiled ``diffpos.channel.snr_nb``): the path model, the channel's
per-slot SNR prediction (``diffpos.channel.emulator.pair_snr_db``, the M-NLS SNR cost) and the rest.
History: 2026-11-23 (load ~10), 64 fixes: numpy path model 4.4 s, first_arrival_paths 37 % /
pair_snr_db 50 % / rest 13 %; compiled path model 3.0 s, 8 % / 63 % / 28 %.
Measured 2026-11-27 05:39 UTC (shared 2-core VM, load 6-8), 64 fixes, thread CPU under
cProfile:

    SNR cost by         total    per fix   path model  pair_snr_db  rest
    numpy emulator      1.18 s   18.5 ms   10 %         75 %         15 %
    compiled kernel     0.44 s    6.8 ms   35 %         22 %         43 %

With the compiled SNR the own-CPU ranking is: ``paths_kernel`` 33 %, ``channel_snr_kernel``
22 % (~880 node-anchor pairs per fix at ~2.3 us), ``link_terms_kernel`` (mnls_nb) 16 %, the
estimator's Python/numpy (``_lm``, a dict comprehension in ``_lm``, einsum, ``solve``, the
edge starts) ~20 %. The 2 ms per node-epoch target of M-NLS is therefore no longer a matter
of the SNR prediction: the path model's evaluations and the number of hypotheses the search
evaluates (diffpos/estimators/mnls/solver.py) dominate.
Since the compiled starts and LM (``mnls(kernel=True)``; ``--reference``: the numpy steps),
2026-11-27 06:35 UTC, load ~4.9, 64 fixes: 0.22 s thread CPU under cProfile (3.5 ms per
fix): ``mnls_nb.lm_kernel`` (path model + link terms + LM steps) 52 %, ``pair_snr_db`` 26 %
(``channel_snr_kernel`` own 26 %), ``first_arrival_paths`` outside the LM 4 %, the rest 18 %.

**Families vs Sionna RT** (``--sionna DATASET.npz ... [--max-order 4]``, no timing): every
traced path of a ``diffpos raytrace`` dataset is classified into the families of
``mechanism_set(max_order)`` (:func:`sionna_chains`: the ray tracer's chain, with a vertical
window-edge diffraction named by its end, ``D(vertical x1)`` / ``D(vertical x2)``, when its
point lies on the receiver floor's window band) and its traced length compared with the
model's closed-form length on the receiver's floor (paths whose family the model says exists,
band ties included): per family the paths, the share the model has, max and p99 |error|.

**Window-edge model and bounds** (the paper's Corollary-1 geometry, target < 100 ns per pair):

- ``window_edge_path`` on 1,000,000 node-anchor pairs (250,000 nodes x 4 anchors), lengths +
  Jacobians, unbounded edge and clamped to the building width;
- a prototype of a faster kernel (``fast_window_edge_path`` below): same numbers, fewer
  square roots (the unfolded closed form gives OPL, IPL and the Jacobian from one sqrt per
  pair plus one per node), structure-of-arrays output and cache-sized chunks;
- ``diffraction_point`` (general edge orientation) on the paper's 17,485 nodes x 4 anchors;
- ``position_error_bound`` on 17,485 nodes x 4 anchors (Jacobian + FIM + eigvalsh + inverse).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse
import cProfile
import importlib
import json
import pstats
import subprocess
import sys
import tempfile
import time

import numba
import numpy as np

from diffpos.bounds import bounds_from_fim, fisher_information, position_error_bound
from diffpos.channel.emulator import _pair_snr_db_numpy, emulate_channel, first_arrival
from diffpos.estimators.mnls.solver import mnls
from diffpos.geometry import diffraction_point, window_edge_path
from diffpos.paths import model_nb as paths_nb
from diffpos.paths.model import _first_arrival_paths_numpy, _kernel_rows, first_arrival_paths
from diffpos.scenario import default_scenario

ANCHORS = np.array([[-15.0, -20.0, 1.0], [0.0, -15.0, 0.0], [0.0, -7.0, 4.0], [15.0, -20.0, 1.0]])
W = 1.5


def fast_window_edge_path(
    anchors_m: np.ndarray,
    nodes_m: np.ndarray,
    window_height_m: float,
    *,
    delta_m: float = 0.0,
    edge_x_m: tuple[float, float] | None = None,
    chunk: int = 4096,
) -> tuple[np.ndarray, np.ndarray]:
    """Prototype: upper-edge lengths (N, M) and Jacobians (3, N, M) for N nodes x M anchors.

    Unfolding the node about the edge line makes the interior (unclamped) path a straight
    segment of length ``L = sqrt((x_n - x_a)^2 + (r_s + r_o)^2)`` with ``r_s`` (anchor) and
    ``r_o = sqrt(y_n^2 + h^2)`` (node, per node only) the distances to the edge line; by similar
    triangles ``OPL = L r_s / (r_s + r_o)`` and ``IPL = L r_o / (r_s + r_o)``, hence

        dp/dx_n = (x_n - x_a) / L,  dp/dy_n = y_n / IPL,  dp/dz_n = (z_e - z_a) / OPL.

    Pairs clamped by ``edge_x_m`` are recomputed with the general formula (boolean fix-up).
    """
    a = np.asarray(anchors_m, dtype=np.float64)
    n = np.asarray(nodes_m, dtype=np.float64)
    h = 0.5 * window_height_m - delta_m
    ax, ay2, az = a[:, 0], a[:, 1] ** 2, a[:, 2] - h  # z_e - z_a = z_n - (z_a - h)
    n_nodes, m = len(n), len(a)
    length = np.empty((n_nodes, m))
    jac = np.empty((3, n_nodes, m))
    nx_all = np.ascontiguousarray(n[:, 0])
    ny_all = np.ascontiguousarray(n[:, 1])
    nz_all = np.ascontiguousarray(n[:, 2])
    buf = [np.empty((chunk, m)) for _ in range(4)]
    for lo in range(0, n_nodes, chunk):
        hi = min(lo + chunk, n_nodes)
        k = hi - lo
        nx = nx_all[lo:hi, None]
        ny = ny_all[lo:hi, None]
        ro = np.sqrt(ny * ny + h * h)  # (k, 1)
        dz, rs, dx, tot = (b[:k] for b in buf)
        np.subtract(nz_all[lo:hi, None], az, out=dz)  # z_e - z_a
        np.multiply(dz, dz, out=rs)
        rs += ay2
        np.sqrt(rs, out=rs)  # r_s
        np.add(rs, ro, out=tot)  # r_s + r_o
        np.subtract(nx, ax, out=dx)  # x_n - x_a
        ln = length[lo:hi]
        np.multiply(dx, dx, out=ln)
        ln += tot * tot
        np.sqrt(ln, out=ln)  # L
        jx, jy, jz = jac[0, lo:hi], jac[1, lo:hi], jac[2, lo:hi]
        np.divide(dx, ln, out=jx)
        # y_n / IPL = y_n (r_s + r_o) / (r_o L);  (z_e - z_a)/OPL = dz (r_s + r_o) / (r_s L)
        np.divide(tot, ln, out=tot)
        np.multiply(tot, ny / ro, out=jy)
        np.multiply(dz, tot, out=jz)
        np.divide(jz, rs, out=jz)
    if edge_x_m is not None:
        x_lo, x_hi = min(edge_x_m), max(edge_x_m)
        # q_x = x_a + (x_n - x_a) r_s / (r_s + r_o): recompute only where it leaves the edge
        qx_cand = np.minimum(ax, nx_all[:, None]), np.maximum(ax, nx_all[:, None])
        maybe = (qx_cand[0] < x_lo) | (qx_cand[1] > x_hi)
        if np.any(maybe):
            ii, jj = np.nonzero(maybe)
            ref = window_edge_path(
                a[jj], n[ii], window_height_m=window_height_m, delta_m=delta_m, edge_x_m=edge_x_m
            )
            length[ii, jj] = ref.length_m
            jac[:, ii, jj] = ref.jacobian.T
    return length, jac


def _nodes(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.stack(
        [rng.uniform(-19.75, 19.75, n), rng.uniform(0.5, 20.0, n), rng.uniform(4.5, 16.5, n)],
        axis=1,
    )


def _time(fn, make_inputs, repeats: int) -> float:
    """Median wall time [s] over ``repeats`` runs (inputs made outside the timed region)."""
    times = []
    fn(*make_inputs())  # warm-up (page faults, caches)
    for _ in range(repeats):
        args = make_inputs()
        t0 = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def geometry_table(args: argparse.Namespace) -> None:
    """The window-edge model and the bounds (module docstring)."""
    rng = np.random.default_rng(0)
    m = len(ANCHORS)
    n_big = args.pairs // m
    n_paper = args.paper_nodes

    # correctness of the prototype against the library before timing it
    chk = _nodes(rng, 20_000)
    for ext in (None, (-20.0, 20.0), (-5.0, 5.0)):
        ref = window_edge_path(ANCHORS, chk[:, None, :], window_height_m=W, edge_x_m=ext)
        ln, jac = fast_window_edge_path(ANCHORS, chk, W, edge_x_m=ext)
        np.testing.assert_allclose(ln, ref.length_m, rtol=1e-12)
        np.testing.assert_allclose(np.moveaxis(jac, 0, -1), ref.jacobian, rtol=1e-9, atol=1e-12)

    rows: list[tuple[str, int, float]] = []

    def big():
        return (_nodes(rng, n_big),)

    def paper():
        return (_nodes(rng, n_paper),)

    t = _time(
        lambda nd: window_edge_path(ANCHORS, nd[:, None, :], window_height_m=W), big, args.repeats
    )
    rows.append(("window_edge_path (unbounded edge)", n_big * m, t))
    t = _time(
        lambda nd: window_edge_path(
            ANCHORS, nd[:, None, :], window_height_m=W, edge_x_m=(-20.0, 20.0)
        ),
        big,
        args.repeats,
    )
    rows.append(("window_edge_path (edge x in [-20, 20])", n_big * m, t))
    t = _time(lambda nd: fast_window_edge_path(ANCHORS, nd, W), big, args.repeats)
    rows.append(("prototype fast kernel (unbounded)", n_big * m, t))
    t = _time(
        lambda nd: fast_window_edge_path(ANCHORS, nd, W, edge_x_m=(-20.0, 20.0)), big, args.repeats
    )
    rows.append(("prototype fast kernel (edge x in [-20, 20])", n_big * m, t))

    def dp(nd):
        ze = nd[:, 2] + 0.5 * W
        p0 = np.stack([np.full_like(ze, -20.0), np.zeros_like(ze), ze], axis=1)[:, None, :]
        p1 = np.stack([np.full_like(ze, 20.0), np.zeros_like(ze), ze], axis=1)[:, None, :]
        return diffraction_point(ANCHORS, nd[:, None, :], p0, p1)

    t = _time(dp, paper, args.repeats)
    rows.append((f"diffraction_point ({n_paper} x {m})", n_paper * m, t))
    sig = np.full(m, 0.01)
    t = _time(lambda nd: position_error_bound(ANCHORS, nd, sig, W), paper, args.repeats)
    rows.append((f"position_error_bound ({n_paper} x {m})", n_paper * m, t))
    jac_p = window_edge_path(ANCHORS, _nodes(rng, n_paper)[:, None, :], window_height_m=W).jacobian
    t = _time(lambda j: fisher_information(j, sig), lambda: (jac_p,), args.repeats)
    rows.append(("  of which fisher_information", n_paper * m, t))
    fim = fisher_information(jac_p, sig)
    t = _time(bounds_from_fim, lambda: (fim,), args.repeats)
    rows.append(("  of which bounds_from_fim", n_paper * m, t))

    name_w = max(len(r[0]) for r in rows)
    print(f"\n## Window-edge model and bounds (numpy {np.__version__}, median of {args.repeats}"
          " runs, one thread)\n")
    print(f"{'what':<{name_w}}  {'pairs':>9}  {'total [ms]':>10}  {'ns/pair':>8}")
    print("-" * (name_w + 33))
    for name, pairs, sec in rows:
        print(f"{name:<{name_w}}  {pairs:>9,}  {sec * 1e3:>10.2f}  {sec / pairs * 1e9:>8.1f}")


#: The 8-anchor layout: the default scenario's 4 plus one at floor 1's window band, one above
#: the windows, one beyond the facade end (x > 20 m) and one high and far [m] (the layout of
#: benchmarks/bench_estimator_cost.py).
ANCHORS_8 = np.concatenate([default_scenario().anchor_positions_m(), np.array(
    [[-25.0, -12.0, 8.5], [10.0, -10.0, 14.0], [28.0, -18.0, 5.5], [-30.0, -25.0, 19.0]])])
N_FLOORS_FA = 5
#: The estimator's module (the package exports the function under the same name).
mnls_module = importlib.import_module("diffpos.estimators.mnls.solver")
channel_module = importlib.import_module("diffpos.channel.emulator")

_COMPILE_PROBE = """
import json, time
t0, c0 = time.perf_counter(), time.process_time()
from diffpos._kernels import paths_nb
t1, c1 = time.perf_counter(), time.process_time()
paths_nb.warm_paths()
t2, c2 = time.perf_counter(), time.process_time()
print(json.dumps({"import": [t1 - t0, c1 - c0], "warm": [t2 - t1, c2 - c1],
                  "signatures": len(paths_nb.paths_kernel.signatures)}))
"""


def _time2(fn, make_inputs, repeats: int) -> tuple[float, float]:
    """Median (wall, thread CPU) seconds over ``repeats`` calls (inputs made outside)."""
    fn(*make_inputs())
    wall, cpu = [], []
    for _ in range(repeats):
        args = make_inputs()
        t0, c0 = time.perf_counter(), time.thread_time()
        fn(*args)
        cpu.append(time.thread_time() - c0)
        wall.append(time.perf_counter() - t0)
    return float(np.median(wall)), float(np.median(cpu))


def compile_costs() -> list[tuple[str, float, float]]:
    """(what, wall s, CPU s) of the module import and warm_paths(), cold and cached cache."""
    out = []
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        for label in ("empty cache (first start)", "cache filled (later starts)"):
            r = json.loads(subprocess.run([sys.executable, "-c", _COMPILE_PROBE], env=env,
                                          check=True, capture_output=True, text=True).stdout)
            out.append((f"warm_paths(), {label}", *r["warm"]))
            out.append((f"  import diffpos.paths.model_nb (numba), {label}", *r["import"]))
    return out


def _fa_nodes(rng: np.random.Generator, n: int) -> np.ndarray:
    b = default_scenario().building
    k = rng.integers(0, b.n_floors, n)
    return np.stack([rng.uniform(-19.5, 19.5, n), rng.uniform(0.3, b.depth_m - 0.3, n),
                     b.floor_z_m(k) + rng.uniform(0.3, 2.7, n)], axis=-1)


def _fa_rows(nodes: np.ndarray) -> np.ndarray:
    """Nodes (B, 3) as (B, floors, 1, 3): every node under every floor hypothesis."""
    return np.ascontiguousarray(np.broadcast_to(nodes[:, None, None, :],
                                                (len(nodes), N_FLOORS_FA, 1, 3)))


def first_arrival_table(args: argparse.Namespace) -> None:
    """Reference vs kernel per (node, anchor, floor) row (module docstring)."""
    b = default_scenario().building
    rng = np.random.default_rng(1)
    m, nb = len(ANCHORS_8), args.fa_nodes
    floors = np.arange(N_FLOORS_FA)[None, :, None]
    paths_nb.warm_paths()
    chk = _fa_rows(_fa_nodes(rng, 500))
    ref = _first_arrival_paths_numpy(chk, ANCHORS_8, b, floor=floors)
    got = first_arrival_paths(chk, ANCHORS_8, b, floor=floors)
    assert np.array_equal(ref.valid, got.valid)
    np.testing.assert_allclose(got.length_m, ref.length_m, rtol=1e-12, equal_nan=True)
    np.testing.assert_allclose(got.jacobian, ref.jacobian, rtol=0, atol=1e-12)

    def batch():
        return (_fa_rows(_fa_nodes(rng, nb)),)

    def single():
        nd = _fa_nodes(rng, 1)
        return (nd[:, None, :], b.floor_index(nd[:, 2])[:, None])

    def rows_of(nd):
        return (_kernel_rows(nd, ANCHORS_8, b, floors, None),)

    def kernel_only(r, want_jac=True):
        paths_nb.eval_paths_kernel(*r.args, want_jac=want_jac)

    n_rows = nb * N_FLOORS_FA * m
    rows: list[tuple[str, int, tuple[float, float]]] = [
        ("batched: numpy reference", n_rows,
         _time2(lambda nd: _first_arrival_paths_numpy(nd, ANCHORS_8, b, floor=floors), batch,
                max(1, args.repeats // 2))),
        ("batched: kernel (first_arrival_paths)", n_rows,
         _time2(lambda nd: first_arrival_paths(nd, ANCHORS_8, b, floor=floors), batch,
                args.repeats)),
        ("batched: kernel alone on prepared rows", n_rows,
         _time2(kernel_only, lambda: rows_of(batch()[0]), args.repeats)),
        ("batched: kernel alone, lengths only (want_jac=False)", n_rows,
         _time2(lambda r: kernel_only(r, False), lambda: rows_of(batch()[0]), args.repeats)),
    ]
    n_single = 20 * args.repeats
    for name, fn in (("single: numpy reference", _first_arrival_paths_numpy),
                     ("single: kernel (first_arrival_paths)", first_arrival_paths)):
        rows.append((name, m, _time2(lambda nd, k, fn=fn: fn(nd, ANCHORS_8, b, floor=k),
                                     single, n_single)))
    print(f"## First-arrival path model, 18 slots + Jacobians (default building, {m} anchors; "
          f"numba {numba.__version__}, median, one thread)\n")
    print("| what | rows per call | ms per call wall / CPU | ns per row wall / CPU | "
          "speed-up vs numpy (CPU) |")
    print("| --- | ---: | ---: | ---: | ---: |")
    base = {"batched": rows[0][2][1] / rows[0][1], "single": rows[4][2][1] / rows[4][1]}
    for name, n, (w, c) in rows:
        up = base[name.split(":")[0]] / (c / n)
        print(f"| {name} | {n:,} | {w * 1e3:.3f} / {c * 1e3:.3f} | {w / n * 1e9:,.0f} / "
              f"{c / n * 1e9:,.0f} | {up:,.1f}x |")
    print("\n| compile / load | wall [s] | process CPU [s] |\n| --- | ---: | ---: |")
    for name, w, c in compile_costs():
        print(f"| {name} | {w:.2f} | {c:.2f} |")


def profile_mnls(n_fixes: int, numpy_paths: bool, numpy_snr: bool = False,
                 top: int = 12, reference: bool = False) -> None:
    """Shares of one batched M-NLS call: path model, SNR prediction, compiled LM, the rest,
    and the ``top`` functions by own CPU time (docstring). ``reference`` (or
    ``numpy_paths``): M-NLS's reference steps (``kernel=False``)."""
    kernel = not (reference or numpy_paths)
    sc = default_scenario()
    rng = np.random.default_rng(0)
    b = sc.building
    k = rng.integers(0, b.n_floors, n_fixes)
    nodes = np.stack([rng.uniform(-19.8, 19.8, n_fixes), rng.uniform(0.2, b.depth_m - 0.2,
                      n_fixes), b.floor_z_m(k) + rng.uniform(0.3, 2.7, n_fixes)], axis=-1)
    fa = first_arrival(emulate_channel(ANCHORS_8, nodes, building=b, radio=sc.radio),
                       radio=sc.radio, rng=rng)
    det = np.asarray(fa.detected, dtype=bool)

    def run(sl):
        return mnls(np.broadcast_to(ANCHORS_8, (n_fixes, *ANCHORS_8.shape))[sl],
                    np.where(det, fa.range_m, 0.0)[sl], np.where(det, fa.sigma_m, 1.0)[sl],
                    mask=det[sl], building=b, snr_db=np.asarray(fa.snr_db)[sl],
                    radio=sc.radio, bandwidth_hz=sc.radio.bandwidth_hz,
                    error_floor_m=sc.radio.range_error_floor_m, kernel=kernel)

    paths_nb.warm_paths()
    if numpy_paths:  # A/B: the estimator on the numpy reference of the path model
        if not hasattr(mnls_module, "first_arrival_paths"):
            raise SystemExit("mnls no longer calls first_arrival_paths: nothing to swap")
        mnls_module.first_arrival_paths = _first_arrival_paths_numpy
    if numpy_snr:  # A/B: the SNR cost on the numpy emulator instead of the compiled kernel
        channel_module.pair_snr_db = _pair_snr_db_numpy
    run(slice(0, 1))  # imports, caches
    prof = cProfile.Profile(time.thread_time)  # CPU time: the machine is shared
    prof.runcall(run, slice(0, n_fixes))
    st = pstats.Stats(prof).stats  # (file, line, name) -> (cc, nc, tottime, cumtime, callers)
    total = sum(v[2] for v in st.values())

    def cum(name: str) -> float:
        return sum(v[3] for key, v in st.items() if key[2] == name)

    fap = cum("first_arrival_paths") + cum("_first_arrival_paths_numpy")
    snr = cum("pair_snr_db") + cum("_pair_snr_db_numpy")
    lmk = cum("lm_kernel")
    which = "numpy reference" if numpy_paths else "compiled kernel"
    which_snr = "numpy emulator" if numpy_snr else "compiled kernel"
    steps = "compiled LM (kernel=True)" if kernel else "reference steps (kernel=False)"
    print(f"## M-NLS, {n_fixes} fixes x {len(ANCHORS_8)} anchors in one call, {steps}, "
          f"path model: {which}, SNR: {which_snr}: {total:.2f} s thread CPU under cProfile "
          f"({1e3 * total / n_fixes:.2f} ms per fix)\n")
    print("| part | share |\n| --- | ---: |")
    for name, t in (("first_arrival_paths (path model)", fap),
                    ("channel.pair_snr_db (SNR cost)", snr),
                    ("mnls_nb.lm_kernel (path model + link terms + LM steps)", lmk),
                    ("rest", total - fap - snr - lmk)):
        print(f"| {name} | {100 * t / total:.0f} % |")
    print(f"\nTop {top} functions by own CPU time (tottime; numba kernels count as their "
          f"dispatcher call):\n")
    print("| function | calls | own CPU share | cumulative share |\n| --- | ---: | ---: | ---: |")
    rows = sorted(st.items(), key=lambda kv: -kv[1][2])[:top]
    for (file, line, name), (_cc, nc, tt, ct, _callers) in rows:
        where = f"{os.path.basename(file)}:{line}" if line else file
        print(f"| `{name}` ({where}) | {nc} | {100 * tt / total:.1f} % | "
              f"{100 * ct / total:.1f} % |")




def sionna_chains(ds, mset):
    """Slot of ``mset`` (``-1``: none) and chain label of every traced path of ``ds`` (module
    docstring, *Families vs Sionna RT*: the classifier names a vertical window edge by its end
    and puts a partition reflection last), the median ``y`` of the traced vertical-edge
    diffraction points (NaN if none) and the partition a path reflects on (``-1``: none)."""
    from diffpos_services.raytrace.mechanisms import (
        NO_PATH,
        OTHER,
        PLANE_TOL_M,
        VERTICAL_EDGE_TOL_M,
        classify_mechanisms,
    )
    from diffpos_services.raytrace.paths import DIFFRACTION, SPECULAR

    mech = classify_mechanisms(ds, mset)
    lab = mech.label.astype(object)
    code = np.where((mech.code == OTHER) | (mech.code == NO_PATH), -1, mech.code)
    b = ds.scenario.building
    x0, x1 = b.edge_x_m
    lo, hi = b.window_z_m(b.floor_index(ds.nodes_m[:, 2]))
    verts = ds.path_vertices_m.astype(np.float64)
    chain = ds.path_chain.astype(np.uint16)
    named = np.zeros(lab.shape, dtype=bool)
    ys = []
    for d in range(min(verts.shape[3], 4)):
        flag = (chain >> np.uint16(4 * d)) & np.uint16(0xF)
        p = verts[:, :, :, d, :]
        in_band = ((p[..., 2] > lo[:, None, None]) & (p[..., 2] < hi[:, None, None])
                   & (np.abs(p[..., 1]) < VERTICAL_EDGE_TOL_M))
        for xe in (x0, x1):
            hit = (flag == DIFFRACTION) & in_band & (np.abs(p[..., 0] - xe) < PLANE_TOL_M)
            hit &= ~named & ds.path_valid
            ys.append(p[..., 1][hit])
            named |= hit
    part = np.full(lab.shape, -1)
    for d in range(min(verts.shape[3], 4)):
        flag = (chain >> np.uint16(4 * d)) & np.uint16(0xF)
        p = verts[:, :, :, d, :]
        for j, pt in enumerate(b.partitions):
            on = np.abs(p[..., 0 if pt.axis == "x" else 1] - pt.position_m) < PLANE_TOL_M
            part = np.where((flag == SPECULAR) & on & (p[..., 1] > PLANE_TOL_M)
                            & (part == -1), j, part)
    y = np.concatenate(ys) if ys else np.zeros(0)
    return code, lab, float(np.median(y)) if y.size else float("nan"), part


def sionna_length_table(paths: list[str], max_order: int) -> None:
    """Traced vs closed-form length per family (module docstring). The vertical-edge families
    are evaluated in the traced scene's frame too (the edge at the traced points' ``y``,
    :data:`VERTICAL_EDGE_TOL_M`), and beside it the model's own (edge at ``y = 0``)."""
    import dataclasses

    from diffpos_services.raytrace.dataset import load_dataset
    from diffpos_services.raytrace.mechanisms import model_lengths

    from diffpos.paths.mechanisms import mechanism_set

    mset = mechanism_set(max_order, partitions=True)
    for path in paths:
        ds = load_dataset(path)
        code, _, y_edge, part = sionna_chains(ds, mset)
        length, _, loose = model_lengths(ds, mset)
        shifted = (length, loose)
        if np.isfinite(y_edge):
            up = np.array([0.0, -y_edge, 0.0])
            sds = dataclasses.replace(ds, nodes_m=ds.nodes_m + up, anchors_m=ds.anchors_m + up)
            shifted = model_lengths(sds, mset)[0::2]
        # a partition family: the model on the traced path's partition alone (in the scene's
        # frame for a vertical edge)
        b = ds.scenario.building
        by_part = {}
        for j, pt in enumerate(b.partitions):
            sc = dataclasses.replace(ds.scenario, building=dataclasses.replace(b, partitions=(pt,)))
            meta = {**ds.metadata, "scenario": sc.to_dict()}
            by_part[j, False] = model_lengths(dataclasses.replace(ds, metadata=meta), mset)[0::2]
            if np.isfinite(y_edge):  # the scene's frame: a y-partition moves with the nodes
                pts = dataclasses.replace(pt, position_m=pt.position_m - y_edge
                                          ) if pt.axis == "y" else pt
                sc = dataclasses.replace(sc, building=dataclasses.replace(b, partitions=(pts,)))
                by_part[j, True] = model_lengths(dataclasses.replace(
                    sds, metadata={**ds.metadata, "scenario": sc.to_dict()}), mset)[0::2]
        print(f"\n{path} (mechanism_set({max_order}, partitions=True): {len(mset)} families; "
              f"traced vertical edge at y = {y_edge:+.4f} m)\n")
        print("| family | paths | model has | max \\|err\\| [mm] | p99 [mm] | model y = 0: p50 [mm] |")
        print("| --- | ---: | ---: | ---: | ---: | ---: |")
        for s, name in enumerate(mset.labels):
            idx = np.argwhere(code == s)
            if s < 18 or len(idx) == 0:  # the 18: `diffpos raytrace` checks them
                continue
            n, m, k = idx.T
            vert = "vertical" in name
            ln, lz = shifted if vert else (length, loose)
            ln, lz = ln[n, m, s], lz[n, m, s]
            if "partition" in name:
                j = part[n, m, k]
                ln = np.array([by_part[jj, vert][0][i, a, s]
                               for jj, i, a in zip(j, n, m, strict=True)])
                lz = np.array([by_part[jj, vert][1][i, a, s]
                               for jj, i, a in zip(j, n, m, strict=True)])
            ok = lz
            err = np.abs(ds.path_length_m[n, m, k] - ln)[ok] * 1e3
            own = np.abs(ds.path_length_m[n, m, k] - length[n, m, s])[loose[n, m, s]] * 1e3
            mx = f"{err.max():.4f}" if err.size else "-"
            p99 = f"{np.percentile(err, 99):.4f}" if err.size else "-"
            p50 = f"{np.median(own):.1f}" if vert and own.size and "partition" not in name else ""
            print(f"| {name} | {len(idx)} | {100 * ok.mean():.1f} % | {mx} | {p99} | {p50} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--paper-nodes", type=int, default=17_485)
    parser.add_argument("--fa-nodes", type=int, default=2_000,
                        help="nodes of the batched first-arrival rows (x 5 floors x 8 anchors)")
    parser.add_argument("--only", choices=("first-arrival", "geometry"), default=None)
    parser.add_argument("--profile-mnls", type=int, default=0, metavar="N",
                        help="only profile one batched M-NLS call on N fixes")
    parser.add_argument("--reference", action="store_true",
                        help="with --profile-mnls: M-NLS's reference steps (kernel=False)")
    parser.add_argument("--numpy-paths", action="store_true",
                        help="with --profile-mnls: the estimator on the numpy path model (A/B)")
    parser.add_argument("--numpy-snr", action="store_true",
                        help="with --profile-mnls: the SNR cost on the numpy emulator (A/B)")
    parser.add_argument("--sionna", nargs="+", metavar="DATASET",
                        help="only check the families' lengths against these ray-trace datasets")
    parser.add_argument("--max-order", type=int, default=4, help="--sionna's mechanism_set order")
    args = parser.parse_args()
    if args.sionna:
        sionna_length_table(args.sionna, args.max_order)
        return
    if args.profile_mnls:
        profile_mnls(args.profile_mnls, args.numpy_paths, args.numpy_snr,
                     reference=args.reference)
        return
    if args.only in (None, "first-arrival"):
        first_arrival_table(args)
    if args.only in (None, "geometry"):
        geometry_table(args)


if __name__ == "__main__":
    main()
