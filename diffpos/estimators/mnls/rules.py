"""Physical candidate rules of M-NLS (:mod:`diffpos.estimators.mnls.solver`), from the path model.

* Same-edge dominance: a diffraction + reflection path that deviates at least as much as the
  plain diffraction over the same edge never arrives first.
* Knife-edge SNR bound: a diffracted first arrival is not much stronger than the ITU-R P.526
  knife-edge prediction at its geometry.
* The detector's skipped paths (:class:`SnrRule`, off by default): the detector threshold's
  lower bound from the measured first arrival, and the soft skip prior
  (:func:`diffpos.channel.detection.skipped_cost`).
* The window edges' material in the SNR model (:class:`SnrRule` ``dielectric_edges``, off by
  default; :func:`snr_radio`).

And :func:`_link_terms_numpy`, the numpy reference of M-NLS's per-link terms that apply them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from diffpos.channel.linkbudget import snr_db as _snr_db
from diffpos.paths.mechanisms import (
    DIFFRACTION_SLOTS,
    MECHANISMS,
    SPECULAR_SLOTS,
    MechanismSet,
)
from diffpos.paths.model import first_arrival_paths

FloatArray = NDArray[np.float64]

#: A diffracted first arrival cannot be much stronger than the knife-edge prediction J(nu):
#: the window edge is a right-angled wedge whose UTD coefficient differs from the half-plane's
#: by up to about a factor 2 in field (6 dB); measured excess - J(nu) >= -4.8 dB over all
#: 58,000 diffracted first arrivals of the default study, and below -6 dB for 0.1 % of 6,289
#: on 40 random buildings (worst -7.2 dB): such a link falls to another mechanism or the tail.
SNR_MARGIN_DB = 20 * np.log10(2.0)
#: Standard deviation of a predicted path SNR against the measured one [dB]: the same factor
#: 2 in field (modelling error of the amplitudes: antenna patterns, materials, wedge vs.
#: UTD), applied when the floor modes are re-scored with the SNR.
SNR_SIGMA_DB = 20 * np.log10(2.0)


@dataclass(frozen=True)
class SnrRule:
    """How M-NLS applies the detector's rule (it reports the earliest path whose SNR is within
    ``radio.fap_threshold_db`` of the strongest) to the candidate mechanisms of a link.
    The defaults are M-NLS as it was (session 26: both off).

    Attributes
    ----------
    measured_threshold : bool
        The detector threshold ``T`` is at least the MEASURED first arrival's SNR less
        ``fap_threshold_db`` (the strongest path is at least as strong as the reported one,
        whatever the amplitude model predicts), not only the predicted strongest path's
        ``P_max - fap_threshold_db`` (and the detection floor). It raises ``T`` where the
        model under-predicts the strongest path, so fewer earlier paths count as surely
        detected (the hard rule) or as likely detected (the skip prior).
    first_arrival_prior : float
        Weight ``w`` in [0, 1) of the soft skip prior
        (:func:`diffpos.channel.detection.skipped_cost`); 0: off, the hard
        rule (no path predicted ``SNR_SIGMA_DB`` above ``T`` arrives before the first
        arrival). ``w > 0`` replaces the hard rule by ``-log(w prod_j Phi((T - S_j) /
        SNR_SIGMA_DB) + 1 - w)`` [nats] added to the SNR cost of every slot, the product
        over the existing paths ``j`` shorter than the slot (``S_j`` their predicted SNR).
    keep_hard_rule : bool
        With ``first_arrival_prior`` > 0: keep the hard rule as well (the skip prior then
        adds to the candidates it leaves; docs/raytrace_study.md "Session 26").
    dielectric_edges : float
        Prior probability in [0, 1] that the 18 slots' horizontal window edges (sill and
        lintel) diffract as a dielectric sheet of the walls' material (Luebbers'
        finite-conductivity UTD, the channel's edge at ``radio.channel_max_order`` >= 3;
        M-NLS's families beyond the 18 and the vertical edges use it already) rather than as
        the perfectly conducting half-plane of the order-2 channel (the paper's model). 1: the
        sheet whatever the channel's order (:func:`snr_radio`); between 0 and 1: the material
        is not known, each slot's Gaussian SNR term is the mixture ``-log((1 - q) exp(-c_radio)
        + q exp(-c_sheet))`` of the radio's and the sheet's prediction (the detector's
        threshold and the skip prior from the radio's). On Sionna RT the conductor's
        ``D(lower)`` is a median 1.3-3.7 dB too weak and ``D(upper)`` 1.7-2.2 dB too strong
        (docs/raytrace_study.md "Session 27"). 0 (the default): the radio's own order.
    floor_box : bool
        Not a detector rule but the floor posterior's (M-NLS's options travel together in this
        record): each floor's Laplace mass ``exp(-C_k) det(H_k)^(-1/2)`` times the share of
        its Gaussian ``N(mu_k, H_k^-1)`` inside the floor's box, where the node is confined
        (``result._box_log_mass``). A mode against a wall, the floor or the ceiling keeps about
        half its Gaussian inside, which the whole-Gaussian Laplace term counts twice.
        ``False`` (the default): the whole Gaussian (docs/raytrace_study.md "Session 29").
    shadow_starts : float
        Not a detector rule but the search's (with the measured SNR): the displacement ``d``
        [m] of the boundary starts. Where a floor's mode explains a link by a horizontal
        window-edge diffraction whose lit counterpart (the same path without the edge,
        :attr:`diffpos.paths.mechanisms.MechanismSet.lit`) does not exist there, the mode
        sits on the edge's shadow side, where the max-mixture cannot see the counterpart
        (the two have the same length at the boundary, the counterpart's SNR term may be
        far cheaper). Six starts at ``+-d`` along x, y and z run ``max_iter`` LM steps; the
        floor takes the cheapest new mode that has crossed (that link now takes the
        counterpart) if it costs less. 0 (the default): none (docs/raytrace_study.md
        "Session 30").
    path_region : bool
        Not a detector rule but the floor posterior's, with ``floor_box``: each floor's Laplace
        mass counted inside its box AND where the mode's mechanism hypothesis holds, i.e.
        where every used link's chosen mechanism exists (the reflection point inside its
        plane and the window, the node on the edge's diffracting side, ...): the share of
        the mode's Gaussian there (``solver._region_log_mass``, fixed draws). The max-mixture
        mode is one assignment of mechanisms to links, and its Gaussian is its likelihood
        only where those paths exist; ``floor_box`` is the same correction for the box's
        faces. ``False`` (the default): the box only (docs/raytrace_study.md "Session 31").
    """

    measured_threshold: bool = False
    first_arrival_prior: float = 0.0
    keep_hard_rule: bool = False
    dielectric_edges: float = 0.0
    floor_box: bool = False
    shadow_starts: float = 0.0
    path_region: bool = False

    def __post_init__(self) -> None:
        if not 0.0 <= self.first_arrival_prior < 1.0:
            raise ValueError("first_arrival_prior must be in [0, 1)")
        if not 0.0 <= self.dielectric_edges <= 1.0:
            raise ValueError("dielectric_edges must be in [0, 1]")
        if not self.shadow_starts >= 0.0:
            raise ValueError("shadow_starts must be >= 0 [m]")
        if self.path_region and not self.floor_box:
            raise ValueError("path_region counts the mass inside the floor's box: it needs "
                             "floor_box")


#: M-NLS's rule as it was: the predicted threshold and the hard rule.
DEFAULT_SNR_RULE = SnrRule()

#: The channel order from which every window edge is a dielectric sheet
#: (:mod:`diffpos.channel.slots`, "Window edges").
SHEET_EDGE_ORDER = 3


def snr_radio(radio, rule: SnrRule):
    """The radio M-NLS predicts its slots' SNR with (:func:`diffpos.channel.emulator.pair_snr_db`):
    ``radio`` itself, or with ``rule.dielectric_edges`` 1 the same radio at channel order
    :data:`SHEET_EDGE_ORDER` if its order is below it (a mixture, ``0 < q < 1``, keeps the
    radio: ``solver._snr_cost`` adds the sheet's prediction). The order only selects the 18 slots'
    horizontal-edge sheet there (``pair_snr_db`` keeps the 18 slots at any order); the link
    budget, the detector's thresholds and M-NLS's families are the same."""
    if (radio is None or rule.dielectric_edges < 1.0
            or radio.channel_max_order >= SHEET_EDGE_ORDER):
        return radio
    return replace(radio, channel_max_order=SHEET_EDGE_ORDER)


_DIFF_MASK = np.zeros(len(MECHANISMS), dtype=bool)
_DIFF_MASK[list(DIFFRACTION_SLOTS)] = True
#: (diffraction + reflection slot, plain diffraction slot over the same edge)
_SAME_EDGE = ((9, 7), (10, 7), (13, 7), (11, 8), (12, 8))
_SPEC_MASK = np.zeros(len(MECHANISMS), dtype=bool)
_SPEC_MASK[list(SPECULAR_SLOTS)] = True
_MASKS: dict[MechanismSet, tuple] = {}


def _masks(mech: MechanismSet | None) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray]:
    """``(specular, diffraction, same_edge)`` of a mechanism set: the slots bounding the first
    arrival (a specular path entering through the window: the 18's and the added specular
    families), the diffraction slots, and the same-edge pairs ``(P, 2)`` (default: the 18's)."""
    if mech is None:
        return _SPEC_MASK, _DIFF_MASK, np.array(_SAME_EDGE, dtype=np.int64)
    out = _MASKS.get(mech)
    if out is None:
        k = len(mech)
        spec = np.zeros(k, dtype=bool)
        spec[list(mech.specular)] = True
        diff = np.zeros(k, dtype=bool)
        diff[list(mech.diffraction)] = True
        out = _MASKS[mech] = (spec, diff,
                              np.array(mech.same_edge, dtype=np.int64).reshape(-1, 2))
    return out


def _dominated(ps, same_edge=_SAME_EDGE) -> NDArray[np.bool_]:
    """Diffraction + reflection paths that cannot arrive first (module docstring).

    A ``D(edge)-R(plane)`` path is longer than the plain ``D(edge)`` path (triangle
    inequality) and has an extra reflection loss; where its diffracted ray also deviates at
    least as much from the incident one (deeper in the shadow: a weaker diffraction
    coefficient), it is weaker too, so it is detected only if the plain path is, which
    arrives earlier. Measured: 0 of 70,000 first arrivals violate this.
    """
    dom = np.zeros(ps.valid.shape, dtype=bool)
    c = ps.deviation_cos
    for b_slot, a_slot in same_edge:
        with np.errstate(invalid="ignore"):
            dom[..., b_slot] = ps.valid[..., a_slot] & (c[..., a_slot] >= c[..., b_slot])
    return dom


def _excess_loss_db(r, snr, radio, shape) -> FloatArray:
    """Free-space SNR at the measured range minus the measured SNR [dB] (NaN without SNR)."""
    if snr is None or radio is None:
        return np.full(shape, np.nan)
    snr = np.broadcast_to(np.asarray(snr, dtype=np.float64), shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        p_fs = (radio.tx_power_dbm + radio.tx_gain_dbi + radio.rx_gain_dbi
                - 20 * np.log10(4 * np.pi * np.maximum(r, 1e-3) / radio.wavelength_m))
    snr_fs = _snr_db(p_fs, bandwidth_hz=radio.bandwidth_hz,
                     processing_gain_db=radio.processing_gain_db,
                     temperature_k=radio.noise_temperature_k,
                     noise_figure_db=radio.noise_figure_db)
    return np.where(np.isfinite(snr), snr_fs - snr, np.nan)


def _knife_edge_loss_db(ps, wavelength_m: float) -> FloatArray:
    """ITU-R P.526 single knife-edge loss ``J(nu)`` of every diffraction slot [dB] (NaN else).

    ``nu = theta sqrt(2 d1 d2 / (lambda (d1 + d2)))`` with ``theta`` the angle between the
    incident and the diffracted ray, ``d1``/``d2`` the lengths before/after the edge;
    ``J = 6.9 + 20 log10(sqrt((nu - 0.1)^2 + 1) + nu - 0.1)`` for ``nu > -0.78``, else 0.
    """
    length = ps.length_m
    d1 = ps.outside_m
    d2 = length - d1
    with np.errstate(invalid="ignore", divide="ignore"):
        theta = np.arccos(np.clip(ps.deviation_cos, -1.0, 1.0))
        nu = theta * np.sqrt(2 * d1 * d2 / (wavelength_m * length))
        j = 6.9 + 20 * np.log10(np.sqrt((nu - 0.1) ** 2 + 1) + nu - 0.1)
    return np.where(nu > -0.78, j, 0.0)


def _link_terms_numpy(p, x: FloatArray, building) -> dict:
    """Numpy reference of :func:`diffpos.estimators.mnls.solver._link_terms` (the compiled kernel
    does the same operations): paths at ``x``, candidates by the rules above, max-mixture
    cost, chosen slot and its residual, Jacobian and IRLS weight of every link."""
    ps = first_arrival_paths(x[:, None, :], p.anchors, building, floor=p.floor[:, None],
                             mechanisms=p.mech)
    length = ps.length_m
    valid = ps.valid
    spec, diff_mask, same_edge = _masks(p.mech)
    l_spec = np.min(np.where(valid & spec, length, np.inf), axis=-1)
    if p.strong is not None:  # nothing surely detected arrives before the first arrival
        l_spec = np.minimum(l_spec, np.min(np.where(valid & p.strong, length, np.inf), axis=-1))
    cand = valid & (length <= l_spec[..., None]) & ~_dominated(ps, same_edge.tolist())
    with np.errstate(invalid="ignore"):
        too_strong = p.excess_db[..., None] < _knife_edge_loss_db(ps, p.wavelength_m) - SNR_MARGIN_DB
    cand &= ~(too_strong & diff_mask)
    if p.allowed is not None:
        cand &= p.allowed
    e = p.r[..., None] - length  # (N, M, K)
    z = e / p.sig[..., None]
    gauss = 0.5 * z * z
    tail = np.where(e > 0, p.tail_a[..., None] + e / p.lam, np.inf)
    cost_k = np.minimum(gauss, tail)
    if p.snr_cost is not None:
        cost_k = cost_k + p.snr_cost
    cost_k = np.where(cand, cost_k, np.inf)
    slot = np.argmin(cost_k, axis=-1)
    take = lambda a: np.take_along_axis(a, slot[..., None], axis=-1)[..., 0]  # noqa: E731
    cost = take(cost_k)
    none = ~np.isfinite(cost)
    is_tail = take(tail) < take(gauss)
    res = np.where(none, 0.0, take(e))
    jac = np.take_along_axis(ps.jacobian, slot[..., None, None], axis=-2)[..., 0, :]
    jac = np.where(none[..., None], 0.0, jac)
    # IRLS weight: the tail's gradient is 1/lambda, i.e. weight sigma^2 / (lambda e)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(is_tail, p.sig**2 / (p.lam * np.maximum(res, 1e-9)), 1.0)
    # a link with no candidate (all paths clamped) costs like a far outlier
    cost = np.where(none, p.tail_a + 10.0, cost)
    # one link out of the model: the worst link above its out-of-model cost is capped at
    # it, no weight (excluded)
    m = p.mask
    over = np.where(m, cost - p.cap, 0.0)
    worst = np.argmax(over, axis=-1)
    capped = (np.arange(over.shape[-1]) == worst[..., None]) & (
        np.take_along_axis(over, worst[..., None], axis=-1) > 0)
    cost = np.where(capped, p.cap, cost)
    is_tail = is_tail | capped
    w = np.where(capped, 0.0, w)
    w = np.where(m & ~none, w, 0.0)
    cost = np.where(m, cost, 0.0)
    prior = 0.5 * (x[:, 2] - p.z_mid) ** 2 / p.prior_var
    return {"cost": cost.sum(axis=-1) + prior, "res": res, "jac": jac, "w": w, "slot": slot,
            "tail": is_tail & m, "none": none & m, "length": length, "cand": cand,
            "jac_all": ps.jacobian}
