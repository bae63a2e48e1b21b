"""Measurement model of the tracker: mechanism selection, iterated EKF update, snapshot init.

Arrays are over N nodes, H hypotheses per node (the floors, or floors x starts at
initialisation) and M anchors; ``floor`` gives every hypothesis' floor index. See
:mod:`diffpos.tracking.tracker` for the design; everything here is deterministic. The links and the
path evaluation are in :mod:`diffpos.tracking.links`, the initialisation's grid search in
:mod:`diffpos.tracking.initialisation`; the SNR term is here (section "SNR term" below). The hot loops
(every slot's paths, the IEKF's link model, the selection's candidates and variances, the
initialisation's grid search) run in the compiled kernels of
:mod:`diffpos.tracking.model_nb`, each bit-identical to the numpy reference kept next to
it (``_all_paths_numpy``, ``_model_numpy``, ``_select_numpy``, ``_grid_starts_numpy``;
tests/core/test_tracking_kernel.py); the selection's log/exp stay numpy's (on the packed
candidates between its kernels: numba's libm exp/log and numpy's SIMD ones differ in the last
bit). The IEKF runs its whole Gauss-Newton loop and evidence in one kernel per hypothesis
(``iekf_kernel``): its 6 x 6 solve/inverse/log-determinant is LU with partial pivoting, not
LAPACK's operation order, so it is held to its numpy reference (``_iekf_numpy``) within a
tolerance (1e-9 m, 1e-8 nats), not bit for bit; live and replay run the same code.

Existence near a window-band edge is graded with every hypothesis' own margin
(:func:`existence_margin`: ``max(exist_margin_m, 2 sigma_z)`` of the covariance at the point
where the mechanisms are selected: the prior, then the fit). With one fixed margin (0.2 m) a
vertical-mode track whose height was 0.3-0.6 m off (its own sigma_z 0.3-0.4 m) at the foot of
a flight called two of four links impossible (a double bounce whose entry point the truth has
inside the band), scored them as outliers, and a mirror floor that explained all four won
(default scenario, r05's descent from the top floor: right floor 58 % of its node-epochs;
100 % with its own margin, seed 0).
Measured (``benchmarks/bench_tracking.py``, seeds 0-2, fixed -> own margin): right floor
default 93.2 -> 97.1 %, other-building 87.9 -> 90.2 %, uavs-above-windows 100 -> 100 %,
anchors-beyond-ends 89.3 -> 89.1 %; 95 % coverage 85.6 -> 87.1, 82.3 -> 83.6, 98.4 -> 97.4,
87.8 -> 88.0 %. The snapshot initialisation keeps the fixed margin for its first selection
(its prior is the grid search's box, a quarter floor height in z, not a tracked point's
uncertainty; measured with the wide margin there: 'uavs-above-windows' locked a node onto a
wrong mechanism set for 7 s, coverage 98.4 -> 93.0 %).

SNR term
--------
SNR term of the tracker's measurement model: the SNR negative log-likelihood of every slot
at position hypotheses (:func:`snr_cost`), and near a window-band edge at the nearest height
within the hypothesis' existence margin where the slot carries power (:func:`snr_cost_near`).

The predicted SNRs are those of the emulator's amplitude model
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
exact predictions, bit for bit. :func:`measurement_update` scores the term with
:func:`snr_term`: these functions' values, bit for bit, in three compiled passes
(:mod:`diffpos.tracking.snr_term_nb`) around the two predictions; the prior-only inputs of
the update are made by :func:`_update_fixed` (:mod:`diffpos.tracking.update_nb`) likewise.
The defaults are 0.05 / 0.1 m (on; their measured accuracy
cost: ``TrackerConfig``). The float32 anchors are compared in the building's frame: their
rounding (< 1e-4 m below 1 km from the origin) is negligible against the anchor margin.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from diffpos.channel.detection import skipped_cost
from diffpos.channel.edge_snr import with_wedge_edges
from diffpos.channel.emulator import pair_family_snr_db, pair_snr_db
from diffpos.channel.snr_nb import snr_cost_kernel
from diffpos.paths.mechanisms import DEFAULT_ORDER
from diffpos.paths.model_nb import building_planes
from diffpos.tracking.iekf_nb import iekf_kernel, prior_info_kernel
from diffpos.tracking.initialisation import grid_starts
from diffpos.tracking.links import (
    _IS_BAND,
    _IS_DIFF,
    K_SLOTS,
    Links,
    PathEval,
    _c,
    _cb,
    _los,
    _relax,
    all_paths,
    candidates,
    slot_paths,
)
from diffpos.tracking.model_nb import (
    iekf_terms_kernel,
    model_kernel,
    select_best_kernel,
    select_mix_kernel,
    select_pack_kernel,
    select_prep_kernel,
)
from diffpos.tracking.snr_nb import cache_plan_kernel, cache_store_kernel
from diffpos.tracking.snr_term_nb import (
    snr_hole_kernel,
    snr_plan_kernel,
    snr_score_kernel,
    snr_skip_kernel,
)
from diffpos.tracking.state import SNR_CACHE_SLOTS, few_ranges
from diffpos.tracking.update_nb import clamp_kernel, update_fixed_kernel

FloatArray = NDArray[np.float64]

# --------------------------------------------------------------------------------------------
# SNR term
# --------------------------------------------------------------------------------------------

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


def _predicted(anchors: FloatArray, nodes: FloatArray, building, radio, need: NDArray,
               edge: str) -> FloatArray:
    """The slots' SNR predictions [dB] (:func:`~diffpos.channel.emulator.pair_snr_db`) with the
    window edge ``edge`` (``"halfplane"``: the emulator's; ``"wedge"``: Sionna RT's,
    :func:`~diffpos.channel.edge_snr.with_wedge_edges`)."""
    pred = pair_snr_db(anchors, nodes, building=building, radio=radio, need=need)
    if edge == "halfplane":
        return pred
    if edge != "wedge":
        raise ValueError(f"snr_edge_model must be 'halfplane' or 'wedge', got {edge!r}")
    return with_wedge_edges(pred, anchors, nodes, building=building, radio=radio, need=need)


def snr_term(pos: FloatArray, links: Links, floor, building, relax_m, pe: PathEval,
             config, cache: SnrCache | None = None) -> FloatArray | None:
    """``cap_snr_cost(snr_cost_near(pos, links, floor, building, relax_m, pe, cache,
    reuse_m), config)`` with ``reuse_m`` = ``config``'s margins and the cache used only when
    :func:`snr_reuse_on`: the measurement update's SNR term, bit for bit, in three compiled
    passes around the two SNR predictions (:mod:`diffpos.tracking.snr_term_nb`; the numpy
    functions above are the reference, tests/core/test_snr_term.py). Falls back to them when
    :data:`HOLE_THRESHOLD_AT_PRIOR` is False."""
    if links.snr is None:
        return None
    use_cache = cache is not None and snr_reuse_on(config)
    reuse_m = (config.snr_reuse_m, config.snr_reuse_anchor_m)
    n, h = pos.shape[:2]
    m = links.rho.shape[-1]
    if not HOLE_THRESHOLD_AT_PRIOR or n * h * m == 0:
        return cap_snr_cost(snr_cost_near(pos, links, floor, building, relax_m, pe,
                                          cache=cache if use_cache else None,
                                          reuse_m=reuse_m), config)
    shape = (n, h, m, K_SLOTS)
    b1 = np.bool_
    need = _cb(pe.loose | ALWAYS_PREDICTED, shape, b1)
    anc = _c(links.anchors[:, 0], dtype=np.float64)
    snr = _c(links.snr[:, 0], dtype=np.float64)
    if use_cache:
        c_node, c_anchor, c_pred = cache.node, cache.anchor, cache.pred
    else:
        c_node, c_anchor, c_pred = (np.empty((1, 1, 3)), np.empty((1, 1, 1, 3), np.float32),
                                    np.empty((1, 1, 1, len(_CACHED)), np.float32))
    near, hit = np.empty((n, h), b1), np.empty((n, h, m), b1)
    mask, at = np.empty(shape, b1), np.empty((n, h, 3))
    rows = n * h * m
    p_anc, p_node, p_need = np.empty((rows, 1, 3)), np.empty((rows, 3)), \
        np.empty((rows, 1, K_SLOTS), b1)
    pc = _c(pos, dtype=np.float64)
    cnt = snr_plan_kernel(pc, anc, snr, need, _cb(pe.strict, shape, b1), use_cache, c_node,
                          c_anchor, c_pred, float(reuse_m[0]), float(reuse_m[1]), _CACHED,
                          _IS_CACHED, near, hit, mask, at, p_anc, p_node, p_need)
    radio = links.radio
    edge = config.snr_edge_model
    p_pred = (_predicted(p_anc[:cnt], p_node[:cnt], building, radio, p_need[:cnt], edge)
              if cnt else np.empty((0, 1, K_SLOTS)))
    pred, cost, thr = np.empty(shape), np.empty(shape), np.empty((n, h, m))
    hole_idx = np.empty((rows, 3), np.int64)
    h_anc, h_node = np.empty((2 * rows, 1, 3)), np.empty((2 * rows, 3))
    h_need, h_meas, h_thr = np.empty((2 * rows, 1, K_SLOTS), b1), np.empty(2 * rows), \
        np.empty(2 * rows)
    sig, fap, det = float(SNR_SIGMA_DB), float(radio.fap_threshold_db), \
        float(radio.detection_snr_db)
    q = snr_score_kernel(_c(p_pred, dtype=np.float64), snr, need, mask, _cb(pe.sure, shape, b1),
                         _cb(pe.loose, shape, b1), near, hit, use_cache, _CACHED, anc, c_anchor,
                         c_pred, sig, fap, det, pc, _relax(relax_m, (n, h)),
                         _cb(floor, (n, h), np.float64), float(building.first_floor_z_m),
                         float(building.floor_height_m), pred, cost, thr, hole_idx, h_anc,
                         h_node, h_need, h_meas, h_thr)
    if use_cache:
        cache.node[...] = at
    h_pred = (_predicted(h_anc[:2 * q], h_node[:2 * q], building, radio, h_need[:2 * q], edge)
              if q else np.empty((0, 1, K_SLOTS)))
    snr_hole_kernel(_c(h_pred, dtype=np.float64), h_need, h_meas, h_thr, hole_idx, q, sig, fap,
                    det, float(config.snr_cost_cap_nats), cost, np.empty((2 * q, K_SLOTS)))
    if config.snr_diffraction_slack_db > 0:  # before the skipped paths: they add to it
        diffraction_slack(cost, pred, thr, snr, links.mask[:, 0], config)
    if config.first_arrival_prior > 0:  # the detector's skipped paths (skip_cost)
        if config.snr_diffraction_slack_db > 0 and config.snr_slack_skip:
            pred = slack_skip_pred(pred, links.mask[:, 0], config)
        if config.skip_threshold_order > DEFAULT_ORDER:
            thr = family_threshold(thr, pc, anc, links.mask[:, 0], building, radio, config)
        snr_skip_kernel(_cb(pe.length, shape, np.float64), _cb(pe.loose, shape, b1),
                        _cb(pe.sure, shape, b1), _IS_DIFF, pred, thr, snr, fap, sig,
                        float(config.first_arrival_prior), cost)
    return cost


def diffraction_slack(cost: FloatArray, pred: FloatArray, thr: FloatArray, snr: FloatArray,
                      mask: NDArray[np.bool_], config) -> FloatArray:
    """The SNR costs ``cost`` (N, H, M, K) [nats] (capped, before the detector's skipped
    paths) with every diffraction slot's Gaussian given an upward slack ``d =
    config.snr_diffraction_slack_db`` [dB] at the nodes with at most
    ``config.snr_slack_max_links`` ranges in ``mask`` (N, M) (0: every node), in place (also
    returned): a
    measured SNR ``snr`` (N, M) [dB] up to ``d`` above the slot's predicted SNR ``pred`` (N,
    H, M, K) [dB] costs nothing, beyond it the Gaussian of :data:`SNR_SIGMA_DB` from ``pred +
    d``, below ``pred`` the Gaussian as before; the detector's threshold term (``thr`` (N, H,
    M) [dB], :func:`snr_cost`) and the cap ``config.snr_cost_cap_nats`` as before; plus the
    density's normaliser ``log(1 + d / (SNR_SIGMA_DB sqrt(2 pi)))``: a flat top ``d`` wide,
    a proper density over the measured SNR, so a diffraction slot gains nothing it has not
    paid for against the other slots and the outlier.

    Why one-sided: the amplitude model's horizontal window edges are a perfectly conducting
    half-plane (the emulator's, :mod:`diffpos.channel.gtd`), whose field falls into the
    edge's deep shadow faster than a real (thick, dielectric) edge's: against an independent
    ray tracer (Sionna RT's live channel) the measured SNR of a ``Tx-D(lower)-Rx`` first
    arrival is within +-1 dB of the model's where its diffraction loss is below ~30 dB and a
    median 6-8 dB above it beyond ~40 dB (docs/tracking_evidence.md "Session 29"). Slots
    without power (+inf) and links with an unknown SNR are unchanged."""
    d = float(config.snr_diffraction_slack_db)
    sig = float(SNR_SIGMA_DB)
    # only the rows of the nodes with few ranges are read (every term is elementwise: the
    # same values as over every row; most calls have no such node and return at once)
    rows = np.flatnonzero(few_ranges(np.sum(mask, axis=-1), int(config.snr_slack_max_links)))
    if rows.size == 0:
        return cost
    c_r, p_r, meas = cost[rows], pred[rows], snr[rows][:, None, :, None]
    use = _IS_DIFF & np.isfinite(c_r) & np.isfinite(p_r) & np.isfinite(meas)
    if not use.any():
        return cost
    with np.errstate(invalid="ignore"):
        r = meas - p_r
        r = np.where(r > d, r - d, np.minimum(r, 0.0))
        short = np.maximum(thr[rows][..., None] - sig - meas, 0.0)
        g = 0.5 * (r / sig) ** 2 + 0.5 * (short / sig) ** 2
    cap = float(config.snr_cost_cap_nats)
    if cap > 0:
        g = np.minimum(g, cap)
    g = g + float(np.log1p(d / (sig * np.sqrt(2.0 * np.pi))))
    c_r[use] = g[use]
    cost[rows] = c_r
    return cost


def family_threshold(thr: FloatArray, pos: FloatArray, anc: FloatArray,
                     mask: NDArray[np.bool_], building, radio, config) -> FloatArray:
    """The detector's thresholds ``thr`` (N, H, M) [dB] of the hypotheses at ``pos`` (N, H,
    3) [m] for the anchors ``anc`` (N, M, 3) [m], raised where the strongest closed-form
    family beyond the 18 (``mechanism_set(config.skip_threshold_order, partitions=True)``,
    :func:`diffpos.channel.emulator.pair_family_snr_db`) less ``radio.fap_threshold_db`` is
    higher (``TrackerConfig.skip_threshold_order``): the detector reports the earliest path
    within ``fap_threshold_db`` of the STRONGEST, whatever its order. Only the present links
    (``mask`` (N, M)) of nodes with at most ``config.skip_threshold_max_links`` ranges (0:
    every node) and at least ``config.min_anchors_tracking`` (fewer do not fix a position);
    the rest as given (a new array)."""
    few = few_ranges(np.sum(mask, axis=-1), int(config.skip_threshold_max_links),
                     config.min_anchors_tracking)
    use = mask & few[:, None]
    idx = np.argwhere(np.broadcast_to(use[:, None, :], thr.shape))
    out = np.array(thr, dtype=np.float64, copy=True)
    if idx.size == 0:
        return out
    n_i, h_i, m_i = idx.T
    fam = pair_family_snr_db(anc[n_i, m_i], pos[n_i, h_i], building=building, radio=radio,
                             max_order=int(config.skip_threshold_order), partitions=True)
    with np.errstate(invalid="ignore"):
        top = np.max(np.where(np.isfinite(fam), fam, -np.inf), axis=-1, initial=-np.inf)
    out[n_i, h_i, m_i] = np.fmax(out[n_i, h_i, m_i], top - float(radio.fap_threshold_db))
    return out


def slack_skip_pred(pred: FloatArray, mask: NDArray[np.bool_], config) -> FloatArray:
    """The predicted SNRs ``pred`` (N, H, M, K) [dB] the detector's skipped paths
    (:func:`skip_cost`) read with ``TrackerConfig.snr_slack_skip``: every diffraction slot of
    a node that :func:`diffraction_slack` applies to (at most ``snr_slack_max_links`` ranges
    in ``mask`` (N, M); 0: every node) raised by half the slack ``snr_diffraction_slack_db``,
    the mean of the slack's flat top (the power the SNR likelihood allows, uniform over
    ``[pred, pred + slack]``): the probability that an earlier diffraction was below the
    threshold is then read at that power's mean, not at the half-plane's (a new array)."""
    few = few_ranges(np.sum(mask, axis=-1), int(config.snr_slack_max_links))
    return np.where(_IS_DIFF & few[:, None, None, None],
                    pred + 0.5 * float(config.snr_diffraction_slack_db), pred)


def skip_cost(pe: PathEval, pred: FloatArray, thr: FloatArray, snr: FloatArray,
              cost: FloatArray, radio, weight: float) -> FloatArray:
    """The SNR costs ``cost`` (N, H, M, K) [nats] with the detector's skipped paths
    (``TrackerConfig.first_arrival_prior`` = ``weight``; the numpy reference of
    :func:`diffpos.tracking.snr_term_nb.snr_skip_kernel`).

    The detector reports the earliest path whose SNR is within ``fap_threshold_db`` of the
    strongest (:func:`diffpos.channel.emulator.first_arrival`), so a candidate mechanism
    ``k`` is the first arrival only if every candidate ``j`` arriving before it was below
    that threshold ``T``: probability ``prod_j Phi((T - S_j) / SNR_SIGMA_DB)``, ``S_j`` the
    slot's predicted SNR ``pred`` [dB] (the spread of :data:`SNR_SIGMA_DB`), ``T`` the
    predicted threshold ``thr`` (N, H, M) or, if higher, the measured first arrival's SNR
    ``snr`` (N, M) less ``fap_threshold_db`` (the strongest path is at least that strong,
    whatever the model predicts). Mixed ``weight : 1 - weight`` with 1 (a model that
    predicts a path tens of dB too strong, as on channels we did not write, costs at most
    ``-log(1 - weight)``; :func:`diffpos.channel.detection.skipped_cost`), it multiplies the
    candidate's uniform prior, so ``-log`` of it is added to the cost. Links with an unknown SNR, slots that are no candidate or carry
    no power (an infinite cost) are unchanged."""
    valid = candidates(pe) & (np.isfinite(cost) | ~pe.sure)
    t = np.fmax(thr, snr[:, None, :] - radio.fap_threshold_db)
    add = skipped_cost(pe.length, valid, pred, t[..., None], SNR_SIGMA_DB, weight)
    use = valid & np.isfinite(cost) & np.isfinite(snr)[:, None, :, None]
    return np.where(use, cost + add, cost)


# --------------------------------------------------------------------------------------------
# mechanism selection, IEKF, measurement update, snapshot
# --------------------------------------------------------------------------------------------

_LOG2PI = float(np.log(2.0 * np.pi))
#: ``log(n)`` of the number of candidates of a link, n = 0..K (numpy's; index 0 unused).
with np.errstate(divide="ignore"):
    _LOG_N = np.log(np.arange(K_SLOTS + 1, dtype=np.float64))
#: Standard deviations of a hypothesis' height within which a window entry point may lie
#: (:func:`existence_margin`): two, the 95 % interval of a Gaussian.
ENTRY_SIGMAS = 2.0


@dataclass(frozen=True)
class Selection:
    """Max-mixture choice per link (N, H, M): slot (-1 outlier/missing), its log-weight, the
    NIS of the chosen slot at the prior (NaN where not used) and the mechanism-ambiguity
    variance ``sum_k p_k (L_k - L_chosen)^2`` over the candidates (their posterior weights
    ``p_k`` given the range): the moment-matched spread of the mixture about the chosen
    mechanism, added to the range variance (model uncertainty)."""

    slot: NDArray[np.int_]
    log_weight: FloatArray
    nis: FloatArray
    extra_var: FloatArray


def cap_snr_cost(snr_c: FloatArray | None, config) -> FloatArray | None:
    """The SNR costs (N, H, M, K) [nats] with every finite one capped at
    ``config.snr_cost_cap_nats``: a robust SNR likelihood,
    the Gaussian of :data:`SNR_SIGMA_DB` about the predicted SNR mixed with a flat tail, so a
    slot whose measured SNR misses its prediction (or the detector's threshold) by more than
    ``sqrt(2 cap)`` standard deviations loses no more than ``cap`` nats (``cap <= 0``: no cap,
    the array itself): the amplitude model
    is the emulator's, and another channel's powers (a ray tracer's materials and
    diffraction coefficients) miss it by tens of dB on whole links. A slot without power
    (``inf``) stays no candidate."""
    cap = float(config.snr_cost_cap_nats)
    if snr_c is None or not cap > 0:
        return snr_c
    return np.where(snr_c > cap, np.where(np.isfinite(snr_c), cap, snr_c), snr_c)


def _select_prep(pos_cov: FloatArray, links: Links, pe: PathEval, snr_c):
    """Candidates, SNR log-likelihood term and innovation variance of every slot, (N, H, M, K)
    (:func:`diffpos.tracking.model_nb.select_prep_kernel`)."""
    shape = pe.length.shape
    valid = np.empty(shape, dtype=np.bool_)
    s_ll, s_var = np.empty(shape), np.empty(shape)
    select_prep_kernel(_c(pe.length), _c(pe.jac), _c(pe.sure), _c(pe.loose), _IS_DIFF,
                       *_prep_inputs(pos_cov, links, snr_c, *shape[:2]), valid, s_ll, s_var)
    return valid, s_ll, s_var


def _prep_inputs(pos_cov: FloatArray, links: Links, snr_c, n: int, h: int) -> tuple:
    """The per-link inputs of ``select_prep_kernel`` / ``select_pack_kernel`` after the paths:
    the covariance, the range variances, the SNRs and their costs, the constants."""
    m = links.rho.shape[-1]
    use_snr = snr_c is not None
    return (_cb(pos_cov, (n, h, 3, 3)), _c(links.var[:, 0]),
            _c(links.snr[:, 0]) if use_snr else np.zeros((n, m)),
            _c(snr_c) if use_snr else np.zeros((1, 1, 1, 1)), use_snr,
            np.array([np.log(SNR_SIGMA_DB), 0.5 * _LOG2PI]), float(-np.log(SNR_SPAN_DB)))


def _select_prep_numpy(pos_cov: FloatArray, links: Links, pe: PathEval, snr_c):
    """The numpy reference of :func:`_select_prep`."""
    valid = candidates(pe)
    if snr_c is not None:
        powered = np.isfinite(snr_c)
        valid = valid & (powered | ~pe.sure)
        has_snr = np.isfinite(links.snr)
        with np.errstate(invalid="ignore"):
            g = np.where(powered, -snr_c - np.log(SNR_SIGMA_DB) - 0.5 * _LOG2PI,
                         -np.log(SNR_SPAN_DB))
        s_ll = np.where(has_snr[..., None], g, 0.0)
    else:
        s_ll = np.zeros(pe.length.shape)
    jac = np.where(valid[..., None], pe.jac, 0.0)
    s_var = np.einsum("nhmki,nhij,nhmkj->nhmk", jac, pos_cov, jac) + links.var[..., None]
    return valid, s_ll, s_var


def link_weights(links: Links, config, use_snr: bool, n: int, h: int) -> FloatArray:
    """Every link's fixed mixture weights (N, H, M, 2), C-contiguous: the inlier weight
    ``log(1 - eps)`` and the outlier component's log-density ``log(eps / span)`` (plus the
    uniform SNR density ``-log(SNR_SPAN_DB)`` where the link's SNR is known), ``eps =
    outlier_weight``: the weights of a link nothing was learned about
    (:mod:`diffpos.tracking.evidence` gives the learned ones)."""
    m = links.rho.shape[-1]
    eps = config.outlier_weight
    w = np.empty((n, h, m, 2))
    w[..., 0] = np.log1p(-eps)
    s_out = (np.where(np.isfinite(links.snr[:, 0]), -np.log(SNR_SPAN_DB), 0.0) if use_snr
             else np.zeros((links.rho.shape[0], m)))
    w[..., 1] = (np.log(eps / config.outlier_span_m) + s_out)[:, None, :]
    return w


def _select_fixed(pos_cov: FloatArray, links: Links, config, snr_c, n: int, h: int,
                  link_w: FloatArray | None = None) -> tuple:
    """:func:`select`'s kernel inputs that do not depend on the paths (the selection passes of
    one update share them): the covariance, the links' columns, the constants and every
    link's mixture weights (``link_w`` (N, H, M, 2), default :func:`link_weights`)."""
    if link_w is None:
        link_w = link_weights(links, config, snr_c is not None, n, h)
    return (*_prep_inputs(pos_cov, links, snr_c, n, h), _c(links.rho[:, 0]),
            _c(links.mask[:, 0]), np.array([_LOG2PI]),
            _cb(link_w, (n, h, links.rho.shape[-1], 2), dtype=np.float64))


