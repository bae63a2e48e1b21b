"""What if the tracker charged for a skipped detectable earlier path? A replay with a
prototype term (NOT the tracker's model; for the diagnosis in docs/heldout_geo14.md).

Usage::

    python benchmarks/whatif_skip_term.py off REC.mcap     # a plain replay (the reference)
    python benchmarks/whatif_skip_term.py 0.15 REC.mcap    # the term, tolerance 0.15 m
    python benchmarks/whatif_skip_term.py soft REC.mcap    # the "soft" term (below)

The tracker's first-arrival rule (:func:`diffpos.tracking.links.candidates`) lets a
diffraction path earlier than the chosen mechanism be skipped at no cost ("it may be too
weak"), while the emulator's detector reports the earliest path above its threshold. The
prototype adds to every slot ``k`` of the tracker's SNR cost, per link with a measured SNR,
``-log Phi((thr - pred_j) / SNR_SIGMA_DB)`` for every diffraction slot ``j`` that exists at
the hypothesis and is shorter than ``k`` by more than the tolerance: ``pred_j`` its
predicted SNR (the emulator's amplitude model, as the SNR term), ``thr`` the detector's
threshold at the hypothesis. ``soft`` (issue 14's second attempt, every quantity the
tracker's own): a slot ``k`` is charged ``-sum_j log(1 - P_j)`` over the other existing
diffraction slots ``j``, ``P_j = Phi((L_k - L_j) / s_kj) Phi((pred_j - thr) / SNR_SIGMA_DB)``
the probability that ``j`` precedes ``k`` at the true position (``s_kj^2 = (J_k - J_j) P
(J_k - J_j)^T``, ``P`` the hypothesis' prior covariance) and is above the threshold; the least
such charge over the hypothesis' height and +- its existence margin (``2 sigma_z``, what
must have been detected wherever the node may be). Numpy, three path evaluations and
predictions more per update: several times the tracker's CPU. It wraps :func:`diffpos.tracking.model.snr_cost_near` and runs
``diffpos replay FILE --workers 1 ...`` in this process.
"""

from __future__ import annotations

import sys

import numpy as np
from scipy.special import log_ndtr, ndtr

import diffpos.tracking.model as tm
from diffpos.channel.emulator import pair_snr_db
from diffpos.tracking.links import _IS_DIFF
from diffpos.tracking.model import SNR_SIGMA_DB

_orig = tm.snr_cost_near


def _detectable(pos, links, building, pe):
    """Predicted SNR of every slot (N, H, M, K), the detector's threshold at the hypothesis
    (N, H, M) and which slots are existing diffraction paths with a prediction."""
    n, h, m, k = pe.length.shape
    anc = np.broadcast_to(links.anchors, (n, h, m, 3)).reshape(n * h, m, 3)
    pred = pair_snr_db(np.ascontiguousarray(anc), pos.reshape(n * h, 3),
                       building=building, radio=links.radio).reshape(n, h, m, k)
    r = links.radio
    top = np.max(np.where(pe.sure, pred, -np.inf), axis=-1)
    thr = np.maximum(top - r.fap_threshold_db, r.detection_snr_db)
    return pred, thr, _IS_DIFF & pe.strict & np.isfinite(pred)


def _with_skip_term(tol_m: float):
    def cost(pos, links, floor, building, relax_m, pe=None, cache=None, reuse_m=(0.0, 0.0)):
        c = _orig(pos, links, floor, building, relax_m, pe, cache, reuse_m)
        if c is None:
            return c
        if pe is None:
            pe = tm.all_paths(pos, links, floor, building, relax_m)
        n, h, m = c.shape[:3]
        pred, thr, det = _detectable(pos, links, building, pe)
        with np.errstate(invalid="ignore"):
            lc = np.where(det, -log_ndtr((thr[..., None] - pred) / SNR_SIGMA_DB), 0.0)
        ln = pe.length
        earlier = det[..., None, :] & (ln[..., None, :] < ln[..., :, None] - tol_m)  # [k, j]
        pen = np.sum(np.where(earlier, lc[..., None, :], 0.0), axis=-1)
        known = np.isfinite(np.broadcast_to(links.snr, (n, h, m)))[..., None]
        return np.where(known & np.isfinite(c), c + pen, c)
    return cost


_prior_cov = {}


def _stash_prior(orig):
    def update(x_prior, p_prior, *a, **k):
        _prior_cov["p"] = p_prior[..., :3, :3]
        return orig(x_prior, p_prior, *a, **k)
    return update


def _soft_pen(pos, links, floor, building, relax_m, pe, cov):
    """(N, H, M, K) penalty of every slot k: ``-sum_j log(1 - Phi((L_k - L_j) / s_kj)
    Phi((pred_j - thr) / SNR_SIGMA_DB))`` over the existing diffraction slots j != k,
    ``s_kj^2 = (J_k - J_j) P (J_k - J_j)^T`` with the hypothesis' prior covariance P."""
    k = pe.length.shape[-1]
    pred, thr, det = _detectable(pos, links, building, pe)
    d = pe.jac[..., :, None, :] - pe.jac[..., None, :, :]  # [k, j]
    s2 = np.einsum("nhmkji,nhil,nhmkjl->nhmkj", d, cov, d)
    s = np.sqrt(np.maximum(s2, 1e-6))
    dl = pe.length[..., :, None] - pe.length[..., None, :]
    with np.errstate(invalid="ignore"):
        pdet = ndtr(dl / s) * ndtr((pred - thr[..., None]) / SNR_SIGMA_DB)[..., None, :]
        lc = -np.log1p(-np.minimum(np.where(det[..., None, :], pdet, 0.0), 1 - 1e-12))
    lc = np.where(np.eye(k, dtype=bool), 0.0, np.nan_to_num(lc))
    return lc.sum(axis=-1)


def _with_soft_term():
    def cost(pos, links, floor, building, relax_m, pe=None, cache=None, reuse_m=(0.0, 0.0)):
        c = _orig(pos, links, floor, building, relax_m, pe, cache, reuse_m)
        if c is None:
            return c
        n, h = pos.shape[:2]
        cov = np.broadcast_to(_prior_cov["p"], (n, h, 3, 3))
        dz = tm._relax(relax_m, (n, h))
        zf = building.floor_z_m(np.broadcast_to(np.asarray(floor), (n, h)))
        pen = None
        for sgn in (0.0, -1.0, 1.0):  # the least over the height uncertainty
            p = pos.copy()
            p[..., 2] = np.clip(pos[..., 2] + sgn * dz, zf + 0.01,
                                zf + building.floor_height_m - 0.01)
            pe_s = tm.all_paths(p, links, floor, building, relax_m)
            v = _soft_pen(p, links, floor, building, relax_m, pe_s, cov)
            pen = v if pen is None else np.minimum(pen, v)
        known = np.isfinite(np.broadcast_to(links.snr, (n, h, pen.shape[2])))[..., None]
        return np.where(known & np.isfinite(c), c + pen, c)
    return cost


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__)
        return 2
    if argv[0] == "soft":
        tm.snr_cost_near = _with_soft_term()
        import diffpos.tracking.tracker as td

        tm.measurement_update = _stash_prior(tm.measurement_update)
        td.measurement_update = tm.measurement_update
    elif argv[0] != "off":
        tm.snr_cost_near = _with_skip_term(float(argv[0]))
    from diffpos_services.cli.main import main as cli

    return cli(["replay", argv[1], "--no-files", "--no-progress", "--workers", "1", *argv[2:]])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
