"""Measurement model of the tracker: mechanism selection, iterated EKF update, snapshot init.

Arrays are over N nodes, H hypotheses per node (the floors, or floors x starts at
initialisation) and M anchors; ``floor`` gives every hypothesis' floor index. See
:mod:`diffpos.tracking.tracker` for the design; everything here is deterministic. The links and the
path evaluation are in :mod:`diffpos.tracking.links`, the initialisation's grid search in
:mod:`diffpos.tracking.initialisation`, the SNR term (:func:`snr_cost`, :func:`snr_cost_near`) in
:mod:`diffpos.tracking.snr` (all re-exported here). The hot loops
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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from diffpos.paths.model_nb import building_planes
from diffpos.tracking.iekf_nb import iekf_kernel, prior_info_kernel
from diffpos.tracking.initialisation import _grid_starts_numpy, grid_starts
from diffpos.tracking.links import (
    _IS_DIFF,
    K_SLOTS,
    Links,
    PathEval,
    _all_paths_numpy,
    _c,
    _cb,
    _los,
    _relax,
    all_paths,
    candidates,
    eval_paths,
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
from diffpos.tracking.snr import (  # noqa: F401  (moved there, still importable from here)
    HOLE_THRESHOLD_AT_PRIOR,
    SNR_SIGMA_DB,
    SNR_SPAN_DB,
    _hole_snr_cost,
    _pair_snr_cost,
    _snr_cost_of,
    _snr_cost_of_numpy,
    _snr_cost_thr,
    snr_cost,
    snr_cost_near,
    snr_reuse_on,
)

FloatArray = NDArray[np.float64]
#: Moved to tracking_paths / tracking_init, still importable from here (tests).
_MOVED = (_all_paths_numpy, eval_paths, _grid_starts_numpy)
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


def _select_fixed(pos_cov: FloatArray, links: Links, config, snr_c, n: int, h: int) -> tuple:
    """:func:`select`'s kernel inputs that do not depend on the paths (the selection passes of
    one update share them): the covariance, the links' columns and the constants."""
    eps = config.outlier_weight
    return (*_prep_inputs(pos_cov, links, snr_c, n, h), _c(links.rho[:, 0]),
            _c(links.mask[:, 0]),
            np.array([_LOG2PI, np.log1p(-eps), np.log(eps / config.outlier_span_m),
                      -np.log(SNR_SPAN_DB)]))


