"""Outdoor-to-indoor multipath emulator and first-arrival ranging (pure, vectorised).

For every anchor x node pair the emulator builds a fixed list of candidate multipath
components (MPCs, the "slots" of :data:`MECHANISMS`), each with its path length/delay, complex
amplitude gain, departure and arrival zenith angles, MPC group (the paper's Table of MPC
groups) and a validity flag. Shapes are ``(N, M, K)``: N nodes, M anchors, K slots. All
geometry is exact (image method, Fermat point on the window edges); there are no loops over
nodes or anchors, only over the handful of slots.

Mechanisms (``Tx`` anchor, ``Rx`` node, ``R`` reflection, ``D`` diffraction, ``T`` transmission)

=====  =====================  =======================================================  =====
group  label                  geometry                                                 slot
=====  =====================  =======================================================  =====
1      ``Tx-Rx``              straight line; through the node floor's window opening,  0
                              otherwise through the wall/slabs with their loss
2      ``Tx-R(ground)-Rx``    ground image of the anchor, entering through the window  1
2      ``Tx-R(floor)-Rx``     node imaged in its floor / ceiling / back / side walls,  2-6
       ... ceiling/back/side  entering through the node floor's window
3      ``Tx-D(upper)-Rx``     Fermat point on the upper / lower window edge of the     7-8
       ``Tx-D(lower)-Rx``     node's floor (UTD amplitude), plus partitions crossed
4      ``Tx-D-R-Rx``          upper/lower edge, then floor/ceiling/back wall           9-13
4      ``Tx-R-R-Rx``          ground+ceiling, ceiling+floor, floor+ceiling,            14-17
                              ceiling+back wall
=====  =====================  =======================================================  =====

Higher-order families (``radio.channel_max_order`` 3 or 4; default 2 = the 18 above): slots
18.. are the families :func:`diffpos.paths.mechanisms.mechanism_set` adds (label
``Channel.mechanism``, group :func:`mpc_class_of`), with the same physics: the image-method /
Fermat-point geometry of :mod:`diffpos.paths.model`, Fresnel reflection of the field vector on
the ground and on every inside slab or wall in path order, the UTD edge field (after a ground
bounce: the image source's reflected field), glass, partitions, Friis spreading
(:func:`diffpos.channel.slots.family_slot`; compiled for :func:`pair_first_arrival` in
:mod:`diffpos.channel.families_nb`). At these orders every window edge is a dielectric sheet
of the walls' material, the 18's horizontal edges included (at order 2 those are perfect
conductors, the paper's model; :mod:`diffpos.channel.slots`, "Window edges").
:func:`pair_snr_db` (an estimator's SNR model) keeps the 18 slots whatever the setting (their
edges' sheet follows it). Measured mix against Sionna RT: ``docs/channel_mix.md``.

Every inside segment adds the loss of the interior partitions it crosses (so MPC-3 includes
the paper's ``Tx-D-T-Rx`` and ``Tx-D-T-T-Rx``); glass windows add ``glass_loss_db`` when
crossed. Reflections use Fresnel coefficients of ITU-R P.2040 materials applied to the field
vector (TE/TM split); diffraction uses the UTD field of ``diffpos.channel.gtd`` with spherical-wave
spreading and the transmit polarisation ``radio.polarization``.

Amplitude normalisation: an MPC's amplitude ``g`` is the ratio of received to transmitted
field such that ``|g|^2`` is the path gain (free space: ``(lambda / (4 pi d))^2``). The
transmitter is a short dipole along the polarisation vector (its field is the transverse
projection of ``E_0``, as in the paper's diffraction formulas) times the radio's antenna
pattern; the receiver collects the full field magnitude (dual-polarised receiver).

Simplifications (documented, not tuned): through-wall paths are straight (no refraction, no
extra delay in the material); slab/wall loss is the normal-incidence loss; corner diffraction
(Fermat point clamped to an edge end) is dropped, identically in the path model
(:mod:`diffpos.paths.model` says why); reflections off partitions
and paths entering through another floor's window are not modelled (they cross >= 1 concrete
slab, > 100 dB).

The ranging part, :func:`first_arrival`, implements the paper's detector: the first arriving
path is the MPC with the smallest delay whose SNR (received power + processing gain - kTB) is
above ``max(P_max - 15 dB, detection floor)``; the measured range is ``c tau`` plus Gaussian
noise of standard deviation ``sqrt(CRLB^2 + floor^2)``: the ranging CRLB ``c / sqrt(8 pi^2 B^2
SNR)`` at that path's SNR and the radio's ``range_error_floor_m`` (calibration, residual
multipath, clock).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from diffpos.channel.families_nb import eval_family_snr
from diffpos.channel.linkbudget import db_to_linear, ranging_crlb_m
from diffpos.channel.slots import (
    _C,
    _Ctx,
    _materials,
    _slots,
    itu_permittivity,
    partition_permittivities,
)
from diffpos.channel.snr_nb import channel_params, eval_snr_kernel, eval_snr_masked_kernel
from diffpos.paths.mechanisms import MECHANISMS, MechanismSet, Recipe, mechanism_set
from diffpos.paths.model import first_arrival_paths
from diffpos.paths.model_nb import mechanism_table
from diffpos.scenario import Building, Radio, Scenario

__all__ = [
    "MPC_CLASS",
    "Channel",
    "FirstArrival",
    "channel_mechanisms",
    "emulate_channel",
    "first_arrival",
    "mpc_class_of",
    "mpc_statistics",
    "pair_family_snr_db",
    "pair_first_arrival",
    "pair_snr_db",
    "scenario_channel",
]

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

# Slot labels (MECHANISMS) come from diffpos.paths.model, the one geometry implementation.
#: MPC group (1..4, the paper's Table) of every slot.
MPC_CLASS: NDArray[np.int8] = np.array([1, 2, 2, 2, 2, 2, 2, 3, 3, 4, 4, 4, 4, 4, 4, 4, 4, 4],
                                       dtype=np.int8)


def mpc_class_of(recipe: Recipe) -> int:
    """MPC group (1..4, the paper's Table) of a mechanism: 1 direct, 2 one reflection (a ground
    bounce included), 3 a window-edge diffraction alone, 4 everything with two or more
    interactions (:data:`MPC_CLASS` for the 18)."""
    if recipe.kind == "direct":
        return 1
    if recipe.order == 1:
        return 2 if recipe.kind == "spec" else 3
    return 4


def _params(building: Building, radio: Radio) -> tuple:
    """The compiled kernels' constants (:func:`diffpos.channel.snr_nb.channel_params`) with the
    numpy emulator's materials, the partitions' permittivities and the window edges' sheets
    (:mod:`diffpos.channel.slots`, "Window edges": the 18's horizontal edges dielectric at
    ``channel_max_order`` >= 3 only)."""
    f = radio.frequency_hz
    eta_wall = itu_permittivity(building.wall_material, f)
    return channel_params(building, radio, _materials(building, f),
                          partition_permittivities(building, f), eta_wall,
                          eta_wall if radio.channel_max_order >= 3 else 0j)


def channel_mechanisms(radio: Radio) -> MechanismSet:
    """The emulated channel's mechanisms: the 18 (``radio.channel_max_order`` 2) or the
    families of :func:`diffpos.paths.mechanisms.mechanism_set` up to that order (the 18
    first, in their slots), with the partition-reflection families (none exists in a building
    without partitions)."""
    return mechanism_set(radio.channel_max_order, partitions=True)




# --------------------------------------------------------------------------------------------
# result types
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Channel:
    """Multipath components of every node x anchor pair, padded to K slots.

    Attributes
    ----------
    delay_s : ndarray, shape (N, M, K) [s]
        Propagation delay (path length / c); NaN where invalid.
    length_m : ndarray, shape (N, M, K) [m]
    gain : ndarray of complex, shape (N, M, K) [-]
        Amplitude gain incl. antenna gains and all interaction losses; ``|gain|^2`` is the
        path gain (0 where invalid).
    power_dbm : ndarray, shape (N, M, K) [dBm]
        Received power ``P_tx + 20 log10 |gain|`` (-inf where invalid).
    snr_db : ndarray, shape (N, M, K) [dB]
        ``power_dbm + processing gain - kTB``.
    aod_deg, aoa_deg : ndarray, shape (N, M, K) [deg]
        Zenith angles (from +z) of departure at the anchor and of arrival at the node (the
        direction towards the last interaction point; 90 = horizontal).
    valid : ndarray of bool, shape (N, M, K)
        Geometrically possible (before any power threshold).
    exists : ndarray of bool, shape (N, M, K)
        ``valid`` and ``snr_db >= radio.detection_snr_db``: the MPC is received.
    mpc_class : ndarray of int8, shape (K,)
        MPC group (1..4) of each slot.
    mechanism : tuple of str, length K
        Slot labels.
    nodes_m, anchors_m : ndarray, shape (N, 3) / (M, 3) [m]
    """

    delay_s: FloatArray
    length_m: FloatArray
    gain: NDArray[np.complex128]
    power_dbm: FloatArray
    snr_db: FloatArray
    aod_deg: FloatArray
    aoa_deg: FloatArray
    valid: BoolArray
    exists: BoolArray
    mpc_class: NDArray[np.int8]
    mechanism: tuple[str, ...]
    nodes_m: FloatArray
    anchors_m: FloatArray


@dataclass(frozen=True)
class FirstArrival:
    """First-arriving path per node x anchor pair and the measured range.

    Attributes
    ----------
    range_m : ndarray, shape (N, M) [m]
        Measured range ``c tau + n``, ``n ~ N(0, sigma_m^2)``; NaN where not detected.
    true_path_m : ndarray, shape (N, M) [m]
        Length of the first-arriving path ``c tau`` (NaN where not detected).
    snr_db : ndarray, shape (N, M) [dB]
        SNR of the first-arriving path.
    sigma_m : ndarray, shape (N, M) [m]
        Ranging standard deviation ``sqrt(CRLB^2 + range_error_floor_m^2)`` at that SNR (inf
        where not detected).
    mpc_class : ndarray of int8, shape (N, M)
        Group (1..4) of the first-arriving path, 0 where not detected.
    slot : ndarray of int, shape (N, M)
        Index into ``Channel.mechanism`` (-1 where not detected).
    aoa_deg : ndarray, shape (N, M) [deg]
        Arrival zenith angle of the first-arriving path.
    detected : ndarray of bool, shape (N, M)
        At least one MPC exists.
    """

    range_m: FloatArray
    true_path_m: FloatArray
    snr_db: FloatArray
    sigma_m: FloatArray
    mpc_class: NDArray[np.int8]
    slot: NDArray[np.int_]
    aoa_deg: FloatArray
    detected: BoolArray


@lru_cache(maxsize=64)
def _kernel_params(building: Building, radio: Radio) -> tuple[np.ndarray, ...]:
    """The compiled kernel's constants of a building and radio (cached: both are frozen)."""
    return _params(building, radio)


