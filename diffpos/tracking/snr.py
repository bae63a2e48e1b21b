"""SNR term of the tracker's measurement model: the SNR negative log-likelihood of every slot
at position hypotheses (:func:`snr_cost`), and near a window-band edge at the nearest height
within the hypothesis' existence margin where the slot carries power (:func:`snr_cost_near`).

Moved verbatim from :mod:`diffpos.tracking.model` (which re-exports every public name here);
the predicted SNRs are those of the emulator's amplitude model
(:func:`diffpos.channel.emulator.pair_snr_db`, compiled in :mod:`diffpos.channel.snr_nb`).

At a hypothesis only the slots that can carry power are predicted (:data:`ALWAYS_PREDICTED`
and the ``loose`` window-band slots; the others cost +inf as their prediction would: bit for
bit), and the tracker keeps every hypothesis' direct and diffraction predictions (~85 % of a
link's cost) from one real update to the next (:class:`SnrCache`, the state's ``snr_*``
fields): they are reused while the hypothesis' prior stays within
``TrackerConfig.snr_reuse_m`` of where they were made and a link's anchor within
``snr_reuse_anchor_m`` (:func:`_snr_cost_cached`). The measured SNR, the window-band slots,
the detector's threshold and the relax holes are scored afresh every update. Why a margin:
the predictions are made at the prior and serve the fit, which moves further (the prior's own
uncertainty), and an anchor's reported position is uncertain by its navigation error (a few
cm); a static responder's prior moves by cm per epoch, so with exact points nothing would be
reused. Measured on replays (all epochs solved): the 30 s 16 x 200 soak (static responders,
static UAVs) reuses 49 % of its links' predictions, the 20 s ``large`` run (walkers) 6.5 %;
half of the soak's updated hypotheses' priors move more than 5 cm between their real updates
(the unlikely floors and the refreshed dormant ones most), a quarter more than 0.26 m.
Margins 0 given to :func:`_snr_cost_cached`: a prediction is reused only at the same point
and anchor, compared with the float32 cached anchor (so only where float32 holds the anchor's
coordinates exactly, e.g. whole metres without navigation noise; the reused values are then
rounded, < 1e-5 dB). A ``TrackerConfig`` with both margins 0 does not use the cache at all
(``tracking_model.measurement_update``): the large and soak replays' estimates are those of the
exact predictions, bit for bit. The defaults are 0.05 / 0.1 m (on; their measured accuracy
cost: ``TrackerConfig``). The float32 anchors are compared in the building's frame: their
rounding (< 1e-4 m below 1 km from the origin) is negligible against the anchor margin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from diffpos.channel.emulator import pair_snr_db
from diffpos.channel.snr_nb import snr_cost_kernel
from diffpos.tracking.links import _IS_BAND, K_SLOTS, Links, PathEval, _c, _cb, _relax, all_paths
from diffpos.tracking.snr_nb import cache_plan_kernel, cache_store_kernel
from diffpos.tracking.state import SNR_CACHE_SLOTS

__all__ = ["HOLE_THRESHOLD_AT_PRIOR", "SNR_SIGMA_DB", "SNR_SPAN_DB", "SnrCache", "snr_cost",
           "snr_cost_near", "snr_reuse_on"]

FloatArray = NDArray[np.float64]
#: Standard deviation of a slot's predicted SNR against the measured one [dB]: a factor 2 in
#: field (antenna patterns, materials, wedge vs. UTD), the value M-NLS uses.
SNR_SIGMA_DB = 20 * np.log10(2.0)
#: Width of the SNR density of a range that is none of the modelled mechanisms [dB].
SNR_SPAN_DB = 60.0
#: :func:`snr_cost_near`: a slot scored at a shifted height (a "hole": it exists within the
#: existence margin but carries no power at the hypothesis) is compared with the detector's
#: threshold of the hypothesis itself (True) or of the shifted point (False; needs the ~7
#: diffraction slots predicted again there, ~80 % of a full prediction). The shift stands for
#: the hypothesis' own height uncertainty; the threshold is that of its strongest sure path,
#: which changes little over it. Measured (``benchmarks/bench_accuracy.py --only default large
#: tall-floors anchors-beyond-ends``, two runs each, 2026-11-27): floor, 3D p90 and cov95
#: within the run-to-run spread of the shifted point's threshold (default and tall-floors
#: identical; large floor 99.72-99.78 -> 99.73-99.91 %, p90 0.299-0.313 -> 0.300 m, cov95
#: 91.20-91.29 -> 91.28-91.30 %; anchors-beyond-ends floor 98.52-98.61 -> 98.43-98.61 %,
#: p90 0.222-0.224 -> 0.224 m, cov95 94.63-95.00 -> 94.63-94.91 %). Replays (all epochs
#: solved) against the shifted point's threshold: a 20 s lockstep ``large`` recording the same
#: floor in 10,000 of 10,000 estimates, positions within 4e-5 m; a 30 s 16 x 200 soak the same
#: floor in 59,921 of 60,000 (no truth recorded there). The SNR part's CPU:
#: 1.34-1.44x less with the exact threshold, 1.65-1.72x with this one
#: (``benchmarks/bench_snr_cost.py``).
HOLE_THRESHOLD_AT_PRIOR = True
#: The slots :func:`snr_cost_near` predicts at a hypothesis whatever their existence there:
#: the diffraction slots (their existence is the emulator's, with no margin: a disagreement
#: would be a rounding one at an edge end) and the direct slot (the emulator keeps the
#: through-wall ray, which the path model does not: it carries power where slot 0 is not
#: loose). A window-band slot (1-6, 14-17) that is not ``loose`` has no power there: its
#: entry point is outside the band widened by ``relax_m`` (>= 0, the emulator needs it
#: strictly inside the band) or its path fails the same geometric test as the emulator's.
ALWAYS_PREDICTED = ~_IS_BAND | (np.arange(K_SLOTS) == 0)
_CACHED = np.array(SNR_CACHE_SLOTS, dtype=np.int64)  # the slots an SnrCache keeps: direct, then diffraction
_IS_CACHED = np.isin(np.arange(K_SLOTS), _CACHED)


@dataclass
class SnrCache:
    """Predicted SNRs of hypotheses kept from one update to the next (the tracker's state
    fields ``snr_node``, ``snr_anchor``, ``snr_pred``; :func:`snr_cost_near` reads and
    updates the arrays in place).

    ``node`` (N, H, 3) [m]: where the predictions were made (NaN: none); ``anchor``
    (N, H, C, 3) float32 [m]: the anchor of every cached link (the first C link columns; NaN:
    none); ``pred`` (N, H, C, len(SNR_CACHE_SLOTS)) float32 [dB]: the predicted SNR of the
    slots :data:`~diffpos.tracking.state.SNR_CACHE_SLOTS` at ``node`` (-inf: no power)."""

    node: FloatArray
    anchor: FloatArray
    pred: FloatArray


def snr_reuse_on(config) -> bool:
    """Whether the tracker reuses cached SNR predictions (``TrackerConfig.snr_reuse_m`` /
    ``snr_reuse_anchor_m``, both 0: off, the cache is neither read nor carried along)."""
    return max(config.snr_reuse_m, config.snr_reuse_anchor_m) > 0


def snr_cost(pos: FloatArray, links: Links, building, trust: NDArray | None = None
             ) -> FloatArray | None:
    """SNR negative log-likelihood of every slot at the hypotheses ``pos`` (N, H, 3):
    (N, H, M, K), +inf where the slot carries no power, 0 where the SNR is unknown; None
    without SNR.

    The measured SNR against the slot's SNR predicted by the emulator's amplitude model
    (:func:`diffpos.channel.emulator.pair_snr_db`), Gaussian with :data:`SNR_SIGMA_DB`, plus the
    detector's rule: a first arrival is not far below the predicted strongest path's
    threshold ``P_max - fap_threshold_db`` (as in M-NLS). This is what separates floors that
    the ranges alone cannot: a ceiling reflection and the floor above's lower-edge
    diffraction have nearly the same length but 20-40 dB different strength.

    A link whose SNR is unknown costs 0 in every slot whatever the prediction, so its slots
    are not predicted at all.
    """
    out = _snr_cost_thr(pos, links, building, trust)
    return None if out is None else out[0]


def _snr_cost_thr(pos: FloatArray, links: Links, building, trust: NDArray | None = None,
                  need: NDArray | None = None) -> tuple[FloatArray, FloatArray] | None:
    """:func:`snr_cost` and the detector's threshold of every link (N, H, M) [dB] (NaN where
    the SNR is unknown). ``need`` (bool, broadcastable to (N, H, M, K)): predict only these
    slots (``channel_snr_masked_kernel``: the needed ones bit for bit), every other slot
    counted as without power (+inf cost); it must hold every ``trust`` slot."""
    if links.snr is None:
        return None
    n, h = pos.shape[:2]
    m = links.rho.shape[-1]
    if n * h == 0:
        return np.zeros((n, h, m, K_SLOTS)), np.full((n, h, m), np.nan)
    known = np.broadcast_to(np.isfinite(links.snr), (n, h, m))
    if known.all():  # every link: no gather
        anc = np.broadcast_to(links.anchors, (n, h, m, 3)).reshape(-1, 3)
        p = np.broadcast_to(pos[:, :, None, :], (n, h, m, 3)).reshape(-1, 3)
        meas = np.broadcast_to(links.snr, (n, h, m)).reshape(-1)
        tr = None if trust is None else \
            np.broadcast_to(trust, (n, h, m, K_SLOTS)).reshape(-1, K_SLOTS)
        nd = None if need is None else \
            np.broadcast_to(need, (n, h, m, K_SLOTS)).reshape(-1, K_SLOTS)
        pred = _predict(anc, p, building, links.radio, nd)
        c, t = _snr_cost_of(pred, meas, links.radio, tr)
        return c.reshape(n, h, m, K_SLOTS), t.reshape(n, h, m)
    out = np.zeros((n, h, m, K_SLOTS))
    thr = np.full((n, h, m), np.nan)
    n_i, h_i, m_i = np.nonzero(known)
    if n_i.size == 0:
        return out, thr
    anc = np.broadcast_to(links.anchors, (n, h, m, 3))[n_i, h_i, m_i]
    meas = np.broadcast_to(links.snr, (n, h, m))[n_i, h_i, m_i]
    tr = None if trust is None else np.broadcast_to(trust, (n, h, m, K_SLOTS))[n_i, h_i, m_i]
    nd = None if need is None else np.broadcast_to(need, (n, h, m, K_SLOTS))[n_i, h_i, m_i]
    pred = _predict(anc, pos[n_i, h_i], building, links.radio, nd)
    out[n_i, h_i, m_i], thr[n_i, h_i, m_i] = _snr_cost_of(pred, meas, links.radio, tr)
    return out, thr


def _predict(anc: FloatArray, pos: FloatArray, building, radio, need: NDArray | None
             ) -> FloatArray:
    """Predicted SNR of every slot of P (anchor, node) pairs (P, K) [dB]; with ``need`` (P, K)
    only those slots (bit for bit), -inf elsewhere (counted as without power)."""
    if need is None:
        return pair_snr_db(anc[:, None, :], pos, building=building, radio=radio)[:, 0]
    pred = pair_snr_db(anc[:, None, :], pos, building=building, radio=radio,
                       need=need[:, None, :])[:, 0]
    return np.where(need, pred, -np.inf)


def _snr_cost_of(pred: FloatArray, meas: FloatArray, radio, trust: NDArray | None = None,
                 thr: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
    """:func:`_pair_snr_cost` of the predicted SNRs ``pred`` (P, K) [dB] and the measured
    ``meas`` (P,) [dB], and the detector's threshold (P,) [dB] (NaN where ``meas`` is not
    finite), or with ``thr`` given that threshold (``trust`` unused): one compiled pass
    (:func:`diffpos.channel.snr_nb.snr_cost_kernel`), bit-identical to
    :func:`_snr_cost_of_numpy`."""
    out = np.empty(pred.shape)
    tr = np.ones(pred.shape, dtype=np.bool_) if trust is None or thr is not None else trust
    th = np.empty(pred.shape[0]) if thr is None else thr
    snr_cost_kernel(_c(pred, dtype=np.float64), _c(meas, dtype=np.float64),
                    _c(tr, dtype=np.bool_), float(SNR_SIGMA_DB),
                    float(radio.fap_threshold_db), float(radio.detection_snr_db),
                    thr is not None, _c(th, dtype=np.float64), out)
    return out, th


def _snr_cost_of_numpy(pred: FloatArray, meas: FloatArray, radio,
                       trust: NDArray | None = None, thr: FloatArray | None = None
                       ) -> tuple[FloatArray, FloatArray]:
    """The numpy reference of :func:`_snr_cost_of`."""
    meas = meas[:, None]
    strong = pred if trust is None else np.where(trust, pred, -np.inf)
    with np.errstate(invalid="ignore"):
        c = 0.5 * ((meas - pred) / SNR_SIGMA_DB) ** 2
        if thr is None:
            thr = np.maximum(np.max(strong, axis=-1) - radio.fap_threshold_db,
                             radio.detection_snr_db)
            thr = np.where(np.isfinite(meas[:, 0]), thr, np.nan)
        short = np.maximum(thr[:, None] - SNR_SIGMA_DB - meas, 0.0)
        c = c + 0.5 * (short / SNR_SIGMA_DB) ** 2
    c = np.where(np.isfinite(pred), c, np.inf)
    return np.where(np.isfinite(meas), c, 0.0), thr


def _pair_snr_cost(anc: FloatArray, pos: FloatArray, meas: FloatArray, building, radio,
                   trust: NDArray | None = None) -> FloatArray:
    """:func:`snr_cost` of P (anchor, node) pairs: (P, K); ``trust`` (P, K): the slots whose
    power sets the detector's threshold (default all)."""
    pred = pair_snr_db(anc[:, None, :], pos, building=building, radio=radio)[:, 0]
    return _snr_cost_of(pred, meas, radio, trust)[0]


