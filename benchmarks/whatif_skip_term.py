"""What if the tracker charged for a skipped detectable earlier path? A replay with a
prototype term (NOT the tracker's model; for the diagnosis in docs/heldout_geo14.md).

Usage::

    python benchmarks/whatif_skip_term.py off REC.mcap     # a plain replay (the reference)
    python benchmarks/whatif_skip_term.py 0.15 REC.mcap    # the term, tolerance 0.15 m

The tracker's first-arrival rule (:func:`diffpos.tracking_paths.candidates`) lets a
diffraction path earlier than the chosen mechanism be skipped at no cost ("it may be too
weak"), while the emulator's detector reports the earliest path above its threshold. The
prototype adds to every slot ``k`` of the tracker's SNR cost, per link with a measured SNR,
``-log Phi((thr - pred_j) / SNR_SIGMA_DB)`` for every diffraction slot ``j`` that exists at
the hypothesis and is shorter than ``k`` by more than the tolerance: ``pred_j`` its
predicted SNR (the emulator's amplitude model, as the SNR term), ``thr`` the detector's
threshold at the hypothesis. It wraps :func:`diffpos.tracking_model.snr_cost_near` and runs
``diffpos replay FILE --workers 1 ...`` in this process.
"""

from __future__ import annotations

import sys

import numpy as np
from scipy.special import log_ndtr

import diffpos.tracking_model as tm
from diffpos.channel import pair_snr_db
from diffpos.tracking_paths import _IS_DIFF
from diffpos.tracking_snr import SNR_SIGMA_DB

_orig = tm.snr_cost_near


def _with_skip_term(tol_m: float):
    def cost(pos, links, floor, building, relax_m, pe=None, cache=None, reuse_m=(0.0, 0.0)):
        c = _orig(pos, links, floor, building, relax_m, pe, cache, reuse_m)
        if c is None:
            return c
        if pe is None:
            pe = tm.all_paths(pos, links, floor, building, relax_m)
        n, h, m, k = c.shape
        anc = np.broadcast_to(links.anchors, (n, h, m, 3)).reshape(n * h, m, 3)
        pred = pair_snr_db(np.ascontiguousarray(anc), pos.reshape(n * h, 3),
                           building=building, radio=links.radio).reshape(n, h, m, k)
        r = links.radio
        top = np.max(np.where(pe.sure, pred, -np.inf), axis=-1)
        thr = np.maximum(top - r.fap_threshold_db, r.detection_snr_db)
        det = _IS_DIFF & pe.strict & np.isfinite(pred)
        with np.errstate(invalid="ignore"):
            lc = np.where(det, -log_ndtr((thr[..., None] - pred) / SNR_SIGMA_DB), 0.0)
        ln = pe.length
        earlier = det[..., None, :] & (ln[..., None, :] < ln[..., :, None] - tol_m)  # [k, j]
        pen = np.sum(np.where(earlier, lc[..., None, :], 0.0), axis=-1)
        known = np.isfinite(np.broadcast_to(links.snr, (n, h, m)))[..., None]
        return np.where(known & np.isfinite(c), c + pen, c)
    return cost


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__)
        return 2
    if argv[0] != "off":
        tm.snr_cost_near = _with_skip_term(float(argv[0]))
    from diffpos_services.cli.main import main as cli

    return cli(["replay", argv[1], "--no-files", "--no-progress", "--workers", "1", *argv[2:]])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