def few_links_weights(w_link: FloatArray, valid: NDArray[np.bool_], mask: NDArray[np.bool_],
                      config) -> FloatArray:
    """The links' mixture weights ``w_link`` (N, H, M, 2) with the inlier weight of every
    link of a node with fewer than ``config.mechanism_prior_min_links`` ranges (``mask``
    (N, M)) raised by ``log n_cand`` (``valid`` (N, H, M, K): the candidates), so that
    :func:`select`'s ``w_in - log n_cand`` is the flat ``log(1 - eps)`` there (a new array;
    ``w_link`` itself where the setting is off or no node has so few ranges)."""
    k = int(config.mechanism_prior_min_links)
    if k <= 0:
        return w_link
    few = np.asarray(mask).sum(axis=-1) < k
    if not few.any():
        return w_link
    w = np.array(w_link, dtype=np.float64)  # C-contiguous copy (w_link may be a broadcast)
    w[few, ..., 0] += _LOG_N[np.maximum(valid[few].sum(axis=-1), 1)]
    return w


def select(pos_cov: FloatArray, links: Links, pe: PathEval, config,
           snr_c: FloatArray | None = None, fixed: tuple | None = None,
           prev_slot: FloatArray | None = None) -> Selection:
    """Most likely mechanism per link given the predicted position Gaussian.

    ``pos_cov``: (N, H, 3, 3). Component log-likelihoods: ``log((1 - eps) / n_cand) + log
    N(rho; L_k, J_k P J_k^T + R)`` for every candidate slot (:func:`candidates`),
    ``log(eps / span)`` for the outlier; with ``snr_c`` (:func:`snr_cost`) every candidate's
    SNR log-likelihood is added (the outlier's SNR is uniform over ``SNR_SPAN_DB``), and it
    is part of the link's log-weight (so of the floor evidence).

    Three compiled passes over the links (:mod:`diffpos.tracking.model_nb`'s
    ``select_pack_kernel``, ``select_best_kernel``, ``select_mix_kernel``: no (N, H, M, K)
    temporaries but the candidate mask) with numpy's log and exp on the packed candidates in
    between (numba's libm exp/log differ from numpy's SIMD ones in the last bit): bit-identical
    to the numpy reference :func:`_select_numpy` (tests/core/test_tracking_kernel.py).
    ``fixed``: :func:`_select_fixed` of the same ``pos_cov``, ``links``, ``config``,
    ``snr_c`` if the caller has it. ``prev_slot`` (N, H, M): the hypotheses' previous choice
    of every link (``TrackerState.link_slot``; NaN / -1: none); with
    ``config.mechanism_switch_p`` the nodes with fewer than ``mechanism_prior_min_links``
    ranges get :func:`select_persistent`'s selection instead (in the same compiled passes,
    bit-identical to that numpy reference: tests/core/test_tracking_mechanism_prior.py).
    """
    shape = pe.length.shape
    n, h, m = shape[:3]
    if fixed is None:
        fixed = _select_fixed(pos_cov, links, config, snr_c, n, h)
    cov, var, snr, sc, use_snr, c_pack, c_span, rho, mask, consts, w_link = fixed
    length = _c(pe.length)
    valid = np.empty(shape, dtype=np.bool_)
    sv, sl = np.empty(valid.size), np.empty(valid.size)
    cnt = select_pack_kernel(length, _c(pe.jac), _c(pe.sure), _c(pe.loose), _IS_DIFF, cov, var,
                             snr, sc, use_snr, c_pack, c_span, valid, sv, sl)
    slot, best = np.empty((n, h, m), dtype=np.int64), np.empty((n, h, m), dtype=np.int64)
    base, nis, extra = np.empty((n, h, m)), np.empty((n, h, m)), np.empty((n, h, m))
    ex = np.empty(cnt)
    persist, prev, consts = _persist_inputs(mask, config, prev_slot, (n, h, m), consts)
    if not persist.any():  # the persistent rows take link_w as it is (select_persistent)
        w_link = few_links_weights(w_link, valid, mask, config)
    select_best_kernel(length, valid, rho, mask, snr, use_snr, sv, sl, np.log(sv[:cnt]),
                       consts, w_link, _LOG_N, ex, best, base, slot, nis, persist, prev)
    np.exp(ex, out=ex)
    mix = np.empty((n, h, m))
    select_mix_kernel(length, valid, slot, best, ex, extra, mix)
    log_w = np.where(slot >= 0, base + np.log(mix), base)
    return Selection(slot=slot, log_weight=log_w, nis=nis, extra_var=extra)