#: The last hashable (building, radio) pair of :func:`_params_for` and its constants: the
#: same objects again (every call of one tracker or fusion) skip hashing the frozen
#: dataclasses (~3 us a call, ~2,000 calls per second of a ``large`` replay).
#: One tuple, read and replaced whole (a thread never sees a mixed pair).
_LAST_PARAMS: list = [(None, None, None)]


def _params_for(building: Building, radio: Radio) -> tuple[np.ndarray, ...]:
    """:func:`_kernel_params`, or computed afresh where a field cannot be hashed (e.g.
    partitions given as a list)."""
    last_b, last_r, last_p = _LAST_PARAMS[0]
    if building is last_b and radio is last_r:
        return last_p
    try:
        params = _kernel_params(building, radio)
    except TypeError:
        return _params(building, radio)
    _LAST_PARAMS[0] = (building, radio, params)
    return params


def pair_snr_db(anchors_m: ArrayLike, nodes_m: ArrayLike, *, building: Building,
                radio: Radio, need: ArrayLike | None = None) -> FloatArray:
    """SNR of every slot for per-node anchor sets: anchors ``(N, M, 3)``, nodes ``(N, 3)``.

    The same amplitudes as :func:`emulate_channel` (which pairs every node with every anchor),
    for estimators scoring position hypotheses; ``-inf`` where a slot is not valid. Nodes must
    be inside the building and anchors outside (not checked).

    Computed by :func:`diffpos.channel.snr_nb.channel_snr_kernel` (the compiled
    :func:`~diffpos.channel.snr_nb.channel_snr_masked_kernel` with every slot needed: one
    loop over node-anchor pairs and slots, the emulator's operations with its common phase
    factors left out and Weideman's Faddeeva function); :func:`_pair_snr_db_numpy` is
    the numpy reference (the emulator's own :func:`_slots`). tests/core/test_channel_kernel.py
    holds them together: the same ``-inf`` pattern and finite values within 1e-9 dB. Inputs
    with a non-finite coordinate go to the reference. Anchors ``(M, 3)`` are shared by all
    nodes.

    ``need`` (bool, broadcastable to ``(N, M, K)``): compute only these slots
    (:func:`diffpos.channel.snr_nb.channel_snr_masked_kernel`); every needed slot has
    the unmasked value, bit for bit, the others are NaN (not evaluated).

    Returns
    -------
    ndarray, shape (N, M, K) [dB]
    """
    anchors = np.asarray(anchors_m, dtype=np.float64)
    nodes = np.asarray(nodes_m, dtype=np.float64)
    if anchors.ndim == 2:
        anchors = np.broadcast_to(anchors[None], (nodes.shape[0], *anchors.shape))
    if need is not None:  # (a mask of the full shape as it is: a broadcast view is copied)
        need, shape = np.asarray(need, dtype=np.bool_), (*anchors.shape[:2], len(MECHANISMS))
        need = _c_w(need if need.shape == shape else np.broadcast_to(need, shape))
    if not (np.isfinite(anchors).all() and np.isfinite(nodes).all()):
        out = _pair_snr_db_numpy(anchors, nodes, building=building, radio=radio)
        return out if need is None else np.where(need, out, np.nan)
    params = _params_for(building, radio)
    if need is None:
        return eval_snr_kernel(_c_w(anchors), _c_w(nodes), params)
    return eval_snr_masked_kernel(_c_w(anchors), _c_w(nodes), params, need)


