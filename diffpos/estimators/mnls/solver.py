"""M-NLS: mechanism-aware non-linear least squares on the first-arrival path model.

The measured range of a link is the length of its *first arrival*, which is one of the
mechanisms of :mod:`diffpos.paths.model` (direct through the window, specular reflections entering
through the window, diffraction over the physical upper/lower window edge, diffraction +
reflection, double bounces), not always the paper's upper-edge diffraction. M-NLS estimates
the node position and, per link, which mechanism arrived first.

Model (numbers measured on the emulator, default scenario, 70,400 links, seed 0, unless
stated otherwise):

* **Floor hypotheses.** The floor fixes the window band and the floor/ceiling planes, so each
  floor of the building is a separate hypothesis (``floor`` passed to the path model); the
  node is confined to its floor's box.
* **Search**, its measured **cost** and the **compiled steps** (``kernel=True``, the
  default: the same answers as the numpy reference steps, bitwise on the tested sets):
  :mod:`diffpos.estimators.mnls.starts`.
* **The best floor's mode carried to the others** (fixes with three links,
  :data:`TRANSFER_MAX_LINKS`): after the refinement, the (x, y) of the fix's lowest-cost floor's
  mode at each other floor's middle height is one more start there (``max_iter`` LM steps with
  the SNR terms); a floor keeps the new mode where it costs less. The floors share the plan,
  so the horizontal position the links fix on one floor is a start inside another floor's
  basin, where every closed-form start is a one-mechanism hypothesis of an exactly determined
  fix (Sionna's heldout-2, K = 4: receiver 68, a partition chain, was on floor 3 at p 0.998
  with a link no mechanism explains; the transfer finds the true floor's mode, cost 0.2;
  docs/raytrace_study.md 4e). Fixes with four links or more are untouched (on the traced
  paper and open-plan buildings the transfer there found cheaper wrong-floor modes: two new
  floors at p 0.95 and one receiver fewer right on the emulated paper building).
* **Same-edge dominance** (:mod:`diffpos.estimators.mnls.rules`): ``D(edge)-R(plane)`` deviating at least as much
  as ``D(edge)`` is never first (0 of 70,000 first arrivals violate it).
* **SNR** (with ``snr_db`` and ``radio``): (a) a diffracted mechanism is not a candidate when
  the measured SNR is within the ITU-R P.526 knife-edge loss ``J(nu)`` - 6 dB of free space;
  (b) each slot's SNR predicted by the emulator's amplitude model
  (:func:`diffpos.channel.emulator.pair_snr_db`) is compared with the measured one (Gaussian, 6 dB: a
  factor 2 in field for pattern/material/diffraction modelling errors); (c) the detector's
  rule: the first arrival is not far below the predicted strongest path's threshold
  ``P_max - fap_threshold_db``, and no path predicted surely detected (6 dB above that
  threshold) arrives before it; options (``snr_rule``, :class:`~diffpos.estimators.mnls.rules.SnrRule`,
  off by default): the threshold at least the MEASURED first arrival's SNR less
  ``fap_threshold_db``, and the soft skip prior ``-log(w prod_j Phi((T - S_j) / 6 dB) + 1 - w)``
  over the earlier paths instead of the hard rule (its path order taken at the refresh point
  and held with the SNR terms; docs/raytrace_study.md "Session 26"), and (b) with the window
  edges as dielectric sheets of the wall material whatever the channel's order
  (``SnrRule.dielectric_edges``, "Session 27"). (b, c) are refreshed every ``SNR_EVERY`` LM steps and at the
  final modes, which are refined with their mechanisms held. This is what makes floors
  separable: with ranges alone (4 anchors, 5 cm sigma) another floor's best mode explains the
  ranges as well as the true one for about half the receivers; with the true mechanisms the
  floor is right for 92 % (300 receivers), with (a-c) M-NLS reaches 89 %.
* **Latent mechanism (max-mixture).** At every iteration, per link, the mechanism is the
  existing one whose length best explains the range under the likelihood below. Ambiguous
  links (two mechanisms within a few cm) pick either; the covariance accounts for it.
* **First arrival never later than a specular path through the opening.** A direct or
  specular path that enters through the window is strong (SNR of such first arrivals: p1 24 dB,
  median 38 dB, vs. -2 dB median for single diffraction) and is always detected: the first
  arrival was later than the shortest existing one on 0 of 32,480 links, and when the direct
  path passes the opening it *is* the first arrival on 100 % of 4,880 links. Diffraction is
  weak and often below the detection threshold (first arrival later than the lower-edge
  diffraction on 51 % of links), so it does not constrain. Hence the candidate mechanisms of
  a link are those no longer than its shortest existing specular path.
* **Robust likelihood.** Gaussian core ``N(0, sigma^2)`` on ``r - L_m`` plus a one-sided
  exponential component for an unmodelled positive excess (NLoS excess is positive: blocked
  or unmodelled paths only delay the first arrival): ``p(e) = (1 - eps) N(e; 0, sigma^2) +
  eps / lambda exp(-e / lambda) [e > 0]``, used as a max-mixture (the cheaper component per
  link). ``eps = 0.02`` (a prior share of links outside the model; the emulator has none: the
  first arrival is a model mechanism on 100 % of links), ``lambda = c / B`` (0.75 m at 400 MHz:
  an unresolved path delays the detected peak by up to one resolution cell). Links that end
  in the tail component are reported as excluded (RAIM).
* **One link out of the model** (any first arrival the families do not have: a shorter or a
  far longer range than every candidate). In a fix with at least five links
  (:data:`diffpos.estimators.mnls.problem.CAP_MIN_LINKS`), the link whose cost exceeds it the
  most (at most one per fix) is capped at the cost of an out-of-model link, the outlier prior ``eps`` times a range uniform over the
  building's extent ``D`` (diagonal of width x depth x all floors): ``C_out = log((1 - eps) /
  eps) + log(D / (sigma sqrt(2 pi)))`` (9.8 nats on the paper building at 5 cm); a capped link
  has no weight and is reported as excluded. The search, the refinement and the floor scores
  share this one objective (inside the compiled link terms and LM as in the numpy reference).
  With three or four links the others cannot outvote a link (any three fit exactly): no cap.
* **Noise.** ``sigma_j = max(sigmas_m, error_floor_m)``: the caller's ranging sigma (the
  emulator's is ``sqrt(CRLB^2 + floor^2)``), never below the chain's error floor.
* **z observability and the floor prior.** With the physical edges an edge path fixes only x
  and the distance to the edge line; z comes from combining mechanisms and anchors at
  different elevations. A weak prior keeps unobservable directions finite: the node is
  uniform over its floor's height, approximated by ``N(z_floor + H/2, H^2/12)`` (H the floor
  height); the node is also kept inside the floor's box.
* **Floor posterior.** Laplace approximation of each floor's best mode:
  ``p_k ~ exp(-C_k) det(H_k)^(-1/2)`` (``C_k`` the cost, ``H_k`` its Gauss-Newton Hessian),
  normalised over the floors. The answer is the most probable floor's mode.
* **Covariance.** ``sum_k p_k (H_k^-1 + (mu_k - x)(mu_k - x)^T)``: the inverse information of
  each floor's mode (with per-link variance ``sigma_j^2`` plus ``(dL / 2)^2`` for an
  alternative mechanism within ``3 sigma_j`` whose length differs by ``dL``), mixed over the
  floor posterior around the answer, times the a posteriori variance factor
  ``max(1, T / dof)`` (``T`` the residual chi-square statistic): residuals larger than the
  sigmas widen it, never narrow it (random held-out buildings: 95 % ellipsoid coverage 79 %
  without, 86 % with it).
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from functools import partial

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos._kernels.pool import LM_MIN_ROWS, run_rows
from diffpos.channel.detection import skipped_cost
from diffpos.constants import SPEED_OF_LIGHT_M_S
from diffpos.estimators.mnls.problem import (
    _c,
    _Problem,
    _problem,
    _replace_snr,
    _sub,
    _take,
)
from diffpos.estimators.mnls.result import (
    MnlsResult,
    _box_log_mass,
    _information,
    _posterior,
    _result,
)
from diffpos.estimators.mnls.rules import (
    DEFAULT_SNR_RULE,
    SNR_MARGIN_DB,
    SNR_SIGMA_DB,
    SnrRule,
    _excess_loss_db,
    _masks,
    snr_radio,
)
from diffpos.estimators.mnls.starts import (
    _grid,
    _kept,
    _link_terms_rows,
    _start_points,
)
from diffpos.estimators.result import prepare_batch
from diffpos.paths.mechanisms import DEFAULT_ORDER, MECHANISMS, mechanism_set
from diffpos.paths.model import first_arrival_paths
from diffpos.paths.model_nb import (
    DEFAULT_TABLE,
    building_planes,
    mechanism_table,
    partition_array,
)

__all__ = [
    "mnls",
]

FloatArray = NDArray[np.float64]
_TABLES: dict = {}


def _table(mech) -> NDArray[np.int64]:
    """The compiled mechanism table of ``mech`` (None: the 18)."""
    if mech is None:
        return DEFAULT_TABLE
    if mech not in _TABLES:
        _TABLES[mech] = mechanism_table(mech.recipes)
    return _TABLES[mech]

#: Fixes with at most this many links: the best floor's mode is carried to the other floors as
#: one more start each (:func:`_transfer`; 0: never). Three: an exactly determined fix.
TRANSFER_MAX_LINKS = 3
#: Levenberg-Marquardt iterations of the refinement with the SNR-chosen mechanisms held.
REFINE_ITER = 6
#: Levenberg-Marquardt steps from every grid cell before the best ``keep_starts`` go on.
SCREEN_ITER = 3
#: An accepted LM step shorter than this (max over x, y, z) ends a hypothesis's iterations [m]
#: (far below any range sigma).
CONVERGED_M = 1e-4
#: Iterations between refreshes of the SNR cost during the search.
SNR_EVERY = 4
#: A floor whose best screened cost exceeds the best floor's by this much [nats] is not
#: refined (posterior odds below exp(-PRUNE_NATS) before refinement).
PRUNE_NATS = 30.0
#: The kept cells of a floor are re-scored with the SNR only when its best screened cost is
#: within this much of the best floor's [nats] (the others are not refined).
RESCORE_NATS = 2 * PRUNE_NATS
#: Most links per fix the compiled LM (``kernel=True``) takes (numpy's pairwise summation
#: order is reproduced up to 128 terms); more: the reference steps.
_KERNEL_MAX_LINKS = 128
#: Default false-alarm probability of the residual test.
FALSE_ALARM_PROBABILITY = 1e-3
#: Per-stage counters (``benchmarks/bench_mnls.py --stages``): ``None`` (off, the default) or
#: a dict that :func:`mnls` fills with ``stage -> {"paths": node-anchor pairs through the
#: path model, "snr": pairs through pair_snr_db, "cpu_s", "paths_cpu_s", "snr_cpu_s": thread
#: CPU time of the stage and of those two calls in it [s]}``; stages ``starts``, ``screen``,
#: ``rescore``, ``refine``, ``final``.
STAGE_STATS: dict | None = None
_STAGE = ["starts"]  # the stage being counted


@contextmanager
def _stage(name: str):
    """Count the enclosed work under stage ``name`` when :data:`STAGE_STATS` is on."""
    if STAGE_STATS is None:
        yield
        return
    prev, _STAGE[0] = _STAGE[0], name
    c0 = time.thread_time()
    try:
        yield
    finally:
        _count("cpu_s", time.thread_time() - c0)
        _STAGE[0] = prev


def _count(key: str, value: float) -> None:
    if STAGE_STATS is not None:
        d = STAGE_STATS.setdefault(_STAGE[0], dict.fromkeys(
            ("paths", "snr", "cpu_s", "paths_cpu_s", "snr_cpu_s", "kernel_cpu_s"), 0.0))
        d[key] += value



def _link_terms(p: _Problem, x: FloatArray, building) -> dict[str, FloatArray]:
    """Paths at ``x`` (N, 3), mechanism choice and the cost terms of every link: the
    compiled kernel (:func:`diffpos.estimators.mnls.solver_nb.link_terms_kernel`) on the path model's
    output, the same operations as :func:`_link_terms_numpy` (the reference)."""
    c0 = time.thread_time()
    ps = first_arrival_paths(x[:, None, :], p.anchors, building, floor=p.floor[:, None],
                             mechanisms=p.mech)
    # imported here: importing solver_nb compiles M-NLS (explicit signatures), which a
    # D-NLS, LLS or IPPA fusion never runs
    from diffpos.estimators.mnls.solver_nb import link_terms_kernel

    n, m, k = ps.length_m.shape
    spec, diff, same_edge = _masks(p.mech)
    _count("paths_cpu_s", time.thread_time() - c0)
    _count("paths", n * m)
    b1 = lambda a: np.zeros((0, 0, 0), bool) if a is None else _c(a, bool)  # noqa: E731
    out = {"cost": np.empty((n, m)), "res": np.empty((n, m)), "w": np.empty((n, m)),
           "slot": np.empty((n, m), dtype=np.int64), "tail": np.empty((n, m), dtype=bool),
           "none": np.empty((n, m), dtype=bool), "cand": np.empty((n, m, k), dtype=bool),
           "jac": np.empty((n, m, 3))}
    link_terms_kernel(
        _c(ps.length_m), b1(ps.valid), _c(ps.jacobian), _c(ps.deviation_cos), _c(ps.outside_m),
        _c(p.r), _c(p.sig), _c(p.mask, bool),
        _c(np.broadcast_to(p.tail_a, (n, m))), _c(np.broadcast_to(p.cap, (n, m))),
        _c(p.excess_db), float(p.lam),
        float(p.wavelength_m), float(SNR_MARGIN_DB),
        np.zeros((0, 0, 0)) if p.snr_cost is None else _c(p.snr_cost), b1(p.strong),
        b1(p.allowed), spec, diff, same_edge, out["cost"], out["res"],
        out["w"], out["slot"], out["tail"], out["none"], out["cand"], out["jac"])
    prior = 0.5 * (x[:, 2] - p.z_mid) ** 2 / p.prior_var
    out["cost"] = out["cost"].sum(axis=-1) + prior
    out["length"] = ps.length_m
    return out


def _snr_cost(p: _Problem, x: FloatArray, building) -> FloatArray | None:
    """Gaussian SNR cost of every slot at ``x``: measured vs predicted (:data:`SNR_SIGMA_DB`);
    predicted for the links in the mask only (a link outside it costs nothing whatever its
    terms; its cost and ``strong`` are 0 / False)."""
    if p.snr_meas is None or p.radio is None:
        return None
    c0 = time.thread_time()
    m = p.mask
    rule = DEFAULT_SNR_RULE if p.rule is None else p.rule
    pred = _slot_snr(p, x, building, p.radio)
    sheet = (_slot_snr(p, x, building, snr_radio(p.radio, SnrRule(dielectric_edges=1.0)))
             if 0.0 < rule.dielectric_edges < 1.0 else None)
    if p.mech is not None and len(p.mech) > len(MECHANISMS):
        fam = _family_snr(p, x, building)
        pred = np.concatenate([pred, fam], axis=-1)
        sheet = None if sheet is None else np.concatenate([sheet, fam], axis=-1)
    _count("snr_cpu_s", time.thread_time() - c0)
    _count("snr", np.count_nonzero(m))
    meas = p.snr_meas[..., None]
    with np.errstate(invalid="ignore", over="ignore"):
        c = 0.5 * ((meas - pred) / SNR_SIGMA_DB) ** 2
        if sheet is not None:  # either edge material (SnrRule.dielectric_edges its prior)
            q = rule.dielectric_edges
            c2 = 0.5 * ((meas - sheet) / SNR_SIGMA_DB) ** 2
            lo = np.fmin(c, c2)
            c = lo - np.log((1 - q) * np.exp(lo - c) + q * np.exp(lo - c2))
            c = np.where(np.isfinite(c), c, lo)
        # the detector keeps paths above max(P_max - fap_threshold, detection floor): a
        # first arrival far below the predicted strongest path's threshold is inconsistent
        thr = np.maximum(np.max(pred, axis=-1, keepdims=True) - p.radio.fap_threshold_db,
                         p.radio.detection_snr_db)
        short = np.maximum(thr - SNR_SIGMA_DB - meas, 0.0)
        c = c + 0.5 * (short / SNR_SIGMA_DB) ** 2
        if rule.measured_threshold:  # the strongest path is at least the measured one
            thr = np.fmax(thr, meas - p.radio.fap_threshold_db)
    c = np.where(np.isfinite(pred), c, np.inf)  # a slot that does not exist is not received
    p.strong = pred >= thr + SNR_SIGMA_DB  # surely detected at this hypothesis
    if rule.first_arrival_prior > 0:  # the soft skip prior (replacing the hard rule)
        ps = first_arrival_paths(x[:, None, :], p.anchors, building, floor=p.floor[:, None],
                                 mechanisms=p.mech)
        c = c + skipped_cost(ps.length_m, ps.valid & np.isfinite(pred), pred, thr,
                             SNR_SIGMA_DB, rule.first_arrival_prior)
        if not rule.keep_hard_rule:
            p.strong = np.zeros(pred.shape, dtype=bool)
    return np.where((np.isfinite(p.snr_meas) & m)[..., None], c, 0.0)


def _slot_snr(p: _Problem, x: FloatArray, building, radio) -> FloatArray:
    """Predicted SNR of the 18 slots at ``x`` with ``radio``
    (:func:`diffpos.channel.emulator.pair_snr_db`), ``-inf`` off the mask."""
    from diffpos.channel.emulator import pair_snr_db

    m = p.mask
    if m.all():
        return pair_snr_db(p.anchors, x, building=building, radio=radio)
    xm = np.broadcast_to(x[:, None, :], p.anchors.shape)[m]  # the linked pairs only
    pm = pair_snr_db(p.anchors[m][:, None, :], xm, building=building, radio=radio)
    pred = np.full((*m.shape, pm.shape[-1]), -np.inf)
    pred[m] = pm[:, 0]
    return pred


def _family_snr(p: _Problem, x: FloatArray, building) -> FloatArray:
    """SNR (:func:`diffpos.estimators.mnls.power.family_snr_db`: the emulated channel's
    physics) of the families beyond the emulator's 18 slots at ``x``, ``-inf`` off the mask."""
    from diffpos.estimators.mnls.power import family_snr_db

    extra = np.arange(len(MECHANISMS), len(p.mech))
    m = p.mask
    out = np.full((*m.shape, extra.size), -np.inf)
    rows, links = np.nonzero(m)
    out[rows, links] = family_snr_db(p.anchors[rows, links], x[rows], building, p.radio,
                                     p.mech, extra)
    return out