def _persist_inputs(mask: NDArray[np.bool_], config, prev_slot: FloatArray | None,
                    shape: tuple, consts: FloatArray) -> tuple:
    """:func:`select`'s persistent-prior inputs of ``select_best_kernel``: which nodes get
    :func:`select_persistent`'s prior (``persist`` (N,): fewer than
    ``mechanism_prior_min_links`` ranges in ``mask`` (N, M), with ``mechanism_switch_p`` > 0
    and a ``prev_slot``), the previous slots (N, H, M) int64 (-1: none) and ``consts`` with
    numpy's ``log q`` and ``log(1 - q)`` appended (its reference's scalar calls)."""
    few = np.asarray(mask).sum(axis=-1) < int(config.mechanism_prior_min_links)
    q = float(config.mechanism_switch_p)
    if prev_slot is None or q <= 0.0 or not few.any():
        return np.zeros(shape[0], dtype=np.bool_), np.empty((1, 1, 1), dtype=np.int64), \
            np.array([consts[0], 0.0, 0.0])
    pv = np.broadcast_to(np.where(np.isfinite(prev_slot), prev_slot, -1.0), shape)
    return few, np.ascontiguousarray(pv, dtype=np.int64), \
        np.array([consts[0], np.log(q), np.log1p(-q)])


