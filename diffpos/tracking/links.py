"""The tracker's links and path evaluation (:mod:`diffpos.tracking.model`'s lower layer).

:class:`Links` holds one epoch's measurements shaped to broadcast against ``(N, H, M)``
(N nodes, H hypotheses, M anchors); :func:`all_paths` evaluates every mechanism of the
first-arrival path model at the hypotheses with graded existence (:class:`PathEval`: strict,
loose and sure, the window band widened / narrowed by ``relax_m``) in one compiled pass
(:func:`diffpos.tracking.model_nb.all_paths_kernel`), bit-identical to the numpy reference
:func:`_all_paths_numpy` kept next to it; :func:`slot_paths` evaluates one chosen slot per
link; :func:`candidates` is the first-arrival rule (which mechanisms can be the detected
first arrival).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from diffpos._kernels.pool import PATHS_MIN_LINKS, run_rows
from diffpos.paths.mechanisms import DIFFRACTION_SLOTS, MECHANISMS, SPECULAR_SLOTS
from diffpos.paths.model import graded_paths
from diffpos.paths.model_nb import building_planes
from diffpos.tracking.model_nb import all_paths_kernel

FloatArray = NDArray[np.float64]
K_SLOTS = len(MECHANISMS)
_IS_DIFF = np.isin(np.arange(K_SLOTS), DIFFRACTION_SLOTS)
_IS_BAND = np.isin(np.arange(K_SLOTS), SPECULAR_SLOTS)  # entry point in the window band


@dataclass(frozen=True)
class Links:
    """The measurements of one epoch, shaped to broadcast against ``(N, H, M)``.

    ``rho``, ``var``, ``mask``: (N, 1, M); ``anchors``: (N, 1, M, 3); ``snr``: (N, 1, M)
    measured SNR [dB] (NaN: unknown) with the ``radio`` that predicts every slot's SNR, or
    None (ranges only).
    """

    rho: FloatArray
    var: FloatArray
    mask: NDArray[np.bool_]
    anchors: FloatArray
    snr: FloatArray | None = None
    radio: object | None = None

    def take(self, idx) -> Links:
        """The links of the nodes ``idx``."""
        return Links(self.rho[idx], self.var[idx], self.mask[idx], self.anchors[idx],
                     None if self.snr is None else self.snr[idx], self.radio)

    @classmethod
    def from_arrays(cls, anchors_m, ranges_m, sigmas_m, mask, sigma_model_m: float,
                    snr_db=None, radio=None) -> Links:
        m = np.asarray(mask, bool) & np.isfinite(ranges_m) & np.isfinite(sigmas_m)
        m &= np.all(np.isfinite(anchors_m), axis=-1)
        rho = np.where(m, ranges_m, 0.0)
        var = np.where(m, np.asarray(sigmas_m, float) ** 2 + sigma_model_m**2, 1.0)
        # a missing link gets a harmless placeholder anchor (its weight is 0)
        anc = np.where(m[..., None], anchors_m, np.array([0.0, -1.0, 0.0]))
        snr = None
        if snr_db is not None and radio is not None:
            snr = np.where(m, np.asarray(snr_db, float), np.nan)[:, None]
        return cls(rho=rho[:, None], var=var[:, None], mask=m[:, None], anchors=anc[:, None],
                   snr=snr, radio=radio if snr is not None else None)


def _c(a, dtype=None) -> NDArray:
    """``a`` as a C-contiguous writable array (a kernel's one compiled signature per argument:
    a read-only view, e.g. from ``broadcast_to``, would compile a second one)."""
    out = np.ascontiguousarray(a, dtype=dtype)
    return out if out.flags.writeable else out.copy()


def _cb(a, shape: tuple, dtype=None) -> NDArray:
    """``_c(np.broadcast_to(a, shape), dtype)``: the same values and array type, without the
    broadcast's read-only view (and so its copy) when ``a`` already has the shape: ``a`` itself
    if it is C-contiguous, writable and of the dtype (e.g. the prior information, the floor
    box and the selection of every hypothesis, copied for every kernel call before)."""
    if isinstance(a, np.ndarray) and a.shape == shape:
        return _c(a, dtype)
    return _c(np.broadcast_to(a, shape), dtype)


def _los(pos: FloatArray, anchors: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Straight-line length and its Jacobian d/d node, shapes (N, H, M) and (N, H, M, 3)."""
    d = pos[:, :, None, :] - anchors
    n = np.sqrt(np.einsum("...i,...i->...", d, d))
    return n, d / np.maximum(n, 1e-12)[..., None]


