"""Compiled pieces of the tracker's measurement model (:mod:`diffpos.tracking.model`).

:func:`model_kernel` evaluates, in one loop over every (node, hypothesis, anchor) link, the
chosen mechanism's raw length and Jacobian (:func:`diffpos.paths.model_nb.slot_path` with
``raw=True``: the same call the path kernel makes for ``graded_paths``, so the same floating-
point operations), the straight line and the link's model value, Jacobian and weight of the
IEKF (:func:`diffpos.tracking.model._model`). Before, the path model was called once per
distinct slot and Gauss-Newton iteration (~10 numpy/kernel calls per iteration, each with
its broadcasting and slot tables) and the straight line by ``einsum``. The numpy version
stays as the reference (``tracking_model._model_numpy``); tests/core/test_tracking_kernel.py
holds them to bit equality.

:func:`all_paths_kernel` evaluates every slot of every link with :func:`default_slots_row`:
the 18 slots of :data:`~diffpos.paths.model_nb.DEFAULT_TABLE` for one row at once, each slot
``slot_path(k, ..., raw=True, want_jac=True)``'s floating-point operations in the same order
(so its values bit for bit: tests/core/test_paths_rows.py), without the per-slot kind
dispatch, partition scan and table look-ups (small per-kind recipe tables made once from the
default table, checked at import) and without the diffraction slots' deviation cosine and
anchor-side length, which the tracker does not use: 0.64x the paths kernel's CPU on the 30 s
``large`` replay's updates (docs/performance.md, "The paths of a row at once").

The selection (``select_pack_kernel``, ``select_best_kernel``, ``select_mix_kernel``) runs
per link over the slots without the numpy version's (N, H, M, K) temporaries and leaves its
log/exp to numpy between the passes (on the packed candidates), so it stays bit-identical to
``tracking_model._select_numpy``. ``iekf_nb.iekf_kernel`` runs the IEKF's Gauss-Newton loop and
Laplace evidence per hypothesis with :func:`model_kernel`'s and :func:`iekf_terms_kernel`'s
bodies (:func:`_model_row`, :func:`_terms_row`) and a 6 x 6 LU with partial pivoting in
place of numpy's batched LAPACK calls: held to ``tracking_model._iekf_numpy`` within a
tolerance.

The per-row / per-link bodies called inside the kernels' loops with array views
(:func:`default_slots_row`, :func:`_model_row`, :func:`_terms_row`, :func:`_prep_link`) are
inlined at numba IR level (``inline="always"``): a view passed to a compiled call costs its
construction, two atomic reference-count operations and the call, per row; inlined, the same
operations in the same order (so the same bits) at ~0.82-0.85x the CPU of the paths, IEKF
and selection kernels on the 30 s ``large`` replay's calls (docs/performance.md, "Session 25").
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from diffpos._kernels.npsum_nb import pairwise_sum as _pairwise_sum
from diffpos.paths.model_nb import (
    COL_EDGE,
    COL_GROUND,
    COL_NPLANES,
    COL_PLANES,
    DEFAULT_TABLE,
    N_SLOTS,
    SLOT_KIND,
    axis_component,
    edge_axis,
    facade_entry,
    fermat_point,
    in_floor_box,
    inside_plane,
    mirror,
    row_planes,
    slot_path,
)

__all__ = ["all_paths_kernel", "candidate_slots", "default_slots_row", "iekf_terms_kernel",
           "model_kernel", "select_best_kernel", "select_mix_kernel", "select_pack_kernel",
           "select_prep_kernel", "warm_model"]

_OPTS = {"cache": True, "error_model": "numpy", "nogil": True}
#: numba keys this file's on-disk cache on this file only, not on the ``*_nb`` code its
#: kernels compile in: a digest of that code (tests/core/test_kernel_stamps.py names the new
#: value after a callee's edit; writing it here is what invalidates a warm cache).
CALLEES_SHA256 = "b407ab71c5258cbf"


# the default table by kind: the direct slot, the specular slots (ground bounce, number of
# inside planes, their codes in path order) and the diffraction slots (upper edge, plane)
_ROW_DIRECT = np.flatnonzero(SLOT_KIND == 0)
_ROW_SPEC_K = np.flatnonzero(SLOT_KIND == 1).astype(np.int64)
_ROW_SPEC_GROUND = np.ascontiguousarray(DEFAULT_TABLE[_ROW_SPEC_K, COL_GROUND])
_ROW_SPEC_NPL = np.ascontiguousarray(DEFAULT_TABLE[_ROW_SPEC_K, COL_NPLANES])
_ROW_SPEC_P1 = np.ascontiguousarray(DEFAULT_TABLE[_ROW_SPEC_K, COL_PLANES])
_ROW_SPEC_P2 = np.ascontiguousarray(DEFAULT_TABLE[_ROW_SPEC_K, COL_PLANES + 1])
_ROW_DIFF_K = np.flatnonzero(SLOT_KIND == 2).astype(np.int64)
_ROW_DIFF_UP = np.ascontiguousarray((DEFAULT_TABLE[_ROW_DIFF_K, COL_EDGE] == 0).astype(np.int64))
_ROW_DIFF_P = np.ascontiguousarray(DEFAULT_TABLE[_ROW_DIFF_K, COL_PLANES])
if not (list(_ROW_DIRECT) == [0] and np.all(_ROW_SPEC_NPL <= 2)
        and np.all(DEFAULT_TABLE[_ROW_DIFF_K, COL_EDGE] < 2)
        and np.all(DEFAULT_TABLE[_ROW_DIFF_K, COL_GROUND] == 0)
        and np.all(DEFAULT_TABLE[_ROW_DIFF_K, COL_NPLANES] <= 1)
        and np.all(DEFAULT_TABLE[:, COL_PLANES:] < 5)):
    raise ValueError("tracking.model_nb: DEFAULT_TABLE has a recipe default_slots_row does not "
                     "cover (direct slot 0 only; <= 2 planes; diffraction on a horizontal "
                     "edge, no ground bounce, <= 1 plane; no partition): extend it")


@njit(**_OPTS)
def _row_hit(c0, c1, c2, m0, m1, m2, ax, c, t_last, zf, zc, x0, x1, depth):
    """One reflection of the walk on the unfolded ray ``c -> m`` (paths.model_nb._reflections_ok's
    body): its ray parameter and whether it exists after ``t_last``."""
    dd0, dd1, dd2 = m0 - c0, m1 - c1, m2 - c2
    t = (c - axis_component(c0, c1, c2, ax)) / axis_component(dd0, dd1, dd2, ax)
    ok = (t > t_last) and (t < 1)
    ok = ok and in_floor_box(c0 + t * dd0, c1 + t * dd1, c2 + t * dd2, zf, zc, x0, x1, depth)
    return ok, t


@njit(**_OPTS, inline="always")
def _row_flip(g0, g1, g2, ax):
    """The mirror signs after a mirror in a plane normal to ``ax``."""
    if ax == 0:
        return -g0, g1, g2
    if ax == 1:
        return g0, -g1, g2
    return g0, g1, -g2


@njit(**_OPTS, inline="always")
def _row_specular(a0, a1, a2, n0, n1, n2, ground, n_pl, p1, p2, zf, zc, x0, x1, depth):
    """paths.model_nb._specular of a default slot (planes ``p1``, ``p2`` in path order, ``n_pl`` of
    them): length, ok (without the band test), entry z, Jacobian."""
    ax1, c1 = inside_plane(p1, zf, zc, x0, x1, depth)
    ax2, c2 = inside_plane(p2, zf, zc, x0, x1, depth)
    i0, i1, i2 = n0, n1, n2
    g0 = g1 = g2 = 1.0
    if n_pl == 2:  # image: last plane first
        i0, i1, i2 = mirror(i0, i1, i2, ax2, c2)
        g0, g1, g2 = _row_flip(g0, g1, g2, ax2)
    if n_pl >= 1:
        i0, i1, i2 = mirror(i0, i1, i2, ax1, c1)
        g0, g1, g2 = _row_flip(g0, g1, g2, ax1)
    s0, s1, s2 = a0, a1, a2
    if ground:
        s2 = 2.0 * 0.0 - a2
    d0, d1, d2, length, t_f, _, ok = facade_entry(s0, s1, s2, i0, i1, i2, ground)
    e0 = s0 + t_f * d0
    ez = s2 + t_f * d2
    ok = ok and (e0 > x0) and (e0 < x1)
    if ok and n_pl >= 1:  # the reflection walk (paths.model_nb: skipped by ``and`` as here)
        ok, t = _row_hit(s0, s1, s2, i0, i1, i2, ax1, c1, t_f, zf, zc, x0, x1, depth)
        if ok and n_pl == 2:
            m0, m1, m2 = mirror(i0, i1, i2, ax1, c1)
            q0, q1, q2 = mirror(s0, s1, s2, ax1, c1)
            ok, _ = _row_hit(q0, q1, q2, m0, m1, m2, ax2, c2, t, zf, zc, x0, x1, depth)
    ok = ok and math.isfinite(length)
    return length, ok, ez, d0 / length * g0, d1 / length * g1, d2 / length * g2


@njit(**_OPTS, inline="always")
def _row_diffracted(a0, a1, a2, n0, n1, n2, z_e, plane, zf, zc, x0, x1, depth, edge):
    """paths.model_nb._diffracted of a default slot (the horizontal edge at ``z_e`` from ``x0``,
    no ground bounce, the inside plane ``plane`` after the edge or none if < 0): length, ok,
    Jacobian."""
    ax, c = inside_plane(plane, zf, zc, x0, x1, depth)
    o0, o1, o2 = n0, n1, n2
    g0 = g1 = g2 = 1.0
    if plane >= 0:
        o0, o1, o2 = mirror(o0, o1, o2, ax, c)
        g0, g1, g2 = _row_flip(g0, g1, g2, ax)
    q0, q1, q2, ok = fermat_point(a0, a1, a2, o0, o1, o2, x0, z_e, edge)
    v0, v1, v2 = a0 - q0, a1 - q1, a2 - q2
    u0, u1, u2 = o0 - q0, o1 - q1, o2 - q2
    d_in = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    nu = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    length = d_in + nu
    if ok and plane >= 0:
        ok, _ = _row_hit(q0, q1, q2, o0, o1, o2, ax, c, 0.0, zf, zc, x0, x1, depth)
    ok = ok and math.isfinite(length)
    return length, ok, (u0 / nu) * g0, (u1 / nu) * g1, (u2 / nu) * g2


@njit(**_OPTS, inline="always")
def default_slots_row(a0, a1, a2, n0, n1, n2, zf, zc, lo, hi, x0, x1, depth, edge, length,
                      valid, jac, entry_z):
    """Every slot of ``DEFAULT_TABLE`` for the anchor ``a``, the node ``n`` and the floor's
    planes ``zf, zc, lo, hi`` (:func:`~diffpos.paths.model_nb.row_planes`; ``edge``: :func:`~diffpos.paths.model_nb.edge_axis`):
    writes ``length`` (18,), ``valid`` (18,) bool (raw: without the entry's band test),
    ``jac`` (18, 3) and ``entry_z`` (18,) (NaN for the diffraction slots): ``slot_path(k,
    ..., raw=True, want_jac=True)``'s values for every ``k``, bit for bit."""
    d0, d1, d2 = n0 - a0, n1 - a1, n2 - a2  # paths.model_nb._direct
    ln = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    t = -a1 / d1
    zcr = a2 + t * d2
    xc = a0 + t * d0
    length[0] = ln
    valid[0] = (xc > x0) and (xc < x1)
    entry_z[0] = zcr
    jac[0, 0], jac[0, 1], jac[0, 2] = d0 / ln * 1.0, d1 / ln * 1.0, d2 / ln * 1.0
    for q in range(_ROW_SPEC_K.shape[0]):
        k = _ROW_SPEC_K[q]
        ln, ok, ez, j0, j1, j2 = _row_specular(a0, a1, a2, n0, n1, n2, _ROW_SPEC_GROUND[q] == 1,
                                           _ROW_SPEC_NPL[q], _ROW_SPEC_P1[q], _ROW_SPEC_P2[q], zf, zc, x0,
                                           x1, depth)
        length[k] = ln
        valid[k] = ok
        entry_z[k] = ez
        jac[k, 0], jac[k, 1], jac[k, 2] = j0, j1, j2
    for q in range(_ROW_DIFF_K.shape[0]):
        k = _ROW_DIFF_K[q]
        ln, ok, j0, j1, j2 = _row_diffracted(a0, a1, a2, n0, n1, n2, hi if _ROW_DIFF_UP[q] == 1 else lo,
                                         _ROW_DIFF_P[q], zf, zc, x0, x1, depth, edge)
        length[k] = ln
        valid[k] = ok
        entry_z[k] = np.nan
        jac[k, 0], jac[k, 1], jac[k, 2] = j0, j1, j2


@njit(**_OPTS)
def model_kernel(pos, anchors, floor, slot, extra_var, rho, var, mask, first_z, floor_h, sill,
                 win_h, x0, x1, depth, model, jm, w):
    """Model value, Jacobian and IEKF weight of every link (writes ``model``, ``jm``, ``w``).

    ``pos`` (N, H, 3) hypothesis positions, ``anchors`` (N, M, 3), ``floor`` (N, H) float64
    floor index, ``slot`` (N, H, M) chosen slot (-1: none), ``extra_var`` (N, H, M), ``rho``,
    ``var`` (N, M), ``mask`` (N, M) bool. A used link (slot >= 0 with a finite length and
    Jacobian) models its slot's length with weight ``1 / (var + extra_var)``; an unused
    present link whose range is shorter than the straight line (the hinge) models the
    straight line with weight ``1 / var``; any other link models its own range, weight 0.
    """
    edge = edge_axis(x0, x1)
    n_n, n_h, _ = slot.shape
    for n in range(n_n):
        for h in range(n_h):
            _model_row(pos[n, h, 0], pos[n, h, 1], pos[n, h, 2], anchors[n], floor[n, h],
                       slot[n, h], extra_var[n, h], rho[n], var[n], mask[n], first_z, floor_h,
                       sill, win_h, x0, x1, depth, edge, model[n, h], jm[n, h], w[n, h])


@njit(**_OPTS, inline="always")
def _model_row(p0, p1, p2, anchors, fl, slot, extra_var, rho, var, mask, first_z, floor_h,
               sill, win_h, x0, x1, depth, edge, model, jm, w):
    """:func:`model_kernel` of one hypothesis at (``p0``, ``p1``, ``p2``): ``anchors`` (M, 3),
    ``slot``, ``extra_var``, ``rho``, ``var``, ``mask`` (M,); writes ``model``, ``w`` (M,),
    ``jm`` (M, 3)."""
    zf, zc, lo, hi = row_planes(fl, first_z, floor_h, sill, win_h)
    for m in range(slot.shape[0]):
        a0, a1, a2 = anchors[m, 0], anchors[m, 1], anchors[m, 2]
        s = slot[m]
        use = False
        ln = np.nan
        j0 = j1 = j2 = 0.0
        if s >= 0:
            ln, _, j0, j1, j2, _, _, _ = slot_path(s, a0, a1, a2, p0, p1, p2, zf, zc,
                                                  lo, hi, x0, x1, depth, edge, True,
                                                  True)
            use = (math.isfinite(ln) and math.isfinite(j0) and math.isfinite(j1)
                   and math.isfinite(j2))
        if use:
            model[m] = ln
            jm[m, 0] = j0
            jm[m, 1] = j1
            jm[m, 2] = j2
            w[m] = 1.0 / (var[m] + extra_var[m])
            continue
        # the straight line, as tracking_model._los: sqrt(d . d), d / max(|d|, 1e-12);
        # numpy's einsum sums a 3-vector as (d0^2 + d2^2) + d1^2 (two SIMD lanes, the
        # odd element into the first), so the same order here (the test checks it)
        d0, d1, d2 = p0 - a0, p1 - a1, p2 - a2
        los = math.sqrt((d0 * d0 + d2 * d2) + d1 * d1)
        if mask[m] and rho[m] < los:
            den = max(los, 1e-12)
            model[m] = los
            jm[m, 0] = d0 / den
            jm[m, 1] = d1 / den
            jm[m, 2] = d2 / den
            w[m] = 1.0 / var[m]
        else:
            model[m] = rho[m]
            jm[m, 0] = 0.0
            jm[m, 1] = 0.0
            jm[m, 2] = 0.0
            w[m] = 0.0


@njit(**_OPTS)
def select_prep_kernel(length, jac, sure, loose, is_diff, pos_cov, var, snr, snr_c, use_snr,
                       g_const, span_ll, valid, s_ll, s_var):
    """The transcendental-free part of ``tracking_model.select`` per (node, hypothesis,
    anchor, slot): the candidates (``tracking_model.candidates``, then without power only
    near an existence boundary), the SNR log-likelihood term ``s_ll`` and the innovation
    variance ``s_var = J P J^T + R`` (0 Jacobian for a non-candidate), with numpy's order of
    operations (``einsum`` sums ``(J_i P_ij) J_j`` over i outer, j inner), so bit-identical.

    ``length`` (N, H, M, K), ``jac`` (N, H, M, K, 3), ``sure``/``loose`` (N, H, M, K) bool,
    ``is_diff`` (K,) bool, ``pos_cov`` (N, H, 3, 3), ``var`` (N, M), ``snr`` (N, M) and
    ``snr_c`` (N, H, M, K) (ignored unless ``use_snr``), ``g_const``: ``log(sigma_snr) +
    log(2 pi) / 2`` is subtracted as ``(-c - log(sigma)) - log(2 pi) / 2``: given as the two
    terms ``g_const[0]``, ``g_const[1]``; ``span_ll = -log(SNR_SPAN_DB)``. The per-link body
    (:func:`_prep_link`) is the one :func:`select_pack_kernel` runs.
    """
    n_n, n_h, n_m, _ = length.shape
    for n in range(n_n):
        for h in range(n_h):
            for m in range(n_m):
                _prep_link(length[n, h, m], jac[n, h, m], sure[n, h, m], loose[n, h, m],
                           is_diff, pos_cov[n, h], var[n, m], snr[n, m],
                           snr_c[n, h, m] if use_snr else snr_c[0, 0, 0], use_snr, g_const,
                           span_ll, valid[n, h, m], s_ll[n, h, m], s_var[n, h, m])


@njit(**_OPTS, inline="always")
def candidate_slots(length, sure, loose, is_diff, valid):
    """:func:`diffpos.tracking.links.candidates` of one link: ``length``, ``sure``, ``loose``
    (K,), ``is_diff`` (K,); writes ``valid`` (K,): the loose slots no later than the earliest
    sure specular path, a diffraction one strictly earlier (a NaN length among the sure
    specular ones: none, as the reference's ``min``)."""
    n_k = length.shape[0]
    e_spec = np.inf  # earliest sure specular path (NaN propagates as in min)
    for k in range(n_k):
        if sure[k] and not is_diff[k]:
            ln = length[k]
            if math.isnan(ln):
                e_spec = np.nan
                break
            if ln < e_spec:
                e_spec = ln
    for k in range(n_k):
        ln = length[k]
        valid[k] = loose[k] and ((ln < e_spec) if is_diff[k] else (ln <= e_spec))


@njit(**_OPTS, inline="always")
def _prep_link(length, jac, sure, loose, is_diff, cov, var, snr, snr_c, use_snr, g_const,
               span_ll, valid, s_ll, s_var):
    """:func:`select_prep_kernel` of one link: ``length``, ``sure``, ``loose``, ``snr_c``
    (K,), ``jac`` (K, 3), ``cov`` (3, 3), scalars ``var``, ``snr``; writes ``valid``,
    ``s_ll``, ``s_var`` (K,)."""
    n_k = length.shape[0]
    candidate_slots(length, sure, loose, is_diff, valid)
    has_snr = use_snr and math.isfinite(snr)
    cov_finite = True
    for i in range(3):
        for j in range(3):
            cov_finite = cov_finite and math.isfinite(cov[i, j])
    for k in range(n_k):
        ok = valid[k]
        sl = 0.0
        if use_snr:
            c = snr_c[k]
            powered = math.isfinite(c)
            ok = ok and (powered or not sure[k])
            if has_snr:
                sl = ((-c - g_const[0]) - g_const[1]) if powered else span_ll
        valid[k] = ok
        s_ll[k] = sl
        acc = 0.0
        if ok:
            for i in range(3):
                for j in range(3):
                    acc += jac[k, i] * cov[i, j] * jac[k, j]
        elif not cov_finite:  # the reference's einsum over a zeroed Jacobian: +0 (the
            for i in range(3):  # sum of +-0 from +0), or NaN when the covariance holds
                for j in range(3):  # inf/NaN
                    acc += 0.0 * cov[i, j] * 0.0
        s_var[k] = acc + var


@njit(**_OPTS)
def select_pack_kernel(length, jac, sure, loose, is_diff, pos_cov, var, snr, snr_c, use_snr,
                       g_const, span_ll, valid, sv_pack, sl_pack):
    """First pass of ``tracking_model.select`` (:func:`_prep_link` per link): writes the
    candidates ``valid`` (N, H, M, K) and packs every candidate's innovation variance and SNR
    term, in (node, hypothesis, anchor, slot) order, into ``sv_pack`` / ``sl_pack`` (1-D, at
    least N H M K long); returns how many. The caller takes numpy's log of the packed
    variances (numpy's SIMD log, so the result is the numpy reference's bit for bit).
    Arguments as :func:`select_prep_kernel`."""
    n_n, n_h, n_m, n_k = length.shape
    sl = np.empty(n_k)
    sv = np.empty(n_k)
    c = 0
    for n in range(n_n):
        for h in range(n_h):
            for m in range(n_m):
                ok = valid[n, h, m]
                _prep_link(length[n, h, m], jac[n, h, m], sure[n, h, m], loose[n, h, m],
                           is_diff, pos_cov[n, h], var[n, m], snr[n, m],
                           snr_c[n, h, m] if use_snr else snr_c[0, 0, 0], use_snr, g_const,
                           span_ll, ok, sl, sv)
                for k in range(n_k):
                    if ok[k]:
                        sv_pack[c] = sv[k]
                        sl_pack[c] = sl[k]
                        c += 1
    return c


@njit(**_OPTS)
def select_best_kernel(length, valid, rho, mask, snr, use_snr, sv_pack, sl_pack, log_sv,
                       consts, w_link, log_n, ex_pack, best, base, slot, nis, persist, prev):
    """Second pass of ``tracking_model.select``: per link the candidates' log-likelihoods
    ``-(e^2 / S + log S + log 2 pi) / 2 + snr term`` (``log_sv``: numpy's log of the packed
    variances of :func:`select_pack_kernel`), the most likely one (``np.argmax``: the first
    maximum or the first NaN; written to ``best``), the inlier test against the outlier and
    ``slot`` (-1 outlier), ``nis`` (NaN unless inlier), ``base`` (N, H, M): the log-weight
    without the mixture term (``log(1 - eps) - log n + snr term`` of an inlier, the outlier's
    ``log(eps / span) + snr term`` of a present link, else 0); packs every candidate's
    ``ll_k - ll_best`` into ``ex_pack`` for numpy's exp. ``consts``: ``log(2 pi)``, ``log q``,
    ``log(1 - q)`` (numpy's; q = ``mechanism_switch_p``); ``w_link`` (N, H, M, 2): every
    link's inlier weight ``log(1 - eps)`` and its outlier component's log-density (with its SNR
    part; ``diffpos.tracking.model.link_weights``); ``log_n`` (K + 1,): ``log(n)``. A node
    with ``persist`` (N,) set gets the persistent mechanism prior instead
    (:func:`_persist_link`, ``prev`` (N, H, M): the previous slot, -1 none). The numpy
    references' operations in their order (``_select_numpy``, ``select_persistent``)."""
    n_n, n_h, n_m, n_k = length.shape
    ll = np.empty(n_k)
    sl = np.empty(n_k)
    sv = np.empty(n_k)
    wk = np.empty(n_k)
    c = 0
    for n in range(n_n):
        for h in range(n_h):
            for m in range(n_m):
                ok = valid[n, h, m]
                r = rho[n, m]
                lk = length[n, h, m]
                c0 = c
                n_ok = _link_ll(lk, ok, r, sv_pack, sl_pack, log_sv, consts[0], c, ll, sl, sv)
                c += n_ok
                if persist[n]:
                    ref = _persist_link(ll, ok, n_ok, prev[n, h, m], w_link[n, h, m], log_n,
                                        consts, mask[n, m], r, lk, sl, sv, wk, n, h, m,
                                        best, base, slot, nis)
                else:
                    ref = _flat_link(ll, n_ok, w_link[n, h, m], log_n, mask[n, m], r, lk, sl,
                                     sv, n, h, m, best, base, slot, nis)
                for k in range(n_k):
                    if ok[k]:
                        ex_pack[c0] = ll[k] - ref
                        c0 += 1


@njit(**_OPTS, inline="always")
def _link_ll(lk, ok, r, sv_pack, sl_pack, log_sv, log2pi, c, ll, sl, sv):
    """One link's candidate log-likelihoods ``ll`` (-inf for a non-candidate), SNR terms
    ``sl`` (0) and variances ``sv`` (NaN) from the packed values from ``c`` on; returns the
    candidate count."""
    n_ok = 0
    for k in range(lk.shape[0]):
        if ok[k]:
            n_ok += 1
            e = r - lk[k]
            v = sv_pack[c]
            sv[k] = v
            sl[k] = sl_pack[c]
            ll[k] = -0.5 * (e * e / v + log_sv[c] + log2pi) + sl_pack[c]
            c += 1
        else:
            ll[k] = -np.inf
            sl[k] = 0.0
            sv[k] = np.nan
    return n_ok


@njit(**_OPTS, inline="always")
def _argmax(x):
    """``np.argmax`` of a 1-D array: the first maximum, or the first NaN."""
    b = 0
    bv = x[0]
    if not math.isnan(bv):
        for k in range(1, x.shape[0]):
            if math.isnan(x[k]):
                return k
            if x[k] > bv:
                bv = x[k]
                b = k
    return b


@njit(**_OPTS, inline="always")
def _flat_link(ll, n_ok, w, log_n, present, r, lk, sl, sv, n, h, m, best, base, slot, nis):
    """:func:`select_best_kernel` of one link with the flat prior ``log(1 - eps) - log n``
    (``w``: the link's two weights); returns the reference the packed ``ll - ref`` take."""
    b = _argmax(ll)
    best[n, h, m] = b
    ll_best = ll[b]
    w_in = w[0] - log_n[n_ok if n_ok > 1 else 1]
    if present and math.isfinite(ll_best) and (ll_best + w_in > w[1]):
        e_b = r - lk[b]
        slot[n, h, m] = b
        nis[n, h, m] = e_b * e_b / sv[b]
        base[n, h, m] = w_in + sl[b]
    else:
        slot[n, h, m] = -1
        nis[n, h, m] = np.nan
        base[n, h, m] = w[1] if present else 0.0
    return ll_best if math.isfinite(ll_best) else 0.0


@njit(**_OPTS, inline="always")
def _persist_link(ll, ok, n_ok, pv, w, log_n, consts, present, r, lk, sl, sv, wk, n, h, m,
                  best, base, slot, nis):
    """:func:`select_best_kernel` of one link with the persistent prior
    (``tracking_model.select_persistent``): the previous slot ``pv`` (if a candidate) gets
    ``log(1 - eps) + log(1 - q)``, the others ``log(1 - eps) + log q - log(n - 1)``, without
    one all get ``log(1 - eps) - log n``; ``ll`` becomes ``ll + prior`` (the total); returns
    the reference the packed ``ll - ref`` take."""
    n_c = n_ok if n_ok > 1 else 1
    has = pv >= 0 and pv < ll.shape[0] and ok[pv]
    if has:
        other = w[0] + consts[1] - log_n[n_c - 1 if n_c > 2 else 1]
    else:
        other = w[0] - log_n[n_c]
    for k in range(ll.shape[0]):
        wk[k] = (w[0] + consts[2]) if (has and k == pv) else other
        ll[k] = ll[k] + wk[k]
    b = _argmax(ll)
    best[n, h, m] = b
    tb = ll[b]
    if present and math.isfinite(tb) and (tb > w[1]):
        e_b = r - lk[b]
        slot[n, h, m] = b
        nis[n, h, m] = e_b * e_b / sv[b]
        base[n, h, m] = wk[b] + sl[b]
    else:
        slot[n, h, m] = -1
        nis[n, h, m] = np.nan
        base[n, h, m] = w[1] if present else 0.0
    return tb if math.isfinite(tb) else 0.0


@njit(**_OPTS)
def select_mix_kernel(length, valid, slot, best, ex_pack, extra, mix_arg):
    """Third pass of ``tracking_model.select``: per link the candidates' posterior weights
    ``p_k`` from ``ex_pack`` (numpy's exp of :func:`select_best_kernel`'s packed relative
    log-likelihoods; 0 for a non-candidate), normalised by their sum (at least 1e-300), the
    mechanism-ambiguity variance ``extra`` = ``sum_k p_k (L_k - L_best)^2`` (0 unless an
    inlier with a finite value) and ``mix_arg`` = ``max(sum, 1)`` of an inlier, 1 otherwise
    (the caller adds numpy's log of it to the log-weight). Sums in numpy's pairwise order."""
    n_n, n_h, n_m, n_k = length.shape
    pk = np.empty(n_k)
    c = 0
    for n in range(n_n):
        for h in range(n_h):
            for m in range(n_m):
                lk = length[n, h, m]
                ok = valid[n, h, m]
                c0 = c
                for k in range(n_k):
                    if ok[k]:
                        pk[k] = ex_pack[c]
                        c += 1
                    else:
                        pk[k] = 0.0
                mass = _pairwise_sum(pk, n_k)
                den = mass if (mass > 1e-300 or math.isnan(mass)) else 1e-300
                l_best = lk[best[n, h, m]]
                c = c0
                for k in range(n_k):
                    if ok[k]:
                        d = lk[k] - l_best
                        pk[k] = ex_pack[c] / den * (d * d)
                        c += 1
                    else:
                        pk[k] = 0.0
                ex = _pairwise_sum(pk, n_k)
                if slot[n, h, m] >= 0:
                    extra[n, h, m] = ex if math.isfinite(ex) else 0.0
                    mix_arg[n, h, m] = mass if (mass > 1.0 or math.isnan(mass)) else 1.0
                else:
                    extra[n, h, m] = 0.0
                    mix_arg[n, h, m] = 1.0


@njit(**_OPTS)
def all_paths_kernel(pos, anchors, floor, relax, is_band, first_z, floor_h, sill, win_h, x0,
                     x1, depth, length, jac, strict, loose, sure):
    """Every slot of every (node, hypothesis, anchor) link with graded existence, as
    ``diffpos.paths.model.graded_paths`` computes it for ``tracking_model.all_paths`` (the
    per-row path function's values with ``raw=True``, all 18 slots of a row at once by
    :func:`default_slots_row`, bit for bit ``slot_path``'s; the same band
    tests), without its flat-row broadcasting: ``pos`` (N, H, 3), ``anchors`` (N, M, 3),
    ``floor`` (N, H) float64, ``relax`` (N, H) float64 (every hypothesis' own widening of the
    band, [m]); writes ``length`` (N, H, M, K), ``jac`` (N, H, M, K, 3) and the three
    existence grades. K must be the default table's 18 slots.
    """
    edge = edge_axis(x0, x1)
    n_n, n_h, n_m, n_k = length.shape
    if n_k != N_SLOTS:
        raise ValueError("all_paths_kernel: every link has the default table's 18 slots")
    ok_row, ez_row = np.empty(n_k, dtype=np.bool_), np.empty(n_k)
    for n in range(n_n):
        for h in range(n_h):
            p0, p1, p2 = pos[n, h, 0], pos[n, h, 1], pos[n, h, 2]
            zf, zc, lo, hi = row_planes(floor[n, h], first_z, floor_h, sill, win_h)
            r = relax[n, h]
            for m in range(n_m):
                a0, a1, a2 = anchors[n, m, 0], anchors[n, m, 1], anchors[n, m, 2]
                default_slots_row(a0, a1, a2, p0, p1, p2, zf, zc, lo, hi, x0, x1, depth, edge,
                                  length[n, h, m], ok_row, jac[n, h, m], ez_row)
                for k in range(n_k):
                    ok, ez = ok_row[k], ez_row[k]
                    if is_band[k]:
                        lz = ok and (ez > lo - r) and (ez < hi + r)
                        m1, m2 = ez - lo, hi - ez
                        margin = m1 if m1 < m2 else m2
                        strict[n, h, m, k] = lz and margin > 0
                        sure[n, h, m, k] = lz and margin > r
                    else:
                        lz = ok
                        strict[n, h, m, k] = lz
                        sure[n, h, m, k] = lz
                    loose[n, h, m, k] = lz


@njit(**_OPTS)
def iekf_terms_kernel(y, x, lo, hi, z_nom, rho, model, jm, w, wb, wh, a, e, eb, eh, gpart):
    """One Gauss-Newton iteration's terms of ``tracking_model.iekf`` except the prior's
    gradient ``-Y (x - x_prior)`` and the solve, with numpy's operations in numpy's order
    (``einsum`` sums over the links in sequence): writes the information matrix ``a`` (N, H,
    6, 6) = Y + J^T W J + the box and height pseudo-measurements, the residuals ``e`` (N, H,
    M), the box residuals ``eb`` (N, H, 3), the height residual ``eh`` (N, H) and the
    position gradient ``gpart`` (N, H, 3) = J^T W e + wb eb. The per-hypothesis body
    (:func:`_terms_row`) is the one :func:`iekf_kernel` runs.
    """
    n_n, n_h, _ = model.shape
    for n in range(n_n):
        for h in range(n_h):
            eh[n, h] = _terms_row(y[n, h], x[n, h], lo[n, h], hi[n, h], z_nom[n, h], rho[n],
                                  model[n, h], jm[n, h], w[n, h], wb, wh[n, h], a[n, h],
                                  e[n, h], eb[n, h], gpart[n, h])


@njit(**_OPTS, inline="always")
def _terms_row(y, x, lo, hi, z_nom, rho, model, jm, w, wb, wh, a, e, eb, gpart):
    """:func:`iekf_terms_kernel` of one hypothesis (``y``, ``a`` (6, 6), ``x`` (6,), ``lo``,
    ``hi``, ``eb``, ``gpart`` (3,), ``rho``, ``model``, ``w``, ``e`` (M,), ``jm`` (M, 3));
    returns the height residual."""
    n_m = model.shape[0]
    for m in range(n_m):
        e[m] = rho[m] - model[m]
    for i in range(6):
        for j in range(6):
            a[i, j] = y[i, j]
    for i in range(3):
        p = x[i]
        c = p if p > lo[i] else lo[i]  # np.clip: min(max(p, lo), hi)
        c = c if c < hi[i] else hi[i]
        eb[i] = c - p
    eh = z_nom - x[2]
    for i in range(3):
        for j in range(3):
            acc = 0.0
            for m in range(n_m):
                acc += jm[m, i] * w[m] * jm[m, j]
            a[i, j] = a[i, j] + acc
    for i in range(3):
        a[i, i] = a[i, i] + (wb if eb[i] != 0 else 0.0)
    a[2, 2] = a[2, 2] + wh
    for i in range(3):
        acc = 0.0
        for m in range(n_m):
            acc += jm[m, i] * (w[m] * e[m])
        gpart[i] = acc + wb * eb[i]
    return eh


def warm_model(planes: tuple, anc: np.ndarray) -> None:
    """Compile (or load from numba's cache) this module's kernels on tiny inputs (the callers
    in :mod:`diffpos.tracking.model` pass C-contiguous writable arrays, so one signature per
    kernel; called by :func:`diffpos.tracking.tracker.warm_tracking`). ``planes``: the
    building's planes (:func:`diffpos.paths.model_nb.building_planes`), ``anc`` (1, 1, 3)."""
    f8 = np.float64
    pos = np.array([[[1.0, 5.0, 4.5]]])
    one, onef = np.ones((1, 1)), np.ones((1, 1, 1))
    mask = np.ones((1, 1), np.bool_)
    model_kernel(pos, anc, np.zeros((1, 1)), np.zeros((1, 1, 1), np.int64), onef, one, one,
                 mask, *planes, np.empty((1, 1, 1)), np.empty((1, 1, 1, 3)),
                 np.empty((1, 1, 1)))
    k = 18
    flags = np.zeros(k, np.bool_)
    select_prep_kernel(np.ones((1, 1, 1, k)), np.zeros((1, 1, 1, k, 3)),
                       np.ones((1, 1, 1, k), np.bool_), np.ones((1, 1, 1, k), np.bool_), flags,
                       np.ones((1, 1, 3, 3)), one, one, np.ones((1, 1, 1, k)), True,
                       np.zeros(2), f8(0.0), np.empty((1, 1, 1, k), np.bool_),
                       np.empty((1, 1, 1, k)), np.empty((1, 1, 1, k)))
    b4 = np.empty((1, 1, 1, k), np.bool_)
    all_paths_kernel(pos, anc, np.zeros((1, 1)), np.full((1, 1), 0.2), flags, *planes,
                     np.empty((1, 1, 1, k)), np.empty((1, 1, 1, k, 3)), b4, b4.copy(), b4.copy())
    b4k = np.ones((1, 1, 1, k), np.bool_)
    sv, sl = np.ones(k), np.ones(k)
    cnt = select_pack_kernel(np.ones((1, 1, 1, k)), np.zeros((1, 1, 1, k, 3)), b4k, b4k.copy(),
                             flags, np.ones((1, 1, 3, 3)), one, one, np.ones((1, 1, 1, k)),
                             True, np.zeros(2), f8(0.0), np.empty((1, 1, 1, k), np.bool_), sv,
                             sl)
    i3 = np.zeros((1, 1, 1), np.int64)
    ex = np.zeros(cnt)
    select_best_kernel(np.ones((1, 1, 1, k)), b4k, one, mask, one, True, sv, sl, np.log(sv[:cnt]),
                       np.zeros(3), np.zeros((1, 1, 1, 2)), np.zeros(k + 1), ex, i3,
                       np.empty((1, 1, 1)), i3.copy(), np.empty((1, 1, 1)),
                       np.ones(1, np.bool_), i3.copy())
    select_mix_kernel(np.ones((1, 1, 1, k)), b4k, i3, i3.copy(), ex, np.empty((1, 1, 1)),
                      np.empty((1, 1, 1)))
    x6, p3 = np.ones((1, 1, 6)), np.ones((1, 1, 3))
    iekf_terms_kernel(np.ones((1, 1, 6, 6)), x6, p3, p3, one, one, onef, np.ones((1, 1, 1, 3)),
                      onef, 1.0, one, np.empty((1, 1, 6, 6)), np.empty((1, 1, 1)),
                      np.empty((1, 1, 3)), np.empty((1, 1)), np.empty((1, 1, 3)))