def _lm(p: _Problem, x: FloatArray, building, iters: int, t_init: dict | None = None,
        kernel: bool = False) -> tuple[FloatArray, dict]:
    """Projected Levenberg-Marquardt with max-mixture re-assignment at every step; with the
    measured SNR, the SNR cost of every slot is refreshed every :data:`SNR_EVERY` steps
    (``t_init``: the terms at ``x``, SNR cost already in ``p``)."""
    if kernel and p.r.shape[1] <= _KERNEL_MAX_LINKS:
        return _lm_compiled(p, x, building, iters, snr_at_start=t_init is None)
    n = x.shape[0]
    lam = np.full(n, 1e-3)
    if t_init is None:  # the SNR cost at the start first: the terms are computed once
        if p.snr_meas is not None:
            p.snr_cost = _snr_cost(p, x, building)
        t = _link_terms(p, x, building)
    else:
        t = t_init
    live = np.arange(n)
    q = p
    for i in range(iters):
        if live.size < q.r.shape[0]:  # drop the converged hypotheses
            q = _sub(p, live)
        if p.snr_meas is not None and i > 0 and i % SNR_EVERY == 0:
            q.snr_cost = _snr_cost(q, x[live], building)
            if q is not p:
                p.snr_cost[live], p.strong[live] = q.snr_cost, q.strong
            tl = _link_terms(q, x[live], building)
            for k in t:
                t[k][live] = tl[k]
        tl = t if live.size == n else {k: t[k][live] for k in ("cost", "w", "res", "jac")}
        xl = x[live]
        ws = tl["w"] / q.sig**2
        h = np.einsum("nm,nmi,nmj->nij", ws, tl["jac"], tl["jac"])
        g = np.einsum("nm,nm,nmi->ni", ws, tl["res"], tl["jac"])
        h[:, 2, 2] += 1.0 / q.prior_var
        g[:, 2] -= (xl[:, 2] - q.z_mid) / q.prior_var
        diag = np.diagonal(h, axis1=1, axis2=2)
        hd = h + lam[live, None, None] * np.eye(3) * (diag + 1e-9)[:, None, :]
        step = np.linalg.solve(hd, g[..., None])[..., 0]
        x_new = np.clip(xl + step, q.lo, q.hi)
        t_new = _link_terms(q, x_new, building)
        ok = t_new["cost"] < tl["cost"]
        acc = live[ok]
        x[acc] = x_new[ok]
        for k in t:
            t[k][acc] = t_new[k][ok]
        lam[live] = np.where(ok, lam[live] / 3.0, lam[live] * 4.0)
        # converged: an accepted step below CONVERGED_M (the mechanisms no longer change)
        moved = np.max(np.abs(x_new - xl), axis=-1)
        live = live[~(ok & (moved < CONVERGED_M)) & (lam[live] < 1e6)]
    return x, t