def select(pos_cov: FloatArray, links: Links, pe: PathEval, config,
           snr_c: FloatArray | None = None, fixed: tuple | None = None) -> Selection:
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
    ``snr_c`` if the caller has it.
    """
    shape = pe.length.shape
    n, h, m = shape[:3]
    if fixed is None:
        fixed = _select_fixed(pos_cov, links, config, snr_c, n, h)
    cov, var, snr, sc, use_snr, c_pack, c_span, rho, mask, consts = fixed
    length = _c(pe.length)
    valid = np.empty(shape, dtype=np.bool_)
    sv, sl = np.empty(valid.size), np.empty(valid.size)
    cnt = select_pack_kernel(length, _c(pe.jac), _c(pe.sure), _c(pe.loose), _IS_DIFF, cov, var,
                             snr, sc, use_snr, c_pack, c_span, valid, sv, sl)
    slot, best = np.empty((n, h, m), dtype=np.int64), np.empty((n, h, m), dtype=np.int64)
    base, nis, extra = np.empty((n, h, m)), np.empty((n, h, m)), np.empty((n, h, m))
    ex = np.empty(cnt)
    select_best_kernel(length, valid, rho, mask, snr, use_snr, sv, sl, np.log(sv[:cnt]),
                       consts, _LOG_N, ex, best, base, slot, nis)
    np.exp(ex, out=ex)
    mix = np.empty((n, h, m))
    select_mix_kernel(length, valid, slot, best, ex, extra, mix)
    log_w = np.where(slot >= 0, base + np.log(mix), base)
    return Selection(slot=slot, log_weight=log_w, nis=nis, extra_var=extra)


def _select_numpy(pos_cov: FloatArray, links: Links, pe: PathEval, config,
                  snr_c: FloatArray | None = None) -> Selection:
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
    if snr_c is not None:
        s_out = np.where(np.isfinite(links.snr), -np.log(SNR_SPAN_DB), 0.0)
    else:
        s_out = 0.0
    lengths = pe.length
    e = links.rho[..., None] - lengths
    n_ok = np.maximum(valid.sum(axis=-1), 1)
    with np.errstate(invalid="ignore"):
        ll = -0.5 * (e * e / s_var + np.log(s_var) + _LOG2PI)
    ll = np.where(valid, ll + s_ll, -np.inf)
    best = np.argmax(ll, axis=-1)
    ll_best = np.take_along_axis(ll, best[..., None], axis=-1)[..., 0]
    s_best = np.take_along_axis(np.broadcast_to(s_ll, ll.shape), best[..., None], -1)[..., 0]
    w_in = np.log1p(-config.outlier_weight) - np.log(n_ok)
    w_out = np.log(config.outlier_weight / config.outlier_span_m) + s_out
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


def clamp_to_floor(x: FloatArray, floor, building, margin_m: float) -> FloatArray:
    """Keep every hypothesis' position inside its floor's box (``margin_m`` from the walls)."""
    zf = building.floor_z_m(np.asarray(floor))
    x0, x1 = building.edge_x_m
    out = x.copy()
    out[..., 0] = np.clip(x[..., 0], x0 + margin_m, x1 - margin_m)
    out[..., 1] = np.clip(x[..., 1], margin_m, building.depth_m - margin_m)
    out[..., 2] = np.clip(x[..., 2], zf + margin_m, zf + building.floor_height_m - margin_m)
    return out


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
                       snr_cache=None):
    """Select mechanisms at the prior, run the IEKF; returns x, P, log_evidence, sel, residual.

    ``level``: the hypotheses' vertical modes (see :func:`iekf`). ``snr_cache``: the
    hypotheses' :class:`~diffpos.tracking.snr.SnrCache` (read and updated in place; reuse
    within ``config.snr_reuse_m`` / ``snr_reuse_anchor_m``; both 0: not used, left as it
    is), or None (every SNR predicted).

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
    # unless the prediction left its floor's box)
    xc = clamp_to_floor(x[..., :3], floor, building, config.z_margin_m)
    # the nodes with a hypothesis whose prior is outside its floor's box (or not finite)
    moved = np.flatnonzero(np.any(xc != x[..., :3], axis=(-2, -1)))
    # the existence margin follows every hypothesis' own height uncertainty (a track on the
    # stairs with a loose height does not call a mechanism impossible that exists a few
    # decimetres away); at initialisation (``level`` None) the prior is the grid search's box,
    # not the uncertainty of a tracked point: the fixed margin there
    relax = (config.exist_margin_m if level is None
             else existence_margin(p_prior, config))
    pe0 = all_paths(xc, links, floor, building, relax)
    snr_c = snr_cost_near(xc, links, floor, building, relax, pe0,
                          cache=snr_cache if snr_reuse_on(config) else None,
                          reuse_m=(config.snr_reuse_m, config.snr_reuse_anchor_m))
    info = prior_information(p_prior)  # shared by the passes
    # and so are the kernels' inputs that do not depend on the paths or the selection
    fix_i = _iekf_fixed(x_prior, p_prior, links, floor, building, config, level, info)
    fix_s = _select_fixed(p_prior[..., :3, :3], links, config, snr_c, *x_prior.shape[:2])
    p = p_prior
    for k in range(config.select_passes):  # later passes: mechanisms re-selected at the fit
        if k > 0:  # at the fit: the margin of the fit's own uncertainty
            relax = existence_margin(p, config)
        if k == 0:  # the prior's paths: only the moved nodes' evaluated once more (into pe0)
            pe = _paths_at(pe0, moved, x[..., :3], links, floor, building, relax)
        else:
            pe = all_paths(x[..., :3], links, floor, building, relax)
        sel = select(p_prior[..., :3, :3], links, pe, config, snr_c, fix_s)
        x, p, log_ev, res = iekf(x_prior, p_prior, links, floor, sel, building, config,
                                 level, info, fix_i)
    return clamp_to_floor(x, floor, building, config.z_margin_m), p, log_ev, sel, res


def snapshot(links: Links, floors: NDArray, building, config):
    """Snapshot fit of every listed floor per node (grid, then the IEKF from the best cells).

    ``floors`` (N, Fs). Returns ``(x, P, log_evidence, sel, residual)`` of the best start per
    node and floor: (N, Fs, 6), (N, Fs, 6, 6), (N, Fs), the selection and residuals (N, Fs, M).
    """
    n, nf = floors.shape
    ns = config.init_starts
    x = np.zeros((n, nf * ns, 6))
    x[..., :3] = grid_starts(links, floors, building, config)
    fl = np.repeat(floors, ns, axis=1)
    g, v = config.init_grid_m, config.init_sigma_v_m_s
    p0 = np.diag([g * g, g * g, (building.floor_height_m / 4) ** 2, v * v, v * v,
                  (config.v_stairs_m_s / 2) ** 2])
    p0 = np.broadcast_to(p0, (n, nf * ns, 6, 6))
    for _ in range(2):  # second pass: mechanisms re-selected at the first pass' estimate
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