def select_persistent(pos_cov: FloatArray, links: Links, pe: PathEval, config,
                      snr_c: FloatArray | None, link_w: FloatArray, prev_slot: FloatArray
                      ) -> Selection:
    """:func:`_select_numpy` with a persistent mechanism prior
    (``TrackerConfig.mechanism_switch_p`` = q): a link's candidate equal to ``prev_slot``
    (N, H, M) (the hypothesis' previous choice; NaN / -1: none) gets the inlier weight
    ``log(1 - eps) + log(1 - q)``, its other candidates ``log(1 - eps) + log q - log(n_cand -
    1)``; a link without a previous choice among its candidates today's ``log(1 - eps) - log
    n_cand``. The prior enters the argmax, the outlier test and the mixture; ``link_w`` (N,
    H, M, 2) as :func:`select`'s. The numpy reference of :func:`select`'s persistent rows
    (which run it compiled, in ``select_best_kernel``)."""
    valid, s_ll, s_var = _select_prep_numpy(pos_cov, links, pe, snr_c)
    e = links.rho[..., None] - pe.length
    n_ok = np.maximum(valid.sum(axis=-1), 1)
    with np.errstate(invalid="ignore"):
        ll = -0.5 * (e * e / s_var + np.log(s_var) + _LOG2PI)
    ll = np.where(valid, ll + s_ll, -np.inf)
    base = np.broadcast_to(link_w[..., 0], n_ok.shape)
    q = float(config.mechanism_switch_p)
    pv = np.broadcast_to(np.where(np.isfinite(prev_slot), prev_slot, -1.0), n_ok.shape)
    pv = pv.astype(np.int64)
    has = (pv >= 0) & np.take_along_axis(valid, np.maximum(pv, 0)[..., None], -1)[..., 0]
    switch = base + np.log(q) - np.log(np.maximum(n_ok - 1, 1))
    wk = np.where(has, switch, base - np.log(n_ok))[..., None] * np.ones(ll.shape[-1])
    same = (np.arange(ll.shape[-1]) == np.maximum(pv, 0)[..., None]) & has[..., None]
    wk = np.where(same, (base + np.log1p(-q))[..., None], wk)
    tot = ll + wk
    best = np.argmax(tot, axis=-1)
    tb = np.take_along_axis(tot, best[..., None], -1)[..., 0]
    s_best = np.take_along_axis(np.broadcast_to(s_ll, ll.shape), best[..., None], -1)[..., 0]
    w_best = np.take_along_axis(wk, best[..., None], -1)[..., 0]
    w_out = link_w[..., 1]
    inlier = links.mask & np.isfinite(tb) & (tb > w_out)
    slot = np.where(inlier, best, -1)
    nis = np.where(inlier, np.take_along_axis(e * e / s_var, best[..., None], -1)[..., 0], np.nan)
    with np.errstate(invalid="ignore"):
        pk = np.where(valid, np.exp(tot - np.where(np.isfinite(tb), tb, 0.0)[..., None]), 0.0)
        mass = pk.sum(axis=-1)
        pk = pk / np.maximum(mass[..., None], 1e-300)
    mix = np.log(np.maximum(np.where(inlier, mass, 1.0), 1.0))
    log_w = np.where(inlier, w_best + s_best + mix, np.where(links.mask, w_out, 0.0))
    l_best = np.take_along_axis(pe.length, best[..., None], axis=-1)
    with np.errstate(invalid="ignore"):
        extra = np.sum(np.where(valid, pk * (pe.length - l_best) ** 2, 0.0), axis=-1)
    extra = np.where(inlier & np.isfinite(extra), extra, 0.0)
    return Selection(slot=slot, log_weight=log_w, nis=nis, extra_var=extra)


