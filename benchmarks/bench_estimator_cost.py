"""Per-fix cost of M-NLS (mechanism-aware) vs D-NLS, single and batched, 4 and 8 anchors.

One markdown table, ratios side by side. Target (issue 13): M-NLS <= 2 ms per node-epoch on
average with 8 anchors.

Input: first arrivals of the O2I emulator (diffpos.channel.emulator) on the paper's building, nodes
uniform over the floor plans of all floors at a random height 0.3-2.7 m above their floor
(not only the window mid-height). 4 anchors: the paper's. 8 anchors: the paper's plus one at
a window band's height, one above the windows, one beyond a facade end and one high and far.

Methods, as they would run live on one node-epoch:

* ``dnls``: D-NLS with its live defaults (multi-start over the default height grid and the
  LLS position, RAIM gating), the building's window height and edge extent, the measured sigmas.
* ``mnls``: M-NLS with its defaults (every floor a hypothesis, coarse grid + LM per floor), the
  building, the measured SNR and the radio (the SNR test), the measured sigmas.

Timing: *single* is one fix per call (the median over ``--single`` calls, each a different
node); *batched* is every fix in one call (total / fixes). Both by wall clock and by this
thread's CPU time; CPU time is the figure to compare when other processes share the cores.
Both solve cold (no warm start), the worst case of a live epoch.

Run:  .venv/bin/python benchmarks/bench_estimator_cost.py [--quick] [--seed N]

``--reference``: M-NLS with its numpy/numba reference steps (``kernel=False``: the same
answers, the steps as before the compiled LM).

``--dnls-search``: D-NLS alone, its bounded exclusion search (the defaults:
``exclusion_ftol``, ``exclusion_recheck_ratio``, ``exclusion_bound``) against the exhaustive
one (all three ``None``) on the same fixes, cold and warm-started (x0 = truth + 0.5 m noise),
timed alternately: CPU per fix, and what changed (used anchor sets, statuses, positions,
median error, right floor). ``--replay R.mcap`` does the same on the D-NLS calls of a
``--method dnls`` replay of R (captured first; the fusion's own warm and cold batches).
docs/dnls_cost.md has the figures.

Measured 2026-11-27 06:35 UTC (``--quick``, seed 0; 2-core x86_64 VM, Python 3.11.7, shared
with two other jobs: load average 4.5-6.2, CPU figures move by +-20 % between runs, so the
runs were interleaved): before = commit adf3856 (the SNR kernel and the morning's search
changes in, M-NLS's steps in numpy around the compiled path model and link terms), after =
the compiled starts and LM (``kernel=True``). M-NLS ms CPU per fix, two runs each:

    anchors  mode           before        after         target M-NLS CPU <= 2 ms (8)
    4        single         13.0, 16.2    4.17, 4.15
    4        batched (128)  4.03, 3.42    2.25, 2.25
    8        single         14.6, 13.4    6.57, 5.41    NO
    8        batched (128)  6.03, 4.91    3.79, 3.07    NO

(``--reference`` in the same window: 8 anchors batched 5.44 / 4.26, single 14.4 / 9.85 ms;
at load 0.2, 06:19 UTC, before: 8 anchors batched 4.18, single 9.19 ms.) The fixes are
bitwise the same before and after. Where the M-NLS CPU goes now (``bench_path_model.py
--profile-mnls 64``, 8 anchors): the compiled LM (path model + link terms + steps) 52 %, the
SNR prediction ``diffpos.channel.emulator.pair_snr_db`` 26 %, the rest 22 %.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.estimators.dnls.solver import dnls
from diffpos.estimators.mnls.solver import mnls
from diffpos.scenario import Scenario, default_scenario

TARGET_MS = 2.0
#: Extra anchors of the 8-anchor layout [m]: at floor 1's window band (7.75-9.25 m), above
#: every window but the top floor's, beyond the facade end (x > 20 m), high and far.
EXTRA_ANCHORS_M = np.array([[-25.0, -12.0, 8.5], [10.0, -10.0, 14.0], [28.0, -18.0, 5.5],
                            [-30.0, -25.0, 19.0]])


def nodes_on_floors(sc: Scenario, rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` nodes uniform over the floor plans, random floor, 0.3-2.7 m above the floor."""
    b = sc.building
    x0, x1 = b.edge_x_m
    k = rng.integers(0, b.n_floors, n)
    z = b.floor_z_m(k) + rng.uniform(0.3, min(2.7, b.floor_height_m - 0.3), n)
    return np.stack([rng.uniform(x0 + 0.2, x1 - 0.2, n), rng.uniform(0.2, b.depth_m - 0.2, n),
                     z], axis=-1)


