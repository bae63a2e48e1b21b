"""Learned per-link evidence of the tracker: an unmodelled-path component whose weight and
excess delay every hypothesis learns per link (``TrackerConfig.link_learn``).

Why. The link likelihood of :func:`diffpos.tracking.model.select` is a max-mixture over the
path model's mechanisms and a fixed outlier component (``outlier_weight`` 0.02, uniform over
``outlier_span_m`` 30 m and over ``SNR_SPAN_DB`` 60 dB: -11.4 nats). On a channel the path
model does not cover (Sionna RT, the paper building, depth 4: a ceiling-floor-ceiling triple
bounce or a lower-edge diffraction with two slab bounces as a link's first arrival) the true
floor pays that price on the link every epoch, while a floor one to three below explains the
same range by one of its own mechanisms for 5-6 nats: a static responder loses ~6 nats per
epoch and the wrong floor wins for good (measured: of the 176 receivers with three anchors or
more, 95 % right with every first arrival in the model, 55 % with one out-of-model link, 10 %
with two; ``benchmarks/bench_tracker_raytrace.py``). The multipath-positioning literature
tracks per-link excess-delay (NLOS bias) states; this is that idea in the tracker's
hypothesis bank.

What. For every hypothesis ``h`` of a node and every link ``l`` (an anchor, recognised from
epoch to epoch by its reported position: :func:`match_links`, so the anchor columns of an
update may change), the hypothesis keeps
* exponentially forgotten counts of its real updates in which the link was present
  (``link_all``) and in which its selection called it an outlier (``link_out``), forgetting
  factor ``link_forget`` per update. The outlier weight is the Beta-Bernoulli posterior mean
  ``eps = (e0 S + out) / (S + all)`` (prior mean ``e0 = outlier_weight``, prior strength
  ``S = link_prior_updates``), bounded to ``[outlier_weight, link_outlier_max]``: the link's
  inlier weight is ``log(1 - eps)`` and its outlier component's is ``log eps``.
* the link's excess delay over the straight line while it is an outlier: a scalar Kalman
  filter (``link_bias``, ``link_bias_var``; a random walk of ``link_bias_q_m2_s``: the
  excess of a bounced path changes as the node walks) and the outlier's mean SNR
  (``link_snr``). The outlier component is then a mixture of the fresh outlier (uniform as
  before) and the learned one: ``N(rho - |a - x|; b, v_b + q dt + R + j P j^T)`` times
  ``N(snr; s, SNR_SIGMA_DB^2)``, weighted ``c = out / (out + 1)`` (how established the bias
  is). A link that stays out of the model for a hypothesis thus costs it the outlier price
  once; after that its predictive density is as sharp as an inlier's, so an out-of-model
  link on the true floor no longer hands the floor to a mirror that explains it, and the
  floor is decided by the links that the model explains.

The learned outlier carries no position information (the IEKF does not use an outlier link:
the position is not pulled by a bias it estimated itself). Every rule is a function of the
node's own inputs and state, deterministic, independent of the batching. A node's learned
state restarts with its snapshot initialisation.
"""

from __future__ import annotations

from math import erfc, lgamma, sqrt

import numpy as np
from numpy.typing import NDArray

from diffpos.tracking.evidence_nb import (
    doubt_dist_kernel,
    eps_kernel,
    learn_counts_kernel,
    match_links_kernel,
)
from diffpos.tracking.state import FloatArray

__all__ = ["LEND_OUTLIER_EPS", "LINK_FIELDS", "LINK_SLOTS", "count_unexplained",
           "fewer_outliers", "learn", "learned_weights", "match_links", "model_doubt",
           "model_unexplained_rate", "node_weights", "posterior_weights", "reset_links",
           "unexplained_log_odds"]

# per node whose learned evidence the state keeps (an anchor beyond it is not learned).
LINK_SLOTS = 16
_LOG2PI = float(np.log(2.0 * np.pi))
#: The state's per-hypothesis learned arrays (n, H, L) (:class:`~diffpos.tracking.state.TrackerState`).
LINK_FIELDS = ("link_out", "link_all", "link_ev", "link_bias", "link_bias_var", "link_snr",
               "link_t_ns", "link_fit")