def _c_w(a: np.ndarray) -> np.ndarray:
    """``a`` C-contiguous and writeable (a copy if not): numba types a read-only array (a
    ``broadcast_to`` view that happens to be contiguous) apart, so it would compile a second
    specialisation of the kernel at its first use, after ``warm_channel``."""
    return np.require(a, requirements=("C", "W"))


def _pair_snr_db_numpy(anchors_m: ArrayLike, nodes_m: ArrayLike, *, building: Building,
                       radio: Radio) -> FloatArray:
    """:func:`pair_snr_db` by the numpy emulator (the reference of the compiled kernel)."""
    anchors = np.asarray(anchors_m, dtype=np.float64)
    nodes = np.asarray(nodes_m, dtype=np.float64)
    return _slots(_Ctx(building, radio, nodes, anchors), radio)[-1]


# --------------------------------------------------------------------------------------------
# public API
# --------------------------------------------------------------------------------------------


def emulate_channel(
    anchors_m: ArrayLike,
    nodes_m: ArrayLike,
    *,
    building: Building,
    radio: Radio,
) -> Channel:
    """All MPCs of every node x anchor pair (see the module docstring).

    Parameters
    ----------
    anchors_m : array_like, shape (M, 3) [m]
        Anchor positions, outside (``y < 0``).
    nodes_m : array_like, shape (N, 3) [m]
        Node positions inside the building's floors.
    building : Building
    radio : Radio

    Returns
    -------
    Channel
        Arrays of shape ``(N, M, K)``, ``K = len(channel_mechanisms(radio))`` (18 at the
        default ``radio.channel_max_order`` 2).

    Raises
    ------
    ValueError
        If an anchor is not outside or a node is not inside the modelled floors.
    """
    anchors = np.atleast_2d(np.asarray(anchors_m, dtype=np.float64))
    nodes = np.atleast_2d(np.asarray(nodes_m, dtype=np.float64))
    if anchors.shape[-1] != 3 or nodes.shape[-1] != 3:
        raise ValueError("anchors_m and nodes_m must have shape (M, 3) and (N, 3)")
    _check_pairs(anchors, nodes, building)
    c = _Ctx(building, radio, nodes, anchors)
    mset = channel_mechanisms(radio)
    extra = mset.recipes[len(MECHANISMS):]
    length, gain, aod, aoa, valid, power, snr = _slots(c, radio, extra)
    exists = valid & (snr >= radio.detection_snr_db)
    mpc_class = np.array([*MPC_CLASS, *(mpc_class_of(r) for r in extra)], dtype=np.int8)
    return Channel(
        delay_s=length / _C, length_m=length, gain=gain, power_dbm=power, snr_db=snr,
        aod_deg=aod, aoa_deg=aoa, valid=valid, exists=exists, mpc_class=mpc_class,
        mechanism=mset.labels, nodes_m=nodes, anchors_m=anchors,
    )