@dataclass(frozen=True)
class PathEval:
    """Mechanisms at hypotheses, (..., K) (slot axis last; Jacobians (..., K, 3)).

    ``length`` and ``jac`` are the raw geometric values (also where the path does not exist,
    so an iterate may cross an existence boundary of its chosen mechanism). ``strict`` is the
    existence of :func:`diffpos.paths.model.first_arrival_paths`; for the specular slots ``loose``
    and ``sure`` also hold with the window band widened / narrowed by ``relax_m`` (the entry
    point is uncertain by about that much); diffraction slots: all three are ``strict``.
    """

    length: FloatArray
    jac: FloatArray
    strict: NDArray[np.bool_]
    loose: NDArray[np.bool_]
    sure: NDArray[np.bool_]


def eval_paths(nodes_m: FloatArray, anchors_m: FloatArray, floor, building, relax_m: float,
               slots=None) -> PathEval:
    """The first-arrival path model with raw lengths and graded existence: the compiled
    kernel of :func:`diffpos.paths.model.graded_paths` (same geometry as
    :func:`diffpos.paths.model.first_arrival_paths`)."""
    g = graded_paths(nodes_m, anchors_m, building, relax_m=relax_m, floor=floor, slots=slots)
    return PathEval(length=g.length_m, jac=g.jacobian, strict=g.strict, loose=g.loose,
                    sure=g.sure)


def _relax(relax_m, shape) -> FloatArray:
    """``relax_m`` (scalar or broadcastable to ``shape`` = (N, H)) as a C-contiguous float64
    (N, H) array, checked >= 0 [m]: ``relax_m`` itself when it is one (:func:`_cb`; the
    callers only read it)."""
    r = _cb(relax_m, tuple(shape), np.float64)
    if not (r >= 0.0).all():
        raise ValueError(f"relax_m must be >= 0 [m]; got {relax_m!r}")
    return r