def _solve_chunk(a, r, sig, mask, excess, building, *, grid, keep, iters, lam, wavelength,
                 snr=None, radio=None, x0=None, kernel=False, mech=None,
                 rule: SnrRule = DEFAULT_SNR_RULE):
    """All floors x starts of B fixes; returns per-fix-per-floor modes and terms."""
    b = r.shape[0]
    nf = building.n_floors
    g = grid.shape[0]
    floors = np.tile(np.repeat(np.arange(nf), g), b)  # (B*F*G,)
    rep = nf * g
    with _stage("starts"):
        p0 = _problem(np.repeat(a, rep, axis=0), np.repeat(r, rep, axis=0),
                      np.repeat(sig, rep, axis=0), np.repeat(mask, rep, axis=0), floors,
                      building, lam, np.repeat(excess, rep, axis=0), wavelength, mech, rule)
        x, closed = _start_points(p0, grid, building, b, x0, kernel=kernel)
    # screening: a few LM steps from every cell (a cell's cost before any step says little:
    # a metre off, every link is explained by the wrong mechanism), with the SNR terms of
    # the closed-form starts' starting points (they steer the mechanism choice: without them
    # the floor accuracy drops by 1-4 points); the grid cells with ranges only
    if snr is not None and radio is not None:
        p0.snr_meas, p0.radio = np.repeat(snr, rep, axis=0), radio
    split = closed.reshape(b, nf, g) if p0.snr_meas is not None else None
    if split is not None and not (split.sum(-1).min() >= keep and (~split).sum(-1).min() >= 1):
        split = None  # too few closed-form starts or no grid cell: every start with the SNR
    with _stage("screen"):
        x, t0 = _screen(p0, x, None if split is None else closed, building, kernel=kernel)
    with _stage("rescore"):
        c0 = t0["cost"].reshape(b, nf, g)
        best = _kept(c0, split, keep)  # (B, F, keep (+ 1 grid cell))
        keep = best.shape[-1]
        rows = ((np.arange(b)[:, None, None] * nf + np.arange(nf)[None, :, None]) * g
                + best).ravel()
        p = _problem(p0.anchors[rows], p0.r[rows], p0.sig[rows], p0.mask[rows], floors[rows],
                     building, lam, p0.excess_db[rows], wavelength, mech, rule)
        x = x[rows]
        if "res" in t0:
            t = {k: v[rows] for k, v in t0.items()}
        else:  # the compiled screen returned the costs only: the kept rows' terms at their
            # points when needed (with the SNR: only of the rows the re-scoring leaves out)
            def t_rows(sel):
                return _link_terms(_sub(p0, rows[sel]), x[sel], building)

            t = t_rows if snr is not None and radio is not None else t_rows(slice(None))
        if snr is not None and radio is not None:  # the kept cells scored with the SNR too
            p.snr_meas, p.radio = np.repeat(snr, nf * keep, axis=0), radio
            t = _rescore(p, x, t, c0, keep, building)
        # floors whose best kept cost is PRUNE_NATS above the best floor's are not refined
        fbest = np.min(t["cost"].reshape(b, nf, keep), axis=-1)
        active = fbest <= np.min(fbest, axis=-1, keepdims=True) + PRUNE_NATS  # (B, F)
    with _stage("refine"):
        sub = np.flatnonzero(np.repeat(active.ravel(), keep))
        ps = _take(p, sub)
        if p.snr_cost is not None:
            ps.snr_meas, ps.radio = p.snr_meas[sub], radio
            ps.snr_cost, ps.strong = p.snr_cost[sub], p.strong[sub]
        x[sub], ts = _lm(ps, x[sub], building, iters,
                         t_init={k: v[sub] for k, v in t.items()}, kernel=kernel)
        for k in t:
            t[k][sub] = ts[k]
        cost = t["cost"].reshape(b, nf, keep)
        pick = np.argmin(cost, axis=-1)  # best start per floor
    sel = ((np.arange(b)[:, None] * nf + np.arange(nf)[None, :]) * keep + pick).ravel()
    xs, ts = x[sel], {k: v[sel] for k, v in t.items()}
    if nf > 1 and np.any(mask.sum(axis=-1) <= TRANSFER_MAX_LINKS):
        with _stage("transfer"):
            xs, ts, moved = _transfer(p, xs, ts, sel, building, iters, snr, radio, kernel)
        fbest = ts["cost"].reshape(b, nf)  # a floor a new mode brings within PRUNE_NATS joins
        active |= moved.reshape(b, nf) & (
            fbest <= np.min(fbest, axis=-1, keepdims=True) + PRUNE_NATS)
    if rule.shadow_starts > 0 and snr is not None and radio is not None:
        with _stage("shadow"):
            xs, ts = _shadow_starts(p, xs, ts, sel, active.ravel(), building, iters,
                                    np.repeat(snr, nf, axis=0), radio, kernel,
                                    rule.shadow_starts)
    return p, xs.reshape(b, nf, 3), ts, sel, active.ravel()


