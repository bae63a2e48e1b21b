"""D-NLS fit of one chunk of fixes: starts, multi-start LM, gating, covariance and status (internal).

:func:`solve_chunk` runs the steps of :func:`diffpos.estimators.dnls.solver` for the fixes of one
chunk and writes them into the output arrays: wall pre-gate -> starts (height grid + LLS, or
the given ``x0``) -> screened multi-start fit (:func:`multistart_fit`) -> RAIM gating (its
exclusion candidates solved by :func:`_solve_candidates`) -> FIM covariance, test statistic
and status (:func:`_final_fields`, :func:`_fix_status`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from diffpos.bounds import bounds_from_fim, fisher_information
from diffpos.estimators.gating import (
    GateState,
    GatingConfig,
    chi2_threshold,
    run_gating,
    wall_pregate,
)
from diffpos.estimators.lls import lls_positions
from diffpos.estimators.lm import PathModel, cost_of, levenberg_marquardt
from diffpos.estimators.lm_nb import FTOL
from diffpos.estimators.result import ExclusionReason, FixStatus
from diffpos.estimators.starts import grid_starts
from diffpos.sym3 import solve3

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class FitSettings:
    """The options of :func:`~diffpos.estimators.dnls.solver` that every chunk uses (validated)."""

    z_starts: FloatArray | None  # start heights (None: one given start per fix)
    y_start: float
    lls_start: bool
    gating: GatingConfig | None
    loss: str
    loss_scale: float
    max_iter: int
    xtol: float
    sigmas_given: bool
    keep_starts: int | None
    screen_iter: int
    exclusion_ftol: float | None = None  # None: the exhaustive exclusion search
    exclusion_recheck_ratio: float | None = None
    exclusion_bound: float | None = None
    exclusion_starts: str = "grid"  # "local": a cold fix's candidates from LLS + the solution


@dataclass(frozen=True)
class _Problems:
    """The solvable fixes of a chunk: anchors, ranges, sigmas, model and given starts."""

    a: FloatArray  # (N, M, 3)
    r: FloatArray  # (N, M)
    sig: FloatArray  # (N, M)
    mdl: PathModel
    x0: FloatArray | None  # (N, 3)


def _lls_starts(
    a: FloatArray, r: FloatArray, mask: NDArray[np.bool_], grid: FloatArray
) -> FloatArray:
    """One extra start per fix from LLS; falls back to the middle grid start."""
    x, _, ok = lls_positions(a, r, mask)
    fallback = grid[:, grid.shape[1] // 2]
    x = np.where(ok[:, None], x, fallback)
    x[:, 1] = np.maximum(np.abs(x[:, 1]), 0.5)
    return x[:, None, :]


def _starts_for(
    prob: _Problems,
    aa: FloatArray,
    rr: FloatArray,
    cu: BoolArray,
    rows: NDArray[np.int_] | slice,
    cfg: FitSettings,
) -> FloatArray:
    """The given start, or the z grid (plus the LLS fix): ``(len(rows), S, 3)``."""
    if prob.x0 is not None:
        return prob.x0[rows][:, None, :]
    st = grid_starts(aa, cu, cfg.z_starts, cfg.y_start)
    if cfg.lls_start:
        st = np.concatenate([st, _lls_starts(aa, rr, cu, st)], axis=1)
    return st


def solve_chunk(
    out: dict[str, np.ndarray],
    sl: slice,
    anchors: FloatArray,
    ranges: FloatArray,
    sigmas: FloatArray,
    mask: BoolArray,
    model: PathModel,
    x0: FloatArray | None,
    cfg: FitSettings,
) -> None:
    """Solve the fixes ``sl`` of the batch and write them into ``out`` (see module docstring)."""
    mask, reason0 = _pregate_walls(out, sl, anchors, ranges, sigmas, mask, cfg)
    idx = np.flatnonzero(mask.sum(axis=-1) >= 3)
    if idx.size == 0:
        return
    prob = _Problems(
        a=anchors[idx],
        r=ranges[idx],
        sig=sigmas[idx],
        mdl=model.take(idx),
        x0=None if x0 is None else x0[idx],
    )
    state = _first_fit(prob, mask[idx], reason0[idx], cfg)
    if cfg.gating is not None:
        run_gating(
            state,
            prob.a,
            prob.r,
            prob.sig,
            prob.mdl,
            cfg.gating,
            active=np.ones(idx.size, dtype=bool),
            sigmas_given=cfg.sigmas_given,
            loss=cfg.loss,
            loss_scale=cfg.loss_scale,
            solve_candidates=functools.partial(_solve_candidates, prob, cfg),
        )
        state.x_m[:, 1] = np.abs(state.x_m[:, 1])
    gi = sl.start + idx
    for key, value in _final_fields(prob, state, cfg).items():
        out[key][gi] = value


def _pregate_walls(
    out: dict[str, np.ndarray],
    sl: slice,
    anchors: FloatArray,
    ranges: FloatArray,
    sigmas: FloatArray,
    mask: BoolArray,
    cfg: FitSettings,
) -> tuple[BoolArray, NDArray[np.int_]]:
    """Drop ranges shorter than the anchor's distance to the wall (recorded in ``out``: the
    reasons of every fix, also of those left with too few anchors to solve, whose ``used``
    stays False).

    Returns the remaining mask and the exclusion reasons ``(n, M)``.
    """
    reason0 = np.zeros((ranges.shape[0], ranges.shape[1]), dtype=np.int_)
    if cfg.gating is not None:
        wall = wall_pregate(
            anchors, ranges, sigmas, mask, cfg.gating, sigmas_given=cfg.sigmas_given
        )
        if np.any(wall):
            mask = mask & ~wall
            reason0[wall] = ExclusionReason.PREGATE_SHORTER_THAN_LOS
            out["exclusion_reason"][sl] = reason0
    return mask, reason0


def _first_fit(
    prob: _Problems, used: BoolArray, reason: NDArray[np.int_], cfg: FitSettings
) -> GateState:
    """Multi-start fit on all used anchors; the gating state it starts from."""
    starts = _starts_for(prob, prob.a, prob.r, used, slice(None), cfg)
    n = starts.shape[0]
    x, cost_best, iters_best, conv_best, _ = multistart_fit(
        prob.a, prob.r, used / prob.sig, starts, prob.mdl, loss=cfg.loss,
        loss_scale=cfg.loss_scale, max_iter=cfg.max_iter, xtol=cfg.xtol,
        keep_starts=cfg.keep_starts, screen_iter=cfg.screen_iter,
        recheck=used.sum(axis=-1) - 3 if cfg.sigmas_given else None,
    )
    x[:, 1] = np.abs(x[:, 1])  # mirror symmetry y -> -y of the model
    return GateState(
        x_m=x,
        cost=cost_best,
        iterations=iters_best,
        converged=conv_best,
        used=used.copy(),
        reason=reason.copy(),
        gating_failed=np.zeros(n, dtype=bool),
        tested=np.zeros(n, dtype=bool),
    )


def _solve_candidates(
    prob: _Problems, cfg: FitSettings, pi: NDArray[np.int_], cu: BoolArray, warm: FloatArray
) -> tuple[FloatArray, NDArray[np.int_], BoolArray]:
    """Exclusion candidates (fix ``pi[i]`` on anchors ``cu[i]``) for :func:`run_gating`.

    The first fit's multi-start on each candidate subset, plus the warm start. The screening
    recheck is done per fix, not per candidate: the candidates that keep the faulty anchor
    all fail, and re-solving each of them from every start would only confirm it. A fix is
    re-solved from all starts (every candidate) only if none of its screened candidates
    passes the residual test itself, and (``exclusion_recheck_ratio``) its best one comes
    within that factor of the threshold. With ``exclusion_ftol`` the candidates are solved
    to that relative cost decrease and each fix's best one is then iterated on to the full
    convergence test (:func:`_polish_best`).
    """
    aa, rr, swc, mc = prob.a[pi], prob.r[pi], cu / prob.sig[pi], prob.mdl.take(pi)
    st = _candidate_starts(prob, aa, rr, cu, pi, warm, cfg)
    ftol = FTOL if cfg.exclusion_ftol is None else cfg.exclusion_ftol
    common = {"loss": cfg.loss, "loss_scale": cfg.loss_scale, "max_iter": cfg.max_iter,
              "xtol": cfg.xtol, "screen_iter": cfg.screen_iter, "ftol": ftol}
    dof_c = cu.sum(axis=-1) - 3
    _, grp = np.unique(pi, return_inverse=True)
    if cfg.exclusion_bound is not None and cfg.loss == "linear":
        first = _loo_first(aa, rr, prob.sig[pi], mc, grp, cu, warm)
        xc, cc, ic, vc, lc = _bounded_candidates(aa, rr, swc, st, mc, grp, first, cfg, common)
    else:
        xc, cc, ic, vc, lc = multistart_fit(aa, rr, swc, st, mc, keep_starts=cfg.keep_starts,
                                        recheck=np.zeros_like(dof_c), **common)
    if cfg.keep_starts is not None and st.shape[1] > cfg.keep_starts:
        thr_c = chi2_threshold(dof_c, cfg.gating.false_alarm_probability)
        good = (dof_c >= 1) & (2.0 * cc <= thr_c)
        fix_good = np.zeros(grp.max(initial=-1) + 1, dtype=bool)
        np.logical_or.at(fix_good, grp, good)
        redo = ~fix_good
        if cfg.exclusion_recheck_ratio is not None:
            near = (dof_c >= 1) & (2.0 * cc <= cfg.exclusion_recheck_ratio * thr_c)
            fix_near = np.zeros_like(fix_good)
            np.logical_or.at(fix_near, grp, near)
            redo &= fix_near
        rows = np.flatnonzero(redo[grp])
        if rows.size:
            x2, c2, i2, v2, l2 = multistart_fit(
                aa[rows], rr[rows], swc[rows], st[rows], mc.take(rows),
                keep_starts=None, recheck=None, **common)
            b = c2 < cc[rows]
            rb = rows[b]
            xc[rb], ic[rb], vc[rb], lc[rb] = x2[b], i2[b], v2[b], l2[b]
    xc[:, 1] = np.abs(xc[:, 1])
    if cfg.exclusion_ftol is not None:
        _polish_best(aa, rr, swc, mc, grp, cfg, xc, ic, vc, lc)
    return xc, ic, vc


def _candidate_starts(prob: _Problems, aa: FloatArray, rr: FloatArray, cu: BoolArray,
                      pi: NDArray[np.int_], warm: FloatArray, cfg: FitSettings) -> FloatArray:
    """The candidates' starts: those of the first fit (the given start, or the height grid
    and the LLS position) plus the warm start (the current solution); with
    ``exclusion_starts="local"`` and no given start, each candidate's own LLS position (if
    ``lls_start``; the warm start where LLS is not identifiable) and the warm start only."""
    if prob.x0 is None and cfg.exclusion_starts == "local":
        own = (_lls_starts(aa, rr, cu, warm[:, None, :]) if cfg.lls_start
               else np.empty((pi.size, 0, 3)))
        return np.concatenate([own, warm[:, None, :]], axis=1)
    return np.concatenate([_starts_for(prob, aa, rr, cu, pi, cfg), warm[:, None, :]], axis=1)


def _bounded_candidates(aa: FloatArray, rr: FloatArray, swc: FloatArray, st: FloatArray,
                        mc: PathModel, grp: NDArray[np.int_], first: NDArray[np.int_],
                        cfg: FitSettings, common: dict
                        ) -> tuple[FloatArray, FloatArray, NDArray[np.int_], BoolArray, FloatArray]:
    """The candidates of :func:`_solve_candidates` with ``exclusion_bound``: each fix's
    candidate row ``first`` (the smallest linearised leave-one-out statistic,
    :func:`_loo_first`) solved first, then the others with their starts given up above
    ``exclusion_bound`` times its cost (``levenberg_marquardt(cost_stop=...)``)."""
    zero = np.zeros(grp.size, dtype=np.int_)
    xc, cc, ic, vc, lc = (np.empty((grp.size, 3)), np.empty(grp.size), np.empty(grp.size, np.int_),
                          np.empty(grp.size, bool), np.empty(grp.size))
    rest = np.setdiff1d(np.arange(grp.size), first)
    for rows, stop in ((first, None), (rest, "bound")):
        if rows.size == 0:
            continue
        kw = {}
        if stop is not None:
            c_first = np.full(grp.max() + 1, np.inf)
            c_first[grp[first]] = np.where(np.isfinite(cc[first]), cc[first], np.inf)
            kw = {"cost_stop": cfg.exclusion_bound * c_first[grp[rows]],
                  "stop_after": EXCLUSION_BOUND_AFTER}
        xc[rows], cc[rows], ic[rows], vc[rows], lc[rows] = multistart_fit(
            aa[rows], rr[rows], swc[rows], st[rows], mc.take(rows), keep_starts=cfg.keep_starts,
            recheck=zero[rows], **common, **kw)
    return xc, cc, ic, vc, lc


def _loo_first(aa: FloatArray, rr: FloatArray, sig: FloatArray, mc: PathModel,
               grp: NDArray[np.int_], cu: BoolArray, warm: FloatArray) -> NDArray[np.int_]:
    """Per fix, the candidate row whose left-out anchor has the smallest linearised
    leave-one-out statistic at the current solution ``warm`` (the kernel's ``_loo_order``):
    ``T - w_j e_j^2 / (1 - h_jj)``, ``T`` the statistic of the fix's anchors, ``h_jj`` the
    leverage of anchor ``j`` (-inf where ``1 - h_jj <= 1e-12``); the first of equal ones."""
    k = grp.size
    used = np.zeros((grp.max() + 1, cu.shape[1]), dtype=bool)
    np.logical_or.at(used, grp, cu)  # a fix's anchors: the union of its candidates' sets
    uf = used[grp]
    left_out = np.argmax(uf & ~cu, axis=-1)
    sw = np.where(uf, 1.0 / sig, 0.0)
    p, jac = mc.evaluate(aa, warm)
    e = np.where(uf, (rr - p) * sw, 0.0)
    jw = np.where(uf[..., None], jac * sw[..., None], 0.0)
    hm = np.einsum("kmi,kmj->kij", jw, jw)
    jl = jw[np.arange(k), left_out]
    with np.errstate(invalid="ignore", divide="ignore"):
        q = solve3(hm, jl)
        one_minus = 1.0 - np.einsum("ki,ki->k", jl, q)
        el = e[np.arange(k), left_out]
        pred = np.where(one_minus > 1e-12, np.einsum("km,km->k", e, e) - el * el / one_minus,
                        -np.inf)
    order = np.lexsort((pred, grp))  # by fix, then statistic (stable)
    head = np.ones(k, dtype=bool)
    head[1:] = grp[order[1:]] != grp[order[:-1]]
    return order[head]


def _polish_best(aa: FloatArray, rr: FloatArray, swc: FloatArray, mc: PathModel,
                 grp: NDArray[np.int_], cfg: FitSettings, xc: FloatArray, ic: NDArray[np.int_],
                 vc: BoolArray, lc: FloatArray) -> None:
    """Each fix's candidate with the smallest test statistic (the one ``run_gating`` picks;
    the first of equal ones) iterated on from its loosely converged solution to the full
    convergence test: the same iteration continued (its damping ``lc``, the iterations its
    start had left of ``max_iter``); updates ``xc``, ``ic``, ``vc`` in place."""
    p, _ = mc.evaluate(aa, xc)
    res = (rr - p) * swc
    tc = np.einsum("nm,nm->n", res, res)
    tc = np.where(np.isfinite(tc), tc, np.inf)
    order = np.lexsort((tc, grp))  # by fix, then statistic (stable: the first of equal ones)
    first = np.ones(order.size, dtype=bool)
    first[1:] = grp[order[1:]] != grp[order[:-1]]
    rows = order[first]
    rows = rows[np.isfinite(tc[rows])]
    if rows.size == 0:
        return
    budget = np.maximum(cfg.max_iter - ic[rows], 0)  # the iterations their starts had left
    for b in np.unique(budget):
        rb = rows[budget == b]
        fit = levenberg_marquardt(aa[rb], rr[rb], swc[rb], xc[rb], mc.take(rb), loss=cfg.loss,
                                  loss_scale=cfg.loss_scale, max_iter=int(b), xtol_m=cfg.xtol,
                                  lambda0=lc[rb])
        xc[rb] = fit.x_m
        xc[rb, 1] = np.abs(xc[rb, 1])
        ic[rb] += fit.iterations
        vc[rb] = fit.converged


def _final_fields(prob: _Problems, state: GateState, cfg: FitSettings) -> dict[str, np.ndarray]:
    """The output fields of the solved fixes: position, FIM covariance (scaled by the
    a-posteriori variance factor without sigmas), PEB, z bound, residuals, test statistic
    and threshold, dof, cost and status."""
    used = state.used
    p, jac = prob.mdl.evaluate(prob.a, state.x_m)
    res = prob.r - p
    n_used = used.sum(axis=-1)
    fim = fisher_information(jac, prob.sig, used)
    bnd = bounds_from_fim(fim)
    cov = bnd.crlb_m2
    cost_final = cost_of(res, used / prob.sig, cfg.loss, cfg.loss_scale)
    if not cfg.sigmas_given:
        # a-posteriori variance factor (unit weights were used)
        ssr = np.einsum("nm,nm->n", res * used, res * used)
        with np.errstate(divide="ignore", invalid="ignore"):
            s2 = np.where(n_used > 3, ssr / (n_used - 3), 1.0)
        cov = cov * s2[:, None, None]
    sw_used = used / prob.sig
    t_stat = np.einsum("nm,nm->n", res * sw_used, res * sw_used)
    dof = n_used - 3
    thr = (
        chi2_threshold(dof, cfg.gating.false_alarm_probability)
        if cfg.gating is not None and cfg.sigmas_given
        else np.full(n_used.shape[0], np.nan)
    )
    return {
        "position_m": state.x_m,
        "covariance_m2": cov,
        "peb_m": np.sqrt(np.trace(cov, axis1=-2, axis2=-1)),
        "z_bound_m": np.sqrt(cov[:, 2, 2]),
        "iterations": state.iterations,
        "converged": state.converged,
        "status": _fix_status(state, n_used, bnd.identifiable, cfg.gating),
        "residuals_m": np.where(used, res, np.nan),
        "used": used,
        "exclusion_reason": state.reason,
        "test_statistic": np.where(cfg.sigmas_given, t_stat, np.nan),
        "test_threshold": thr,
        "dof": dof,
        "cost": cost_final,
    }


def _fix_status(
    state: GateState,
    n_used: NDArray[np.int_],
    identifiable: BoolArray,
    gating: GatingConfig | None,
) -> NDArray[np.int_]:
    """Status per fix; later rules override earlier ones (the most basic failure wins)."""
    status = np.full(n_used.shape[0], int(FixStatus.OK), dtype=np.int_)
    status[~state.tested] = FixStatus.OK_UNVERIFIED
    status[state.gating_failed] = FixStatus.GATING_FAILED
    if gating is not None and gating.z_range_m is not None:
        z_lo, z_hi = gating.z_range_m
        z = state.x_m[:, 2]
        status[(status == FixStatus.OK) & ((z < z_lo) | (z > z_hi))] = FixStatus.GATING_FAILED
    status[~state.converged] = FixStatus.NOT_CONVERGED
    status[~identifiable] = FixStatus.NOT_IDENTIFIABLE
    status[n_used < 3] = FixStatus.TOO_FEW_ANCHORS
    return status


#: Screened fixes whose residual statistic exceeds this quantile are re-solved from all starts.
RECHECK_PROBABILITY = 0.1
#: Default ``dnls(exclusion_ftol=...)``: the relative cost decrease to which the exclusion
#: candidates are solved before the best is iterated on (docs/dnls_cost.md).
EXCLUSION_FTOL = 1e-6
#: Default ``dnls(exclusion_recheck_ratio=...)``: a fix's exclusion candidates are re-solved
#: from all starts only if the best one's statistic is within this factor of its threshold.
EXCLUSION_RECHECK_RATIO = 2.0
#: Default ``dnls(exclusion_bound=...)``: an exclusion candidate's start is given up once a
#: Gauss-Newton step would leave its cost above this factor times the first candidate's.
EXCLUSION_BOUND = 3.0
#: Iterations every candidate's start makes before it may be given up (far from its minimum
#: the Gauss-Newton prediction can overstate the cost it will reach).
EXCLUSION_BOUND_AFTER = 2


def multistart_fit(
    a: FloatArray,
    r: FloatArray,
    sw: FloatArray,
    starts: FloatArray,
    mdl: PathModel,
    *,
    loss: str,
    loss_scale: float,
    max_iter: int,
    xtol: float,
    keep_starts: int | None,
    screen_iter: int,
    recheck: NDArray[np.int_] | None,
    ftol: float = FTOL,
    cost_stop: FloatArray | None = None,
    stop_after: int = 0,
) -> tuple[FloatArray, FloatArray, NDArray[np.int_], NDArray[np.bool_]]:
    """Best-of-starts LM fit per problem: ``starts (N, S, 3)`` -> x, cost, iterations, converged
    and the final damping (``LMResult.lam``) of the start kept.

    With screening (``keep_starts``), every start gets ``screen_iter`` iterations and only the
    ``keep_starts`` lowest-cost ones go on. Screening can drop the start that would have
    reached the global minimum (measured: 0.3 % of random 4-anchor fixes), which then shows
    up as a large residual; so fixes whose statistic ``2 cost`` exceeds the
    ``1 - RECHECK_PROBABILITY`` chi-square quantile for ``recheck`` dof (or all fixes, if
    ``recheck`` is None: no noise model to judge) are re-solved from all starts and the
    better answer kept. ``ftol``, ``cost_stop`` (per problem) and ``stop_after``: those of
    :func:`~diffpos.estimators.lm.levenberg_marquardt` (``cost_stop`` not in the screening).
    """
    n, s = starts.shape[0], starts.shape[1]
    common = {"loss": loss, "loss_scale": loss_scale, "xtol_m": xtol, "ftol": ftol}

    def stops(rows: NDArray[np.int_] | slice, times: int) -> dict:
        if cost_stop is None:
            return {}
        return {"cost_stop": np.repeat(cost_stop[rows], times), "stop_after": stop_after}

    def full(rows: NDArray[np.int_]):
        k = rows.size
        fit = levenberg_marquardt(
            np.repeat(a[rows], s, axis=0), np.repeat(r[rows], s, axis=0),
            np.repeat(sw[rows], s, axis=0), starts[rows].reshape(k * s, 3),
            mdl.take(rows).repeat(s), max_iter=max_iter, **common, **stops(rows, s),
        )
        return _pick_best(fit.x_m, fit.cost, fit.iterations, fit.converged, fit.lam, k, s)

    if keep_starts is None or s <= keep_starts or max_iter <= screen_iter:
        return full(np.arange(n))
    scr = levenberg_marquardt(
        np.repeat(a, s, axis=0), np.repeat(r, s, axis=0), np.repeat(sw, s, axis=0),
        starts.reshape(n * s, 3), mdl.repeat(s), max_iter=screen_iter, **common,
    )
    c_scr = np.where(np.isfinite(scr.cost), scr.cost, np.inf).reshape(n, s)
    k = keep_starts
    order = np.argsort(c_scr, axis=-1, kind="stable")[:, :k]
    pick = (np.arange(n)[:, None] * s + order).ravel()
    fit = levenberg_marquardt(
        np.repeat(a, k, axis=0), np.repeat(r, k, axis=0), np.repeat(sw, k, axis=0),
        scr.x_m[pick], mdl.repeat(k), max_iter=max_iter - screen_iter, **common,
        **stops(slice(None), k),
    )
    x, cost, iters, conv, lam = _pick_best(
        fit.x_m, fit.cost, scr.iterations[pick] + fit.iterations, fit.converged, fit.lam, n, k
    )
    if recheck is None:
        redo = np.ones(n, dtype=bool)
    else:
        thr = chi2_threshold(recheck, RECHECK_PROBABILITY)
        redo = ~np.isfinite(cost) | ((recheck >= 1) & (2.0 * cost > thr))
    rows = np.flatnonzero(redo)
    if rows.size:
        x2, c2, i2, v2, l2 = full(rows)
        better = c2 < cost[rows]
        rb = rows[better]
        x[rb], cost[rb], iters[rb], conv[rb] = x2[better], c2[better], i2[better], v2[better]
        lam[rb] = l2[better]
    return x, cost, iters, conv, lam


def _pick_best(x_m, cost, iters, conv, lam, n, s):
    c = np.where(np.isfinite(cost), cost, np.inf).reshape(n, s)
    best = np.argmin(c, axis=-1)
    sel = np.arange(n) * s + best
    return x_m[sel].copy(), cost[sel].copy(), iters[sel].copy(), conv[sel].copy(), lam[sel].copy()
