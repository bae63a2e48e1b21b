"""Where the tracker's update spends its CPU, and what per-link candidate mechanism sets
could save (issue 37, item 1: "mechanisms that cannot win a link are not evaluated").

Usage::

    python benchmarks/bench_tracker_candidates.py RECORDING [--calls 300] [--reps 4]

1. *Profile*: the recording replayed in this process (M-NLS + tracker, all epochs, as
   ``diffpos replay``) with CPU timers (``time.process_time``) around the tracker bank's
   update and its compiled kernels: the SNR prediction (``eval_snr_masked_kernel``), the paths
   of every mechanism (``all_paths_kernel``), the IEKF, the three selection kernels; the rest
   is Python and numpy.
2. *Candidates*: the inputs of ``--calls`` tracking measurement updates (after the first 100)
   are kept; at each one's prior (paths, SNR term, selection of the first pass, as
   :func:`diffpos.tracking.model.measurement_update` makes them) it counts the diffraction
   candidates (the slots that are ~82 % of the SNR prediction's CPU) whose log-likelihood is
   far below the link's best one: by the range term alone beyond ``snr_cost_cap_nats`` +
   margin (a bound: those cannot win whatever their SNR), and by the whole term (range + SNR:
   an oracle, what a tracker-kept candidate set could at best drop); then it times the SNR
   prediction (``_snr_cost_thr`` with those slots not predicted; best of ``--reps``).
3. *Per call*: the emulated ``scenarios/large.toml`` (50 nodes x 8 anchors, ``--epochs``
   lockstep epochs, the default TrackerConfig) tracked with every epoch's nodes given to
   :func:`diffpos.tracking.tracker.update` in calls of 50, 10 and 5 nodes (the same rows,
   the same results: checked): the CPU per call and per node-epoch, and the fitted fixed
   cost of a call (``a + b n``).
"""

from __future__ import annotations

import argparse
import collections
import copy
import time

import numpy as np


def profile(recording: str) -> None:
    import diffpos_services.fusion.tracked as tracked
    from diffpos_services.replay.run import replay

    import diffpos.channel.emulator as emu
    import diffpos.tracking.links as links_mod
    import diffpos.tracking.model as model

    acc: collections.Counter = collections.Counter()

    def wrap(mod, name, key):
        f = getattr(mod, name)

        def g(*a, **k):
            t0 = time.process_time()
            try:
                return f(*a, **k)
            finally:
                acc[key] += time.process_time() - t0
        setattr(mod, name, g)

    replay(recording, end_s=10.0, keep_estimates=False)  # compile / cache load
    wrap(emu, "eval_snr_masked_kernel", "SNR prediction kernel")
    wrap(links_mod, "all_paths_kernel", "paths kernel (every mechanism)")
    wrap(model, "iekf_kernel", "IEKF kernel")
    for n in ("select_pack_kernel", "select_best_kernel", "select_mix_kernel"):
        wrap(model, n, "selection kernels")
    wrap(tracked, "update", "tracker update (TrackBank.update)")
    t0 = time.process_time()
    replay(recording, keep_estimates=False)
    total = acc["tracker update (TrackBank.update)"]
    print(f"replay CPU {time.process_time() - t0:.2f} s")
    for k, v in acc.most_common():
        print(f"  {k:36s} {v:7.3f} s  {100 * v / total:5.1f} % of the tracker")
    kern = sum(v for k, v in acc.items() if "kernel" in k)
    print(f"  {'Python and numpy (the rest)':36s} {total - kern:7.3f} s  "
          f"{100 * (total - kern) / total:5.1f} %")


def capture(recording: str, n_calls: int) -> list:
    from diffpos_services.replay.run import replay

    import diffpos.tracking.tracker as tracker

    calls: list = []
    orig = tracker.measurement_update

    def mu(*a, **k):
        if len(calls) < 100 + n_calls and k.get("level") is not None:
            calls.append(copy.deepcopy((a, k)))
        return orig(*a, **k)
    tracker.measurement_update = mu
    try:
        replay(recording, keep_estimates=False)
    finally:
        tracker.measurement_update = orig
    return calls[100:]


