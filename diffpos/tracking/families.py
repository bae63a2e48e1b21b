"""Higher-order first-arrival families in the tracker's out-of-model component
(``TrackerConfig.max_order``).

Why. The tracker's path model is the 18 mechanisms of :data:`diffpos.paths.mechanisms.MECHANISMS`
(its compiled kernels evaluate those slots). On a channel we did not write (Sionna RT, paper
building, depth 4) a link's first arrival is often one of the families those 18 leave out (a
ceiling-floor-ceiling triple bounce, a lower-edge diffraction then two slab bounces): the true
floor can only call it an outlier (uniform over ``outlier_span_m``, -3.4 nats and the outlier
weight) while a mirror floor one to three below explains it by one of its own mechanisms, and
the wrong floor wins. :func:`diffpos.paths.mechanisms.mechanism_set` derives those families in
closed form (M-NLS: 60 -> 75.5 % right floor on Sionna paper with ``max_order`` 4).

What. With ``max_order`` > 2 (default 3) the out-of-model component of a link is no longer
uniform alone. ``TrackerConfig.family_weight="mechanism"`` (default): every extra family that
exists at the hypothesis' prior (``loose`` existence with ``exist_margin_m``) is one more
candidate of the link, with a mechanism's prior: the component becomes ``eps / span + (1 - eps)
n_fam / (n_18 + n_fam) f``, ``f`` the mean over the existing families of ``N(rho; L_k, J_k P
J_k^T + R)``, with the outlier's uniform SNR density (no amplitude model for them) -- what
M-NLS does with its ``max_order`` families. ``"one"``: the families together are ONE more
candidate, ``n_fam / (n_18 + n_fam)`` replaced by ``1 / (n_18 + 1)`` (a weaker prior, measured
between the two on Sionna's and the synthetic in-model channels). ``"outlier"`` (before): half of the component
(:data:`FAMILY_SHARE`) is that mixture at the PRIOR outlier weight. The link stays an outlier
for the IEKF (no position information: the position is fitted by the 18 mechanisms, whose
Jacobians and SNR the kernels have), but a floor whose own extra family explains the range no
longer pays the outlier's price for it every epoch.

Which links (``TrackerConfig.family_gate``): ``"misfit"`` (default), those the hypothesis'
last real update called an outlier or fitted with an NIS above ``nis_limit`` (a 3-sigma miss;
``TrackerState.link_fit``), once the hypothesis has had the link in ``family_history`` real
updates (a link not fitted yet is no misfit: before, at a track's start every link offered the
families to every floor), of a node with at least ``family_min_links`` ranges (three ranges
are fitted exactly on any floor, so a family chosen for one of them is tested by nothing);
``"outlier"`` (before), those with a forgotten outlier count above 0.5; and with
``family_minority`` (default) only while a hypothesis' misfits are fewer than half of the
node's ranges (a hypothesis misfitting most of them has a wrong state: offered the families,
its misfits leave its position fit and it does not re-converge). Why the misfits: on Sionna RT's paper building (depth 4)
the true floor mostly did NOT call its out-of-model link an outlier but fitted it with a wrong
mechanism at -7..-9 nats (its mirror floor one to three below: -4..-5.5), so an outlier gate
never offered it the family; a link the 18 explain (NIS <= ``nis_limit``) costs nothing. On a
channel the 18 mechanisms explain, few links are misfits, so the cost stays small: one compiled
pass per gated link over the set's slots (:func:`graded_split`, the values of
:func:`diffpos.paths.model.graded_paths` bit for bit) and numpy for the densities.

Measured (docs/raytrace_study.md section 2c): live paper on Sionna 72.2 -> 79.3 % right floor
on the same recorded inputs, heldout-2 54.2 -> 63.7 % (confidently wrong 1.39 -> 0.46 %),
large 87.5 -> 88.7 % (1.03 -> 0.36 %); the emulator's channel as before (paper 99.5 -> 99.6 %,
large 99.6 %, heldout-2 89.7 -> 96.1 %).
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import NDArray

from diffpos.channel.emulator import pair_family_snr_db, pair_snr_db
from diffpos.paths.graded_nb import graded_split_kernel
from diffpos.paths.mechanisms import DEFAULT_ORDER, MECHANISMS, MechanismSet, mechanism_set
from diffpos.paths.model import graded_paths
from diffpos.paths.model_nb import building_planes, mechanism_table, partition_array
from diffpos.tracking.state import FloatArray, few_ranges

__all__ = ["FAMILY_SHARE", "best_family", "extra_families", "family_log_weight",
           "family_snr_log_lik", "family_terms", "first_arrival_log_prob", "graded_split"]

#: Share of the out-of-model component given to the enumerated extra families (the rest stays
#: uniform over ``outlier_span_m``).
FAMILY_SHARE = 0.5
_LOG2PI = float(np.log(2.0 * np.pi))


@functools.cache
def extra_families(max_order: int) -> tuple[MechanismSet, NDArray[np.int64]] | None:
    """The mechanism set of ``max_order`` and the slots of its families beyond the 18 (None
    for ``max_order`` <= 2: none)."""
    if max_order <= DEFAULT_ORDER:
        return None
    mset = mechanism_set(max_order)
    return mset, np.arange(len(MECHANISMS), len(mset.recipes), dtype=np.int64)


@functools.cache
def _family_table(max_order: int, partitions: bool = False
                  ) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
    """The compiled mechanism table of ``mechanism_set(max_order, partitions=partitions)`` and
    its window-band (specular) slots, as :func:`diffpos.paths.model.graded_paths` tests them."""
    mset = mechanism_set(max_order, partitions=partitions)
    table = mechanism_table(mset.recipes)
    return table, np.isin(np.arange(table.shape[0]), mset.specular)


def graded_split(pos: FloatArray, anchor: FloatArray, floor: NDArray, building, max_order: int,
                 relax_m: float, partitions: bool = False
                 ) -> tuple[NDArray[np.int64], FloatArray, NDArray[np.bool_], FloatArray]:
    """:func:`diffpos.paths.model.graded_paths` of flat rows (``pos``, ``anchor`` (Q, 3),
    ``floor`` (Q,)) with ``max_order``'s mechanism set, reduced to what
    :func:`family_log_lik` reads: ``ok = loose & isfinite(length_m)``; returns the number of
    the 18 mechanisms with ``ok`` (Q,) and the raw length (Q, F), ``ok`` (Q, F) and Jacobian
    (Q, F, 3) of the F extra families (``partitions``: of
    ``mechanism_set(max_order, partitions=True)``; the tracker's are without), bit for bit ``graded_paths``' values (one compiled
    pass, :func:`diffpos.paths.graded_nb.graded_split_kernel`; tests/core/test_paths_split.py).
    Measured on the calls of a 16-anchor replay: 0.67 -> 0.48 s CPU for
    :func:`family_log_lik` (docs/soak.md)."""
    if not relax_m >= 0.0:
        raise ValueError(f"relax_m must be >= 0 [m]; got {relax_m!r}")
    table, band = _family_table(max_order, partitions)
    nb = len(MECHANISMS)
    n = np.require(pos, np.float64, ("C", "W"))
    a = np.require(anchor, np.float64, ("C", "W"))
    fl = np.require(floor, np.float64, ("C", "W"))
    q, f = n.shape[0], table.shape[0] - nb
    n_base = np.empty(q, np.int64)
    length, ok, jac = np.empty((q, f)), np.empty((q, f), np.bool_), np.empty((q, f, 3))
    graded_split_kernel(n, a, fl, *building_planes(building), partition_array(building), table,
                        band, float(relax_m), nb, n_base, length, ok, jac)
    return n_base, length, ok, jac


def family_log_lik(pos: FloatArray, cov: FloatArray, anchor: FloatArray, rho: FloatArray,
                   var: FloatArray, floor: NDArray, building, max_order: int,
                   relax_m: float, radio=None, cap_nats: float = 0.0,
                   snr_sigma_db: float | None = None, snr: tuple | None = None,
                   snr_span_db: float | None = None
                   ) -> tuple[FloatArray, NDArray[np.int_], NDArray[np.int_]]:
    """``log mean_k N(rho; L_k, J_k P J_k^T + var)`` over the extra families (``max_order``)
    that exist (``loose`` at ``relax_m``) for every link (Q,); -inf where none exists; and the
    number of extra families and of the 18 mechanisms that exist (``loose``) there, (Q,)
    each. Flat links: ``pos`` (Q, 3), ``cov`` (Q, 3, 3), ``anchor`` (Q, 3), ``rho``, ``var``,
    ``floor`` (Q,). ``radio`` given: every family's density is weighted by the probability
    that it can be the first arrival there (:func:`first_arrival_log_prob` with the SNR
    model's ``snr_sigma_db``, at least ``-cap_nats``). ``snr`` ``(snr_db (Q,), radio)`` given
    (``TrackerConfig.family_snr``): every family's density is also weighted by
    :func:`family_snr_log_lik` (its SNR likelihood against the outlier's, ``snr_sigma_db``
    and ``cap_nats`` as the 18's, ``snr_span_db`` the outlier's SNR span)."""
    q = rho.shape[0]
    if extra_families(max_order) is None or q == 0:
        return np.full(q, -np.inf), np.zeros(q, np.int64), np.zeros(q, np.int64)
    ll, ok, _, _, n_base = family_terms(pos, cov, anchor, rho, var, floor, building,
                                        max_order, relax_m, radio, cap_nats, snr_sigma_db,
                                        snr, snr_span_db)
    return _mean_density(ll, ok), ok.sum(axis=-1), n_base


def _mean_density(ll: FloatArray, ok: NDArray[np.bool_]) -> FloatArray:
    """``log mean_k exp(ll_k)`` over the existing families ``ok`` (Q, F) of every link (Q,);
    -inf where none exists."""
    n_ok = ok.sum(axis=-1)
    with np.errstate(divide="ignore"):
        top = np.max(ll, axis=-1)
        safe = np.where(np.isfinite(top), top, 0.0)
        tot = safe + np.log(np.sum(np.exp(ll - safe[:, None]), axis=-1))
        return np.where(n_ok > 0, tot - np.log(np.maximum(n_ok, 1)), -np.inf)


def family_terms(pos: FloatArray, cov: FloatArray, anchor: FloatArray, rho: FloatArray,
                 var: FloatArray, floor: NDArray, building, max_order: int,
                 relax_m: float, radio=None, cap_nats: float = 0.0,
                 snr_sigma_db: float | None = None, snr: tuple | None = None,
                 snr_span_db: float | None = None) -> tuple:
    """:func:`family_log_lik`'s terms per extra family (``max_order`` > 2; its arguments):
    ``ll`` (Q, F), every family's log-density ``log N(rho; L_k, J_k P J_k^T + var)`` plus its
    first-arrival and SNR weights (-inf where it does not exist, and with the SNR where it is
    negligible in its link's mixture: :func:`_snr_terms`), ``ok`` (Q, F) where it
    exists, its length ``L_k`` (Q, F) and Jacobian ``J_k`` (Q, F, 3) with respect to the node
    position at ``pos``, and the number of the 18 mechanisms that exist (Q,)."""
    mset, _ = extra_families(max_order)
    nb = len(MECHANISMS)
    if radio is None:  # the extra families' paths only, the 18's existence counted (compiled)
        n_base, length, ok, jac = graded_split(pos, anchor, floor, building, max_order,
                                               relax_m)
    else:  # the first-arrival condition needs the 18's lengths too
        g = graded_paths(pos, anchor, building, relax_m=relax_m, floor=floor, mechanisms=mset)
        ok = g.loose & np.isfinite(g.length_m)
        n_base = ok[:, :nb].sum(axis=-1)
        ok, length, jac = ok[:, nb:], g.length_m[:, nb:], g.jacobian[:, nb:]
    j = np.where(ok[..., None], jac, 0.0)
    s = var[:, None] + np.sum(np.matmul(j, cov) * j, axis=-1)
    with np.errstate(invalid="ignore"):
        e = rho[:, None] - length
        ll = np.where(ok, -0.5 * (e * e / s + np.log(s) + _LOG2PI), -np.inf)
    if radio is not None:
        if snr_sigma_db is None:
            raise ValueError("family_log_lik: the first-arrival condition (a radio given) needs "
                             "snr_sigma_db, the SNR model's spread (tracking.model.SNR_SIGMA_DB)")
        ll = ll + first_arrival_log_prob(pos, anchor, g.length_m, np.sqrt(var), building,
                                         radio, snr_sigma_db, cap_nats)
    if snr is not None:
        if snr_sigma_db is None or snr_span_db is None:
            raise ValueError("family_log_lik: the families' SNR likelihood (snr given) needs "
                             "snr_sigma_db and snr_span_db, the SNR model's spread and the "
                             "outlier's SNR span (tracking.model.SNR_SIGMA_DB, SNR_SPAN_DB)")
        ll = ll + _snr_terms(ll, ok, (pos, anchor, snr[0], building, snr[1], max_order,
                                      snr_sigma_db, snr_span_db, cap_nats))
    return ll, ok, length, j, n_base


#: A log-density this far below its link's largest adds exactly nothing to the families'
#: mixture (``exp(-750)`` is 0.0 in float64, as is its share of the moment-matched spread).
_NEGLIGIBLE_NATS = 750.0


def _snr_terms(ll: FloatArray, ok: NDArray[np.bool_], args: tuple) -> FloatArray:
    """:func:`family_snr_log_lik` (``args``, without ``ok``) for the families that can change
    their link's mixture: those that exist (``ok``) and whose log-density ``ll`` (Q, F),
    before the SNR term, is within :data:`_NEGLIGIBLE_NATS` plus the SNR cost's cap of the
    link's largest; ``-inf`` for the others, which :func:`_mean_density` and
    :func:`best_family` then weigh exactly as before (0.0). A link whose evaluated families
    do not bound the rest that way (e.g. its best has no power) gets every existing family.
    Without a cap (``cap_nats`` <= 0) every existing family."""
    cap = float(args[8])
    if cap <= 0:
        return family_snr_log_lik(*args, ok)
    with np.errstate(invalid="ignore"):
        near = ok & (ll >= np.max(ll, axis=-1, keepdims=True) - (_NEGLIGIBLE_NATS + cap))
    term = family_snr_log_lik(*args, near)
    rest = ok & ~near
    if not np.any(rest):
        return term
    t_max = np.log(args[7]) - np.log(args[6]) - 0.5 * _LOG2PI  # the SNR term at cost 0
    with np.errstate(invalid="ignore"):
        top = np.max(ll + term, axis=-1)
        far = np.max(np.where(rest, ll, -np.inf), axis=-1) + t_max
    redo = np.isfinite(args[2]) & np.any(rest, axis=-1) & ~(far < top - _NEGLIGIBLE_NATS)
    if np.any(redo):
        term[redo] = family_snr_log_lik(args[0][redo], args[1][redo], args[2][redo],
                                        *args[3:], ok[redo])
    return term


def family_snr_log_lik(pos: FloatArray, anchor: FloatArray, snr_db: FloatArray, building,
                       radio, max_order: int, snr_sigma_db: float, snr_span_db: float,
                       cap_nats: float = 0.0, ok: NDArray[np.bool_] | None = None
                       ) -> FloatArray:
    """Log-ratio (Q, F) of every extra family's SNR density to the outlier's for links at
    ``pos`` (Q, 3) from ``anchor`` (Q, 3) with measured SNR ``snr_db`` (Q,):
    ``log N(snr; S_k, snr_sigma_db^2) + log snr_span_db`` (the outlier's SNR density is
    uniform, ``1 / snr_span_db``: :data:`diffpos.tracking.model.SNR_SPAN_DB`), ``S_k`` the
    family's SNR by the emulator's amplitude model
    (:func:`diffpos.channel.emulator.pair_family_snr_db`), the robust SNR likelihood the 18
    mechanisms get (:func:`diffpos.tracking.model.cap_snr_cost`: the cost ``z^2 / 2`` at most
    ``cap_nats`` when > 0). ``-inf`` where a family carries no power (no candidate); 0 where
    the SNR is unknown (NaN: as without it). ``ok`` (Q, F): the families that exist there
    (:func:`family_terms`' ``ok``; None: every one); only those of the links with a known
    SNR are evaluated (``-inf`` for the others, the rest bit for bit), as
    :func:`family_terms` adds this to a log-density that is ``-inf`` outside ``ok``."""
    known = np.isfinite(snr_db)
    pred = np.full((snr_db.shape[0], len(extra_families(max_order)[1])), -np.inf)
    if np.any(known):
        pred[known] = pair_family_snr_db(anchor[known], pos[known], building=building,
                                         radio=radio, max_order=max_order,
                                         mask=None if ok is None else ok[known])
    with np.errstate(invalid="ignore"):
        z = (snr_db[:, None] - pred) / snr_sigma_db
        cost = 0.5 * z * z
        if cap_nats > 0:
            cost = np.minimum(cost, cap_nats)
        term = -cost - np.log(snr_sigma_db) - 0.5 * _LOG2PI + np.log(snr_span_db)
    term = np.where(np.isfinite(pred), term, -np.inf)
    return np.where(np.isfinite(snr_db)[:, None], term, 0.0)


def first_arrival_log_prob(pos: FloatArray, anchor: FloatArray, length_m: FloatArray,
                           sigma_m: FloatArray, building, radio, snr_sigma_db: float,
                           cap_nats: float = 0.0) -> FloatArray:
    """Log-probability (Q, F) that each extra family (``length_m[:, 18:]``) can be the first
    arrival of its link at ``pos`` (Q, 3) from ``anchor`` (Q, 3): that none of the 18
    mechanisms shorter than it by more than ``3 sigma_m`` (Q,) was detected,
    ``sum_j log(1 - P_det,j)`` over them, ``P_det,j = Phi((S_j - T) / snr_sigma_db)`` (the
    SNR model's spread, :data:`diffpos.tracking.model.SNR_SIGMA_DB`) with
    ``S_j`` the mechanism's SNR predicted by the emulator's amplitude model
    (:func:`diffpos.channel.emulator.pair_snr_db`; -inf: no power, never detected) and ``T``
    the detector's threshold of the link, ``max(max_j S_j - fap_threshold_db,
    detection_snr_db)`` (as :func:`diffpos.tracking.model.snr_cost`). A mechanism is only
    not detected if it is weak: a family longer than a strong in-model path is never the
    first arrival, whatever the range says. ``cap_nats`` > 0: the log-probability is at
    least ``-cap_nats`` (the robust SNR likelihood of
    :func:`diffpos.tracking.model.cap_snr_cost`: the amplitude model is the emulator's, and
    another channel's powers miss it by tens of dB on whole links, so a shorter path it
    calls strong may be absent; at the default 4.5 nats such a family keeps ~1 % of a
    mechanism's prior, about the outlier's share)."""
    from scipy.special import log_ndtr  # only here: family_first is off by default, and a
    # module-level import costs every fusion process ~0.1-0.2 s (docs/startup.md)
    nb = len(MECHANISMS)
    pred = pair_snr_db(anchor[:, None, :], pos, building=building, radio=radio)[:, 0]
    fin = np.isfinite(pred)
    top = np.max(np.where(fin, pred, -np.inf), axis=-1)
    thr = np.maximum(top - radio.fap_threshold_db, radio.detection_snr_db)
    with np.errstate(invalid="ignore"):
        z = (pred - thr[:, None]) / snr_sigma_db
        log_miss = np.where(fin & np.isfinite(length_m[:, :nb]), log_ndtr(-z), 0.0)  # (Q, 18)
        shorter = length_m[:, None, :nb] < length_m[:, nb:, None] - 3.0 * sigma_m[:, None, None]
    out = np.sum(np.where(shorter, log_miss[:, None, :], 0.0), axis=-1)
    return np.maximum(out, -cap_nats) if cap_nats > 0 else out


def _family_snr(links, rows: NDArray, pi: NDArray, mi: NDArray, config) -> tuple | None:
    """The measured SNRs (Q,) and radio that score the extra families of the links ``(rows[pi],
    mi)`` (:func:`family_log_lik`'s ``snr``): every link's with ``config.family_snr``; with
    ``config.family_few_links`` only those of nodes with at most that many ranges (NaN
    elsewhere: scored as without), and at least ``min_anchors_tracking``; None: none (or no
    SNR)."""
    if links.snr is None or not (config.family_snr or config.family_few_links > 0):
        return None
    snr = links.snr[rows[pi], 0, mi]
    if not config.family_snr:
        few = few_ranges(np.sum(links.mask[rows[pi], 0], axis=-1), config.family_few_links,
                         config.min_anchors_tracking)
        snr = np.where(few, snr, np.nan)
    return snr, links.radio


def family_log_weight(pos: FloatArray, cov: FloatArray, links, rows: NDArray,
                      floor: NDArray, gate: NDArray[np.bool_], building, config,
                      log_eps: FloatArray | None = None,
                      snr_sigma_db: float | None = None,
                      snr_span_db: float | None = None, fit: bool = False):
    """The change (P, M) of the out-of-model component's log-density of the pairs (node rows
    ``rows`` of ``links``, prior ``pos`` (P, 3), ``cov`` (P, 3, 3), ``floor`` (P,)) by the
    extra families, for the present links of ``gate`` (P, M) (the others: 0, not evaluated);
    0 everywhere for ``max_order`` <= 2. ``log_eps`` (P, M): every link's (learned) outlier
    weight (None: ``outlier_weight``).

    ``config.family_weight`` ``"outlier"`` (before): :data:`FAMILY_SHARE` of the outlier
    component is the families' mixture at the PRIOR outlier weight, ``log((1 - c) + c span f)``
    (``f`` :func:`family_log_lik`'s density); ``"mechanism"``: every existing family is one
    more candidate of the link's inlier component, with a mechanism's prior: the outlier
    component becomes ``eps / span + (1 - eps) n_fam / (n_18 + n_fam) f`` (``n_fam``,
    ``n_18``: the families and the 18 mechanisms that exist at the prior), as M-NLS's
    ``max_order`` treats them (module docstring); ``"one"``: the same with ``1 / (n_18 + 1)``
    for ``n_fam / (n_18 + n_fam)`` (the families as one more candidate). With
    ``config.family_first`` and the links' radio model each family is weighted by
    :func:`first_arrival_log_prob` (``snr_sigma_db``: the SNR model's spread, needed then);
    with ``config.family_snr`` (``family_few_links``: at the nodes with that many ranges or
    fewer) by :func:`family_snr_log_lik` (``snr_sigma_db`` and ``snr_span_db``, the
    outlier's SNR span, needed then). ``fit`` (``TrackerConfig.family_fit_links``): returns
    ``(change, best)``, ``best`` every gated link's most probable family at ``pos``
    (:func:`best_family`: length (P, M), NaN where not gated, none exists or the families'
    part of the out-of-model component is not larger than the uniform outlier's; Jacobian
    (P, M, 3), spread (P, M); None for ``max_order`` <= 2), the same change bit for bit."""
    if extra_families(config.max_order) is None:
        return (np.zeros(gate.shape), None) if fit else np.zeros(gate.shape)
    gate = gate & links.mask[rows, 0]
    pi, mi = np.nonzero(gate)
    args = (pos[pi], cov[pi], links.anchors[rows[pi], 0, mi], links.rho[rows[pi], 0, mi],
            links.var[rows[pi], 0, mi], floor[pi], building, config.max_order,
            config.exist_margin_m, links.radio if config.family_first else None,
            config.snr_cost_cap_nats, snr_sigma_db, _family_snr(links, rows, pi, mi, config),
            snr_span_db)
    if pi.size == 0:
        ll, n_fam, n_base = family_log_lik(*args)  # (empty)
        best = None
    else:  # family_log_lik's terms, every link's best family from them where fitted
        terms = family_terms(*args)
        ll, n_fam, n_base = _mean_density(terms[0], terms[1]), terms[1].sum(axis=-1), terms[4]
        best = best_family(*terms[:4]) if fit else None
    out = np.zeros(gate.shape)
    e0 = np.log(config.outlier_weight)
    log_e = np.full(pi.shape, e0) if log_eps is None else log_eps[pi, mi]
    span = np.log(config.outlier_span_m)
    if config.family_weight in ("mechanism", "one"):
        prior = (np.log(np.maximum(n_fam, 1) / np.maximum(n_base + n_fam, 1))
                 if config.family_weight == "mechanism" else -np.log(n_base + 1.0))
        uni, fam = 0.0, np.log(-np.expm1(log_e)) + prior + ll - log_e + span
    else:
        c = FAMILY_SHARE
        # the families at the prior outlier weight, whatever the link's learned one (log_eps)
        uni, fam = np.log1p(-c), np.log(c) + span + ll + e0 - log_e
    out[pi, mi] = np.logaddexp(uni, fam)
    if not fit:
        return out
    return out, _scatter_best(best, fam > uni, pi, mi, gate.shape)


def best_family(ll: FloatArray, ok: NDArray[np.bool_], length: FloatArray, jac: FloatArray
                ) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Every link's most probable extra family (:func:`family_terms`' ``ll``, ``ok``,
    ``length``, ``jac``, (Q, F[, 3])): its length (Q,) (NaN where none exists), Jacobian
    (Q, 3) and the mixture's moment-matched spread about it, ``sum_k p_k (L_k - L_best)^2``
    [m^2] with ``p_k`` the families' posterior weights (``exp(ll_k)`` normalised; the 18's
    ``Selection.extra_var``)."""
    q = ll.shape[0]
    if q == 0 or ll.shape[1] == 0:
        return np.full(q, np.nan), np.zeros((q, 3)), np.zeros(q)
    k = np.argmax(ll, axis=-1)
    top = np.take_along_axis(ll, k[..., None], -1)[..., 0]
    has = ok.any(axis=-1) & np.isfinite(top)
    with np.errstate(invalid="ignore", over="ignore"):
        pk = np.where(ok, np.exp(ll - np.where(has, top, 0.0)[:, None]), 0.0)
        pk = pk / np.maximum(pk.sum(axis=-1, keepdims=True), 1e-300)
        lb = np.take_along_axis(length, k[..., None], -1)[..., 0]
        spread = np.sum(np.where(ok, pk * (length - lb[:, None]) ** 2, 0.0), axis=-1)
    jb = np.take_along_axis(jac, k[:, None, None], 1)[:, 0]
    return (np.where(has, lb, np.nan), np.where(has[:, None], jb, 0.0),
            np.where(has & np.isfinite(spread), spread, 0.0))


def _scatter_best(best: tuple | None, explained: NDArray[np.bool_], pi: NDArray, mi: NDArray,
                  shape: tuple) -> tuple:
    """:func:`best_family`'s per-link arrays at the gated links ``(pi, mi)`` of a (P, M)
    grid: length (P, M) (NaN: not gated, no family, or the families' part of the
    out-of-model component not larger than the uniform outlier's, ``explained`` False),
    Jacobian (P, M, 3), spread (P, M)."""
    length, jac, spread = np.full(shape, np.nan), np.zeros((*shape, 3)), np.zeros(shape)
    if best is not None:
        length[pi, mi] = np.where(explained, best[0], np.nan)
        jac[pi, mi], spread[pi, mi] = best[1], best[2]
    return length, jac, spread