def _shadow_starts(p: _Problem, xs: FloatArray, ts: dict, sel, active, building, iters: int,
                   snr, radio, kernel: bool, d: float) -> tuple[FloatArray, dict]:
    """The boundary starts (:attr:`~diffpos.estimators.mnls.rules.SnrRule.shadow_starts`):
    for every active row of ``xs`` (B*F, 3; rows of ``p`` at ``sel``, ``snr`` per row) whose
    mode explains a link by a horizontal window-edge diffraction whose lit counterpart does
    not exist there, six starts at ``+-d`` along x, y, z, ``iters`` LM steps with the SNR
    terms; the row takes the cheapest new mode where that link takes the counterpart, if it
    costs less than the mode (terms at the mode with the SNR refreshed there). Returns
    ``xs`` and ``ts`` updated."""
    act = np.flatnonzero(active)
    q = _take(p, sel[act])
    q.snr_meas, q.radio = snr[act], radio
    q.snr_cost = _snr_cost(q, xs[act], building)
    t0 = _link_terms(q, xs[act], building)
    lit = np.asarray(mechanism_set(DEFAULT_ORDER).lit if p.mech is None else p.mech.lit)
    cp = lit[t0["slot"]]  # (A, M) the chosen slot's counterpart
    cp_len = np.take_along_axis(t0["length"], np.maximum(cp, 0)[..., None], axis=-1)[..., 0]
    shadow = (q.mask & ~t0["tail"] & ~t0["none"] & (cp >= 0) & ~np.isfinite(cp_len))
    go = np.flatnonzero(np.any(shadow, axis=-1))
    if go.size == 0:
        return xs, ts
    rows = np.repeat(go, 6)
    qs = _take(q, rows)
    qs.snr_meas, qs.radio = q.snr_meas[rows], radio
    x0 = np.clip(xs[act][rows] + np.tile(d * np.vstack([np.eye(3), -np.eye(3)]), (go.size, 1)),
                 qs.lo, qs.hi)
    xn, tn = _lm(qs, x0, building, iters, kernel=kernel)
    crossed = np.any(shadow[rows] & (tn["slot"] == cp[rows]), axis=-1)
    c2 = np.where(crossed, tn["cost"], np.inf).reshape(go.size, 6)
    j = np.argmin(c2, axis=-1)
    better = c2[np.arange(go.size), j] < t0["cost"][go] - 1e-6
    pick = (np.arange(go.size) * 6 + j)[better]  # rows of the LM call
    dest = act[go[better]]
    xs, ts = xs.copy(), {k: v.copy() for k, v in ts.items()}
    xs[dest] = xn[pick]
    for k in ts:
        ts[k][dest] = tn[k][pick]
    return xs, ts


