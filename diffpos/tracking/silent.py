"""Negative information of silent anchors (``TrackerConfig.silent_anchor_nats``, off by default).

An anchor that reported for a node's epoch but detected no path (the wire's null range, see
:class:`diffpos_services.wire.messages.RangeMeasurement`) says where the node is probably
not: where the emulator's amplitude model (:func:`diffpos.channel.emulator.pair_snr_db`)
predicts a path far above the detector's threshold. The fusion passes such an anchor to
:func:`diffpos.tracking.tracker.update` as a masked link with its position and ``snr_db``
-inf (:func:`silent_links`); :func:`silent_cost` is the likelihood of the silence under each
hypothesis and :func:`silent_update` multiplies it into the hypotheses' probabilities.

The likelihood of silence at a hypothesis whose strongest predicted path has SNR ``S`` [dB]:
``e + (1 - e) Phi((T + margin - S) / SNR_SIGMA_DB)``, ``T`` the detector's threshold
(``Radio.detection_snr_db``), ``margin`` = ``silent_anchor_margin_db`` (the model may
overestimate the power by that much on a channel we did not write without any cost) and
``e = exp(-silent_anchor_nats)`` (a model that predicts a path tens of dB too strong costs at
most ``silent_anchor_nats`` per anchor and epoch, as the skipped paths' mixture of
:func:`diffpos.channel.detection.skipped_cost`). A hypothesis at which no slot carries power
(``S`` = -inf) costs nothing.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from diffpos.channel.detection import normal_cdf
from diffpos.channel.emulator import pair_snr_db
from diffpos.tracking.state import clamp_to_floor, few_ranges, hypothesis_floor

__all__ = ["sigma_points", "silent_cost", "silent_links", "silent_update"]

FloatArray = NDArray[np.float64]


def silent_links(anchors_m: FloatArray, mask: NDArray[np.bool_], snr_db, config
                 ) -> NDArray[np.bool_] | None:
    """The silent links (N, M) of one epoch's inputs: masked, ``snr_db`` -inf and a finite
    anchor position; None when the setting is off, without SNRs or without a silent link
    (nothing to do)."""
    if config.silent_anchor_nats <= 0 or snr_db is None:
        return None
    snr = np.asarray(snr_db, dtype=np.float64)
    out = (~np.asarray(mask, bool) & np.isneginf(snr)
           & np.all(np.isfinite(np.asarray(anchors_m, dtype=np.float64)), axis=-1))
    return out if out.any() else None


def sigma_points(pos: FloatArray, cov: FloatArray, floor: NDArray[np.int_], building
                 ) -> FloatArray:
    """The six points ``pos +- sqrt(3) sqrt(w_i) v_i`` (N, H, 6, 3) [m] of every hypothesis'
    position ``pos`` (N, H, 3) and covariance ``cov`` (N, H, 3, 3) [m^2] (``w_i``, ``v_i``
    its eigenvalues, clipped at 0, and eigenvectors: the unscented transform's points with
    equal weights 1/6, which average a function's first two moments exactly for a Gaussian
    up to third order), each kept inside its hypothesis' floor box ``floor`` (H,)
    (:func:`diffpos.tracking.state.clamp_to_floor`, 5 cm from the walls)."""
    w, v = np.linalg.eigh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    d = np.sqrt(3.0 * np.maximum(w, 0.0))[..., None, :] * v  # (N, H, 3, 3): columns
    steps = np.concatenate([np.swapaxes(d, -1, -2), -np.swapaxes(d, -1, -2)], axis=-2)
    pts = pos[..., None, :] + steps  # (N, H, 6, 3)
    return clamp_to_floor(pts, np.asarray(floor)[None, :, None], building, 0.05)


def silent_cost(pos: FloatArray, anchors_m: FloatArray, silent: NDArray[np.bool_], building,
                radio, config, sigma_db: float) -> FloatArray:
    """Negative log-likelihood [nats] (N, H) of the silent links ``silent`` (N, M) (anchors
    ``anchors_m`` (N, M, 3) [m]) at the hypotheses' positions ``pos`` (N, H, 3) [m], or
    averaged over each hypothesis' points ``pos`` (N, H, P, 3) (:func:`sigma_points`: the
    probability of the silence averaged, then its log), summed over the node's silent links
    (module docstring); 0 where a position is not finite. ``sigma_db``: the SNR term's spread
    (:data:`diffpos.tracking.model.SNR_SIGMA_DB`)."""
    pts = pos if pos.ndim == 4 else pos[:, :, None, :]
    n, h, k = pts.shape[:3]
    out = np.zeros((n, h))
    ni, mi = np.nonzero(silent)
    if ni.size == 0:
        return out
    p = pts[ni].reshape(-1, 3)  # (S * H * P, 3): silent link s, hypothesis j, point q
    a = np.repeat(anchors_m[ni, mi], h * k, axis=0)[:, None, :]
    ok = np.all(np.isfinite(p), axis=-1)
    s = np.full(p.shape[0], -np.inf)
    if ok.any():
        pred = pair_snr_db(a[ok], p[ok], building=building, radio=radio)[:, 0]
        s[ok] = np.max(pred, axis=-1)
    e = float(np.exp(-config.silent_anchor_nats))
    with np.errstate(invalid="ignore"):
        z = (float(radio.detection_snr_db) + float(config.silent_anchor_margin_db) - s) \
            / sigma_db
    miss = np.where(np.isfinite(s), normal_cdf(z), 1.0).reshape(ni.size, h, k).mean(axis=-1)
    np.add.at(out, ni, -np.log(e + (1.0 - e) * miss))
    return out


def silent_update(lp: FloatArray, mean: FloatArray, anchors_m, mask, snr_db, n_meas,
                  live: NDArray[np.bool_], building, radio, config, sigma_db: float,
                  cov: FloatArray | None = None) -> FloatArray:
    """The hypotheses' log-probabilities ``lp`` (N, H) after the silent links of one epoch
    (``anchors_m`` (N, M, 3), ``mask``, ``snr_db`` (N, M): :func:`silent_links`) at the
    hypotheses' means ``mean`` (N, H, 6) (with ``silent_anchor_spread`` averaged over the
    :func:`sigma_points` of their position covariances ``cov`` (N, H, 6, 6)), for the
    ``live`` nodes (N,) with at most ``silent_anchor_max_links`` ranges ``n_meas`` (N,) (0:
    any); ``lp`` itself when the setting is off or nothing is silent, else a new array (each
    changed row normalised)."""
    silent = silent_links(anchors_m, mask, snr_db, config) if radio is not None else None
    if silent is None:
        return lp
    rows = live & silent.any(axis=1) & few_ranges(n_meas, config.silent_anchor_max_links)
    idx = np.flatnonzero(rows)
    if idx.size == 0:
        return lp
    pos = mean[idx, :, :3]
    if config.silent_anchor_spread and cov is not None:
        pos = sigma_points(pos, cov[idx, :, :3, :3], hypothesis_floor(lp.shape[1] // 2),
                           building)
    cost = silent_cost(pos, np.asarray(anchors_m, dtype=np.float64)[idx], silent[idx],
                       building, radio, config, sigma_db)
    out = lp.copy()
    x = lp[idx] - cost
    x = np.maximum(x - x.max(axis=1, keepdims=True), -700.0)
    out[idx] = x - np.log(np.exp(x).sum(axis=1, keepdims=True))
    return out