def candidates(calls: list, reps: int) -> None:
    import diffpos.tracking.model as M
    import diffpos.tracking.state as S
    from diffpos.tracking.links import _IS_DIFF, all_paths

    prep, cnt = [], collections.Counter()
    for a, _ in calls:
        x_prior, p_prior, links, floor, b, cfg = a
        xc = S.clamp_to_floor(x_prior[..., :3], floor, b, cfg.z_margin_m)
        pe = all_paths(xc, links, floor, b, M.existence_margin(p_prior, cfg))
        need = pe.loose | M.ALWAYS_PREDICTED
        snr_c = M.cap_snr_cost(M._snr_cost_thr(xc, links, b, trust=pe.sure, need=need)[0], cfg)
        valid, s_ll, s_var = M._select_prep_numpy(p_prior[..., :3, :3], links, pe, snr_c)
        v0, _, s0 = M._select_prep_numpy(p_prior[..., :3, :3], links, pe, None)
        e = links.rho[..., None] - pe.length
        with np.errstate(invalid="ignore", divide="ignore"):
            rl = np.where(v0, -0.5 * (e * e / s0 + np.log(s0)), -np.inf)
            tl = np.where(valid, -0.5 * (e * e / s_var + np.log(s_var)) + s_ll, -np.inf)
        cap = cfg.snr_cost_cap_nats
        known = np.isfinite(np.broadcast_to(links.snr, pe.length.shape[:3]))[..., None]
        dv = valid & _IS_DIFF & known
        cnt["diffraction candidates"] += int(dv.sum())
        sets = {"every slot (as now)": need}
        for mg in (5, 10):
            far = v0 & _IS_DIFF & (rl < rl.max(-1, keepdims=True) - cap - mg)
            sets[f"range term > cap + {mg} nats below"] = need & ~far
            cnt[f"range term > cap + {mg} nats below"] += int((dv & far).sum())
        for mg in (5, 10):
            far = valid & _IS_DIFF & (tl < tl.max(-1, keepdims=True) - mg)
            sets[f"oracle: whole term > {mg} nats below"] = need & ~far
            cnt[f"oracle: whole term > {mg} nats below"] += int((dv & far).sum())
        sets["no diffraction slot at all"] = need & ~_IS_DIFF
        prep.append((xc, links, b, pe, sets))
    times: dict = collections.defaultdict(list)
    for _ in range(reps):
        for key in prep[0][4]:
            t0 = time.process_time()
            for xc, links, b, pe, sets in prep:
                M._snr_cost_thr(xc, links, b, trust=pe.sure, need=sets[key])
            times[key].append(time.process_time() - t0)
    n_dc = cnt["diffraction candidates"]
    print(f"{len(calls)} measurement updates, {n_dc:,} diffraction candidates with a known SNR")
    print(f"  {'diffraction slots not predicted':40s} {'share far':>9s} {'SNR CPU [s]':>12s}"
          f" {'of now':>7s}")
    base = min(times["every slot (as now)"])
    for key, ts in times.items():
        share = f"{100 * cnt[key] / n_dc:8.1f}%" if key in cnt else " " * 9
        print(f"  {key:40s} {share} {min(ts):12.3f} {min(ts) / base:7.2f}")


def per_call(n_epochs: int, chunks=(50, 10, 5)) -> None:
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_tracker_raytrace import emulator_epochs, emulator_scenario

    from diffpos.tracking.state import TrackerConfig, TrackerState
    from diffpos.tracking.tracker import init_state, update

    sc = emulator_scenario("scenarios/large.toml")
    b, n, cfg = sc.building, len(sc.nodes), TrackerConfig()
    fields = TrackerState.__dataclass_fields__
    states = {c: init_state(n, b) for c in chunks}
    cpu, calls = dict.fromkeys(chunks, 0.0), dict.fromkeys(chunks, 0)
    for t_ns, rep, fa, _ in emulator_epochs(sc, n_epochs=n_epochs, seed=0):
        a = np.broadcast_to(rep, (n, *rep.shape))
        for c in chunks:
            parts, t0 = [], time.process_time()
            for lo in range(0, n, c):
                r = np.arange(lo, min(lo + c, n))
                sub = TrackerState(*(getattr(states[c], f)[r] for f in fields))
                parts.append(update(sub, a[r], fa.range_m[r], fa.sigma_m[r], fa.detected[r],
                                    t_ns, b, cfg, snr_db=fa.snr_db[r], radio=sc.radio)[0])
                calls[c] += 1
            states[c] = TrackerState(*(np.concatenate([getattr(p, f) for p in parts])
                                       for f in fields))
            if t_ns > 0:  # the snapshot initialisation of epoch 0 excluded
                cpu[c] += time.process_time() - t0
    same = all(np.array_equal(getattr(states[chunks[0]], f), getattr(states[c], f),
                              equal_nan=True) for c in chunks for f in fields)
    per = {c: cpu[c] / (calls[c] * (n_epochs - 1) / n_epochs) for c in chunks}
    size = {c: n / -(-n // c) for c in chunks}
    slope = (per[chunks[0]] - per[chunks[-1]]) / (size[chunks[0]] - size[chunks[-1]])
    print(f"large, {n_epochs} epochs, nodes per call: states identical: {same}")
    for c in chunks:
        print(f"  {c:3d} per call: {1e3 * cpu[c] / (n * (n_epochs - 1)):.3f} ms per node-epoch,"
              f" {1e3 * per[c]:.2f} ms per call")
    print(f"  fit: {1e3 * (per[chunks[-1]] - slope * size[chunks[-1]]):.2f} ms per call + "
          f"{1e3 * slope:.3f} ms per node-epoch")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording")
    ap.add_argument("--calls", type=int, default=300)
    ap.add_argument("--reps", type=int, default=4)
    ap.add_argument("--epochs", type=int, default=80, help="per-call part: epochs of large")
    args = ap.parse_args(argv)
    per_call(args.epochs)
    profile(args.recording)
    candidates(capture(args.recording, args.calls), args.reps)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