def _transfer(p: _Problem, xs: FloatArray, ts: dict, sel, building, iters: int, snr, radio,
              kernel: bool) -> tuple[FloatArray, dict, NDArray[np.bool_]]:
    """The best floor's mode carried to every other floor (module docstring): per
    fix, the (x, y) of its lowest-cost floor's mode with each other floor's middle height
    starts :func:`_lm` (``iters`` steps, the SNR terms as in the refinement) on that floor;
    a floor keeps the new mode where it costs less. ``xs`` (B*F, 3) and ``ts`` the modes and
    terms of every fix x floor (rows of ``p`` at ``sel``); returns them updated and which
    rows took a new mode."""
    nf = building.n_floors
    b = xs.shape[0] // nf
    top = np.argmin(ts["cost"].reshape(b, nf), axis=-1)  # (B,): each fix's best floor
    best = xs.reshape(b, nf, 3)[np.arange(b), top]  # (B, 3)
    q = _take(p, sel)
    x0 = np.repeat(best, nf, axis=0)
    x0[:, 2] = q.z_mid
    go = np.flatnonzero(np.all(np.isfinite(x0), axis=-1)
                        & (np.arange(b * nf) % nf != np.repeat(top, nf))
                        & (q.mask.sum(axis=-1) <= TRANSFER_MAX_LINKS))
    moved = np.zeros(b * nf, dtype=bool)
    if go.size == 0:
        return xs, ts, moved
    q = _take(q, go)
    if snr is not None and radio is not None:
        q.snr_meas, q.radio = np.repeat(snr, nf, axis=0)[go], radio
    xn, tn = _lm(q, np.clip(x0[go], q.lo, q.hi), building, iters, kernel=kernel)
    better = tn["cost"] < ts["cost"][go]
    rows = go[better]
    moved[rows] = True
    xs = xs.copy()
    xs[rows] = xn[better]
    ts = {k: v.copy() for k, v in ts.items()}
    for k in ts:
        ts[k][rows] = tn[k][better]
    return xs, ts, moved


def _screen(p0: _Problem, x: FloatArray, closed, building, kernel: bool = False
            ) -> tuple[FloatArray, dict]:
    """:data:`SCREEN_ITER` LM steps from every start ``x``; with the measured SNR, the SNR
    terms at the start held for the steps: of every start (``closed`` None) or only of the
    closed-form and caller's starts (``closed``, a row mask; the grid cells' SNR cost is 0
    and nothing is ``strong`` there: screened with the ranges only). With ``kernel``, the
    steps run in :func:`diffpos.estimators.mnls.solver_nb.lm_kernel` and the terms returned hold the
    ``cost`` only (the caller evaluates the rows it keeps)."""
    compiled = kernel and p0.r.shape[1] <= _KERNEL_MAX_LINKS
    if closed is None:
        if compiled:
            return _lm_compiled(p0, x, building, SCREEN_ITER, want_terms=False)
        return _lm(p0, x, building, SCREEN_ITER)
    _closed_snr(p0, x, closed, building)
    if compiled:
        return _lm_compiled(p0, x, building, SCREEN_ITER, snr_at_start=False, want_terms=False)
    return _lm(p0, x, building, SCREEN_ITER, t_init=_link_terms(p0, x, building))