def measurements(sc: Scenario, anchors: np.ndarray, nodes: np.ndarray,
                 rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Batched solver inputs from the emulator's first arrivals."""
    fa = first_arrival(emulate_channel(anchors, nodes, building=sc.building, radio=sc.radio),
                       radio=sc.radio, rng=rng)
    det = np.asarray(fa.detected, dtype=bool)
    return {"a": np.broadcast_to(anchors, (len(nodes), *anchors.shape)),
            "r": np.where(det, fa.range_m, 0.0), "sig": np.where(det, fa.sigma_m, 1.0),
            "mask": det, "snr": np.asarray(fa.snr_db)}


def solvers(sc: Scenario, kernel: bool = True):
    b = sc.building

    def run_dnls(meas, sl):
        return dnls(meas["a"][sl], meas["r"][sl], meas["sig"][sl], mask=meas["mask"][sl],
                    window_height_m=b.window_height_m, edge_x_m=b.edge_x_m)

    def run_mnls(meas, sl):
        return mnls(meas["a"][sl], meas["r"][sl], meas["sig"][sl], mask=meas["mask"][sl],
                    building=b, snr_db=meas["snr"][sl], radio=sc.radio,
                    bandwidth_hz=sc.radio.bandwidth_hz,
                    error_floor_m=sc.radio.range_error_floor_m, kernel=kernel)

    return {"dnls": run_dnls, "mnls": run_mnls}


def timed(fn, meas, sl) -> tuple[float, float, object]:
    """(wall, CPU) seconds of one call and its result."""
    t0, c0 = time.perf_counter(), time.thread_time()
    res = fn(meas, sl)
    return time.perf_counter() - t0, time.thread_time() - c0, res


def cost_rows(sc: Scenario, anchors: np.ndarray, rng: np.random.Generator, n_batch: int,
              n_single: int, kernel: bool = True) -> tuple[list[str], list[str]]:
    nodes = nodes_on_floors(sc, rng, n_batch)
    meas = measurements(sc, anchors, nodes, rng)
    fns = solvers(sc, kernel)
    m = anchors.shape[0]
    ms: dict[tuple[str, str], tuple[float, float]] = {}
    acc = []
    for name, fn in fns.items():
        fn(meas, slice(0, 1))  # warm-up (imports, caches)
        single = np.array([timed(fn, meas, slice(i, i + 1))[:2] for i in range(n_single)])
        ms[name, "single"] = tuple(1e3 * np.median(single, axis=0))
        wall, cpu, res = timed(fn, meas, slice(0, n_batch))
        ms[name, "batched"] = (1e3 * wall / n_batch, 1e3 * cpu / n_batch)
        err = np.linalg.norm(res.position_m - nodes, axis=1)
        floor_ok = sc.building.floor_index(np.where(np.isfinite(res.position_m[:, 2]),
                                                    res.position_m[:, 2], -1e9))
        floor_ok = np.mean(floor_ok == sc.building.floor_index(nodes[:, 2]))
        acc.append(f"| {m} | {name} | {np.median(np.where(np.isfinite(err), err, np.inf)):.2f} "
                   f"| {100 * floor_ok:.1f}% |")
    rows = []
    for mode, batch in (("single", 1), ("batched", n_batch)):
        d, mn = ms["dnls", mode], ms["mnls", mode]
        verdict = ("yes" if mn[1] <= TARGET_MS else "NO") if m == 8 else ""
        rows.append(f"| {m} | {mode} ({batch:,}) | {d[0]:.2f} / {d[1]:.2f} | "
                    f"{mn[0]:.2f} / {mn[1]:.2f} | {mn[0] / d[0]:.1f}x / {mn[1] / d[1]:.1f}x | "
                    f"{verdict} |")
    return rows, acc


EXHAUSTIVE = {"exclusion_ftol": None, "exclusion_recheck_ratio": None, "exclusion_bound": None}


def _capture_replay_calls(recording: str) -> list:
    """The arguments of every ``dnls`` call of a ``--method dnls`` replay of ``recording``."""
    from diffpos_services.replay.run import replay

    import diffpos.estimators.dnls.solver as dnls_solver

    calls: list = []
    orig = dnls_solver.dnls

    def capture(*a, **k):
        calls.append((a, k))
        return orig(*a, **k)

    dnls_solver.dnls = capture
    try:
        replay(recording, method="dnls", keep_estimates=False)
    finally:
        dnls_solver.dnls = orig
    return calls


def _changes(old, new, truth, sc: Scenario | None) -> str:
    """What the bounded search changed against the exhaustive one (same fixes)."""
    used = int((old.used != new.used).any(axis=1).sum())
    status = int((old.status != new.status).sum())
    d = np.linalg.norm(old.position_m - new.position_m, axis=1)
    moved = int((d > 0.01).sum())
    txt = f"{used} / {status} / {moved}"
    if truth is not None and sc is not None:
        cols = []
        for res in (old, new):
            ok = res.status == 0
            err = np.linalg.norm(res.position_m - truth, axis=1)[ok]
            fl = sc.building.floor_index(res.position_m[ok, 2]) == sc.building.floor_index(
                truth[ok, 2])
            cols.append(f"{ok.mean():.3f}, {np.median(err):.2f} m, {fl.mean():.3f}")
        txt += f" | {cols[0]} | {cols[1]}"
    return txt


def search_rows(sc: Scenario, rng: np.random.Generator, n: int, rounds: int) -> list[str]:
    """Bounded vs exhaustive exclusion search on emulated 8-anchor fixes, cold and warm."""
    b = sc.building
    anchors = np.concatenate([sc.anchor_positions_m(), EXTRA_ANCHORS_M])
    nodes = nodes_on_floors(sc, rng, n)
    meas = measurements(sc, anchors, nodes, rng)
    x0 = nodes + rng.normal(0.0, 0.5, nodes.shape)
    rows = ["| fixes | bounded CPU ms/fix (least of rounds) | exhaustive | ratio | used sets / "
            "statuses / positions > 1 cm changed | exhaustive: OK share, median error, right "
            "floor | bounded |", "| --- | ---: | ---: | ---: | --- | --- | --- |"]
    for label, start in (("cold", None), ("warm (x0 = truth + 0.5 m)", x0)):
        def run(kw, start=start):
            return dnls(meas["a"], meas["r"], meas["sig"], mask=meas["mask"], x0_m=start,
                        window_height_m=b.window_height_m, edge_x_m=b.edge_x_m, **kw)
        run({})
        run(EXHAUSTIVE)
        cpu = {"new": [], "old": []}
        for _ in range(rounds):
            for key, kw in (("new", {}), ("old", EXHAUSTIVE)):
                c0 = time.thread_time()
                res = run(kw)
                cpu[key].append(1e3 * (time.thread_time() - c0) / n)
                if key == "new":
                    new = res
                else:
                    old = res
        a, o = min(cpu["new"]), min(cpu["old"])
        rows.append(f"| {label}, {n:,} | {a:.3f} | {o:.3f} | {a / o:.2f} | "
                    f"{_changes(old, new, nodes, sc)} |")
    return rows


def replay_rows(recording: str, rounds: int) -> list[str]:
    """Bounded vs exhaustive on the D-NLS calls of a replay (captured), alternately timed."""
    calls = _capture_replay_calls(recording)
    rows = ["| calls (fixes) | bounded CPU [s] (least / median) | exhaustive | ratio | used "
            "sets / statuses / positions > 1 cm changed |", "| --- | ---: | ---: | ---: | --- |"]
    cpu: dict[str, list[float]] = {"new": [], "old": []}
    outs: dict[str, list] = {}
    for _ in range(rounds):
        for key, over in (("new", {}), ("old", EXHAUSTIVE)):
            c0 = time.thread_time()
            outs[key] = [dnls(*a, **{**k, **over}) for a, k in calls]
            cpu[key].append(time.thread_time() - c0)
    n_fix = sum(len(f.status) for f in outs["new"])
    same_m = [(o, n) for o, n in zip(outs["old"], outs["new"], strict=True)]
    ch = [0, 0, 0]
    for o, nw in same_m:
        ch[0] += int((o.used != nw.used).any(axis=1).sum())
        ch[1] += int((o.status != nw.status).sum())
        ch[2] += int((np.linalg.norm(o.position_m - nw.position_m, axis=1) > 0.01).sum())
    a, o = min(cpu["new"]), min(cpu["old"])
    rows.append(f"| {len(calls)} ({n_fix:,}) | {a:.3f} / {np.median(cpu['new']):.3f} | "
                f"{o:.3f} / {np.median(cpu['old']):.3f} | {a / o:.2f} | "
                f"{ch[0]} / {ch[1]} / {ch[2]} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer fixes (128 batched, 20 single)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--reference", action="store_true",
                    help="M-NLS with its numpy/numba reference steps (kernel=False)")
    ap.add_argument("--dnls-search", action="store_true",
                    help="D-NLS bounded vs exhaustive exclusion search (docs/dnls_cost.md)")
    ap.add_argument("--replay", metavar="R.mcap",
                    help="with --dnls-search: also on the D-NLS calls of a replay of R")
    ap.add_argument("--rounds", type=int, default=3, help="--dnls-search: timing rounds")
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    sc = default_scenario()
    if args.dnls_search:
        n = 256 if args.quick else 2048
        print(f"## D-NLS exclusion search, bounded vs exhaustive (emulated channel, scenario "
              f"{sc.name}, 8 anchors, seed {args.seed})\n")
        print("\n".join(search_rows(sc, rng, n, args.rounds)))
        if args.replay:
            print(f"\n## The same on the D-NLS calls of `diffpos replay {args.replay} --method "
                  "dnls`\n")
            print("\n".join(replay_rows(args.replay, args.rounds)))
        return
    n_batch, n_single = (128, 20) if args.quick else (1024, 100)
    layouts = {4: sc.anchor_positions_m(),
               8: np.concatenate([sc.anchor_positions_m(), EXTRA_ANCHORS_M])}
    rows = ["| anchors | mode (fixes per call) | D-NLS ms/fix wall / CPU | "
            "M-NLS ms/fix wall / CPU | M-NLS / D-NLS wall / CPU | "
            f"M-NLS CPU <= {TARGET_MS:g} ms (8 anchors) |",
            "| ---: | --- | ---: | ---: | ---: | --- |"]
    acc = ["| anchors | method | median 3D error [m] | right floor |",
           "| ---: | --- | ---: | ---: |"]
    for anchors in layouts.values():
        r, a = cost_rows(sc, anchors, rng, n_batch, n_single, kernel=not args.reference)
        rows += r
        acc += a
    how = "reference steps, kernel=False" if args.reference else "compiled LM"
    print(f"## Per-fix cost, M-NLS ({how}) vs D-NLS (scenario {sc.name}, seed {args.seed})\n")
    print("\n".join(rows))
    print(f"\nsingle: median over {n_single} one-fix calls; batched: {n_batch:,} fixes in one "
          "call, total / fixes. Cold solves (no warm start).\n")
    print("## Accuracy of the batched fixes (context)\n")
    print("\n".join(acc))


if __name__ == "__main__":
    main()