def scenario_channel(scenario: Scenario, t_s: float = 0.0) -> Channel:
    """:func:`emulate_channel` for a scenario's anchors and receivers at time ``t_s``."""
    return emulate_channel(scenario.anchor_positions_m(t_s), scenario.node_positions_m(t_s),
                           building=scenario.building, radio=scenario.radio)


def first_arrival(
    channel: Channel,
    *,
    radio: Radio,
    rng: np.random.Generator | None = None,
) -> FirstArrival:
    """The paper's first-arrival detector and the measured ranges.

    The first arriving path of a pair is the existing MPC with the smallest delay among those
    with ``snr_db >= max(P_max - radio.fap_threshold_db, radio.detection_snr_db)``, ``P_max``
    the pair's strongest MPC. Existence is re-evaluated with ``radio.detection_snr_db`` (so a
    different detector can be applied to the same channel). Its measured range is ``c tau + n`` with
    ``n ~ N(0, sigma^2)``, ``sigma = sqrt(CRLB^2 + radio.range_error_floor_m^2)``, ``CRLB = c /
    sqrt(8 pi^2 B^2 SNR)`` (the floor: calibration, residual multipath, clock; see
    :class:`~diffpos.scenario.Radio`).

    Parameters
    ----------
    channel : Channel
    radio : Radio
    rng : numpy.random.Generator, optional
        Noise source; ``None`` returns noise-free ranges (``range_m == true_path_m``).

    Returns
    -------
    FirstArrival
    """
    d = _detect(channel.valid, channel.snr_db, channel.delay_s, channel.length_m, radio, rng)
    measured, true_path, snr_f, sigma, slot, detected = d
    take = lambda arr: np.take_along_axis(arr, slot[..., None], axis=-1)[..., 0]  # noqa: E731
    return FirstArrival(
        range_m=measured, true_path_m=true_path, snr_db=snr_f, sigma_m=sigma,
        mpc_class=np.where(detected, channel.mpc_class[slot], 0).astype(np.int8),
        slot=np.where(detected, slot, -1), aoa_deg=np.where(detected, take(channel.aoa_deg),
                                                            np.nan),
        detected=detected,
    )