def _closed_snr(p0: _Problem, x: FloatArray, closed, building) -> None:
    """The SNR cost and ``strong`` flags of the ``closed`` rows at ``x``, 0 / False on the
    other rows (set on ``p0``)."""
    rows = np.flatnonzero(closed)
    q = _sub(p0, rows)
    q.snr_cost = _snr_cost(q, x[rows], building)
    p0.snr_cost = np.zeros((*p0.mask.shape, q.snr_cost.shape[-1]))
    p0.strong = np.zeros(p0.snr_cost.shape, dtype=bool)
    p0.snr_cost[rows], p0.strong[rows] = q.snr_cost, q.strong


def _lm_compiled(p: _Problem, x: FloatArray, building, iters: int, snr_at_start: bool = True,
                 want_terms: bool = True) -> tuple[FloatArray, dict]:
    """:func:`_lm` in :func:`diffpos.estimators.mnls.solver_nb.lm_kernel`: the steps between two SNR
    refreshes in one compiled call, the refreshes as in :func:`_lm`; the terms at the
    returned points evaluated once at the end (the same values: row by row the same function
    of the point and the held SNR terms), or ``{"cost": ...}`` only (``want_terms`` False).
    ``snr_at_start`` False: the SNR terms in ``p`` are those at ``x`` (``_lm``'s ``t_init``)."""
    n = x.shape[0]
    x = _c(x).copy()
    if p.snr_meas is not None and snr_at_start:  # the SNR cost at the start
        p.snr_cost = _snr_cost(p, x, building)
    damp = np.full(n, 1e-3)
    live = np.ones(n, dtype=bool)
    cost = np.full(n, np.nan)
    e3 = np.zeros((0, 0, 0))
    per_row = (_c(p.anchors), _c(p.r), _c(p.sig), _c(p.mask, bool),
               _c(np.broadcast_to(p.tail_a, p.r.shape)), _c(np.broadcast_to(p.cap, p.r.shape)),
               _c(p.excess_db), _c(p.floor),
               _c(p.lo), _c(p.hi), _c(p.z_mid))
    consts = (float(p.prior_var), float(p.lam), float(p.wavelength_m), float(SNR_MARGIN_DB),
              np.array(building_planes(building)), _table(p.mech), partition_array(building))
    allowed = e3.astype(bool) if p.allowed is None else _c(p.allowed, bool)
    done = 0
    while done < iters and live.any():
        seg = iters - done
        if p.snr_meas is not None and p.snr_cost is not None:
            if done > 0:  # refresh the SNR terms of the live rows (as _lm at i % SNR_EVERY)
                rows = np.flatnonzero(live)
                q = _sub(p, rows)
                q.snr_cost = _snr_cost(q, x[rows], building)
                p.snr_cost[rows], p.strong[rows] = q.snr_cost, q.strong
            seg = min(seg, SNR_EVERY)
        c_seg = np.empty(n)
        evals = np.empty(n, dtype=np.int64)
        live_after = live.copy()
        snr = (e3 if p.snr_cost is None else _c(p.snr_cost),
               e3.astype(bool) if p.strong is None else _c(p.strong, bool), allowed)
        kernel_cpu = run_rows(partial(_lm_rows, per_row, consts, snr, _masks(p.mech), int(seg),
                                      x, damp, live_after, c_seg, evals), n,
                              min_rows=LM_MIN_ROWS)
        _count("kernel_cpu_s", kernel_cpu)
        _count("paths", int(evals.sum()))
        cost = np.where(live, c_seg, cost)  # rows live at the call: their cost now
        live = live_after
        done += seg
    if not want_terms:
        return x, {"cost": cost}
    return x, _link_terms(p, x, building)


def _lm_rows(per_row: tuple, consts: tuple, snr: tuple, masks: tuple, iters: int,
             x: FloatArray, damp: FloatArray, live: NDArray[np.bool_], cost: FloatArray,
             evals: NDArray[np.int64], lo: int, hi: int) -> None:
    """:func:`diffpos.estimators.mnls.solver_nb.lm_kernel` on the rows ``[lo, hi)``
    (:func:`diffpos._kernels.pool.run_rows`): the row slices of every per-row array (an empty
    SNR array, (0, 0, 0), stays whole), ``consts`` whole, the same compiled signature."""
    from diffpos.estimators.mnls.solver_nb import lm_kernel  # compiles on import: when used

    rows = slice(lo, hi)
    s = [v if v.shape[0] == 0 else v[rows] for v in snr]
    lm_kernel(*(v[rows] for v in per_row), *consts, *s, *masks, iters, float(CONVERGED_M),
              x[rows], damp[rows], live[rows], cost[rows], evals[rows])


def _rescore(p: _Problem, x: FloatArray, t, c0: FloatArray, keep: int, building
             ) -> dict:
    """The kept cells' terms with the SNR at their screened points, for the floors whose
    screened best ``c0`` (B, F, G) is within :data:`RESCORE_NATS` of the fix's best floor;
    the other floors' cells get an infinite cost. ``t``: the screened terms of the kept
    cells, or a function of a row selection returning them (evaluated for the rows left
    out only)."""
    f0 = np.min(c0, axis=-1)
    go = np.repeat((f0 <= np.min(f0, axis=-1, keepdims=True) + RESCORE_NATS).ravel(), keep)
    if go.all():
        p.snr_cost = _snr_cost(p, x, building)
        return _link_terms(p, x, building)
    rows = np.flatnonzero(go)
    q = _sub(p, rows)
    q.snr_cost = _snr_cost(q, x[rows], building)
    tq = _link_terms(q, x[rows], building)
    n, (m, k) = go.size, tq["length"].shape[1:]
    p.snr_cost, p.strong = np.zeros((n, m, k)), np.zeros((n, m, k), dtype=bool)
    p.snr_cost[rows], p.strong[rows] = q.snr_cost, q.strong
    if callable(t):
        out = _link_terms_rows(t, ~go, n)
    else:
        out = {key: v.copy() for key, v in t.items()}
    for key in out:
        out[key][rows] = tq[key]
    out["cost"][~go] = np.inf
    return out