#: A learned outlier weight above which a hypothesis counts the link as one it has learned to
#: call an outlier (:func:`fewer_outliers`; five times the prior weight 0.02; wt-eps-29's donor
#: census used the same threshold).
LEND_OUTLIER_EPS = 0.1


def match_links(table: FloatArray, seen_ns: NDArray[np.int64], anchors: FloatArray,
                mask: NDArray[np.bool_], t_ns: NDArray[np.int64], tol_m: float
                ) -> tuple[NDArray[np.int_], FloatArray, NDArray[np.int64], NDArray[np.bool_]]:
    """The learned link of every present anchor column.

    ``table`` (n, L, 3): every learned link's anchor position (NaN: free), ``seen_ns`` (n, L)
    when it was last seen; ``anchors`` (n, M, 3), ``mask`` (n, M) this update's. A column takes
    the nearest link within ``tol_m`` of its anchor not taken by an earlier column; else a
    free link, else the least recently seen one not taken (restarted). Returns the link of
    every column (n, M) (-1: none), the new table and times and which links restarted (n, L).
    Compiled (:func:`diffpos.tracking.evidence_nb.match_links_kernel`; the distances numpy's),
    bit-identical to :func:`_match_links_numpy`.
    """
    n, m = mask.shape
    tab = np.array(table, dtype=np.float64)
    seen = np.array(seen_ns, dtype=np.int64)
    anc = np.ascontiguousarray(anchors, dtype=np.float64)
    d = _distances(tab, anc)  # (n, M, L)
    col = np.empty((n, m), np.int64)
    reset = np.empty(seen.shape, np.bool_)
    match_links_kernel(d, np.ascontiguousarray(mask, dtype=np.bool_), anc, float(tol_m),
                       np.ascontiguousarray(t_ns, dtype=np.int64), tab, seen, col, reset)
    return col, tab, seen, reset


def _distances(tab: FloatArray, anc: FloatArray) -> FloatArray:
    """``np.sqrt(np.sum((tab[:, None] - anc[:, :, None]) ** 2, axis=-1))`` (n, M, L) of the
    links ``tab`` (n, L, 3) and the columns' anchors ``anc`` (n, M, 3), bit for bit: numpy's
    sum over a last axis of three is ``(d0^2 + d1^2) + d2^2`` (``x ** 2`` is ``x * x``), here
    on one coordinate plane at a time (~0.25x the CPU of the (n, M, L, 3) temporaries)."""
    t, a = np.moveaxis(tab, -1, 0), np.moveaxis(anc, -1, 0)
    d0, d1, d2 = (t[i][:, None] - a[i][:, :, None] for i in range(3))
    with np.errstate(invalid="ignore"):
        return np.sqrt((d0 * d0 + d1 * d1) + d2 * d2)


def _match_links_numpy(table: FloatArray, seen_ns: NDArray[np.int64], anchors: FloatArray,
                       mask: NDArray[np.bool_], t_ns: NDArray[np.int64], tol_m: float
                       ) -> tuple[NDArray[np.int_], FloatArray, NDArray[np.int64],
                                  NDArray[np.bool_]]:
    """The reference of :func:`match_links` (numpy, column by column): the same outputs bit
    for bit (tested). The learned link of every present anchor column.

    ``table`` (n, L, 3): every learned link's anchor position (NaN: free), ``seen_ns`` (n, L)
    when it was last seen; ``anchors`` (n, M, 3), ``mask`` (n, M) this update's. A column takes
    the nearest link within ``tol_m`` of its anchor not taken by an earlier column; else a
    free link, else the least recently seen one not taken (restarted). Returns the link of
    every column (n, M) (-1: none), the new table and times and which links restarted (n, L).
    """
    n, m = mask.shape
    nl = table.shape[1]
    tab, seen = table.copy(), seen_ns.copy()
    col = np.full((n, m), -1)
    taken = np.zeros((n, nl), bool)
    reset = np.zeros((n, nl), bool)
    rows = np.arange(n)
    for j in range(m):
        a = anchors[:, j]
        with np.errstate(invalid="ignore"):
            d = np.sqrt(np.sum((tab - a[:, None]) ** 2, axis=-1))
        d = np.where(np.isfinite(d) & ~taken, d, np.inf)
        near = np.argmin(d, axis=1)
        hit = mask[:, j] & (d[rows, near] <= tol_m)
        free = np.isnan(tab[..., 0]) & ~taken
        age = np.where(taken, np.iinfo(np.int64).max, seen)
        alloc = np.where(free.any(axis=1), np.argmax(free, axis=1), np.argmin(age, axis=1))
        new = mask[:, j] & ~hit & ~taken[rows, alloc]
        li = np.where(hit, near, alloc)
        use = hit | new
        col[use, j] = li[use]
        reset[rows[new], li[new]] = True
        taken[rows[use], li[use]] = True
        tab[rows[use], li[use]] = a[use]
        seen[rows[use], li[use]] = t_ns[use]
    return col, tab, seen, reset


