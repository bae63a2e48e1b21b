"""Closed-form SNR of any first-arrival family of the path model (M-NLS's SNR term beyond the
channel emulator's 18 slots).

The emulator's amplitude model (:func:`diffpos.channel.emulator.pair_snr_db`) covers the 18
slots of :data:`diffpos.paths.mechanisms.MECHANISMS`; the families that
:func:`diffpos.paths.mechanisms.mechanism_set` adds beyond them get this estimate:

* free space over the path length (transmit power and gains, ``20 log10(4 pi L / lambda)``),
  with the link budget's processing gain and noise (:func:`diffpos.channel.linkbudget.snr_db`);
* every reflection: the power reflection coefficient ``(|Gamma_s|^2 + |Gamma_p|^2) / 2`` of the
  surface (:func:`diffpos.channel.slots.fresnel_coefficients`, ITU-R P.2040 permittivity of the
  building's interior material; the ground's for the ground bounce) at the reflection's
  incidence angle: the unfolded ray's direction cosine along the plane's normal (the Jacobian's
  component, equal at every reflection on planes of one axis); for a ground bounce before the
  diffraction, ``(z_anchor + z_edge) / outside_m``;
* a window-edge diffraction: the ITU-R P.526 knife-edge loss ``J(nu)``
  (:func:`diffpos.estimators.mnls.rules._knife_edge_loss_db`);
* the window glass loss (``glass_loss_db`` with glass windows);
* a partition reflection (``mechanism_set(..., partitions=True)``): the Fresnel loss of the
  partition the path reflects on (its material's permittivity, as the emulator's
  :func:`diffpos.channel.slots.partition_permittivities`) at the unfolded ray's direction
  cosine along that partition's normal; the partition is the one whose path is the shortest
  existing (the path model's choice: each partition evaluated alone, the first on a tie);
* every interior partition the path crosses (its loss: ``loss_db`` or
  :func:`diffpos.channel.slots.slab_loss_db`): floor and ceiling reflections leave the path's
  plan view straight, so it is the segment from the facade entry (the diffraction point) to the
  node; with a wall or partition reflection the same segment (an approximation).

Left out: antenna patterns (isotropic), the wedge's UTD coefficient and the polarisation (an
unpolarised average). tests/core/test_mnls_power.py holds the estimate to
the emulator on the 18 slots both have.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from diffpos.channel.linkbudget import snr_db as _snr_db
from diffpos.channel.slots import fresnel_coefficients, itu_permittivity, slab_loss_db
from diffpos.estimators.mnls.rules import _knife_edge_loss_db
from diffpos.paths.mechanisms import MechanismSet
from diffpos.paths.model import first_arrival_paths

FloatArray = NDArray[np.float64]
_AXIS = {"floor": 2, "ceiling": 2, "back": 1, "side x1": 0, "side x2": 0}


def _reflection_db(cos_theta: FloatArray, eta: complex) -> FloatArray:
    """Power reflection loss of an unpolarised wave [dB] at incidence ``cos_theta``."""
    gs, gp = fresnel_coefficients(np.abs(cos_theta), eta)
    with np.errstate(divide="ignore", invalid="ignore"):
        return -10.0 * np.log10(0.5 * (np.abs(gs) ** 2 + np.abs(gp) ** 2))


def _partition_db(entry_x: FloatArray, node: FloatArray, building, frequency_hz: float
                  ) -> FloatArray:
    """Loss of the partitions crossed by the plan-view segment (entry_x, 0) -> node [dB]."""
    loss = np.zeros(entry_x.shape)
    nx, ny = node[..., 0], node[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        for p in building.partitions:
            db = (p.loss_db if p.loss_db is not None
                  else slab_loss_db(p.material, p.thickness_m, frequency_hz))
            c = p.position_m
            if p.axis == "x":
                t = (c - entry_x) / (nx - entry_x)
                other = t * ny
            else:
                t = c / ny
                other = entry_x + t * (nx - entry_x)
            hit = (t > 0) & (t < 1) & (other >= p.span_m[0]) & (other <= p.span_m[1])
            loss = loss + np.where(hit, db, 0.0)
    return loss


def _partition_reflection_db(ps, j: int, slot: int, mech: MechanismSet, anchors, nodes,
                             building, floor, frequency_hz: float) -> FloatArray:
    """Fresnel loss [dB] of the partition reflection of ``slot`` (column ``j`` of ``ps``):
    on the partition whose path alone is the shortest existing one (the path model's choice),
    at ``ps``'s direction cosine along that partition's normal."""
    if floor is None:
        raise ValueError("family_snr_db: a partition family needs floor= (the node's floor "
                         "hypothesis of every link)")
    best = np.full(ps.length_m.shape[:-1], np.inf)
    out = np.full(best.shape, np.nan)
    for q, pt in enumerate(building.partitions):
        one = dataclasses.replace(building, partitions=(pt,))
        pj = first_arrival_paths(nodes, anchors, one, floor=floor, slots=[slot],
                                 mechanisms=mech)
        lj = np.where(pj.valid[..., 0], pj.length_m[..., 0], np.inf)
        ax = 0 if pt.axis == "x" else 1
        db = _reflection_db(ps.jacobian[..., j, ax], itu_permittivity(pt.material, frequency_hz))
        take = (lj < best) | (q == 0)  # the first partition on a tie / where none exists
        out = np.where(take, db, out)
        best = np.where(lj < best, lj, best)
    return out


def family_snr_db(ps, mech: MechanismSet, slots, anchors: FloatArray, nodes: FloatArray,
                  building, radio, edge_z_m: tuple[FloatArray, FloatArray],
                  floor=None) -> FloatArray:
    """SNR estimate [dB] of the ``slots`` of ``mech`` (module docstring), ``-inf`` where the
    path does not exist.

    Parameters
    ----------
    ps : diffpos.paths.model.PathSet
        The paths of these slots (last axis = ``slots``), shape (..., S).
    anchors : ndarray, shape (..., 3) [m]
        The anchor of every link (broadcast against the batch shape).
    nodes : ndarray, shape (..., 3) [m]
        The node of every link (broadcast against the batch shape).
    edge_z_m : (ndarray, ndarray) [m]
        Upper and lower window-edge height of every link's floor (batch shape).
    floor : array_like of int, optional
        Every link's floor hypothesis (batch shape); needed by a partition family only.
    """
    r = radio
    f = r.frequency_hz
    eta_in = itu_permittivity(building.interior_material, f)
    eta_g = itu_permittivity(building.ground_material, f)
    length = ps.length_m
    with np.errstate(divide="ignore", invalid="ignore"):
        p_fs = (r.tx_power_dbm + r.tx_gain_dbi + r.rx_gain_dbi
                - 20 * np.log10(4 * np.pi * np.maximum(length, 1e-3) / r.wavelength_m))
    loss = np.zeros(length.shape)
    glass = building.glass_loss_db if building.windows == "glass" else 0.0
    knife = _knife_edge_loss_db(ps, r.wavelength_m)
    shape = length.shape[:-1]
    a = np.broadcast_to(anchors, (*shape, 3))
    n = np.broadcast_to(nodes, (*shape, 3))
    a_z = a[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):  # straight-line facade crossing
        x_line = a[..., 0] + (0.0 - a[..., 1]) / (n[..., 1] - a[..., 1]) * (n[..., 0] - a[..., 0])
    for j, s in enumerate(np.ravel(slots)):
        rec = mech.recipes[int(s)]
        lj = np.full(shape, glass)
        jx, jy = ps.jacobian[..., j, 0], ps.jacobian[..., j, 1]
        if rec.kind == "diff" or any(p in _AXIS and _AXIS[p] < 2 for p in rec.planes):
            with np.errstate(divide="ignore", invalid="ignore"):  # the last leg back to y = 0
                entry_x = np.where(jy != 0, n[..., 0] - n[..., 1] * jx / jy, x_line)
        else:
            entry_x = x_line
        if building.partitions:
            lj = lj + _partition_db(entry_x, n, building, f)
        for plane in rec.planes:
            if plane == "partition":
                lj = lj + _partition_reflection_db(ps, j, int(s), mech, anchors, nodes,
                                                   building, floor, f)
            else:
                lj = lj + _reflection_db(ps.jacobian[..., j, _AXIS[plane]], eta_in)
        if rec.kind == "diff":
            lj = lj + knife[..., j]
            if rec.ground:
                z_e = edge_z_m[0] if rec.edge == "upper" else edge_z_m[1]
                with np.errstate(divide="ignore", invalid="ignore"):
                    cos_g = (a_z + z_e) / ps.outside_m[..., j]
                lj = lj + _reflection_db(cos_g, eta_g)
        elif rec.ground:
            lj = lj + _reflection_db(ps.jacobian[..., j, 2], eta_g)
        loss[..., j] = lj
    snr = _snr_db(p_fs - loss, bandwidth_hz=r.bandwidth_hz,
                  processing_gain_db=r.processing_gain_db, temperature_k=r.noise_temperature_k,
                  noise_figure_db=r.noise_figure_db)
    return np.where(ps.valid, snr, -np.inf)