def mnls(
    anchors_m: ArrayLike,
    ranges_m: ArrayLike,
    sigmas_m: ArrayLike | None = None,
    *,
    building,
    mask: ArrayLike | None = None,
    snr_db: ArrayLike | None = None,
    radio=None,
    error_floor_m: float = 0.05,
    bandwidth_hz: float = 400e6,
    grid_shape: tuple[int, int] = (4, 3),
    keep_starts: int = 2,
    max_iter: int = 10,
    false_alarm_probability: float = FALSE_ALARM_PROBABILITY,
    chunk_size: int = 256,
    x0_m: ArrayLike | None = None,
    kernel: bool = True,
    max_order: int = DEFAULT_ORDER,
    snr_rule: SnrRule = DEFAULT_SNR_RULE,
) -> MnlsResult:
    """Batched mechanism-aware position fixes (module docstring).

    Parameters
    ----------
    anchors_m : array_like, shape (B, M, 3) or (M, 3) [m]
    ranges_m : array_like, shape (B, M) or (M,) [m]
        Measured first-arrival ranges.
    sigmas_m : array_like, shape (B, M), scalar or None [m]
        Ranging standard deviations (e.g. ``FirstArrival.sigma_m``); ``None``: the error floor.
    building : diffpos.scenario.Building
        Floors, window bands, width and depth (the path model's geometry).
    mask : array_like of bool, shape (B, M), optional
        Which measurements exist.
    snr_db : array_like, shape (B, M), optional [dB]
        Measured SNR of each first arrival; with ``radio``, a diffracted mechanism is not a
        candidate for a link whose loss below free space is smaller than its knife-edge loss
        minus :data:`SNR_MARGIN_DB` (module docstring).
    radio : diffpos.scenario.Radio, optional
        Link budget for the free-space SNR (power, gains, processing gain, noise, frequency).
    error_floor_m : float [m]
        Lower bound of every link's sigma (the ranging chain's error floor).
    bandwidth_hz : float [Hz]
        Signal bandwidth; the NLoS excess scale is ``c / B``.
    grid_shape : (int, int)
        Coarse start grid (cells along x, along y) per floor.
    keep_starts : int
        Closed-form (or caller's) starts refined per floor, by their SNR-aware screened cost;
        with ``snr_db`` and ``radio`` the best grid cell (screened with the ranges only) is
        refined beside them.
    max_iter : int
        Levenberg-Marquardt iterations per start.
    false_alarm_probability : float
        Of the chi-square residual test on the links kept (Gaussian component).
    chunk_size : int
        Fixes solved together (memory bound).
    x0_m : array_like, shape (B, 3) or (3,), optional [m]
        An extra start per fix (e.g. a tracker's prediction), searched on the floor it lies
        on beside the regular starts (NaN rows: none).
    kernel : bool
        Levenberg-Marquardt steps (screen, refinement) in the compiled kernel
        (:func:`diffpos.estimators.mnls.solver_nb.lm_kernel`, the default) or in the numpy/numba
        reference steps (``False``); the same answers (tests/core/test_mnls.py).
    max_order : int
        The path model's mechanisms (:func:`diffpos.paths.mechanisms.mechanism_set`): 2 (the
        default) the 18 of :data:`diffpos.paths.mechanisms.MECHANISMS`; 3 or 4 adds the
        higher-order families (slab image series, ground bounce before the diffraction, wall
        reflections; on a building with interior partitions also the partition-reflection
        families, ``mechanism_set(max_order, partitions=True)``), whose SNR term is
        :mod:`diffpos.estimators.mnls.power`'s estimate.
        ``MnlsResult.mechanism`` then indexes ``mechanism_set(max_order, partitions=bool(
        building.partitions)).labels``.
    snr_rule : diffpos.estimators.mnls.rules.SnrRule
        How the detector's rule bounds the candidates (with ``snr_db`` and ``radio``): the
        default is the predicted threshold and the hard rule of the module docstring's (c);
        the measured first arrival's lower bound on the threshold and the soft skip prior
        are options (off by default; docs/raytrace_study.md "Session 26").

    Returns
    -------
    MnlsResult
        ``method="mnls"``, ``covariance_model="first-arrival model, floor mixture"``.
    """
    if not error_floor_m >= 0 or not bandwidth_hz > 0:
        raise ValueError("error_floor_m must be >= 0 and bandwidth_hz > 0")
    bi = prepare_batch(anchors_m, ranges_m, sigmas_m, mask)
    radio = snr_radio(radio, snr_rule)  # the edges' material of the SNR model (rules.SnrRule)
    bsz, m = bi.ranges_m.shape
    nf = building.n_floors
    sig = bi.sigmas_m if bi.sigmas_given else np.full((bsz, m), max(error_floor_m, 1e-3))
    sig = np.maximum(sig, max(error_floor_m, 1e-6))
    lam = SPEED_OF_LIGHT_M_S / bandwidth_hz
    grid = _grid(building, *grid_shape)
    excess = _excess_loss_db(bi.ranges_m, snr_db, radio, (bsz, m))
    snr_all = None if snr_db is None else np.broadcast_to(
        np.asarray(snr_db, dtype=np.float64), (bsz, m))
    wavelength = SPEED_OF_LIGHT_M_S / (28e9 if radio is None else radio.frequency_hz)
    mech = None if max_order <= DEFAULT_ORDER else mechanism_set(
        max_order, partitions=bool(building.partitions))
    out = {
        "position_m": np.full((bsz, 3), np.nan), "covariance_m2": np.full((bsz, 3, 3), np.nan),
        "residuals_m": np.full((bsz, m), np.nan), "used": np.zeros((bsz, m), dtype=bool),
        "tail": np.zeros((bsz, m), dtype=bool), "mechanism": np.full((bsz, m), -1),
        "floor": np.full(bsz, -1), "floor_probability": np.full((bsz, nf), np.nan),
        "cost": np.full(bsz, np.nan), "stat": np.full(bsz, np.nan),
    }
    x0 = None if x0_m is None else np.broadcast_to(np.asarray(x0_m, dtype=np.float64),
                                                    (bsz, 3))
    solvable = np.flatnonzero(bi.mask.sum(axis=-1) >= 3)
    step = max(int(chunk_size), 1)
    for lo in range(0, solvable.size, step):
        idx = solvable[lo:lo + step]
        modes = _solve_chunk(bi.anchors_m[idx], bi.ranges_m[idx], sig[idx], bi.mask[idx],
                             excess[idx], building, grid=grid, keep=keep_starts,
                             wavelength=wavelength, iters=max_iter, lam=lam, radio=radio,
                             snr=None if snr_all is None else snr_all[idx],
                             x0=None if x0 is None else x0[idx], kernel=kernel, mech=mech,
                             rule=snr_rule)
        with _stage("final"):
            _finish(out, idx, *modes, nf=nf, snr_meas=None if snr_db is None else snr_all[idx],
                    building=building, radio=radio, kernel=kernel)
    return _result(out, bi, false_alarm_probability)