def _select_numpy(pos_cov: FloatArray, links: Links, pe: PathEval, config,
                  snr_c: FloatArray | None = None, link_w: FloatArray | None = None
                  ) -> Selection:
    """The numpy reference of :func:`select`.

    Most likely mechanism per link given the predicted position Gaussian.

    ``pos_cov``: (N, H, 3, 3). Component log-likelihoods: ``log((1 - eps) / n_cand) + log
    N(rho; L_k, J_k P J_k^T + R)`` for every candidate slot (:func:`candidates`),
    ``log(eps / span)`` for the outlier; with ``snr_c`` (:func:`snr_cost`) every candidate's
    SNR log-likelihood is added (the outlier's SNR is uniform over ``SNR_SPAN_DB``), and it
    is part of the link's log-weight (so of the floor evidence).
    """
    # the candidates (a slot without power at the hypothesis is no candidate, unless the
    # hypothesis is within the entry point's uncertainty of the slot's existence boundary: the
    # prediction flips from a strong path to none over a few cm there, so its SNR is then
    # uninformative, uniform over SNR_SPAN_DB), every candidate's SNR log-likelihood and
    # innovation variance (the kernel's per-link body is _select_prep's, bit-identical)
    valid, s_ll, s_var = _select_prep_numpy(pos_cov, links, pe, snr_c)
    if link_w is None:
        link_w = link_weights(links, config, snr_c is not None, *pe.length.shape[:2])
    lengths = pe.length
    e = links.rho[..., None] - lengths
    n_ok = np.maximum(valid.sum(axis=-1), 1)
    with np.errstate(invalid="ignore"):
        ll = -0.5 * (e * e / s_var + np.log(s_var) + _LOG2PI)
    ll = np.where(valid, ll + s_ll, -np.inf)
    best = np.argmax(ll, axis=-1)
    ll_best = np.take_along_axis(ll, best[..., None], axis=-1)[..., 0]
    s_best = np.take_along_axis(np.broadcast_to(s_ll, ll.shape), best[..., None], -1)[..., 0]
    w_in = few_links_weights(np.broadcast_to(link_w, (*n_ok.shape, 2)), valid,
                             links.mask[:, 0], config)[..., 0] - np.log(n_ok)
    w_out = link_w[..., 1]
    inlier = links.mask & np.isfinite(ll_best) & (ll_best + w_in > w_out)
    slot = np.where(inlier, best, -1)
    nis = np.where(inlier, np.take_along_axis(e * e / s_var, best[..., None], -1)[..., 0], np.nan)
    with np.errstate(invalid="ignore"):
        pk = np.where(valid, np.exp(ll - np.where(np.isfinite(ll_best), ll_best, 0.0)[..., None]),
                      0.0)
        mass = pk.sum(axis=-1)
        pk = pk / np.maximum(mass[..., None], 1e-300)
    # the link's likelihood is the mixture's sum over the candidates, not its largest term:
    # a hypothesis where two mechanisms explain the range equally well is not penalised
    # (log of sum / max >= 0, the chosen slot's own term is in the IEKF's residual)
    mix = np.log(np.maximum(np.where(inlier, mass, 1.0), 1.0))
    log_w = np.where(inlier, w_in + s_best + mix, np.where(links.mask, w_out, 0.0))
    l_best = np.take_along_axis(lengths, best[..., None], axis=-1)
    with np.errstate(invalid="ignore"):
        extra = np.sum(np.where(valid, pk * (lengths - l_best) ** 2, 0.0), axis=-1)
    extra = np.where(inlier & np.isfinite(extra), extra, 0.0)
    return Selection(slot=slot, log_weight=log_w, nis=nis, extra_var=extra)


def _model(pos, links: Links, floor, sel: Selection, building):
    """Model values, Jacobians and weights of the used links at ``pos`` (incl. the hinge):
    (N, H, M), (N, H, M, 3), (N, H, M). One compiled pass over every link
    (:func:`diffpos.tracking.model_nb.model_kernel`), bit-identical to
    :func:`_model_numpy`."""
    n, h, m = sel.slot.shape
    fl = np.empty((n, h))
    fl[...] = np.broadcast_to(np.asarray(floor), (n, h))
    model, jm, w = np.empty((n, h, m)), np.empty((n, h, m, 3)), np.empty((n, h, m))
    model_kernel(_c(pos, dtype=np.float64),
                 _c(links.anchors[:, 0]), fl,
                 _c(sel.slot, dtype=np.int64),
                 _cb(sel.extra_var, (n, h, m), dtype=np.float64),
                 _c(links.rho[:, 0]), _c(links.var[:, 0]),
                 _c(links.mask[:, 0]), *building_planes(building),
                 model, jm, w)
    return model, jm, w


def _model_numpy(pos, links: Links, floor, sel: Selection, building):
    """The numpy reference of :func:`_model` (the path model once per distinct slot)."""
    length, jac, ok = slot_paths(pos, links, floor, sel.slot, building)
    los, jlos = _los(pos, links.anchors)
    use = (sel.slot >= 0) & ok
    hinge = links.mask & ~use & (links.rho < los)
    model = np.where(use, length, np.where(hinge, los, links.rho))
    jm = np.where(use[..., None], jac, np.where(hinge[..., None], jlos, 0.0))
    # a link whose range two mechanisms explain about equally gets their spread as extra
    # variance (model uncertainty: the covariance must not pretend the choice is known)
    w = np.where(use, 1.0 / (links.var + sel.extra_var), np.where(hinge, 1.0 / links.var, 0.0))
    return model, jm, w


def _box(x: FloatArray, floor, building, margin_m: float) -> tuple[FloatArray, FloatArray]:
    """Lower and upper bounds (N, H, 3) of every hypothesis' position: its floor's box."""
    zf = building.floor_z_m(np.broadcast_to(np.asarray(floor), x.shape[:2]))
    x0, x1 = building.edge_x_m
    lo = np.stack(np.broadcast_arrays(x0 + margin_m, margin_m, zf + margin_m), axis=-1)
    hi = np.stack(np.broadcast_arrays(x1 - margin_m, building.depth_m - margin_m,
                                      zf + building.floor_height_m - margin_m), axis=-1)
    return lo, hi