def _gather(a: FloatArray, col: NDArray[np.int_]) -> FloatArray:
    """``a`` (n, H, L) at every column's link (n, H, M); NaN where a column has none.

    One flat index into ``a`` (row ``(i, h)`` starts at ``(i H + h) L``): the elements
    ``np.take_along_axis(a, col, axis=2)`` picks, without its index building (~0.5x the CPU
    on the tracker's arrays; :func:`_gather_numpy` is the reference, tested equal)."""
    n, h, n_l = a.shape
    start = (np.arange(n * h) * n_l).reshape(n, h, 1)
    picked = np.ravel(a)[start + np.maximum(col, 0)[:, None, :]]
    return np.where(col[:, None, :] >= 0, picked, np.nan)


def _gather_numpy(a: FloatArray, col: NDArray[np.int_]) -> FloatArray:
    """The reference of :func:`_gather` (``np.take_along_axis``)."""
    idx = np.broadcast_to(np.maximum(col, 0)[:, None, :], (a.shape[0], a.shape[1], col.shape[1]))
    return np.where(col[:, None, :] >= 0, np.take_along_axis(a, idx, axis=2), np.nan)


def _los(x: FloatArray, p: FloatArray, links) -> tuple[FloatArray, FloatArray]:
    """Straight-line length (n, H, M) from every hypothesis' position to every anchor and its
    variance ``j P j^T`` from the position covariance."""
    d = x[:, :, None, :3] - links.anchors[:, 0][:, None, :, :]
    los = np.sqrt(np.sum(d * d, axis=-1))
    j = d / np.maximum(los, 1e-12)[..., None]
    var = np.einsum("nhmi,nhij,nhmj->nhm", j, p[..., :3, :3], j)
    return los, np.maximum(var, 0.0)


def _eps(out: FloatArray, n_all: FloatArray, config) -> FloatArray:
    e0, s = config.outlier_weight, config.link_prior_updates
    eps = (e0 * s + np.nan_to_num(out)) / (s + np.nan_to_num(n_all))
    return np.clip(eps, e0, max(config.link_outlier_max, e0))


def _link_eps(out: FloatArray, n_all: FloatArray, col: NDArray[np.int_], config) -> FloatArray:
    """Every column's learned outlier weight (n, H, M) from the counts ``out``, ``n_all``
    (n, H, L) at its link ``col`` (n, M): compiled
    (:func:`diffpos.tracking.evidence_nb.eps_kernel`), bit-identical to
    :func:`_link_eps_numpy`."""
    e0 = float(config.outlier_weight)
    eps = np.empty((*out.shape[:2], col.shape[1]))
    eps_kernel(np.ascontiguousarray(out, dtype=np.float64),
               np.ascontiguousarray(n_all, dtype=np.float64),
               np.ascontiguousarray(col, dtype=np.int64), e0, float(config.link_prior_updates),
               float(max(config.link_outlier_max, e0)), eps)
    return eps


def _link_eps_numpy(out: FloatArray, n_all: FloatArray, col: NDArray[np.int_],
                    config) -> FloatArray:
    """The reference of :func:`_link_eps`."""
    return _eps(_gather(out, col), _gather(n_all, col), config)