def _snr_cost_cached(pos: FloatArray, links: Links, building, trust: NDArray, need: NDArray,
                     strict: NDArray, cache: SnrCache, reuse_m: tuple[float, float]
                     ) -> tuple[FloatArray, FloatArray]:
    """:func:`_snr_cost_thr` (with ``need``) with the predictions of ``cache`` reused.

    A hypothesis whose point ``pos`` is within ``reuse_m[0]`` of ``cache.node`` has every
    link predicted at ``cache.node``: a cached link whose anchor is within ``reuse_m[1]`` of
    its cached one keeps its cached slots (:data:`~diffpos.tracking.state.SNR_CACHE_SLOTS`:
    the direct and diffraction slots, ~85 % of a link's prediction; its window-band slots are
    predicted there again), the others are predicted there and cached. A hypothesis further
    away, or with a cached link whose diffraction slots' existence (exact, no margin) differs
    from the one at ``pos`` (``strict``), is predicted afresh at ``pos`` and its cache
    restarted there. Reused or not, every row's cost and threshold are :func:`_snr_cost_of`'s
    of its predictions. The cache holds float32 (a reused SNR is rounded by < 1e-5 dB)."""
    n, h = pos.shape[:2]
    m = links.rho.shape[-1]
    mc = min(m, cache.pred.shape[2])
    known = np.broadcast_to(np.isfinite(links.snr), (n, h, m))
    anc = np.broadcast_to(links.anchors, (n, h, m, 3))
    with np.errstate(invalid="ignore"):  # NaN (nothing cached): no reuse
        near = np.sqrt(np.sum((pos - cache.node) ** 2, axis=-1)) <= reuse_m[0]
        kept = np.sqrt(np.sum((anc[:, :, :mc] - cache.anchor[:, :, :mc]) ** 2,
                              axis=-1)) <= reuse_m[1]
    # a cached link whose diffraction slots' existence flipped restarts its hypothesis; the
    # reused links (hit) and the slots to predict (a reused link: its other slots only):
    # compiled (diffpos.tracking.snr_nb), the numpy operations' values
    near = _c(near, dtype=np.bool_)
    known_nm = _c(np.isfinite(links.snr[:, 0]))
    hit = np.empty((n, h, m), dtype=np.bool_)
    mask = np.empty((n, h, m, K_SLOTS), dtype=np.bool_)
    cache_plan_kernel(near, _cb(kept, (n, h, mc)), known_nm, cache.pred,
                      _c(strict, dtype=np.bool_), _cb(need, mask.shape),
                      _CACHED, _IS_CACHED, hit, mask)
    at = np.where(near[..., None], cache.node, pos)
    if known.all():  # every link: no gather
        n_i = None
        pred = _predict(anc.reshape(-1, 3),
                        np.broadcast_to(at[:, :, None, :], (n, h, m, 3)).reshape(-1, 3),
                        building, links.radio, mask.reshape(-1, K_SLOTS)).reshape(n, h, m, -1)
    else:
        pred = np.full((n, h, m, K_SLOTS), -np.inf)
        n_i, h_i, m_i = np.nonzero(known)
        if n_i.size:
            pred[n_i, h_i, m_i] = _predict(anc[n_i, h_i, m_i], at[n_i, h_i], building,
                                           links.radio, mask[n_i, h_i, m_i])
    # the reused links' cached slots; then the cache: a hypothesis that moved starts afresh
    # at ``pos``, the fresh links' predictions stored (in place; float32)
    cache_store_kernel(near, hit, known_nm, _cb(need, mask.shape), _CACHED,
                       _c(links.anchors[:, 0], dtype=np.float64), pred, cache.anchor,
                       cache.pred)
    cache.node[...] = at
    if known.all():  # every link (row by row the same values as the gather below)
        c, thr = _snr_cost_of(pred.reshape(-1, K_SLOTS),
                              np.broadcast_to(links.snr, (n, h, m)).reshape(-1), links.radio,
                              np.broadcast_to(trust, pred.shape).reshape(-1, K_SLOTS))
        c, thr = c.reshape(pred.shape), thr.reshape(n, h, m)
    else:
        c, thr = np.zeros((n, h, m, K_SLOTS)), np.full((n, h, m), np.nan)
        if n_i is not None and n_i.size:
            meas = np.broadcast_to(links.snr, (n, h, m))[n_i, h_i, m_i]
            c[n_i, h_i, m_i], thr[n_i, h_i, m_i] = _snr_cost_of(
                pred[n_i, h_i, m_i], meas, links.radio, trust[n_i, h_i, m_i])
    return c, thr


