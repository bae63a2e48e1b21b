"""CPU of the tracker's SNR prediction (``diffpos.tracking.model.snr_cost_near``) on the calls of
a real replay: every slot predicted everywhere (the algorithm before the slot masks) against
the current code, with the shifted point's and with the prior's threshold for the relax holes.

Usage::

    python benchmarks/bench_snr_cost.py RECORDING [--every 1] [--reps 3] [--method mnls]

Replays the recording in this process once (:func:`diffpos_services.replay.run.replay`,
all epochs solved, no recorded decisions) and keeps the inputs of every ``--every``-th
``snr_cost_near`` call; then times (``time.process_time``, the best of ``--reps`` passes) one
pass over the kept calls with

* ``all slots``: the brute force, every slot of every link predicted at the hypothesis and
  at both shifted heights (``pair_snr_db`` unmasked, the numpy cost);
* ``masked, exact``: ``HOLE_THRESHOLD_AT_PRIOR = False``; its outputs must equal the brute
  force's bit for bit (checked, printed);
* ``masked, prior thr``: the default; the number of slot costs that differ is printed.

The variants run interleaved call by call, so a change of the machine's load hits all three.

The table names the machine and the load average (the VM is shared: the ratio of the variants
within one run is the figure to read, not the absolute seconds).

Measured 2026-11-27 11:48-11:51 UTC (2-core x86_64 VM shared with other jobs, load 2.4-3.2),
commit fd0434f::

    recording                       calls  links x hyp.  all slots  masked, exact  prior thr
    /tmp/s8/soak/soak16x200.mcap   205/617     1269648     5.585 s  3.882 s 1.44x  3.255 s 1.72x
    /tmp/s8/large.mcap             399/399      321808     1.594 s  1.188 s 1.34x  0.965 s 1.65x

(``--every 3 --reps 3`` and ``--reps 3``.) Exact: outputs equal to the brute force in every
call; prior threshold: 0.08 % (soak) / 0.12 % (large) of the slot costs differ. What is left is
the prediction at the hypotheses themselves (~80 % of the masked time: all 18 slots of every
link with a known SNR; the 7 diffraction slots are needed there, as candidates and for the
detector's threshold).
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

import diffpos.tracking.model as tm
from diffpos.channel.emulator import pair_snr_db
from diffpos.tracking.links import K_SLOTS, PathEval, _relax


def _brute_force(pos, links, floor, building, relax_m, pe):
    """snr_cost_near predicting every slot everywhere (the shifted point's threshold)."""
    n, h = pos.shape[:2]
    m = links.rho.shape[-1]
    anc = np.broadcast_to(links.anchors, (n, h, m, 3)).reshape(-1, 3)
    p = np.broadcast_to(pos[:, :, None, :], (n, h, m, 3)).reshape(-1, 3)
    meas = np.broadcast_to(links.snr, (n, h, m)).reshape(-1)
    sure = pe.sure.reshape(-1, K_SLOTS)
    pred = pair_snr_db(anc[:, None, :], p, building=building, radio=links.radio)[:, 0]
    c = tm._snr_cost_of_numpy(pred, meas, links.radio, sure)[0]
    hole = ~np.isfinite(c) & pe.loose.reshape(-1, K_SLOTS)
    rows = np.flatnonzero(np.any(hole, axis=-1))
    if rows.size:
        dz = np.broadcast_to(_relax(relax_m, (n, h))[..., None], (n, h, m)).reshape(-1)[rows]
        fl = np.broadcast_to(np.broadcast_to(np.asarray(floor), (n, h))[..., None],
                             (n, h, m)).reshape(-1)[rows]
        zf = building.floor_z_m(fl)
        best = np.full((rows.size, K_SLOTS), np.inf)
        for sign in (-1.0, 1.0):
            q = p[rows].copy()
            q[:, 2] = np.clip(q[:, 2] + sign * dz, zf + 0.01,
                              zf + building.floor_height_m - 0.01)
            pq = pair_snr_db(anc[rows, None, :], q, building=building, radio=links.radio)[:, 0]
            best = np.minimum(best, tm._snr_cost_of_numpy(pq, meas[rows], links.radio,
                                                          sure[rows])[0])
        c[rows] = np.where(hole[rows], best, c[rows])
    return c.reshape(n, h, m, K_SLOTS)


def _masked(exact: bool):
    def run(*args):
        old = tm.HOLE_THRESHOLD_AT_PRIOR
        tm.HOLE_THRESHOLD_AT_PRIOR = not exact
        try:
            return tm.snr_cost_near(*args)
        finally:
            tm.HOLE_THRESHOLD_AT_PRIOR = old
    return run


def capture(path: str, every: int, method: str) -> list[tuple]:
    """The inputs of every ``every``-th snr_cost_near call of a replay of ``path``."""
    from diffpos_services.replay.run import replay

    calls, count = [], [0]
    orig = tm.snr_cost_near

    def keep(pos, links, floor, building, relax_m, pe=None):
        if count[0] % every == 0 and pe is not None:
            lite = PathEval(length=None, jac=None, strict=None, loose=pe.loose.copy(),
                            sure=pe.sure.copy())  # only these are read
            calls.append((pos.copy(), links, floor, building, relax_m, lite))
        count[0] += 1
        return orig(pos, links, floor, building, relax_m, pe)

    tm.snr_cost_near = keep
    try:
        replay(path, use_decisions=False, method=method, out_mcap=None, keep_estimates=False)
    finally:
        tm.snr_cost_near = orig
    return calls


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("recording")
    ap.add_argument("--every", type=int, default=1, help="keep every n-th call")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--method", default="mnls")
    args = ap.parse_args()
    calls = capture(args.recording, args.every, args.method)
    variants = {"all slots": _brute_force, "masked, exact": _masked(True),
                "masked, prior thr": _masked(False)}
    ref = [_brute_force(*c) for c in calls]  # also the warm-up
    same = sum(np.array_equal(r, _masked(True)(*c)) for r, c in zip(ref, calls, strict=True))
    diff = sum(int(np.sum(r != _masked(False)(*c))) for r, c in zip(ref, calls, strict=True))
    size = sum(r.size for r in ref)
    pairs = sum(r.shape[0] * r.shape[1] * r.shape[2] for r in ref)
    cpu = {k: [] for k in variants}
    names = list(variants)
    for _ in range(args.reps):  # the variants interleaved call by call (the load drifts)
        acc = dict.fromkeys(names, 0.0)
        for i, c in enumerate(calls):
            for k in names[i % 3:] + names[:i % 3]:
                t0 = time.process_time()
                variants[k](*c)
                acc[k] += time.process_time() - t0
        for k in names:
            cpu[k].append(acc[k])
    base = min(cpu["all slots"])
    print(f"bench_snr_cost: {args.recording}, {len(calls)} snr_cost_near calls "
          f"(every {args.every}), {pairs} links x hypotheses; best of {args.reps}")
    print(f"machine: {platform.machine()} {os.cpu_count()} cores, Python "
          f"{platform.python_version()}, load avg {os.getloadavg()[0]:.1f}")
    print(f"{'variant':20s} {'CPU s':>8s} {'us/link':>8s} {'speed-up':>9s}")
    for k, v in cpu.items():
        print(f"{k:20s} {min(v):8.3f} {1e6 * min(v) / pairs:8.2f} {base / min(v):8.2f}x")
    print(f"masked, exact = all slots bit for bit: {same}/{len(calls)} calls; "
          f"prior thr: {diff} of {size} slot costs differ")


if __name__ == "__main__":
    main()