def _detect(valid: NDArray, snr_db: FloatArray, delay_s: FloatArray, length_m: FloatArray,
            radio: Radio, rng: np.random.Generator | None):
    """The detector of :func:`first_arrival` on slot arrays (..., K): measured range, true
    path, SNR, sigma, slot (argmin, meaningful where detected) and detection (..., )."""
    exists = valid & (snr_db >= radio.detection_snr_db)
    snr = np.where(exists, snr_db, -np.inf)
    pmax = snr.max(axis=-1)
    thr = np.maximum(pmax - radio.fap_threshold_db, radio.detection_snr_db)
    ok = exists & (snr >= thr[..., None])
    delay = np.where(ok, delay_s, np.inf)
    slot = np.argmin(delay, axis=-1)
    detected = np.any(ok, axis=-1)
    take = lambda arr: np.take_along_axis(arr, slot[..., None], axis=-1)[..., 0]  # noqa: E731
    true_path = np.where(detected, take(length_m), np.nan)
    snr_f = np.where(detected, take(snr), -np.inf)
    crlb = ranging_crlb_m(db_to_linear(snr_f), radio.bandwidth_hz)
    sigma = np.where(detected, np.hypot(crlb, radio.range_error_floor_m), np.inf)
    if rng is None:
        rng_noise = np.zeros(true_path.shape)
    else:
        rng_noise = rng.standard_normal(true_path.shape)
    with np.errstate(invalid="ignore"):
        measured = np.where(detected, true_path + sigma * rng_noise, np.nan)
    return measured, true_path, snr_f, sigma, slot, detected