def _hole_snr_cost(anc: FloatArray, pos: FloatArray, meas: FloatArray, building, radio,
                   hole: NDArray, trust: NDArray, thr: FloatArray | None = None
                   ) -> FloatArray:
    """The costs of the ``hole`` slots (P, K) of P pairs with a known SNR ``meas`` at the
    points ``pos``; the other slots' costs are not computed (+inf or any value: not to be
    used).

    ``thr`` (P,) [dB]: the detector's threshold to use (the prior point's, model of
    :func:`snr_cost_near`): only the hole slots are predicted. ``thr`` None: the threshold of
    the points themselves, :func:`_pair_snr_cost`'s values bit for bit: a hole slot's cost
    then needs the predictions of the ``trust`` slots where the hole slot's is finite; the
    hole slots are predicted first (mostly specular slots near a window-band edge: cheap),
    the trusted ones (the ~7 diffraction slots, ~80 % of a pair's cost) only for the pairs
    where a hole slot carries power; elsewhere every hole slot costs +inf whatever the
    threshold."""
    pred = pair_snr_db(anc[:, None, :], pos, building=building, radio=radio,
                       need=hole[:, None, :])[:, 0]
    if thr is not None:
        return _snr_cost_of(np.where(hole, pred, -np.inf), meas, radio, thr=thr)[0]
    rows = np.flatnonzero(np.any(hole & np.isfinite(pred), axis=-1))
    more = trust[rows] & ~hole[rows]
    if rows.size:
        pred_t = pair_snr_db(anc[rows, None, :], pos[rows], building=building, radio=radio,
                             need=more[:, None, :])[:, 0]
        pred[rows] = np.where(more, pred_t, pred[rows])
    # the threshold from the trusted slots that were predicted (all of them on ``rows``)
    done = hole.copy()
    done[rows] |= more
    return _snr_cost_of(np.where(done, pred, -np.inf), meas, radio, trust & done)[0]