def all_paths(pos: FloatArray, links: Links, floor, building, relax_m) -> PathEval:
    """Every mechanism for every hypothesis (N, H, M, K) at positions ``pos`` (N, H, 3):
    one compiled pass (:func:`diffpos.tracking.model_nb.all_paths_kernel`), bit-identical
    to :func:`_all_paths_numpy` (:func:`eval_paths`). ``relax_m`` [m]: the widening of the
    window band at the entry point, a scalar or one per hypothesis (broadcastable to (N, H))."""
    n, h = pos.shape[:2]
    r = _relax(relax_m, (n, h))
    m = links.anchors.shape[-2]
    shape = (n, h, m, K_SLOTS)
    fl = _cb(floor, (n, h), np.float64)
    length, jac = np.empty(shape), np.empty((*shape, 3))
    strict, loose, sure = (np.empty(shape, dtype=np.bool_) for _ in range(3))
    anc = np.empty((n, m, 3))
    anc[...] = links.anchors[:, 0]
    pc, planes = _c(pos, dtype=np.float64), building_planes(building)

    def rows(lo: int, hi: int) -> None:  # the node rows [lo, hi) (diffpos._kernels.pool)
        all_paths_kernel(pc[lo:hi], anc[lo:hi], fl[lo:hi], r[lo:hi], _IS_BAND, *planes,
                         length[lo:hi], jac[lo:hi], strict[lo:hi], loose[lo:hi], sure[lo:hi])

    run_rows(rows, n, min_rows=-(-PATHS_MIN_LINKS // max(h * m, 1)))
    return PathEval(length=length, jac=jac, strict=strict, loose=loose, sure=sure)


def _all_paths_numpy(pos: FloatArray, links: Links, floor, building, relax_m) -> PathEval:
    """The reference of :func:`all_paths`: :func:`diffpos.paths.model.graded_paths` with the widest
    widening, then every hypothesis' band test with its own (the same comparisons)."""
    n, h = pos.shape[:2]
    r = _relax(relax_m, (n, h))
    fl = np.broadcast_to(np.asarray(floor), (n, h))
    g = graded_paths(pos[:, :, None, :], links.anchors, building, relax_m=float(r.max()),
                     floor=fl[:, :, None])
    lo, hi = (v[:, :, None, None] for v in building.window_z_m(fl))
    rr = r[:, :, None, None]
    z = g.entry_z_m
    with np.errstate(invalid="ignore"):
        margin = np.minimum(z - lo, hi - z)
        loose = g.loose & np.where(_IS_BAND, (z > lo - rr) & (z < hi + rr), True)
        strict = loose & np.where(_IS_BAND, margin > 0, True)
        sure = loose & np.where(_IS_BAND, margin > rr, True)
    return PathEval(length=g.length_m, jac=g.jacobian, strict=strict, loose=loose, sure=sure)


def slot_paths(pos: FloatArray, links: Links, floor, slot: NDArray, building):
    """Raw length and Jacobian of the chosen slot per link (slot -1: NaN, 0).

    The path model is evaluated once per distinct slot on the links that use it (the cost
    of one full evaluation divided by the number of slots).
    """
    shape = slot.shape  # (N, H, M)
    p = np.broadcast_to(pos[:, :, None, :], (*shape, 3)).reshape(-1, 3)
    a = np.broadcast_to(links.anchors, (*shape, 3)).reshape(-1, 3)
    fl = np.broadcast_to(np.broadcast_to(np.asarray(floor), shape[:2])[..., None],
                         shape).reshape(-1)
    s = slot.reshape(-1)
    length = np.full(s.shape, np.nan)
    jac = np.zeros((s.size, 3))
    for k in np.unique(s[s >= 0]):
        idx = np.flatnonzero(s == k)
        pe = eval_paths(p[idx], a[idx], fl[idx], building, 0.0, slots=[int(k)])
        length[idx] = pe.length[:, 0]
        jac[idx] = pe.jac[:, 0]
    ok = np.isfinite(length) & np.all(np.isfinite(jac), axis=-1)
    return length.reshape(shape), np.where(ok[:, None], jac, 0.0).reshape(*shape, 3), \
        ok.reshape(shape)


def candidates(pe: PathEval) -> NDArray[np.bool_]:
    """Mechanisms that can be the detected first arrival at a hypothesis, (..., K).

    The first-arrival rule: a first arrival is never later than an existing specular path
    (direct, single or double bounce entering through the opening: Fresnel losses of a few dB,
    always within the detector's 15 dB of the strongest path), while an edge-diffraction path
    (UTD shadow loss 10-30 dB) may be too weak and be skipped. So the candidates are the
    earliest specular path that surely exists, every specular path that may exist (entry
    within ``relax_m`` of the band) and is not later, and every diffraction path earlier than
    it. Measured with the emulator on 3,000 random nodes x every anchor of five geometries
    (the shipped two and the three held-out variants of ``benchmarks/bench_tracking.py``): no
    detected first arrival was later than an existing specular path, and every skipped earlier
    path was a diffraction slot (7-13).
    """
    e_spec = np.where(pe.sure & ~_IS_DIFF, pe.length, np.inf).min(axis=-1, keepdims=True)
    return pe.loose & np.where(_IS_DIFF, pe.length < e_spec, pe.length <= e_spec)