def prior_information(p_prior: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Information matrix of the prior and its log-determinant (N, H, 6, 6), (N, H): one
    compiled pass (:func:`diffpos.tracking.iekf_nb.prior_info_kernel`, LU with partial
    pivoting; :func:`_prior_information_numpy` within 1e-12 relative, tested)."""
    shape = p_prior.shape[:-2]
    y, logdet_y = np.empty((*shape, 6, 6)), np.empty(shape)
    prior_info_kernel(_c(p_prior, dtype=np.float64), y, logdet_y)
    return y, logdet_y


def _prior_information_numpy(p_prior: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The numpy reference of :func:`prior_information`."""
    y = np.linalg.inv(p_prior)
    return y, np.linalg.slogdet(y)[1]


def _iekf_terms(y, x, lo, hi, z_nom, rho, model, jm, w, wb: float, wh):
    """Information matrix (N, H, 6, 6), residuals of the links (N, H, M), of the box (N, H, 3)
    and of the height (N, H), and the position gradient ``J^T W e + wb eb`` (N, H, 3) of one
    Gauss-Newton iteration (:func:`diffpos.tracking.model_nb.iekf_terms_kernel`),
    bit-identical to :func:`_iekf_terms_numpy`. ``rho`` (N, 1, M)."""
    n, h, m = model.shape
    c = _c
    a, e, eb, eh = np.empty((n, h, 6, 6)), np.empty((n, h, m)), np.empty((n, h, 3)), \
        np.empty((n, h))
    gpart = np.empty((n, h, 3))
    iekf_terms_kernel(c(np.broadcast_to(y, (n, h, 6, 6))), c(x),
                      c(np.broadcast_to(lo, (n, h, 3))), c(np.broadcast_to(hi, (n, h, 3))),
                      c(np.broadcast_to(z_nom, (n, h)), dtype=np.float64),
                      c(np.broadcast_to(rho[:, 0], (n, m))), model, jm, w, float(wb),
                      c(np.broadcast_to(wh, (n, h)), dtype=np.float64), a, e, eb, eh, gpart)
    return a, e, eb, eh, gpart


def _iekf_terms_numpy(y, x, lo, hi, z_nom, rho, model, jm, w, wb: float, wh):
    """The numpy reference of :func:`_iekf_terms`."""
    e = rho - model
    p3 = x[..., :3]
    eb = np.clip(p3, lo, hi) - p3  # pseudo-measurement residuals (0 inside the box)
    eh = z_nom - x[..., 2]
    hth = np.einsum("nhmi,nhm,nhmj->nhij", jm, w, jm)
    a = np.broadcast_to(y, (*x.shape[:2], 6, 6)).copy()
    a[..., :3, :3] += hth
    a[..., [0, 1, 2], [0, 1, 2]] += np.where(eb != 0, wb, 0.0)
    a[..., 2, 2] += wh
    return a, e, eb, eh, np.einsum("nhmi,nhm->nhi", jm, w * e) + wb * eb


def _height_prior(x: FloatArray, floor, building, config, level):
    """The height prior of every hypothesis (:func:`iekf`'s ``level``): nominal height,
    weight and the mode's log-normaliser, C-contiguous float64 (N, H)."""
    z_nom = building.floor_z_m(np.broadcast_to(np.asarray(floor), x.shape[:2])) + \
        building.nominal_node_height_m
    sh = config.height_sigma_m
    ll_gauss = -np.log(sh) - 0.5 * _LOG2PI
    ll_any = -np.log(building.floor_height_m)
    if level is None:
        # device height above the floor: on the level (Gaussian about the nominal height) or
        # anywhere on the floor (stairs, crouching: uniform), chosen at the prior
        w_lvl, w_any = np.log1p(-config.stairs_weight), np.log(config.stairs_weight)
        level = (w_lvl + ll_gauss - 0.5 * ((x[..., 2] - z_nom) / sh) ** 2) > w_any + ll_any
    else:
        w_lvl = w_any = 0.0
    level = np.broadcast_to(level, x.shape[:2])
    wh = np.where(level, 1.0 / sh**2, 0.0)
    h_const = np.where(level, w_lvl + ll_gauss, w_any + ll_any)
    return tuple(_cb(v, x.shape[:2], dtype=np.float64)
                 for v in (z_nom, wh, h_const))


def _iekf_fixed(x_prior: FloatArray, p_prior: FloatArray, links: Links, floor, building,
                config, level=None, prior_info=None) -> tuple[tuple, tuple]:
    """:func:`iekf`'s kernel arguments that do not depend on the selection (the selection
    passes of one update share them): those before and those after the selection's three."""
    y, logdet_y = prior_information(p_prior) if prior_info is None else prior_info
    n, h = x_prior.shape[:2]
    lo, hi = _box(x_prior, floor, building, config.z_margin_m)
    z_nom, wh, h_const = _height_prior(x_prior, floor, building, config, level)
    fl = np.empty((n, h))
    fl[...] = np.broadcast_to(np.asarray(floor), (n, h))
    f8 = np.float64
    head = (_c(x_prior, dtype=f8), _cb(y, (n, h, 6, 6), dtype=f8),
            _cb(logdet_y, (n, h), dtype=f8), _cb(lo, (n, h, 3), dtype=f8),
            _cb(hi, (n, h, 3), dtype=f8), z_nom, wh, h_const,
            _c(links.anchors[:, 0], dtype=f8), fl)
    tail = (_c(links.rho[:, 0], dtype=f8), _c(links.var[:, 0], dtype=f8),
            _c(links.mask[:, 0]), int(config.gn_iterations),
            float(1.0 / config.box_sigma_m**2), _LOG2PI, *building_planes(building))
    return head, tail


def _floor_box(building, margin_m: float) -> NDArray:
    """The constants of every floor box (:func:`diffpos.tracking.update_nb._bounds`): the x
    and y bounds ``margin_m`` inside the walls, the floors' planes and the margin."""
    x0, x1 = building.edge_x_m
    return np.array([x0 + margin_m, x1 - margin_m, margin_m, building.depth_m - margin_m,
                     building.first_floor_z_m, building.floor_height_m, margin_m],
                    dtype=np.float64)


def _update_fixed(x_prior: FloatArray, p_prior: FloatArray, links: Links, floor, building,
                  config, level=None) -> tuple:
    """Everything of :func:`measurement_update` that depends on the prior only, in one
    compiled pass (:func:`diffpos.tracking.update_nb.update_fixed_kernel`): the clamped prior
    ``xc`` (N, H, 3), the nodes it moved (indices), every hypothesis' existence margin (the
    fixed one at initialisation, ``level`` None), the prior information and
    :func:`_iekf_fixed` (the values of :func:`~diffpos.tracking.state.clamp_to_floor`, :func:`existence_margin`,
    :func:`prior_information` and :func:`_iekf_fixed`, bit for bit)."""
    n, h = x_prior.shape[:2]
    f8, b1 = np.float64, np.bool_
    fl = _cb(floor, (n, h), f8)
    sh = config.height_sigma_m
    ll_gauss = -np.log(sh) - 0.5 * _LOG2PI
    ll_any = -np.log(building.floor_height_m)
    if level is None:
        w_lvl, w_any = np.log1p(-config.stairs_weight), np.log(config.stairs_weight)
        lv = np.zeros((1, 1), b1)
    else:
        w_lvl = w_any = 0.0
        lv = _cb(level, (n, h), b1)
    height = np.array([building.nominal_node_height_m, 1.0 / sh**2, w_lvl + ll_gauss,
                       w_any + ll_any, sh], dtype=f8)
    e = np.empty
    xc, moved, relax = e((n, h, 3)), e(n, b1), e((n, h))
    y, logdet_y = e((n, h, 6, 6)), e((n, h))
    lo, hi, z_nom, wh, h_const = e((n, h, 3)), e((n, h, 3)), e((n, h)), e((n, h)), e((n, h))
    xp = _c(x_prior, dtype=f8)
    update_fixed_kernel(xp, _c(p_prior, dtype=f8), fl, lv, level is not None,
                        _floor_box(building, config.z_margin_m),
                        np.array([config.exist_margin_m, ENTRY_SIGMAS]), height, xc, moved,
                        relax, y, logdet_y, lo, hi, z_nom, wh, h_const)
    if not (relax >= 0.0).all():
        raise ValueError(f"relax_m must be >= 0 [m]; got {relax!r}")
    head = (xp, y, logdet_y, lo, hi, z_nom, wh, h_const, _c(links.anchors[:, 0], dtype=f8), fl)
    tail = (_c(links.rho[:, 0], dtype=f8), _c(links.var[:, 0], dtype=f8),
            _c(links.mask[:, 0]), int(config.gn_iterations),
            float(1.0 / config.box_sigma_m**2), _LOG2PI, *building_planes(building))
    return xc, np.flatnonzero(moved), relax, (y, logdet_y), (head, tail)


def iekf(x_prior: FloatArray, p_prior: FloatArray, links: Links, floor, sel: Selection,
         building, config, level=None, prior_info=None, fixed: tuple | None = None):
    """Iterated EKF (Gauss-Newton on the MAP cost) of every hypothesis with fixed mechanisms.

    The hypothesis' floor box is a hard-ish constraint: a coordinate outside it gets a
    pseudo-measurement of the nearest bound with ``box_sigma_m`` (so the fit and its evidence
    are those of a position on the floor the paths were computed for).

    ``level`` (bool, broadcastable to (N, H)): the hypothesis' vertical mode. Level: the
    device is at the building's nominal height above its floor (Gaussian, ``height_sigma_m``);
    vertical (stairs): anywhere between floor and ceiling (uniform); the mode's prior
    probability is the caller's. ``None`` (snapshot initialisation, no mode yet): a
    max-mixture of both chosen at the prior, weighted ``1 - stairs_weight`` /
    ``stairs_weight``.
    ``prior_info``: :func:`prior_information` of ``p_prior`` if the caller has it (the
    selection passes of one update share the prior).
    Returns ``(x, P, log_evidence, residual)``: posterior means (N, H, 6), covariances
    (N, H, 6, 6), the Laplace log marginal likelihood (N, H) and the residuals (N, H, M).

    One compiled pass per hypothesis (:func:`diffpos.tracking.iekf_nb.iekf_kernel`: the
    link model and the iteration's terms are the bit-identical kernels' bodies, the 6 x 6
    solve/inverse/log-determinant LU with partial pivoting); :func:`_iekf_numpy` (numpy's
    LAPACK) is the reference, held to a tolerance by tests/core/test_tracking_kernel.py.
    ``fixed``: :func:`_iekf_fixed` of the same arguments if the caller has it (the kernel
    reads its inputs only).
    """
    if fixed is None:
        fixed = _iekf_fixed(x_prior, p_prior, links, floor, building, config, level,
                            prior_info)
    head, tail = fixed
    n, h = x_prior.shape[:2]
    m = sel.slot.shape[-1]
    x, p = np.empty((n, h, 6)), np.empty((n, h, 6, 6))
    log_ev, residual = np.empty((n, h)), np.empty((n, h, m))
    f8 = np.float64
    iekf_kernel(*head, _c(sel.slot, dtype=np.int64), _cb(sel.extra_var, (n, h, m), dtype=f8),
                _cb(sel.log_weight, (n, h, m), dtype=f8), *tail, x, p, log_ev, residual)
    return x, p, log_ev, residual


def _iekf_numpy(x_prior: FloatArray, p_prior: FloatArray, links: Links, floor,
                sel: Selection, building, config, level=None, prior_info=None):
    """The numpy reference of :func:`iekf` (the link model and the terms by their
    bit-identical kernels, the 6 x 6 algebra by numpy's LAPACK)."""
    y, logdet_y = _prior_information_numpy(p_prior) if prior_info is None else prior_info
    x = x_prior.copy()
    lo, hi = _box(x, floor, building, config.z_margin_m)
    wb = 1.0 / config.box_sigma_m**2
    z_nom, wh, h_const = _height_prior(x, floor, building, config, level)
    for it in range(config.gn_iterations + 1):
        model, jm, w = _model(x[..., :3], links, floor, sel, building)
        # information matrix, residuals (links, box: 0 inside it, height) and the position
        # gradient in one compiled pass
        a, e, eb, eh, gpart = _iekf_terms(y, x, lo, hi, z_nom, links.rho, model, jm, w, wb, wh)
        if it == config.gn_iterations:
            break
        g = -np.einsum("nhij,nhj->nhi", y, x - x_prior)
        g[..., :3] += gpart
        g[..., 2] += wh * eh
        x = x + np.linalg.solve(a, g[..., None])[..., 0]
    p = np.linalg.inv(a)
    p = 0.5 * (p + np.swapaxes(p, -1, -2))
    d = x - x_prior
    quad = (np.einsum("nhi,nhij,nhj->nh", d, y, d) + np.sum(w * e * e, axis=-1)
            + wb * np.sum(eb * eb, axis=-1) + wh * eh * eh)
    used = w > 0
    norm = np.sum(np.where(used, 0.5 * (np.log(np.where(used, w, 1.0)) - _LOG2PI), 0.0), axis=-1)
    logdet = np.linalg.slogdet(a)[1] - logdet_y
    log_ev = norm + h_const - 0.5 * quad - 0.5 * logdet + np.sum(sel.log_weight, axis=-1)
    residual = np.where(sel.slot >= 0, e, np.nan)
    return x, p, log_ev, residual


def fold_ranges(x_prior: FloatArray, p_prior: FloatArray, rho: FloatArray, length: FloatArray,
                jac: FloatArray, var: FloatArray, at: FloatArray
                ) -> tuple[FloatArray, FloatArray]:
    """The Kalman update of the priors ``x_prior`` (P, 6), ``p_prior`` (P, 6, 6) by the range
    ``rho`` (P, M) of every link whose path length ``length`` (P, M) is finite (NaN: not
    used), linearised at the position ``at`` (P, 3): ``rho = L + J (x - at) + e``, ``J``
    (P, M, 3) the length's Jacobian with respect to the node position, ``e ~ N(0, var)``
    (P, M). The links in turn (exact for a linear model: the joint update), Joseph form.
    Returns the updated means and covariances (new arrays)."""
    x = np.array(x_prior, dtype=np.float64)
    p = np.array(p_prior, dtype=np.float64)
    eye = np.eye(x.shape[-1])
    for m in range(rho.shape[1]):
        use = np.isfinite(length[:, m])
        if not use.any():
            continue
        h = np.zeros(x.shape)
        h[:, :3] = np.where(use[:, None], jac[:, m], 0.0)
        r = np.where(use, var[:, m], 1.0)
        ph = np.einsum("pij,pj->pi", p, h)
        s = np.einsum("pi,pi->p", h, ph) + r
        k = ph / s[:, None]
        pred = np.where(use, length[:, m], 0.0) + np.einsum("pi,pi->p", h[:, :3],
                                                            x[:, :3] - at)
        x = x + k * np.where(use, rho[:, m] - pred, 0.0)[:, None]
        a = eye - k[:, :, None] * h[:, None, :]
        p = (np.einsum("pij,pjk,plk->pil", a, p, a)
             + r[:, None, None] * k[:, :, None] * k[:, None, :])
        p = 0.5 * (p + np.swapaxes(p, -1, -2))
    return x, p


def family_refit(x_prior: FloatArray, p_prior: FloatArray, links: Links, floor, sel: Selection,
                 fam_length: FloatArray, fam_jac: FloatArray, fam_var: FloatArray,
                 at: FloatArray, building, config, level=None):
    """``TrackerConfig.family_fit_links``: the IEKF of the hypotheses (P, 1) with the
    mechanisms ``sel`` (their last selection; the links fitted by a family are outliers
    there, ``slot`` -1) from the prior updated by those links' ranges as the family's path
    (:func:`fold_ranges`: ``fam_length`` (P, M), NaN: no family, ``fam_jac`` (P, M, 3),
    ``fam_var`` (P, M) the range variance plus the families' spread, linearised at the
    clamped prior ``at`` (P, 3)). The family links' log-weights in ``sel`` hold their
    predictive density at the prior (:func:`diffpos.tracking.families.family_log_weight`),
    so the evidence is ``p(family links) p(other links | family links)``: the joint, and the
    posterior keeps the family links' information. Returns x (clamped to the floor's box),
    P, log-evidence, residual as :func:`measurement_update`."""
    xf, pf = fold_ranges(x_prior[:, 0], p_prior[:, 0], links.rho[:, 0], fam_length, fam_jac,
                         fam_var, at)
    x, p, log_ev, res = iekf(xf[:, None], pf[:, None], links, floor, sel, building, config,
                             level)
    return _clamped(x, floor, building, config), p, log_ev, res


def existence_margin(cov: FloatArray, config) -> FloatArray:
    """Every hypothesis' widening of the window band at the entry point [m], (N, H), from its
    own position covariance ``cov`` (N, H, >=3, >=3): ``max(exist_margin_m, ENTRY_SIGMAS *
    sigma_z)``.

    A specular path enters through the window band at the height where the straight line from
    the anchor to the (mirrored) node crosses the facade; moving the node by ``dz`` moves that
    entry point by ``t dz`` with ``t`` < 1 the fraction of the unfolded ray outside the
    building. So a hypothesis whose height is uncertain by ``sigma_z`` has its entry points
    uncertain by up to ``sigma_z``: a mechanism whose entry lies within ``ENTRY_SIGMAS``
    standard deviations of the band may exist (95 % for a Gaussian height) and is a candidate
    (its SNR scored at the nearest height where it exists). The fixed ``exist_margin_m`` stays
    the floor of the margin (a level track's height is known to a few cm, the entry point
    also moves with the horizontal position).
    """
    sz = np.sqrt(np.maximum(cov[..., 2, 2], 0.0))
    return np.maximum(config.exist_margin_m, ENTRY_SIGMAS * sz)


def _paths_at(pe0: PathEval, nodes, pos: FloatArray, links: Links, floor, building,
              relax_m) -> PathEval:
    """``pe0`` (the paths of every hypothesis at another position) with the rows of the nodes
    ``nodes`` evaluated at ``pos``: equal to ``all_paths(pos, ...)`` when the other nodes'
    positions are ``pos`` (every row is computed on its own), at the cost of those nodes.
    ``pe0``'s arrays are overwritten in place and returned (the caller's own, not read after:
    a copy of the (N, H, M, K, 3) Jacobians per update cost more than the moved rows)."""
    if nodes.size == 0:
        return pe0
    shape = pos.shape[:2]
    sub = all_paths(pos[nodes], links.take(nodes),
                    np.broadcast_to(np.asarray(floor), shape)[nodes], building,
                    _relax(relax_m, shape)[nodes])
    for f in ("length", "jac", "strict", "loose", "sure"):
        getattr(pe0, f)[nodes] = getattr(sub, f)
    return pe0


def measurement_update(x_prior, p_prior, links: Links, floor, building, config, level=None,
                       snr_cache=None, link_w=None, min_margin=None, prev_slot=None):
    """Select mechanisms at the prior, run the IEKF; returns x, P, log_evidence, sel, residual.

    ``level``: the hypotheses' vertical modes (see :func:`iekf`). ``snr_cache``: the
    hypotheses' :class:`~diffpos.tracking.model.SnrCache` (read and updated in place; reuse
    within ``config.snr_reuse_m`` / ``snr_reuse_anchor_m``; both 0: not used, left as it
    is), or None (every SNR predicted). ``link_w``: every link's mixture weights (N, H, M, 2)
    (:func:`link_weights`, the default; the learned ones: :mod:`diffpos.tracking.evidence`).
    A slot's SNR cost is capped at ``config.snr_cost_cap_nats`` (:func:`cap_snr_cost`).
    ``min_margin`` [m] (broadcastable to (N, H)): the existence margins of every selection pass
    at least this wide (``TrackerConfig.edge_retry_margin_m``; None: as they are).
    ``prev_slot`` (N, H, M): the hypotheses' previous mechanisms (:func:`select`).

    The IEKF reads the selection only through ``slot``, ``extra_var`` and ``log_weight``, so a
    later pass could keep the previous pass' IEKF output for the hypotheses whose three are
    the same bit for bit. Measured (2026-11-27, ``select_passes`` 2): they almost never are
    (the fit moves every path length, so the mixture's spread and log-weights): on 250 calls
    captured from the 16 x 200 soak's schedule 4,313 of 115,215 pairs (3.7 %; the same slots
    43.5 %), on the ``large`` replay 1,929 of 38,820 (5.0 %; slots 61.6 %): not done. The
    inputs of the IEKF and of the selection that depend on neither the paths nor the
    selection are made once for all passes (:func:`_iekf_fixed`, :func:`_select_fixed`)."""
    x = x_prior
    # the SNR of every slot at the prior (a path's strength changes little over the fit);
    # the paths at the prior serve the SNR term and the first selection (the same point
    # unless the prediction left its floor's box): ``xc`` the prior clamped into its box,
    # ``moved`` the nodes with a hypothesis whose prior is outside it (or not finite).
    # The existence margin follows every hypothesis' own height uncertainty (a track on the
    # stairs with a loose height does not call a mechanism impossible that exists a few
    # decimetres away); at initialisation (``level`` None) the prior is the grid search's box,
    # not the uncertainty of a tracked point: the fixed margin there. The prior information
    # and the IEKF's inputs that depend on neither the paths nor the selection are shared by
    # the passes. All of it in one compiled pass (:func:`_update_fixed`).
    xc, moved, relax, info, fix_i = _update_fixed(x_prior, p_prior, links, floor, building,
                                                  config, level)
    if min_margin is not None:
        relax = np.maximum(relax, min_margin)
    pe0 = all_paths(xc, links, floor, building, relax)
    snr_c = snr_term(xc, links, floor, building, relax, pe0, config, snr_cache)
    fix_s = _select_fixed(p_prior[..., :3, :3], links, config, snr_c, *x_prior.shape[:2],
                          link_w)
    p = p_prior
    for k in range(config.select_passes):  # later passes: mechanisms re-selected at the fit
        if k > 0:  # at the fit: the margin of the fit's own uncertainty
            relax = existence_margin(p, config)
            if min_margin is not None:
                relax = np.maximum(relax, min_margin)
        if k == 0:  # the prior's paths: only the moved nodes' evaluated once more (into pe0)
            pe = _paths_at(pe0, moved, x[..., :3], links, floor, building, relax)
        else:
            pe = all_paths(x[..., :3], links, floor, building, relax)
        sel = select(p_prior[..., :3, :3], links, pe, config, snr_c, fix_s, prev_slot)
        x, p, log_ev, res = iekf(x_prior, p_prior, links, floor, sel, building, config,
                                 level, info, fix_i)
    return _clamped(x, floor, building, config), p, log_ev, sel, res


def _clamped(x: FloatArray, floor, building, config) -> FloatArray:
    """The states ``x`` (P, H, 6) clamped to their floors' boxes (compiled
    :func:`~diffpos.tracking.state.clamp_to_floor`, bit for bit; a new array)."""
    xo = np.empty(x.shape)
    clamp_kernel(_c(x, dtype=np.float64), _cb(floor, x.shape[:2], np.float64),
                 _floor_box(building, config.z_margin_m), xo)
    return xo


def snapshot(links: Links, floors: NDArray, building, config, starts: int | None = None,
             passes: int = 2):
    """Snapshot fit of every listed floor per node (grid, then the IEKF from the best cells).

    ``floors`` (N, Fs). Returns ``(x, P, log_evidence, sel, residual)`` of the best start per
    node and floor: (N, Fs, 6), (N, Fs, 6, 6), (N, Fs), the selection and residuals (N, Fs, M).
    ``starts``: the grid's best cells fitted (None: ``config.init_starts``); ``passes``: the
    measurement updates from each (the second re-selects the mechanisms at the first's fit).
    """
    n, nf = floors.shape
    ns = config.init_starts if starts is None else int(starts)
    if ns != config.init_starts:
        config = replace(config, init_starts=ns)
    x = np.zeros((n, nf * ns, 6))
    x[..., :3] = grid_starts(links, floors, building, config)
    fl = np.repeat(floors, ns, axis=1)
    g, v = config.init_grid_m, config.init_sigma_v_m_s
    p0 = np.diag([g * g, g * g, (building.floor_height_m / 4) ** 2, v * v, v * v,
                  (config.v_stairs_m_s / 2) ** 2])
    p0 = np.broadcast_to(p0, (n, nf * ns, 6, 6))
    for _ in range(passes):  # second pass: mechanisms re-selected at the first's estimate
        x, p, ev, sel, res = measurement_update(x, p0, links, fl, building, config)
    ev = np.where(np.isfinite(ev), ev, -1e300).reshape(n, nf, ns)
    best = np.argmax(ev, axis=-1)  # (N, Fs)
    idx = (np.arange(n)[:, None], np.arange(nf)[None, :] * ns + best)
    lev = np.take_along_axis(ev, best[..., None], axis=-1)[..., 0]
    sel_best = Selection(slot=sel.slot[idx], log_weight=sel.log_weight[idx], nis=sel.nis[idx],
                         extra_var=sel.extra_var[idx])
    return x[idx], p[idx], lev, sel_best, res[idx]


def snapshot_init(links: Links, building, config):
    """Snapshot initialisation of every floor hypothesis: :func:`snapshot` over all floors,
    the floor log-probabilities normalised from the evidences."""
    n, nf = links.rho.shape[0], building.n_floors
    x, p, lev, sel, res = snapshot(links, np.broadcast_to(np.arange(nf), (n, nf)), building,
                                   config)
    lp = lev - lev.max(axis=1, keepdims=True)
    lp = lp - np.log(np.exp(lp).sum(axis=1, keepdims=True))
    return x, p, lp, sel, res
