"""Speed of the path model and the bounds: ns per node-anchor pair.

Run:  /work/venv/bin/python benchmarks/bench_path_model.py [--pairs 1000000] [--repeats 7]

Times (median of the repeats, each on fresh inputs of the same size, one thread: set
OMP_NUM_THREADS=1 / OPENBLAS_NUM_THREADS=1 before numpy loads, done below) for

- ``window_edge_path`` on 1,000,000 node-anchor pairs (250,000 nodes x 4 anchors), lengths +
  Jacobians, unbounded edge and clamped to the building width;
- a prototype of a faster kernel (``fast_window_edge_path`` below): same numbers, fewer
  square roots (the unfolded closed form gives OPL, IPL and the Jacobian from one sqrt per
  pair plus one per node), structure-of-arrays output and cache-sized chunks;
- ``diffraction_point`` (general edge orientation) on the paper's 17,485 nodes x 4 anchors;
- ``position_error_bound`` on 17,485 nodes x 4 anchors (Jacobian + FIM + eigvalsh + inverse).

The target is < 100 ns per pair for lengths + Jacobians on one core.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse
import time

import numpy as np

from diffpos.bounds import bounds_from_fim, fisher_information, position_error_bound
from diffpos.geometry import diffraction_point, window_edge_path

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=1_000_000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--paper-nodes", type=int, default=17_485)
    args = parser.parse_args()
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
    print(f"numpy {np.__version__}, median of {args.repeats} runs, one thread")
    print(f"{'what':<{name_w}}  {'pairs':>9}  {'total [ms]':>10}  {'ns/pair':>8}")
    print("-" * (name_w + 33))
    for name, pairs, sec in rows:
        print(f"{name:<{name_w}}  {pairs:>9,}  {sec * 1e3:>10.2f}  {sec / pairs * 1e9:>8.1f}")


if __name__ == "__main__":
    main()
