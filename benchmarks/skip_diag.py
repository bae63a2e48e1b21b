"""Where does a skipped-earlier-path penalty land? (issue 14, cause 1 of docs/heldout_geo14.md)

Usage::

    python benchmarks/skip_diag.py DIR rand-0-20 rand-0-24 rand-0-36 ...

For node-epochs after the first 2 s of a ``bench_accuracy --keep`` recording (every 3rd),
split into right / wrong floor and level / stairs (:mod:`heldout_diag`), the penalty a
missed-detection term would charge at the published estimate, from the emulator's own
channel (:func:`diffpos.channel.emulator.emulate_channel`) and the noise-free first arrival at the
truth (the measured range without noise): per link with a detection, every diffraction path
that exists and is shorter than that range by more than ``tol`` costs
``-log Phi((thr - snr_j) / SNR_SIGMA_DB)`` (``thr`` the detector's threshold at the point).

- ``proto``: at the estimate itself, tol 0.15 m (``whatif_skip_term.py``'s term);
- ``cons``: the least of that penalty over the estimate's height uncertainty (the estimate
  and +- ``ENTRY_SIGMAS`` sigma_z of its reported covariance, floored at the tracker's
  ``exist_margin_m``): only what must have been detected wherever the node may be;
- ``soft``: :func:`soft_penalty` at the estimate (no fixed tolerance: the probability that
  an earlier slot precedes the explaining one under the estimate's covariance, times its
  detection probability);
- ``softcons``: the least ``soft`` over the same three heights as ``cons``;
- ``softcons@truth``: ``softcons`` at the truth (its floor, the estimate's covariance);
- ``|dz| sz``: the |z error| and the reported sigma_z (medians).

Columns per penalty: the mean over the node-epochs [nats] and the share of node-epochs with
more than 1 nat. Classes: right / wrong floor, level / stairs (:mod:`heldout_diag`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from heldout_diag import Run, detector_threshold, scenario_of
from scipy.special import log_ndtr, ndtr

from diffpos.channel.emulator import emulate_channel
from diffpos.paths.model import graded_paths
from diffpos.tracking.links import _IS_DIFF
from diffpos.tracking.model import ENTRY_SIGMAS, SNR_SIGMA_DB
from diffpos.tracking.state import TrackerConfig


def penalty(run: Run, p_m: np.ndarray, anchors_m: np.ndarray, meas_m: np.ndarray,
            tol_m: float) -> float:
    """The missed-detection penalty [nats] at ``p_m`` for the measured ranges ``meas_m``."""
    b, r = run.sc.building, run.sc.radio
    ch = emulate_channel(anchors_m, p_m[None], building=b, radio=r)
    cost = 0.0
    for j in range(len(anchors_m)):
        if not np.isfinite(meas_m[j]):
            continue
        ex, snr, ln = ch.exists[0, j], ch.snr_db[0, j], ch.length_m[0, j]
        thr = detector_threshold(ex, snr, r)
        earlier = ex & _IS_DIFF & (ln < meas_m[j] - tol_m) & np.isfinite(snr)
        cost -= float(np.sum(log_ndtr((thr - snr[earlier]) / SNR_SIGMA_DB)))
    return cost


def soft_penalty(run: Run, p_m: np.ndarray, anchors_m: np.ndarray, meas_m: np.ndarray,
                 cov_m2: np.ndarray, floor: int) -> float:
    """The soft penalty [nats]: per link, the slot ``k`` the estimate explains the range with
    (the existing slot nearest to it), and for every other existing diffraction slot ``j`` the
    probability that it precedes ``k`` at the true position, ``Phi((L_k - L_j) / s)`` with
    ``s^2 = (J_k - J_j) P (J_k - J_j)^T`` (the estimate's covariance ``P``), times its
    detection probability ``Phi((snr_j - thr) / SNR_SIGMA_DB)``; the term is
    ``-sum log(1 - P_det_j)``."""
    b, r = run.sc.building, run.sc.radio
    ch = emulate_channel(anchors_m, p_m[None], building=b, radio=r)
    g = graded_paths(p_m[None, None], anchors_m[None], b, relax_m=0.0,
                     floor=np.array([[floor]]))
    cost = 0.0
    for j in range(len(anchors_m)):
        if not np.isfinite(meas_m[j]):
            continue
        ex, snr, ln = ch.exists[0, j], ch.snr_db[0, j], ch.length_m[0, j]
        jac = g.jacobian[0, j]
        if not ex.any():
            continue
        thr = detector_threshold(ex, snr, r)
        k = int(np.argmin(np.where(ex, np.abs(ln - meas_m[j]), np.inf)))
        for i in np.flatnonzero(ex & _IS_DIFF & np.isfinite(snr)):
            if i == k or not np.all(np.isfinite(jac[i])):
                continue
            dj = jac[k] - jac[i]
            s = np.sqrt(max(float(dj @ cov_m2 @ dj), 1e-6))
            pd = ndtr((ln[k] - ln[i]) / s) * ndtr((snr[i] - thr) / SNR_SIGMA_DB)
            cost -= np.log1p(-min(pd, 1 - 1e-12))
    return cost


def _heights(run: Run, z_m: float, dz_m: float, floor: int) -> np.ndarray:
    """``z_m`` and ``z_m +- dz_m``, kept 1 cm inside the floor ``floor``."""
    zf = run.sc.building.floor_z_m(floor)
    return np.clip(z_m + np.array([-dz_m, 0.0, dz_m]), zf + 0.01,
                   zf + run.sc.building.floor_height_m - 0.01)


def main(argv: list[str]) -> int:
    root, names = Path(argv[0]), argv[1:]
    margin = TrackerConfig().exist_margin_m
    print("run        class           n  proto      | cons       | soft       | softcons   |"
          " softcons@truth | |dz| sz (p50)")
    for name in names:
        run = Run(root / f"{name}.mcap", scenario_of(name))
        acc: dict[str, list] = {}
        for x in run.rows[::3]:
            if x[3] is None or x[2] is None:
                continue
            e = x[7]
            key = ("right" if x[3] == x[2] else "wrong") + "/" + x[8]
            anchors = run.anchors_at(e.t_ns)
            fa = run.first_arrival_at(x[6], anchors)
            meas = np.where(fa.detected[0], fa.true_path_m[0], np.nan)
            p = np.asarray(e.position_m, float)
            sz = float(np.sqrt(np.asarray(e.covariance_m2)[2, 2])) if e.covariance_m2 else 0.0
            dz = max(margin, ENTRY_SIGMAS * sz)
            zs = _heights(run, p[2], dz, e.floor_index)
            cons = min(penalty(run, np.array([p[0], p[1], z]), anchors, meas, 0.15) for z in zs)
            cov = np.asarray(e.covariance_m2, float) if e.covariance_m2 else np.eye(3) * 1e-4
            soft = soft_penalty(run, p, anchors, meas, cov, e.floor_index)
            softc = min(soft_penalty(run, np.array([p[0], p[1], z]), anchors, meas, cov,
                                     e.floor_index) for z in zs)
            at_truth = min(soft_penalty(run, np.array([x[6][0], x[6][1], z]), anchors, meas,
                                        cov, x[2]) for z in _heights(run, x[6][2], dz, x[2]))
            acc.setdefault(key, []).append((penalty(run, p, anchors, meas, 0.15), cons, soft, softc,
                                            at_truth,
                                            abs(p[2] - x[6][2]), sz))
        for key, v in sorted(acc.items()):
            a = np.array(v)
            cols = " | ".join(f"{a[:, c].mean():6.2f} {np.mean(a[:, c] > 1):4.0%}"
                              for c in range(5))
            print(f"{name:10s} {key:12s} {len(a):4d}  {cols} | {np.median(a[:, 5]):5.2f}"
                  f" {np.median(a[:, 6]):5.2f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