def snr_cost_near(pos: FloatArray, links: Links, floor, building, relax_m,
                  pe: PathEval | None = None, cache: SnrCache | None = None,
                  reuse_m: tuple[float, float] = (0.0, 0.0)) -> FloatArray | None:
    """:func:`snr_cost` where a slot that exists within ``relax_m`` of the hypothesis (its
    window entry point within the entry's uncertainty of the band; a scalar or one margin per
    hypothesis, broadcastable to (N, H)) but carries no power at the point itself is scored
    at the nearest height (``pos`` +- ``relax_m`` in z) where it does: the best-matching prediction over the position's uncertainty. At the point alone a
    node at the nominal height just below a band edge lost 1.4 nats per such link and epoch
    (the slot's SNR counted as unknown) whenever its prior was a few cm too high, which
    accumulated into a wrong floor lock (default run, top-floor walker).

    At the shifted heights only the hole slots are predicted (:func:`_hole_snr_cost`); with
    :data:`HOLE_THRESHOLD_AT_PRIOR` their detector threshold is the hypothesis' own (at
    ``pos``), else the shifted point's (the trusted slots predicted there too where a hole
    slot carries power: the values of predicting all 18 slots, bit for bit).

    ``cache`` (:class:`SnrCache` of the hypotheses, updated in place): the predictions at the
    hypotheses reused within ``reuse_m`` = (node, anchor) margins [m]
    (:func:`_snr_cost_cached`); the shifted heights are always predicted."""
    if links.snr is None:
        return None
    if pe is None:  # the paths at ``pos`` with ``relax_m`` (a caller may pass them)
        pe = all_paths(pos, links, floor, building, relax_m)
    # the detector's threshold is set by the strongest path that surely exists (a path that
    # exists only on one side of a band edge a few cm away is no evidence of a strong path)
    # a window-band slot that is not even loose has no power at ``pos`` (not predicted,
    # :data:`ALWAYS_PREDICTED`): its cost is +inf as predicted, bit for bit
    need = pe.loose | ALWAYS_PREDICTED
    if cache is None:
        c, thr = _snr_cost_thr(pos, links, building, trust=pe.sure, need=need)
    else:
        c, thr = _snr_cost_cached(pos, links, building, pe.sure, need, pe.strict, cache,
                                  reuse_m)
    hole = ~np.isfinite(c) & pe.loose
    pairs = np.argwhere(np.any(hole, axis=-1))  # (P, 3): n, h, m
    if pairs.size == 0:
        return c
    n_i, h_i, m_i = pairs.T
    dz = _relax(relax_m, c.shape[:2])[n_i, h_i]
    anc = np.broadcast_to(links.anchors, (*c.shape[:3], 3))[n_i, h_i, m_i]
    meas = np.broadcast_to(links.snr, c.shape[:3])[n_i, h_i, m_i]
    fl = np.broadcast_to(np.asarray(floor), pos.shape[:2])[n_i, h_i]
    zf = building.floor_z_m(fl)
    hole_p = hole[n_i, h_i, m_i]
    thr_p = thr[n_i, h_i, m_i] if HOLE_THRESHOLD_AT_PRIOR else None
    # both shifted heights in one call (every row is scored on its own: the same values as
    # one call per height), then the better of the two per slot
    p = np.concatenate([pos[n_i, h_i]] * 2)
    shift = np.concatenate([-dz, dz])
    p[:, 2] = np.clip(p[:, 2] + shift, np.concatenate([zf] * 2) + 0.01,
                      np.concatenate([zf] * 2) + building.floor_height_m - 0.01)
    two = _hole_snr_cost(np.concatenate([anc] * 2), p, np.concatenate([meas] * 2), building,
                         links.radio, np.concatenate([hole_p] * 2),
                         np.concatenate([pe.sure[n_i, h_i, m_i]] * 2),
                         None if thr_p is None else np.concatenate([thr_p] * 2))
    best = np.minimum(two[:len(pairs)], two[len(pairs):])
    sub = c[n_i, h_i, m_i]
    c[n_i, h_i, m_i] = np.where(hole_p, best, sub)
    return c
