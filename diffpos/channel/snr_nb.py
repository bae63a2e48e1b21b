"""Compiled SNR prediction: the SNR of every slot of :func:`diffpos.channel.emulator.pair_snr_db`.

One loop over (node, anchor) pairs and the 18 slots of ``diffpos.channel.emulator.MECHANISMS``,
scalars only, no allocation in the loop. Every slot is the numpy emulator's computation
(``diffpos.channel.emulator._slots``: geometry of ``diffpos.paths.model``, transmit dipole and antenna
pattern, Fresnel reflections with the TE/TM split, the UTD field of ``diffpos.channel.gtd`` with
spherical spreading, partition / wall / slab / glass losses, receive pattern, link budget)
with the same floating-point operations in the same order, except:

* **Global phases are dropped.** Only ``|gain|`` enters the SNR. The numpy emulator multiplies
  every field by phase factors common to all its components (``exp(-j k d)`` of the ray, the
  incident ``exp(-j k s')`` and diffracted ``exp(-j k s)`` of the UTD field, the
  ``-exp(-j pi/4)`` of the UTD prefactor); a common phase survives the (linear) reflections
  unchanged and cancels in the magnitude, so the kernel leaves them out (``|gain|`` changes by
  rounding only, ~1e-16 relative).
* **Gains and losses in dB.** The transmit pattern and the wall / slab / glass / partition
  losses scale the field linearly, so the kernel adds them to ``20 log10 |gain|`` instead of
  multiplying the field by ``10 ** (dB / 20)`` (rounding only).
* **Angles without trigonometry.** The UTD coefficients need ``cos((psi -/+ psi') / 2)`` and
  ``sin gamma0`` only; they are formed from the unit vectors (half-angle vectors of ``psi``
  and ``psi'``, :func:`_half_angle`) instead of ``atan2`` / ``mod`` / ``cos`` / ``sin`` of the
  angles (a few ulp; the sign of ``cos(b/2)``, which decides the side of a shadow boundary,
  can differ from numpy's only within a few ulp of the boundary itself).
* **Transition function.** ``F(X)`` through the Faddeeva function ``w`` (Weideman's
  rational approximation and asymptotic series, compiled): :mod:`.transition_nb`.

The resulting SNRs agree with the numpy emulator to 3.4e-12 dB (max over 12,000 random links x
3 radios x 4 buildings, tests/core/test_channel_kernel.py; tolerance 1e-9 dB) with the same
``-inf`` pattern.

Cost (``benchmarks/bench_channel.py --snr-only``): ~2.2 us CPU per link (18 slots), 6x less
than numpy on large batches and ~400x less on one-node calls (numpy's per-call overhead);
about 80 % of it in the 7 diffraction slots (the UTD field). The per-slot rays of
:mod:`.channel_rays_nb` that take arrays are inlined at numba IR level (``inline="always"``:
no call and no reference counting of ``prm`` / ``parts`` per slot; the same operations, so
the same bits): ~0.84x the CPU of separate calls on the tracker's calls (docs/performance.md,
"Session 25"); one compiled loop (below) keeps :func:`warm_channel`'s first compile at
~12 s CPU (~18 s with two inlined copies); ~0.2 s to load numba's on-disk cache.

Existence (``valid``) is the emulator's: the geometry of ``diffpos.paths.model`` (specular paths
entering through the window band, Fermat point strictly inside the edge, reflection points on
the floor's inside surface within 1e-9 m), the through-wall direct ray always valid, and the
slot dropped where its length or field is not finite. The per-row pieces of
:mod:`diffpos.paths.model_nb` are reused (plane codes and slot recipes, ``row_planes``,
``edge_axis``, ``inside_plane``, ``mirror``, ``in_floor_box``); the path functions themselves are
re-stated in :mod:`.channel_rays_nb` (the per-slot rays: direct, specular, UTD diffraction,
with the complex fields carried as ``(re, im)`` pairs where they meet a real factor, the
complex arithmetic's values) because the amplitudes need their interaction points (entry,
ground and reflection points, the diffraction point), which ``slot_path`` does not return.
numba keys this file's cache on this file only: after editing :mod:`.channel_rays_nb`,
:mod:`.paths_nb` or :mod:`.transition_nb` update ``CALLEES_SHA256`` below (the value
tests/core/test_kernel_stamps.py names; DEVELOPING.md).

Inputs are plain arrays prepared once in Python (:func:`channel_params`): the building's
planes and losses, the partitions as a ``(P, 5)`` array ``(axis, position, span lo, span hi,
loss dB)``, the radio (wavenumber, wavelength, patterns, link-budget constants, polarisation)
and the complex permittivities (ground, interior, partitions, walls, and the sheet of the
window's horizontal edges: 0, a perfect conductor, at ``channel_max_order`` 2, the wall's
material above; :mod:`diffpos.channel.slots`, "Window edges").

The loop is compiled once: :func:`channel_snr_masked_kernel`, over a per-pair slot mask
``need`` (:data:`MASKED_SIGNATURE`, ``cache=True``; :func:`warm_channel` compiles it or loads
numba's on-disk cache: call it at service start). A slot not needed is not evaluated and
holds NaN (the tracker re-scores a pair's "hole" slots at a shifted height,
``diffpos.tracking.model.snr_cost_near``: mostly specular slots near a window-band edge, and
not the 7 diffraction slots that are ~80 % of a full prediction). :func:`channel_snr_kernel`
(every slot, :data:`SIGNATURE`'s arguments) is that kernel with every slot needed, so both
give every slot the same statements' bits. A second compiled copy of the loop without the
mask (kept apart before for CPU) ran the full prediction ~1.6 % faster but took ~6 s CPU
more to compile once the rays were inlined (docs/performance.md, "Session 25: the SNR
kernels' compile").

:func:`snr_cost_kernel` is the tracker's SNR cost of the predicted slots (Gaussian about the
prediction plus the detector's threshold), the numpy reference's operations in one pass.
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit, types

from diffpos._kernels.pool import SNR_MIN_PAIRS, run_rows
from diffpos.channel.linkbudget import noise_floor_dbm
from diffpos.channel.rays_nb import (
    _OPTS,
    _P_E0,
    _P_FIRST_Z,
    _P_FLOOR_H,
    _P_K,
    _P_N0,
    _P_N_FLOORS,
    _P_PGAIN,
    _P_POWER0,
    _P_RX_HPBW,
    _P_RX_PEAK,
    _P_SILL,
    _P_WIN_H,
    _P_X0,
    _P_X1,
    N_PARAMS,
    _diffracted,
    _direct,
    _floor_index,
    _pattern_db,
    _specular,
    _zenith_deg,
)
from diffpos.constants import SPEED_OF_LIGHT_M_S
from diffpos.paths.model_nb import N_SLOTS, SLOT_KIND, edge_axis, row_planes

#: numba keys this file's on-disk cache on this file only, not on the ``*_nb`` code its
#: kernels compile in: a digest of that code (tests/core/test_kernel_stamps.py names the new
#: value after a callee's edit; writing it here is what invalidates a warm cache).
CALLEES_SHA256 = "13024189c1a90fce"

__all__ = [
    "COST_SIGNATURE",
    "MASKED_MIN_PAIRS",
    "MASKED_SIGNATURE",
    "SIGNATURE",
    "channel_params",
    "channel_snr_kernel",
    "channel_snr_masked_kernel",
    "eval_snr_kernel",
    "eval_snr_masked_kernel",
    "snr_cost_kernel",
    "warm_channel",
]


@njit(**_OPTS)
def channel_snr_masked_kernel(anchors, nodes, prm, parts, eta, need, out):
    """:func:`channel_snr_kernel` of the needed slots only: ``need`` (N, M, 18) bool; a slot
    not needed is not evaluated and its ``out`` is NaN (a value no caller uses); a needed slot
    is the SNR [dB] of :func:`channel_snr_kernel` (``-inf`` where not valid), which is this
    kernel with every slot needed: one compiled body for both (module docstring)."""
    first_z, floor_h, sill, win_h = prm[_P_FIRST_Z], prm[_P_FLOOR_H], prm[_P_SILL], prm[_P_WIN_H]
    edge = edge_axis(prm[_P_X0], prm[_P_X1])
    eta_g, eta_in, eta_edge = eta[0], eta[1], eta[eta.shape[0] - 1]
    c0, pgain, n0_dbm = prm[_P_POWER0], prm[_P_PGAIN], prm[_P_N0]
    rx_hpbw, rx_peak = prm[_P_RX_HPBW], prm[_P_RX_PEAK]
    sq2pik = math.sqrt(2.0 * math.pi * prm[_P_K])  # the UTD prefactor's, once
    ninf = -np.inf
    for i in range(nodes.shape[0]):
        n0, n1, n2 = nodes[i, 0], nodes[i, 1], nodes[i, 2]
        k_node = _floor_index(n2, first_z, floor_h, prm[_P_N_FLOORS])
        zf, zc, lo, hi = row_planes(k_node, first_z, floor_h, sill, win_h)
        for j in range(anchors.shape[1]):
            a0, a1, a2 = anchors[i, j, 0], anchors[i, j, 1], anchors[i, j, 2]
            for s in range(N_SLOTS):
                if not need[i, j, s]:
                    out[i, j, s] = np.nan
                    continue
                kind = SLOT_KIND[s]
                if kind == 0:
                    g, att, v0, v1, v2, length = _direct(a0, a1, a2, n0, n1, n2, k_node, lo,
                                                         hi, prm, parts)
                    ok = math.isfinite(length)
                elif kind == 1:
                    g, att, v0, v1, v2, length, ok = _specular(s, a0, a1, a2, n0, n1, n2, zf, zc,
                                                          lo, hi, prm, parts, eta_g, eta_in)
                else:
                    g, att, v0, v1, v2, length, ok = _diffracted(s, a0, a1, a2, n0, n1, n2, zf,
                                                            zc, lo, hi, prm, parts, eta_in,
                                                            edge, sq2pik, eta_edge)
                if not ok:
                    out[i, j, s] = ninf
                    continue
                rx_db = 0.0
                if not math.isnan(rx_hpbw):
                    rx_db = _pattern_db(_zenith_deg(v0, v1, v2), rx_hpbw, rx_peak)
                if g == 0.0:
                    out[i, j, s] = ninf
                    continue
                power = c0 + rx_db + (20 * math.log10(g) - att)
                out[i, j, s] = power + pgain - n0_dbm


@njit(**_OPTS)
def snr_cost_kernel(pred, meas, trust, sigma_db, fap_db, det_db, given_thr, thr, out):
    """The tracker's SNR cost of every slot (``diffpos.tracking.model._snr_cost_of``, its
    numpy reference: the same operations in the same order, NaN propagated as numpy's ``max``
    does, so bit-identical): ``pred`` (P, K) predicted SNRs [dB], ``meas`` (P,) measured
    [dB], ``trust`` (P, K) bool (the slots whose maximum sets the detector's threshold) ->
    ``out`` (P, K): ``((meas - pred) / sigma)^2 / 2`` plus the same of the shortfall below
    ``thr - sigma``, ``thr = max(max_trust pred - fap_db, det_db)`` the detector's threshold;
    +inf where ``pred`` is not finite, 0 where ``meas`` is not. ``thr`` (P,): written (NaN
    where ``meas`` is not finite), or with ``given_thr`` read (``trust`` unused)."""
    n_k = pred.shape[1]
    for i in range(pred.shape[0]):
        mi = meas[i]
        if not math.isfinite(mi):
            for k in range(n_k):
                out[i, k] = 0.0
            if not given_thr:
                thr[i] = np.nan
            continue
        if given_thr:
            th = thr[i]
        else:
            top = -np.inf
            for k in range(n_k):
                if trust[i, k]:
                    v = pred[i, k]
                    if math.isnan(v):
                        top = np.nan
                        break
                    if v > top:
                        top = v
            th = top - fap_db
            if not th >= det_db:  # np.maximum: NaN propagates
                th = det_db if not math.isnan(th) else th
            thr[i] = th
        short = (th - sigma_db) - mi
        if not short >= 0.0:
            short = 0.0 if not math.isnan(short) else short
        q = short / sigma_db
        extra = 0.5 * (q * q)
        for k in range(n_k):
            v = pred[i, k]
            if not math.isfinite(v):
                out[i, k] = np.inf
                continue
            r = (mi - v) / sigma_db
            out[i, k] = 0.5 * (r * r) + extra


#: :func:`eval_snr_masked_kernel`'s smallest chunk [node-anchor pairs]: a masked pair
#: predicts ~6 of its 18 slots (the tracker's: the direct and diffraction slots and the loose
#: window-band ones; ~1.5 us per pair on the 30 s ``large`` replay), so twice the unmasked
#: kernel's :data:`~diffpos._kernels.pool.SNR_MIN_PAIRS` for the same ~0.3-0.5 ms of work.
MASKED_MIN_PAIRS = 2 * SNR_MIN_PAIRS

_c16_1d = types.complex128[::1]
#: The argument types of :func:`channel_snr_kernel` (not compiled: it runs
#: :func:`channel_snr_masked_kernel`, whose arguments are these with ``need`` before ``out``).
SIGNATURE = types.void(types.float64[:, :, ::1], types.float64[:, ::1], types.float64[::1],
                       types.float64[:, ::1], _c16_1d, types.float64[:, :, ::1])
#: The compiled signature of :func:`channel_snr_masked_kernel` (``need`` before ``out``).
MASKED_SIGNATURE = types.void(types.float64[:, :, ::1], types.float64[:, ::1],
                              types.float64[::1], types.float64[:, ::1], _c16_1d,
                              types.boolean[:, :, ::1], types.float64[:, :, ::1])
#: The compiled signature of :func:`snr_cost_kernel`.
COST_SIGNATURE = types.void(types.float64[:, ::1], types.float64[::1], types.boolean[:, ::1],
                            types.float64, types.float64, types.float64, types.boolean,
                            types.float64[::1], types.float64[:, ::1])
_state: dict[str, object] = {}


def warm_channel() -> float:
    """Compile :func:`channel_snr_masked_kernel` for :data:`MASKED_SIGNATURE` (also the body
    of :func:`channel_snr_kernel`) and :func:`snr_cost_kernel` for :data:`COST_SIGNATURE`, or
    load them from numba's cache. Idempotent; returns the seconds it took (0 once warm). Call
    it at service start."""
    if "entry" in _state:
        return 0.0
    t0 = time.perf_counter()
    channel_snr_masked_kernel.compile(MASKED_SIGNATURE.args)
    snr_cost_kernel.compile(COST_SIGNATURE.args)
    _state["entry"] = channel_snr_masked_kernel
    return time.perf_counter() - t0


def channel_params(building, radio, materials, eta_parts=(), eta_wall=0j, eta_edge=0j
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernel's constants: ``(prm, parts, eta)`` (module docstring) of a building and radio.

    ``materials``: ``(eta_ground, eta_in, wall_db, slab_db, glass_db, parts)`` as the numpy
    emulator computes them (``diffpos.channel.emulator._materials``), so both use the same numbers;
    ``eta_parts``: the partitions' permittivities
    (``diffpos.channel.slots.partition_permittivities``: their reflections), after the two in
    ``eta``; ``eta_wall``: the walls' permittivity (the window edges' dielectric sheet in
    :mod:`diffpos.channel.families_nb`: the vertical edges' side wall, the horizontal edges'
    facade wall; 0: a perfect conductor), then ``eta_edge``, ``eta``'s last entry: the sheet of
    the 18 slots' horizontal window edges in :func:`channel_snr_kernel` (0, the default: a
    perfect conductor, the paper's model and the emulator's at ``channel_max_order`` 2; the
    emulator passes the wall's permittivity at orders >= 3, :mod:`diffpos.channel.slots`).
    """
    eta_g, eta_in, wall_db, slab_db, glass_db, plist = materials
    x0, x1 = building.edge_x_m
    nan = float("nan")
    k = 2.0 * math.pi * radio.frequency_hz / SPEED_OF_LIGHT_M_S  # gtd.wavenumber_rad_m
    prm = np.empty(N_PARAMS)
    prm[:_P_E0] = (
        float(building.first_floor_z_m), float(building.floor_height_m),
        float(building.sill_height_m), float(building.window_height_m), float(x0), float(x1),
        float(building.depth_m), float(building.n_floors),
        float(wall_db), float(slab_db), float(glass_db), float(k), float(radio.wavelength_m),
        nan if radio.tx_hpbw_deg is None else float(radio.tx_hpbw_deg), float(radio.tx_peak_deg),
        nan if radio.rx_hpbw_deg is None else float(radio.rx_hpbw_deg), float(radio.rx_peak_deg),
        radio.tx_power_dbm + radio.tx_gain_dbi + radio.rx_gain_dbi,
        float(radio.processing_gain_db),
        float(noise_floor_dbm(radio.bandwidth_hz, temperature_k=radio.noise_temperature_k,
                              noise_figure_db=radio.noise_figure_db)),
    )
    prm[_P_E0:] = np.asarray(radio.polarization, dtype=np.float64)
    parts = np.array([[float(axis), float(pos), float(lo), float(hi), float(db)]
                      for axis, pos, (lo, hi), db in plist], dtype=np.float64).reshape(-1, 5)
    eta = np.array([eta_g, eta_in, *eta_parts, eta_wall, eta_edge], dtype=np.complex128)
    return prm, np.ascontiguousarray(parts), eta


def channel_snr_kernel(anchors: np.ndarray, nodes: np.ndarray, prm: np.ndarray,
                       parts: np.ndarray, eta: np.ndarray, out: np.ndarray) -> None:
    """SNR of every slot: ``anchors`` (N, M, 3), ``nodes`` (N, 3) -> ``out`` (N, M, 18) [dB],
    ``-inf`` where the slot is not valid (``diffpos.channel.emulator.pair_snr_db``).

    ``prm``: :func:`channel_params`' float vector; ``parts``: (P, 5) partitions; ``eta``:
    :func:`channel_params`' complex permittivities (the ground's and the interior surfaces'
    first, the horizontal window edges' sheet last: 0 a perfect conductor). Arrays as
    :data:`SIGNATURE` (C-contiguous, writeable). :func:`channel_snr_masked_kernel` with every
    slot needed (its one compiled body: a separate compiled loop doubled
    :func:`warm_channel`'s first compile once the rays were inlined; docs/performance.md,
    "Session 25: the SNR kernels' compile"); releases the GIL like it.
    """
    need = np.ones(out.shape, dtype=np.bool_)
    channel_snr_masked_kernel(anchors, nodes, prm, parts, eta, need, out)


def eval_snr_kernel(anchors: np.ndarray, nodes: np.ndarray,
                    params: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """Run the kernel: ``anchors`` (N, M, 3), ``nodes`` (N, 3) C-contiguous float64,
    ``params`` from :func:`channel_params`; returns (N, M, 18) [dB]."""
    warm_channel()
    out = np.empty((nodes.shape[0], anchors.shape[1], N_SLOTS))
    prm, parts, eta = params

    def rows(lo: int, hi: int) -> None:  # the node rows [lo, hi): slices keep the signature
        channel_snr_kernel(anchors[lo:hi], nodes[lo:hi], prm, parts, eta, out[lo:hi])

    run_rows(rows, nodes.shape[0], min_rows=-(-SNR_MIN_PAIRS // max(anchors.shape[1], 1)))
    return out


def eval_snr_masked_kernel(anchors: np.ndarray, nodes: np.ndarray,
                           params: tuple[np.ndarray, np.ndarray, np.ndarray],
                           need: np.ndarray) -> np.ndarray:
    """:func:`eval_snr_kernel` of the slots ``need`` (N, M, 18) C-contiguous bool only
    (:func:`channel_snr_masked_kernel`: NaN elsewhere); split by node rows over the kernel
    threads like it (every row's values the one-thread call's, bit for bit)."""
    warm_channel()
    out = np.empty((nodes.shape[0], anchors.shape[1], N_SLOTS))
    prm, parts, eta = params

    def rows(lo: int, hi: int) -> None:  # the node rows [lo, hi): slices keep the signature
        channel_snr_masked_kernel(anchors[lo:hi], nodes[lo:hi], prm, parts, eta, need[lo:hi],
                                  out[lo:hi])

    run_rows(rows, nodes.shape[0],
             min_rows=-(-MASKED_MIN_PAIRS // max(anchors.shape[1], 1)))
    return out