def learned_weights(lk: dict, col: NDArray[np.int_], x: FloatArray, p: FloatArray,
                    links, t_ns: NDArray[np.int64], config, snr_sigma_db: float,
                    snr_span_db: float, closed: NDArray[np.bool_] | None = None) -> FloatArray:
    """Every link's mixture weights (n, H, M, 2) (inlier ``log(1 - eps)``, outlier
    log-density; :func:`diffpos.tracking.model.link_weights` without learning) at the
    hypotheses' priors ``x`` (n, H, 6), ``p`` (n, H, 6, 6): module docstring. ``lk``: the
    nodes' learned arrays (``link_out``, ``link_all``, ``link_bias``, ``link_bias_var``,
    ``link_snr``, ``link_t_ns``: (n, H, L)); ``col``: :func:`match_links`'s links; ``links``:
    the epoch's :class:`diffpos.tracking.links.Links`; the SNR's spread and span [dB]
    (:data:`diffpos.tracking.model.SNR_SIGMA_DB`, ``SNR_SPAN_DB``). ``closed`` (n,): the
    nodes whose links keep the prior weight ``outlier_weight`` and no learned excess delay
    (``TrackerConfig.link_learn_unexplained``; None: none)."""
    eps = _link_eps(lk["link_out"], lk["link_all"], col, config)
    if closed is not None:
        eps[closed] = config.outlier_weight
    w = np.empty((*col.shape[:1], x.shape[1], col.shape[1], 2))
    w[..., 0] = np.log1p(-eps)
    if not config.link_bias_learn:  # the learned weight, the fixed uniform density
        s_out = (np.where(np.isfinite(links.snr[:, 0]), -np.log(snr_span_db), 0.0)
                 if links.snr is not None else np.zeros(col.shape))
        w[..., 1] = np.log(eps) + (-np.log(config.outlier_span_m) + s_out)[:, None, :]
        return w
    snr = links.snr[:, 0][:, None, :] if links.snr is not None else None
    known = np.zeros(col.shape, bool)[:, None, :] if snr is None else np.isfinite(snr)
    fresh = -np.log(config.outlier_span_m) + np.where(known, -np.log(snr_span_db), 0.0)
    bias, bvar = _gather(lk["link_bias"], col), _gather(lk["link_bias_var"], col)
    dt = np.maximum((t_ns[:, None, None] - _gather(lk["link_t_ns"].astype(float), col)) * 1e-9,
                    0.0)
    los, lvar = _los(x, p, links)
    s = bvar + config.link_bias_q_m2_s * dt + links.var[:, 0][:, None, :] + lvar
    e = links.rho[:, 0][:, None, :] - los
    with np.errstate(invalid="ignore"):
        ll = -0.5 * ((e - bias) ** 2 / s + np.log(s) + _LOG2PI)
        if snr is not None:
            s_mean = _gather(lk["link_snr"], col)
            ll_s = np.where(np.isfinite(s_mean),
                            -0.5 * (((snr - s_mean) / snr_sigma_db) ** 2 + _LOG2PI)
                            - np.log(snr_sigma_db), -np.log(snr_span_db))
            ll = ll + np.where(known, ll_s, 0.0)
    o = np.nan_to_num(_gather(lk["link_out"], col))
    if closed is not None:
        o[closed] = 0.0
    c = o / (o + 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        learned = np.where(np.isfinite(ll) & (c > 0) & config.link_bias_learn,
                           np.log(c) + ll, -np.inf)
        w[..., 1] = np.log(eps) + np.logaddexp(np.log1p(-c) + fresh, learned)
    return w


def node_weights(w: FloatArray, use: NDArray[np.bool_] | None = None) -> FloatArray:
    """The links' mixture weights ``w`` (n, H, M, 2) (:func:`learned_weights`) with every
    hypothesis of a node given the node's outlier weight of each link
    (``TrackerConfig.link_eps_node``): ``e`` = the largest ``eps = 1 - exp(w[..., 0])`` over
    the node's hypotheses ``use`` (n, H) (None, or a node with none: all of them); the inlier
    weight becomes ``log(1 - e)``, the outlier component's ``log eps`` becomes ``log e`` (its
    densities, fresh and learned, unchanged). A new array."""
    eps = -np.expm1(w[..., 0])
    pick = eps
    if use is not None:
        u = np.where(np.any(use, axis=1, keepdims=True), use, True)
        pick = np.where(u[..., None], eps, 0.0)
    e = np.broadcast_to(np.max(pick, axis=1, keepdims=True), eps.shape)
    out = np.empty(w.shape)
    out[..., 0] = np.log1p(-e)
    out[..., 1] = w[..., 1] - np.log(eps) + np.log(e)
    return out


def posterior_weights(w: FloatArray, log_prob: FloatArray,
                      use: NDArray[np.bool_] | None = None) -> FloatArray:
    """The links' mixture weights ``w`` (n, H, M, 2) (:func:`learned_weights`) with every
    hypothesis' outlier component at the larger of its own ``eps_h = 1 - exp(w[..., 0])`` and
    the node's posterior mean ``sum_k p_k eps_k`` over its hypotheses, ``p`` the normalised
    ``exp(log_prob)`` (n, H), at the nodes ``use`` (n,) (None: all;
    ``TrackerConfig.link_eps_posterior``; or (n, H): the hypotheses that borrow,
    :func:`lend_borrowers`): the outlier component's ``log eps_h`` becomes
    ``log max(eps_h, mean)``, the inlier weight and the densities unchanged. A new array."""
    eps = -np.expm1(w[..., 0])
    p = np.exp(log_prob - np.max(log_prob, axis=1, keepdims=True))
    p /= np.sum(p, axis=1, keepdims=True)
    e = np.maximum(eps, np.einsum("nh,nhm->nm", p, eps)[:, None, :])
    if use is not None:
        e = np.where((use if use.ndim == 2 else use[:, None])[..., None], e, eps)
    out = w.copy()
    out[..., 1] += np.log(e) - np.log(eps)
    return out


def fewer_outliers(w: FloatArray, log_prob: FloatArray, present: NDArray[np.bool_]
                   ) -> NDArray[np.bool_]:
    """The hypotheses (n, H) that have learned fewer of their node's present links
    ``present`` (n, M) as outliers (``eps = 1 - exp(w[..., 0]) > LEND_OUTLIER_EPS``, ``w``
    (n, H, M, 2): :func:`learned_weights`) than the node's most probable hypothesis (the
    largest ``log_prob`` (n, H)); ``TrackerConfig.link_eps_lend_fewer``."""
    eps = -np.expm1(w[..., 0])
    n_out = np.sum((eps > LEND_OUTLIER_EPS) & present[:, None, :], axis=2)
    top = np.argmax(log_prob, axis=1)
    return n_out < n_out[np.arange(top.size), top][:, None]


def learn(lk: dict, col: NDArray[np.int_], run: NDArray[np.bool_], x: FloatArray,
          p: FloatArray, slot: NDArray[np.int_], links, t_ns: NDArray[np.int64],
          config, ev_link: FloatArray | None = None, nis: FloatArray | None = None,
          learn_run: NDArray[np.bool_] | None = None) -> dict:
    """The learned arrays after one update (new arrays): the hypotheses ``run`` (n, H) that had
    a real update, at their posteriors ``x``, ``p``, with their selections ``slot``
    (n, H, M; -1 outlier or absent); module docstring. ``ev_link`` (n, H, M) [nats]: every
    link's share of the hypothesis' log-evidence in this update (its forgotten sum is
    ``link_ev``, :func:`diffpos.tracking.state.robust_floor_log_prob`); None: 0. ``nis``
    (n, H, M): every link's NIS in this update (NaN: outlier or absent), kept as ``link_fit``
    (:func:`last_fit`); None: ``link_fit`` unchanged. ``learn_run`` (n, H): the hypotheses
    of ``run`` whose counts, evidence shares and excess delays learn from this update
    (``TrackerConfig.link_learn_minority``; None: all of ``run``); ``link_fit`` is that of
    every hypothesis of ``run``."""
    new = _learn(lk, col, run if learn_run is None else run & learn_run, x, p, slot, links,
                 t_ns, config, ev_link)
    if nis is not None and "link_fit" in new:
        new["link_fit"] = last_fit(new["link_fit"], col, run, links.mask[:, 0], nis)
    return new


def last_fit(fit: FloatArray, col: NDArray[np.int_], run: NDArray[np.bool_],
             mask: NDArray[np.bool_], nis: FloatArray) -> FloatArray:
    """``fit`` (n, H, L) (in place, returned) with every present link of the hypotheses ``run``
    (n, H) set to its NIS ``nis`` (n, H, M) of this update (inf where NaN: an outlier)."""
    present = mask[:, None, :] & run[:, :, None] & (col[:, None, :] >= 0)
    r, c, j = np.nonzero(present)
    v = nis[r, c, j]
    fit[r, c, col[r, j]] = np.where(np.isnan(v), np.inf, v)
    return fit


def _learn(lk: dict, col: NDArray[np.int_], run: NDArray[np.bool_], x: FloatArray,
           p: FloatArray, slot: NDArray[np.int_], links, t_ns: NDArray[np.int64],
           config, ev_link: FloatArray | None = None) -> dict:
    """:func:`learn` but ``link_fit``."""
    if ev_link is None:
        ev_link = np.zeros(slot.shape)
    n, h = run.shape
    m = col.shape[1]
    new = {k: v.copy() for k, v in lk.items()}
    f = config.link_forget
    if not config.link_bias_learn:  # the counts only (a node's columns: distinct links)
        learn_counts_kernel(np.ascontiguousarray(links.mask[:, 0], dtype=np.bool_),
                            np.ascontiguousarray(run, dtype=np.bool_),
                            np.ascontiguousarray(col, dtype=np.int64),
                            np.ascontiguousarray(slot, dtype=np.int64),
                            np.ascontiguousarray(ev_link, dtype=np.float64), float(f),
                            new["link_out"], new["link_all"], new["link_ev"])
        return new
    present = links.mask[:, 0][:, None, :] & run[:, :, None] & (col[:, None, :] >= 0)
    is_out = present & (slot < 0)
    los, lvar = _los(x, p, links)
    var = links.var[:, 0][:, None, :] + lvar
    e = np.maximum(links.rho[:, 0][:, None, :] - los, 0.0)
    snr = None if links.snr is None else np.broadcast_to(links.snr[:, 0][:, None, :], (n, h, m))
    nn, hh = np.meshgrid(np.arange(n), np.arange(h), indexing="ij")
    for j in range(m):  # a node's columns hold distinct links (match_links)
        pj = present[:, :, j]
        if not pj.any():
            continue
        r, c = nn[pj], hh[pj]
        li = np.broadcast_to(col[:, None, j], (n, h))[pj]
        oj = is_out[:, :, j][pj]
        new["link_out"][r, c, li] = f * new["link_out"][r, c, li] + oj
        new["link_all"][r, c, li] = f * new["link_all"][r, c, li] + 1.0
        new["link_ev"][r, c, li] = f * new["link_ev"][r, c, li] + ev_link[:, :, j][pj]
        ro, co, lo = r[oj], c[oj], li[oj]
        if ro.size == 0:
            continue
        ej, vj = e[ro, co, j], var[ro, co, j]
        b0, v0 = new["link_bias"][ro, co, lo], new["link_bias_var"][ro, co, lo]
        dt = np.maximum((t_ns[ro] - new["link_t_ns"][ro, co, lo]) * 1e-9, 0.0)
        had = np.isfinite(v0) & np.isfinite(b0)
        vp = np.where(had, v0, 0.0) + config.link_bias_q_m2_s * dt
        k = vp / (vp + vj)
        b0 = np.where(had, b0, 0.0)
        new["link_bias"][ro, co, lo] = np.where(had, b0 + k * (ej - b0), ej)
        new["link_bias_var"][ro, co, lo] = np.where(had, (1.0 - k) * vp, vj)
        new["link_t_ns"][ro, co, lo] = t_ns[ro]
        if snr is not None:
            sj, s0 = snr[ro, co, j], new["link_snr"][ro, co, lo]
            upd = np.where(np.isfinite(s0), s0 + config.link_snr_gain * (sj - s0), sj)
            new["link_snr"][ro, co, lo] = np.where(np.isfinite(sj), upd, s0)
    return new


def _learn_counts_numpy(new: dict, mask: NDArray[np.bool_], run: NDArray[np.bool_],
                       col: NDArray[np.int_], slot: NDArray[np.int_], ev_link: FloatArray,
                       f: float) -> None:
    """The reference of :func:`diffpos.tracking.evidence_nb.learn_counts_kernel` (``new``'s
    ``link_out``, ``link_all``, ``link_ev`` in place)."""
    present = mask[:, None, :] & run[:, :, None] & (col[:, None, :] >= 0)
    is_out = present & (slot < 0)
    r, c, j = np.nonzero(present)
    li = col[r, j]
    new["link_out"][r, c, li] = f * new["link_out"][r, c, li] + is_out[r, c, j]
    new["link_all"][r, c, li] = f * new["link_all"][r, c, li] + 1.0
    new["link_ev"][r, c, li] = f * new["link_ev"][r, c, li] + ev_link[r, c, j]


def reset_links(lk: dict, rows: NDArray, links_reset: NDArray[np.bool_] | None = None) -> None:
    """Forget (in place) what the nodes ``rows`` learned: every link of theirs, or with
    ``links_reset`` (len(rows), L) the links marked there (a new anchor took the link)."""
    if links_reset is not None and not links_reset.any():  # the usual update: nothing new
        return
    sel = (np.ones((rows.size, lk["link_out"].shape[2]), bool) if links_reset is None
           else links_reset)
    for k, v in lk.items():
        fill = 0 if k in ("link_out", "link_all", "link_ev", "link_t_ns") else np.nan
        sub = v[rows]
        sub[np.broadcast_to(sel[:, None, :], sub.shape)] = fill
        v[rows] = sub


def model_doubt(log_prob: FloatArray, link_out: FloatArray, link_all: FloatArray,
                config, n_links: NDArray | None = None, prob: FloatArray | None = None
                ) -> FloatArray:
    """Probability (N,) that a node's floor evidence rests on first arrivals its path model
    does not explain, by the node's own most probable hypothesis
    (``TrackerConfig.floor_model_doubt``; the published floor probabilities are mixed towards
    uniform by it: :func:`diffpos.tracking.state.published_floor_probabilities`).

    The best hypothesis (over the vertical modes) of the most probable floor has learned every
    link's outlier weight ``eps_l`` (module docstring: the Beta-Bernoulli mean, prior mean
    ``e0 = outlier_weight``); ``q_l = 1 - (1 - eps_l) / (1 - e0)`` is the probability that
    link ``l`` is out of the model beyond the prior rate the filter's evidence already assumes
    (0 for a link explained as the prior expects or never seen). The doubt is the probability
    that at least ``r = max(n_links - 3, 1)`` links are out of the model (independent links,
    the Poisson-binomial tail; ``n_links`` (N,) the node's ranges this epoch, None: ``r = 1``):
    three ranges fix a position on any floor, so the floor is tested by the ranges beyond
    three, and it is at risk once no in-model range is left beyond them. Why: the floor
    evidence is a likelihood ratio under the path model; an arrival the model cannot explain
    is explained on a mirror floor by one of its own mechanisms (Sionna RT, paper building,
    4 anchors: a receiver with one out-of-model link is on a wrong floor in 88 of 135 cases),
    so the floor evidence is not to be trusted with that probability. A function of the node's
    own state and ranges only. ``prob``: ``exp(log_prob)`` if the caller has it.
    """
    n, h = log_prob.shape
    nf = h // 2
    rows = np.arange(n)
    p = np.exp(log_prob) if prob is None else prob
    pf = p[:, :nf] + p[:, nf:]
    top = np.argmax(pf, axis=1)
    hs = np.where(p[rows, top] >= p[rows, top + nf], top, top + nf)
    nl = link_out.shape[-1]  # every link of the best hypothesis, as one hypothesis' columns
    eps = _link_eps(link_out[rows, hs][:, None], link_all[rows, hs][:, None],
                    np.tile(np.arange(nl), (n, 1)), config)[:, 0]  # writeable: one kernel signature
    q = np.clip(1.0 - (1.0 - eps) / (1.0 - config.outlier_weight), 0.0, 1.0)  # (N, L)
    r = (np.ones(n, int) if n_links is None
         else np.maximum(np.asarray(n_links, int) - 3, 1))
    # distribution of the number of out-of-model links (Poisson-binomial), counts >= r pooled
    nl = q.shape[1]
    dist = np.empty((n, nl + 1))
    doubt_dist_kernel(np.ascontiguousarray(q, dtype=np.float64), dist)
    below = np.arange(nl + 1)[None, :] < r[:, None]
    return np.clip(1.0 - np.sum(np.where(below, dist, 0.0), axis=1), 0.0, 1.0)


def _doubt_dist_numpy(q: FloatArray) -> FloatArray:
    """The reference of :func:`diffpos.tracking.evidence_nb.doubt_dist_kernel`: the
    distribution (n, L + 1) of the number of links out of the model (probabilities ``q``
    (n, L))."""
    n, nl = q.shape
    dist = np.zeros((n, nl + 1))
    dist[:, 0] = 1.0
    for j in range(nl):
        qj = q[:, j:j + 1]
        dist[:, 1:] = dist[:, 1:] * (1.0 - qj) + dist[:, :-1] * qj
        dist[:, 0] *= 1.0 - qj[:, 0]
    return dist


# --------------------------------------------------------------------------------------------
# the track's learned rate of epochs no hypothesis explains (TrackerConfig.family_learned_links)
# --------------------------------------------------------------------------------------------


def count_unexplained(unexplained: FloatArray, redundant: FloatArray, fit: FloatArray,
                      col: NDArray[np.int_], mask: NDArray[np.bool_], n_meas: NDArray[np.int_],
                      config) -> tuple[FloatArray, FloatArray]:
    """The nodes' counts (n,) after one update (new arrays): an epoch with at least four
    ranges (one beyond the three that fit a position exactly on any floor) counts in
    ``redundant``; in ``unexplained`` too when EVERY hypothesis misfits (NIS above
    ``nis_limit``, or an outlier) one of the present links at its last real update
    (``fit`` (n, H, L), the learned ``link_fit`` after this update; ``col`` (n, M), ``mask``
    (n, M) the epoch's links). A hypothesis that has not fitted a present link yet does not
    misfit it. Why every hypothesis: on the path model's own channel the true floor explains
    every range but for the outlier prior and the NIS tail, whichever floor is the most
    probable; a first arrival out of the model is misfit there, and a mirror floor that
    explains it by one of its own mechanisms often misfits another range (the redundant one),
    so the count does not depend on which floor the track believes (a mirror floor that
    explains all four stops the count: the rate is then forgotten). Both counts are forgotten by
    ``link_forget`` per counted epoch."""
    f = config.link_forget
    g = _gather(fit, col)  # (n, H, M), NaN: not fitted / no link
    with np.errstate(invalid="ignore"):
        mis = np.any((g > config.nis_limit) & mask[:, None, :], axis=2)  # (n, H)
    every = np.all(mis, axis=1)
    count = n_meas >= 4
    return (np.where(count, f * unexplained + every, unexplained),
            np.where(count, f * redundant + 1.0, redundant))


def model_unexplained_rate(n_links: NDArray[np.int_], config) -> FloatArray:
    """The rate (n,) at which the path model itself predicts an epoch of ``n_links`` ranges
    with a misfit at the true state: every range an outlier with ``outlier_weight`` or beyond
    ``nis_limit`` by the Gaussian tail, ``1 - (1 - e0 - P(chi2_1 > nis_limit))^n``; an upper
    bound of its rate of epochs that every hypothesis misfits."""
    tail = erfc(sqrt(config.nis_limit / 2.0))
    p_ok = max(1.0 - config.outlier_weight - tail, 0.0)
    return 1.0 - p_ok ** np.asarray(n_links, float)


def unexplained_log_odds(unexplained: FloatArray, redundant: FloatArray,
                         n_links: NDArray[np.int_], config) -> FloatArray:
    """The log Bayes factor (n,) of the nodes' counts (:func:`count_unexplained`) for a channel
    with first arrivals out of the path model against the model's own: ``u`` unexplained of
    ``r`` counted epochs (forgotten counts, Bernoulli trials), the model's rate ``r0``
    (:func:`model_unexplained_rate` at ``n_links``) against an unknown rate with a uniform
    prior, ``ln B(1 + u, 1 + r - u) - u ln r0 - (r - u) ln(1 - r0)``. > 0: the data favour
    the out-of-model channel. Nothing counted: 0 (no evidence either way); one unexplained
    epoch of one favours it (the uniform rate explains it better than ``r0`` does), one of
    four no longer, and with the forgetting's 20 epochs it takes about five (a quarter)."""
    r0 = model_unexplained_rate(n_links, config)
    u = np.asarray(unexplained, float)
    r = np.maximum(np.asarray(redundant, float), u)
    lb = np.array([lgamma(1.0 + a) + lgamma(1.0 + b - a) - lgamma(2.0 + b)
                   for a, b in zip(u.tolist(), r.tolist(), strict=True)]).reshape(u.shape)
    return lb - u * np.log(r0) - (r - u) * np.log1p(-r0)