def pair_first_arrival(anchors_m: ArrayLike, nodes_m: ArrayLike, *, building: Building,
                       radio: Radio, rng: np.random.Generator | None = None
                       ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, NDArray]:
    """:func:`first_arrival` of :func:`emulate_channel` for P (anchor, node) pairs, compiled.

    The detector and the noise draws are those of :func:`first_arrival` (same generator
    calls, same shapes); the slot SNRs come from the compiled :func:`pair_snr_db` and the
    slot lengths from the compiled path model (:func:`diffpos.paths.model.first_arrival_paths`,
    the emulator's own geometry), so the result equals the numpy emulator's to rounding
    (``tests/core/test_channel_kernel.py``) at ~10x less CPU: what an emulated anchor needs per
    epoch (no gains, phases or angles are kept). With ``radio.channel_max_order`` > 2 the
    higher-order families join the candidates (:mod:`diffpos.channel.families_nb` for their
    SNR, the path model with their :class:`~diffpos.paths.mechanisms.MechanismSet` for their
    lengths; ``tests/core/test_channel_families.py``), as in :func:`emulate_channel`.

    Parameters
    ----------
    anchors_m, nodes_m : array_like, shape (P, 3) [m]
        Pair ``p`` is anchor ``anchors_m[p]`` to node ``nodes_m[p]``.

    Returns
    -------
    range_m, sigma_m, snr_db, true_path_m : ndarray, shape (P,)
    detected : ndarray of bool, shape (P,)

    Raises
    ------
    ValueError
        As :func:`emulate_channel`: an anchor not outside or a node not inside the floors.
    """
    anchors = np.asarray(anchors_m, dtype=np.float64).reshape(-1, 3)
    nodes = np.asarray(nodes_m, dtype=np.float64).reshape(-1, 3)
    if anchors.shape != nodes.shape:
        raise ValueError("anchors_m and nodes_m must have the same shape (P, 3)")
    _check_pairs(anchors, nodes, building)
    snr = pair_snr_db(anchors[:, None, :], nodes, building=building, radio=radio)[:, 0]
    length = first_arrival_paths(nodes, anchors, building).length_m
    valid = np.isfinite(snr)
    if radio.channel_max_order > 2:
        snr_x, length_x = _family_snr_length(anchors, nodes, building, radio)
        snr = np.concatenate([snr, snr_x], axis=-1)
        length = np.concatenate([length, length_x], axis=-1)
        valid = np.concatenate([valid, np.isfinite(snr_x) & np.isfinite(length_x)], axis=-1)
    length = np.where(valid, length, np.nan)
    measured, true_path, snr_f, sigma, _, detected = _detect(valid, snr, length / _C, length,
                                                             radio, rng)
    return measured, sigma, snr_f, true_path, detected


@lru_cache(maxsize=8)
def _set_table(max_order: int, partitions: bool) -> tuple[np.ndarray, np.ndarray]:
    """The compiled table of ``mechanism_set(max_order, partitions=partitions)`` and the slots
    of its families beyond the 18."""
    mset = mechanism_set(max_order, partitions=partitions)
    return mechanism_table(mset.recipes), np.arange(len(MECHANISMS), len(mset), dtype=np.int64)


def _family_snr_length(anchors: FloatArray, nodes: FloatArray, building: Building,
                       radio: Radio) -> tuple[FloatArray, FloatArray]:
    """SNR and length (compiled :mod:`diffpos.channel.families_nb`, the path model's geometry)
    of the families beyond the 18 for P pairs: (P, K - 18) each."""
    table, slots = _set_table(radio.channel_max_order, True)
    params = _params_for(building, radio)
    snr, length = eval_family_snr(_c_w(anchors[:, None, :]), _c_w(nodes), params, table, slots)
    return snr[:, 0], length[:, 0]