#: Standard normal draws of the path-region mass (:func:`_region_log_mass`): fixed, so the
#: posterior is deterministic; antithetic pairs.
_REGION_HALF = np.random.default_rng(31).standard_normal((256, 3))
_REGION_DRAWS = np.concatenate([_REGION_HALF, -_REGION_HALF])
#: Floors whose box-mass Laplace term is this far below the fix's best [nats] keep their box
#: mass (posterior odds below exp(-REGION_NATS); the region mass only lowers a floor's).
REGION_NATS = 12.0


def _region_log_mass(p: _Problem, sel, xk: FloatArray, h: FloatArray, t: dict,
                     cost: FloatArray, box: FloatArray, building) -> FloatArray:
    """Log of the share of each floor's Laplace Gaussian ``N(x_k, H_k^-1)`` inside its
    floor's box where every used link's chosen mechanism exists
    (:attr:`~diffpos.estimators.mnls.rules.SnrRule.path_region`): the share of the fixed draws
    :data:`_REGION_DRAWS` (at least half a draw). ``xk`` (B, F, 3), ``h`` (B, F, 3, 3),
    ``cost`` and ``box`` (B, F) (``box``: :func:`_box_log_mass`, kept where the floor is
    :data:`REGION_NATS` below the best or ``h`` is singular); ``t`` the terms at the modes
    (rows of ``p`` at ``sel``)."""
    b, nf = cost.shape
    sign, logdet = np.linalg.slogdet(h)
    with np.errstate(invalid="ignore"):
        lp = np.where(sign > 0, -cost - 0.5 * logdet + box, -np.inf)
    lp = np.where(np.isfinite(lp), lp, -np.inf)
    go = np.flatnonzero((np.isfinite(lp) & (lp >= lp.max(axis=-1, keepdims=True)
                                            - REGION_NATS)).ravel())
    used = p.mask[sel] & ~t["tail"] & ~t["none"]
    out = box.reshape(-1).copy()
    n = len(_REGION_DRAWS)
    for g in go:
        r = sel[g]
        w, v = np.linalg.eigh(np.linalg.inv(h.reshape(-1, 3, 3)[g]))
        pts = xk.reshape(-1, 3)[g] + _REGION_DRAWS @ (v * np.sqrt(np.maximum(w, 0.0))).T
        ok = np.all((pts >= p.lo[r]) & (pts <= p.hi[r]), axis=-1)
        links = np.flatnonzero(used[g])
        if links.size:
            slots = t["slot"][g, links]
            uniq = np.unique(slots)
            ps = first_arrival_paths(pts[:, None, :], p.anchors[r, links][None], building,
                                     floor=np.full((n, 1), p.floor[r]), slots=uniq,
                                     mechanisms=p.mech)
            ok &= np.all(ps.valid[:, np.arange(links.size), np.searchsorted(uniq, slots)],
                         axis=-1)
        out[g] = np.log(max(ok.mean(), 0.5 / n))
    return out.reshape(b, nf)


def _finish(out, idx, p, xk, t, sel, active, *, nf: int, snr_meas=None, building=None,
            radio=None, kernel: bool = False) -> None:
    b = idx.size
    act = np.flatnonzero(active)
    if radio is not None and snr_meas is not None:
        # refine every active floor's mode with the mechanisms chosen there held, then score
        # them with the SNR terms evaluated at their final modes
        ps = _take(p, sel[act])
        ps.snr_meas, ps.radio = np.repeat(snr_meas, nf, axis=0)[act], radio
        x = xk.reshape(-1, 3)[act]
        ps.snr_cost = _snr_cost(ps, x, building)
        ta = _link_terms(ps, x, building)
        k = ta["length"].shape[-1]
        ps.allowed = np.where(ta["tail"][..., None], True, np.arange(k) == ta["slot"][..., None])
        snr_hold = ps.snr_cost
        held = _replace_snr(ps)
        held.snr_cost = None
        x, _ = _lm(held, x, building, REFINE_ITER, kernel=kernel)
        ps.allowed = None
        xk = xk.reshape(-1, 3).copy()
        xk[act] = x
        xk = xk.reshape(b, nf, 3)
        ps.snr_cost = _snr_cost(ps, x, building) if snr_hold is not None else None
        ta = _link_terms(ps, x, building)
        t = {key: v.copy() for key, v in t.items()}
        for key in t:
            t[key][act] = ta[key]
    h, var = _information(p, sel, t)
    h = h.reshape(b, nf, 3, 3)
    cost = np.where(active, t["cost"], np.inf).reshape(b, nf)
    box = None  # the Laplace mass inside each floor's box (SnrRule.floor_box)
    if getattr(p.rule, "floor_box", False):
        box = _box_log_mass(xk, h, p.lo[sel].reshape(b, nf, 3), p.hi[sel].reshape(b, nf, 3))
        if getattr(p.rule, "path_region", False):
            box = _region_log_mass(p, sel, xk, h, t, cost, box, building)
    post = _posterior(cost, h, box)
    kb = np.argmax(post, axis=-1)
    rows = np.arange(b) * nf + kb
    x = xk[np.arange(b), kb]
    with np.errstate(invalid="ignore", over="ignore"):
        cov_k = np.linalg.inv(h)
        d = xk - x[:, None, :]
        mix = np.where(post[..., None, None] > 0, cov_k + d[..., :, None] * d[..., None, :], 0.0)
        cov = np.einsum("bf,bfij->bij", post, mix)
    used = p.mask[sel][rows] & ~t["tail"][rows] & ~t["none"][rows]
    res = t["res"][rows]
    out["position_m"][idx] = x
    out["covariance_m2"][idx] = cov
    out["residuals_m"][idx] = np.where(p.mask[sel][rows], res, np.nan)
    out["used"][idx] = used
    out["tail"][idx] = t["tail"][rows]
    out["mechanism"][idx] = np.where(p.mask[sel][rows], t["slot"][rows], -1)
    out["floor"][idx] = kb
    out["floor_probability"][idx] = post
    out["cost"][idx] = t["cost"].reshape(b, nf)[np.arange(b), kb]
    out["stat"][idx] = np.sum(np.where(used, res**2 / var[rows], 0.0), axis=-1)
