"""Diagnose ``bench_accuracy.py --random`` recordings (kept with ``--keep DIR``).

Usage::

    python benchmarks/heldout_diag.py levels DIR rand-0-0 rand-0-1 ...   # level vs stairs
    python benchmarks/heldout_diag.py links DIR rand-0-36                # bad epochs' links
    python benchmarks/heldout_diag.py skip DIR rand-0-36 rand-0-20       # skipped paths
    python benchmarks/heldout_diag.py flight DIR rand-0-25 rand-0-26 ...  # along the stairs
    python benchmarks/heldout_diag.py changes DIR rand-0-0 rand-0-1 ...  # floor changes

The scenario of ``rand-S-i`` is regenerated from its name (:mod:`heldout`).

- ``levels``: per run, the node-epochs after the first 2 s on the level (the truth at a
  floor's nominal height) and on the stairs: floor accuracy, truth inside the reported 95 %
  ellipsoid (over the fixes), and the wrong-floor estimates below / above the truth.
- ``links``: per node, the wrong-floor and > 1.5 m epochs; over them, per anchor, the
  emulator's noise-free first-arrival mechanism at the truth against the mechanism the
  estimate explained the range with; a few epochs in full (floor probabilities, SNRs,
  residuals).
- ``skip``: for wrong-floor (and, for reference, right-floor) epochs, the paths the
  emulator's detector would have reported before the measured first arrival had the node
  been at the estimate (existing, > 0.15 m shorter than the noise-free measured range, SNR
  above the detector's threshold there: ``max(P_max - fap_threshold_db, detection_snr_db)``)
  and ``-log P(all of them below the threshold)`` with the tracker's SNR standard deviation
  (:data:`diffpos.tracking.model.SNR_SIGMA_DB`); the same at the truth.
- ``flight``: the right-floor stairs node-epochs of all the runs named, pooled by the truth's
  height along the flight (fifths of a floor height above a floor's nominal height): truth
  inside the 95 % ellipsoid, ``|z error| / sigma_z`` and the mean z error.
- ``changes``: every floor change of a responder's truth (after the first 2 s, the truth on
  the new floor for at least :data:`HOLD_S`) in all the runs named: how long until the
  published floor settles on the new one (the first epoch from which it equals the new
  floor for :data:`HOLD_S` or until the truth changes again; the tracking issue's bar: within
  2 s), pooled over the runs; up and down apart, and the slowest.
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import numpy as np
from common import SKIP_S
from diffpos_services.recording.reader import McapScanner
from diffpos_services.recording.topics import parse_topic
from diffpos_services.wire import messages as M
from heldout import random_scenario
from scipy.special import log_ndtr

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.metrics import truth_at
from diffpos.paths.mechanisms import MECHANISMS
from diffpos.scenario import Scenario
from diffpos.tracking.model import SNR_SIGMA_DB

CHI2_3_95 = 7.814727903251178  # 95 % quantile of chi-square with 3 degrees of freedom
#: a floor change counts when the truth then stays on the new floor this long; the estimate
#: has settled when it then shows the new floor this long (or until the truth changes) [s]
HOLD_S = 1.0


def scenario_of(name: str) -> Scenario:
    _, seed, i = name.split("-")
    return Scenario.from_dict(random_scenario(int(seed), int(i)))


class Run:
    """A recording's truth (nodes, anchors) and estimates, node-epochs after ``SKIP_S``."""

    def __init__(self, path: Path, sc: Scenario):
        self.sc, b = sc, sc.building
        d_est, d_truth, d_rc = M.estimate_decoder(), M.decoder(M.GroundTruth), M.decoder(
            M.RunControl)
        truth, atruth, self.est, self.t0 = {}, {}, {}, None
        for batch in McapScanner(path).iter_batches():
            for m in batch:
                kind = parse_topic(m.topic)[0]
                if kind in ("truth_node", "truth_anchor"):
                    g = d_truth(m.data)
                    (truth if kind == "truth_node" else atruth)[(g.id, g.t_ns)] = g
                elif kind == "estimate":
                    e = d_est(m.data)
                    self.est[(e.node_id, e.epoch)] = e
                elif kind == "run_control" and self.t0 is None:
                    self.t0 = d_rc(m.data).t0_ns
        ts = np.unique([k[1] for k in truth])
        self.period = int(np.min(np.diff(ts)))
        self.tracks = {n: self._track(truth, n, True) for n in sorted({k[0] for k in truth})}
        self.anchors = {a.id: self._track(atruth, a.id, False) for a in sc.anchors}
        h = b.nominal_node_height_m
        self.rows = []  # node, t_s, truth floor, est floor, 3D error, inside, truth, est, kind
        for n, (tt, pp, ff) in self.tracks.items():
            for t, p in zip(tt, pp, strict=True):
                if t < self.t0 + SKIP_S * 1e9:
                    continue
                frac = (p[2] - b.first_floor_z_m - h) / b.floor_height_m
                kind = "stairs" if abs(frac - round(frac)) > 0.02 else "level"
                e = self.est.get((n, t // self.period))
                if e is None or e.position_m is None or e.status not in M.GOOD_STATUSES:
                    self.rows.append((n, (t - self.t0) * 1e-9, None, None, np.nan, False, p,
                                      e, kind))
                    continue
                pt, ft = truth_at([e.t_ns], tt, pp, ff, floor_of=b.floor_index)
                err = np.asarray(e.position_m) - pt[0]
                inside = (e.covariance_m2 is not None and float(
                    err @ np.linalg.solve(np.asarray(e.covariance_m2), err)) <= CHI2_3_95)
                self.rows.append((n, (t - self.t0) * 1e-9, int(ft[0]), e.floor_index,
                                  float(np.linalg.norm(err)), inside, pt[0], e, kind))

    @staticmethod
    def _track(truth, ident, node):
        ks = sorted(k for k in truth if k[0] == ident)
        t = np.array([k[1] for k in ks], np.int64)
        p = np.array([truth[k].position_m for k in ks])
        f = np.array([truth[k].floor_index if node else 0 for k in ks])
        return t, p, f

    def anchors_at(self, t_ns: int) -> np.ndarray:
        return np.stack([truth_at([t_ns], t, p, f)[0][0] for t, p, f in self.anchors.values()])

    def first_arrival_at(self, p_m: np.ndarray, anchors_m: np.ndarray):
        b, r = self.sc.building, self.sc.radio
        return first_arrival(emulate_channel(anchors_m, p_m[None], building=b, radio=r),
                             radio=r, rng=None)


def levels(run: Run, name: str) -> str:
    out = {}
    for kind in ("level", "stairs"):
        r = [x for x in run.rows if x[8] == kind]
        fixes = [x for x in r if x[3] is not None or np.isfinite(x[4])]
        ok = sum(1 for x in r if x[2] is not None and x[3] == x[2])
        out[kind] = (len(r), 100 * ok / max(len(r), 1),
                     100 * sum(x[5] for x in fixes) / max(len(fixes), 1))
    wrong = [x for x in run.rows if x[3] is not None and x[2] is not None and x[3] != x[2]]
    below = sum(1 for x in wrong if x[3] < x[2])
    top = sum(1 for x in wrong if x[2] == run.sc.building.n_floors - 1)
    (ln, lf, lc), (sn, sf, sc) = out["level"], out["stairs"]
    return (f"{name:10s} level {ln:4d} floor {lf:5.1f}% cov {lc:5.1f}% | stairs {sn:4d} floor "
            f"{sf:5.1f}% cov {sc:5.1f}% | wrong floor {below} below, {len(wrong) - below} "
            f"above ({top} on the top floor)")


def links(run: Run, name: str, show: int = 4) -> None:
    b, ids = run.sc.building, [a.id for a in run.sc.anchors]
    print(f"{name}: {b.n_floors} floors x {b.floor_height_m:g} m from {b.first_floor_z_m:g} m, "
          f"sill {b.sill_height_m:g} + window {b.window_height_m:g} m")
    for a in run.sc.anchors:
        print(f"  {a.id} at {np.round(a.position_m, 2)}")
    bad = []
    for n in run.tracks:
        r = [x for x in run.rows if x[0] == n]
        wrong = [x for x in r if x[3] is not None and x[2] is not None and x[3] != x[2]]
        big = [x for x in r if x[4] > 1.5]
        print(f"  {n}: {len(r)} epochs, wrong floor {len(wrong)} "
              f"(truth {dict(collections.Counter(x[2] for x in wrong))} -> estimate "
              f"{dict(collections.Counter(x[3] for x in wrong))}), > 1.5 m {len(big)} "
              f"({sum(1 for x in big if x[8] == 'stairs')} on the stairs), outside the "
              f"ellipsoid {sum(1 for x in r if not x[5])}"
              + (f", bad at t {min(x[1] for x in wrong + big):.1f}-"
                 f"{max(x[1] for x in wrong + big):.1f} s" if wrong or big else ""))
        bad += [x for x in r if x in wrong or x in big]
    count, detail = collections.Counter(), []
    for x in bad:
        e = x[7]
        fa = run.first_arrival_at(x[6], run.anchors_at(e.t_ns))
        lk = {link.anchor_id: link for link in e.links}
        row = []
        for j, a in enumerate(ids):
            true_m = MECHANISMS[fa.slot[0, j]] if fa.slot[0, j] >= 0 else "-"
            got = lk.get(a)
            count[(a, true_m, None if got is None else got.mechanism)] += 1
            row.append((a, true_m, round(float(fa.snr_db[0, j]), 1),
                        None if got is None else got.mechanism,
                        None if got is None or got.residual_m is None
                        else round(got.residual_m, 2)))
        detail.append((x, row))
    print(f"  {len(bad)} bad epochs: (anchor, emulator's first arrival at the truth, the "
          f"estimate's mechanism): count")
    for k, v in count.most_common(12):
        print(f"    {k}: {v}")
    for x, row in detail[:: max(1, len(detail) // show)][:show]:
        print(f"  {x[0]} t={x[1]:.1f} s floor {x[2]} -> {x[3]}, error {x[4]:.2f} m, truth "
              f"{np.round(x[6], 2)}, estimate {np.round(x[7].position_m, 2)}, floor "
              f"probabilities {np.round(x[7].floor_probabilities, 2)}")
        for link in row:
            print(f"      {link}")


def detector_threshold(exists: np.ndarray, snr_db: np.ndarray, radio) -> float:
    """The emulator's first-arrival threshold of one link [dB]: ``max(P_max -
    fap_threshold_db, detection_snr_db)`` over its existing paths."""
    return max(np.max(np.where(exists, snr_db, -np.inf)) - radio.fap_threshold_db,
               radio.detection_snr_db)


def _skipped(run: Run, p_m: np.ndarray, anchors_m: np.ndarray, meas: np.ndarray):
    b, r = run.sc.building, run.sc.radio
    ch = emulate_channel(anchors_m, p_m[None], building=b, radio=r)
    n_det, cost = 0, 0.0
    for j in range(len(anchors_m)):
        if not np.isfinite(meas[j]):
            continue
        ex, snr, ln = ch.exists[0, j], ch.snr_db[0, j], ch.length_m[0, j]
        thr = detector_threshold(ex, snr, r)
        earlier = ex & (ln < meas[j] - 0.15) & (snr >= thr)
        n_det += int(earlier.sum())
        cost -= float(np.sum(log_ndtr((thr - snr[earlier]) / SNR_SIGMA_DB)))
    return n_det, cost


def skip(run: Run, name: str, every: int = 3, max_right: int = 60) -> str:
    res = {"wrong": [], "right": []}
    for x in run.rows[::every]:
        if x[3] is None or x[2] is None:
            continue
        key = "wrong" if x[3] != x[2] else "right"
        if key == "right" and len(res[key]) >= max_right:
            continue
        e = x[7]
        anchors = run.anchors_at(e.t_ns)
        fa = run.first_arrival_at(x[6], anchors)
        meas = np.where(fa.detected[0], fa.true_path_m[0], np.nan)  # noise-free ranges
        res[key].append((_skipped(run, x[6], anchors, meas),
                         _skipped(run, np.asarray(e.position_m), anchors, meas)))
    out = []
    for key, v in res.items():
        if not v:
            out.append(f"{name} {key}-floor: none")
            continue
        tr, es = np.array([a for a, _ in v]), np.array([b for _, b in v])
        out.append(f"{name} {key}-floor epochs (every {every} epochs) {len(v)}: skipped detectable "
                   f"paths per epoch at the truth {tr[:, 0].mean():.2f} (-log P median "
                   f"{np.median(tr[:, 1]):.2f}), at the estimate {es[:, 0].mean():.2f} (median "
                   f"{np.median(es[:, 1]):.2f}, p10 {np.percentile(es[:, 1], 10):.2f} nats); "
                   f"epochs with >= 1 at the estimate {100 * np.mean(es[:, 0] > 0):.0f} %")
    return "\n".join(out)


def flight(runs: list[Run]) -> str:
    """Stairs node-epochs on the right floor by the truth's height along the flight."""
    bins: dict[int, list] = collections.defaultdict(list)
    for run in runs:
        b = run.sc.building
        for r in run.rows:
            if r[8] != "stairs" or r[3] is None or r[2] != r[3]:
                continue
            frac = (r[6][2] - b.first_floor_z_m - b.nominal_node_height_m) / b.floor_height_m
            err = np.asarray(r[7].position_m) - r[6]
            sz = float(np.sqrt(np.asarray(r[7].covariance_m2)[2, 2]))
            bins[min(int((frac - np.floor(frac)) * 5), 4)].append((r[5], abs(err[2]) / sz,
                                                                   err[2]))
    out = []
    for k in sorted(bins):
        v = np.array(bins[k], float)
        out.append(f"height along the flight {20 * k:3d}-{20 * k + 20:3d} %: n {len(v):5d} "
                   f"covered {100 * v[:, 0].mean():5.1f} %  |z err|/sigma_z p50 "
                   f"{np.median(v[:, 1]):.2f} p90 {np.percentile(v[:, 1], 90):.2f}  "
                   f"mean z err {v[:, 2].mean():+.3f} m")
    return "\n".join(out)


def _settle_delays(run: Run, name: str) -> list[tuple[float, int, str, str, float]]:
    """(delay [s] or inf, +1 up / -1 down, run, node, t of the change [s]) per floor change."""
    out = []
    for n, (tt, _pp, ff) in run.tracks.items():
        ts = (tt - run.t0) * 1e-9
        est = np.full(tt.size, -99.0)  # -99: no estimate with a position
        for j, t in enumerate(tt):
            e = run.est.get((n, t // run.period))
            if e is not None and e.status in M.GOOD_STATUSES and e.floor_index is not None:
                est[j] = e.floor_index
        changes = np.flatnonzero(np.diff(ff) != 0) + 1
        ends = np.append(changes[1:], ff.size)[:changes.size]
        # HOLD_S in epochs: the truth's stay on the new floor and the estimate's are both
        # counted in samples (samples k .. end - 1 are end - k periods on the new floor)
        hold = max(round(HOLD_S / (run.period * 1e-9)), 1)
        for k, end in zip(changes, ends, strict=True):
            if ts[k] < SKIP_S or end - k < hold:
                continue  # in the skipped start, or the truth did not stay there
            delay = np.inf
            # the estimate's hold may end early only where the truth changes again, not
            # where the recording ends (a flicker in its last second is not a settling)
            last = end if end < ff.size else end - hold + 1
            for j in range(k, last):
                window = est[j:min(j + hold, end)]
                if window.size and np.all(window == ff[k]):
                    # from the integer ns: (ts[j] - ts[k]) is off by an ulp often enough to
                    # put a delay of exactly 2 s over the 2 s bar
                    delay = int(tt[j] - tt[k]) / 1e9
                    break
            out.append((delay, int(np.sign(ff[k] - ff[k - 1])), name, n, float(ts[k])))
    return out


def changes(runs: list[tuple[str, Run]]) -> str:
    """Floor changes of the truth and how long the published floor took to follow."""
    rows = [d for name, run in runs for d in _settle_delays(run, name)]
    out = []
    for label, sel in (("all", rows), ("up", [r for r in rows if r[1] > 0]),
                       ("down", [r for r in rows if r[1] < 0])):
        if not sel:
            continue
        d = np.array([r[0] for r in sel])
        fin = d[np.isfinite(d)]
        # no interpolation: between a finite delay and a never (inf) it would give NaN
        p50, p90 = np.percentile(d, (50, 90), method="inverted_cdf")
        out.append(f"{label:>5}: {d.size} floor changes, within 2 s {100 * np.mean(d <= 2.0):.1f} %"
                   f", delay p50 {p50:.1f} s p90 {p90:.1f} s, "
                   f"never settled {int(np.sum(~np.isfinite(d)))}"
                   + (f", slowest settled {fin.max():.1f} s" if fin.size else ""))
    slow = sorted((r for r in rows if r[0] > 2.0), key=lambda r: -r[0])[:8]
    out += [f"  over 2 s: {r[2]} {r[3]} at t = {r[4]:.1f} s ({'up' if r[1] > 0 else 'down'}): "
            f"{r[0]:.1f} s" for r in slow]
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["levels", "links", "skip", "flight", "changes"])
    ap.add_argument("dir", type=Path, help="bench_accuracy --keep directory")
    ap.add_argument("names", nargs="+", help="rand-S-i runs")
    args = ap.parse_args(argv)
    if args.what == "flight":
        print(flight([Run(args.dir / f"{n}.mcap", scenario_of(n)) for n in args.names]))
        return 0
    if args.what == "changes":
        print(changes([(n, Run(args.dir / f"{n}.mcap", scenario_of(n))) for n in args.names]))
        return 0
    for name in args.names:
        run = Run(args.dir / f"{name}.mcap", scenario_of(name))
        if args.what == "levels":
            print(levels(run, name), flush=True)
        elif args.what == "links":
            links(run, name)
        else:
            print(skip(run, name), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