def pair_family_snr_db(anchors_m: ArrayLike, nodes_m: ArrayLike, *, building: Building,
                       radio: Radio, max_order: int, partitions: bool = False,
                       mask: NDArray[np.bool_] | None = None) -> FloatArray:
    """SNR [dB] of the families beyond the 18 of ``mechanism_set(max_order,
    partitions=partitions)`` for P (anchor, node) pairs (``anchors_m``, ``nodes_m`` (P, 3)),
    (P, K - 18): the emulator's amplitude model for them (:mod:`diffpos.channel.families_nb`,
    as :func:`pair_first_arrival` draws them at ``radio.channel_max_order`` > 2), with the
    channel's constants at order ``max(radio.channel_max_order, max_order)`` (the window
    edges' sheets of order >= 3); ``-inf`` where a family carries no power. For an estimator
    that scores a family by its SNR (``TrackerConfig.family_snr``). Nodes inside the building
    and anchors outside (not checked). ``mask`` (P, K - 18) bool: only those families are
    evaluated (``-inf`` elsewhere; the rest bit for bit); None: every one."""
    anchors = np.asarray(anchors_m, dtype=np.float64).reshape(-1, 3)
    nodes = np.asarray(nodes_m, dtype=np.float64).reshape(-1, 3)
    table, slots = _set_table(max_order, partitions)
    radio = replace(radio, channel_max_order=max(radio.channel_max_order, max_order))
    params = _params_for(building, radio)
    snr, _ = eval_family_snr(_c_w(anchors[:, None, :]), _c_w(nodes), params, table, slots,
                             None if mask is None else np.asarray(mask, bool)[:, None, :])
    return snr[:, 0]


def _check_pairs(anchors: FloatArray, nodes: FloatArray, building: Building) -> None:
    if np.any(anchors[:, 1] >= 0):
        raise ValueError("anchors_m: every anchor must be outside the building (y < 0)")
    bad = ~building.inside(nodes)
    if np.any(bad):
        raise ValueError(f"nodes_m: {int(bad.sum())} node(s) outside the building's floors, "
                         f"e.g. {nodes[bad][0].tolist()}")


def mpc_statistics(
    channel: Channel,
    fap: FirstArrival,
    *,
    path_class: ArrayLike | None = None,
) -> dict[str, dict[str, float]]:
    """The paper's Table of MPC groups: ``P_e`` and ``P_fap`` per group, in percent.

    ``P_e`` (group g) = percentage of node x anchor pairs where at least one MPC of group g
    exists (is received); ``P_fap`` = percentage of pairs whose first-arriving path belongs to
    group g. (The paper sums per-anchor counts over anchors and divides by the number of
    receivers; dividing by the number of pairs is the same average for every anchor.)

    Parameters
    ----------
    channel : Channel
    fap : FirstArrival
    path_class : array_like of int, shape (N, M, K), optional
        Group of every path when it varies per link (ray-traced data); default the per-slot
        ``channel.mpc_class``.

    Returns
    -------
    dict
        ``{"MPC-1": {"P_e": ..., "P_fap": ...}, ..., "none": {"P_fap": ...}}`` [%].
    """
    exists = channel.exists
    cls = np.broadcast_to(channel.mpc_class if path_class is None else np.asarray(path_class),
                          exists.shape)
    pairs = max(exists.shape[0] * exists.shape[1], 1)
    out: dict[str, dict[str, float]] = {}
    for g in (1, 2, 3, 4):
        pe = np.any(exists & (cls == g), axis=-1).sum()
        pf = np.sum(fap.mpc_class == g)
        out[f"MPC-{g}"] = {"P_e": 100.0 * float(pe) / pairs, "P_fap": 100.0 * float(pf) / pairs}
    out["none"] = {"P_fap": 100.0 * float(np.sum(~fap.detected)) / pairs}
    return out
