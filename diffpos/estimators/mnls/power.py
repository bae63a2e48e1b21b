"""SNR of the first-arrival families beyond the channel emulator's 18 slots (M-NLS's SNR term
at ``max_order`` > 2): the channel's own physics, not a closed-form shortcut.

The 18 slots of :data:`diffpos.paths.mechanisms.MECHANISMS` get
:func:`diffpos.channel.emulator.pair_snr_db`; the families that
:func:`diffpos.paths.mechanisms.mechanism_set` adds beyond them get the emulator's compiled
family kernel (:func:`diffpos.channel.families_nb.eval_family_snr`, the numpy reference
:func:`diffpos.channel.slots.family_slot`): the anchor dipole's transverse field, Fresnel
reflections of the field VECTOR (TE/TM split, ITU-R P.2040 permittivities: ground, interior,
each partition's material) on the ground, slabs, walls and partitions in path order, the UTD
field of the window edge (the vertical edges as a dielectric sheet of the wall material),
glass on a specular entry, every inside segment's partitions, Friis spreading over the
unfolded length, the radio's link budget. On Sionna RT's corrected traces this agrees with the
traced first arrivals' SNR within about 0.5 dB (median, every family; docs/raytrace_study.md
section 3a).

Why not the former closed form (free space minus an UNPOLARISED Fresnel loss per reflection
``(|G_s|^2 + |G_p|^2) / 2`` plus the knife-edge ``J(nu)``): an anchor's horizontal dipole meets
the floor and ceiling slabs mostly as a TE wave, whose reflection is several dB stronger than
the unpolarised average near grazing (the TM part falls towards the Brewster angle). Per
reflection that is 1.5-2.5 dB; on Sionna's paper building it put the ceiling-floor-ceiling
triple bounce a median 7.4 dB and diffraction + two slab bounces 4.3 dB below the traced
power (the 18 slots' own model within 0.3 dB on the same links), so the SNR term argued
against the right floor wherever those families arrive first.

The kernel's constants are built from the building and radio here with the public material
functions (the numbers :func:`diffpos.channel.emulator.pair_snr_db` uses: slab/wall/partition
losses by :func:`diffpos.channel.slots.slab_loss_db`, permittivities by
:func:`diffpos.channel.slots.itu_permittivity`); tests/core/test_mnls_family_power.py holds
them to the numpy emulator (:func:`diffpos.channel.emulator.emulate_channel`).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from diffpos.channel.families_nb import eval_family_snr
from diffpos.channel.slots import itu_permittivity, partition_permittivities, slab_loss_db
from diffpos.channel.snr_nb import channel_params
from diffpos.paths.mechanisms import MECHANISMS, MechanismSet
from diffpos.paths.model_nb import mechanism_table

FloatArray = NDArray[np.float64]
_TABLES: dict[MechanismSet, NDArray[np.int64]] = {}


def _materials(b, frequency_hz: float) -> tuple:
    """``(eta_ground, eta_in, wall_db, slab_db, glass_db, parts)``: the materials tuple
    :func:`diffpos.channel.snr_nb.channel_params` takes, as the emulator computes it."""
    f = frequency_hz
    wall_db = (b.wall_loss_db if b.wall_loss_db is not None
               else slab_loss_db(b.wall_material, b.wall_thickness_m, f))
    slab_db = (b.slab_loss_db if b.slab_loss_db is not None
               else slab_loss_db(b.slab_material, b.slab_thickness_m, f))
    parts = [(0 if p.axis == "x" else 1, p.position_m, p.span_m,
              p.loss_db if p.loss_db is not None else slab_loss_db(p.material, p.thickness_m, f))
             for p in b.partitions]
    return (itu_permittivity(b.ground_material, f), itu_permittivity(b.interior_material, f),
            wall_db, slab_db, b.glass_loss_db if b.windows == "glass" else 0.0, parts)


def _build_params(building, radio) -> tuple:
    f = radio.frequency_hz
    return channel_params(building, radio, _materials(building, f),
                          partition_permittivities(building, f),
                          itu_permittivity(building.wall_material, f))


@lru_cache(maxsize=64)
def _cached_params(building, radio) -> tuple:
    return _build_params(building, radio)


def _params(building, radio) -> tuple:
    try:
        return _cached_params(building, radio)
    except TypeError:  # an unhashable field (e.g. partitions given as a list)
        return _build_params(building, radio)


def _table(mech: MechanismSet) -> NDArray[np.int64]:
    if mech not in _TABLES:
        _TABLES[mech] = mechanism_table(mech.recipes)
    return _TABLES[mech]


def family_snr_db(anchors: FloatArray, nodes: FloatArray, building, radio, mech: MechanismSet,
                  slots) -> FloatArray:
    """SNR [dB] of the ``slots`` of ``mech`` (families beyond the 18: slot >= 18) for P
    (anchor, node) pairs by the emulated channel's physics (module docstring); ``-inf`` where
    the path does not exist. The node's floor is the one its height lies on (M-NLS keeps a
    hypothesis's node inside its floor's box).

    Parameters
    ----------
    anchors, nodes : ndarray, shape (P, 3) [m]
    slots : array_like of int, shape (S,)

    Returns
    -------
    ndarray, shape (P, S) [dB]
    """
    slots = np.asarray(slots, dtype=np.int64).ravel()
    if slots.size and slots.min() < len(MECHANISMS):
        raise ValueError("family_snr_db: slots must be families beyond the 18 (>= "
                         f"{len(MECHANISMS)}); the 18 are diffpos.channel.emulator.pair_snr_db's")
    a = np.ascontiguousarray(np.asarray(anchors, dtype=np.float64).reshape(-1, 1, 3))
    n = np.ascontiguousarray(np.asarray(nodes, dtype=np.float64).reshape(-1, 3))
    if a.shape[0] != n.shape[0]:
        raise ValueError("family_snr_db: anchors and nodes must both be (P, 3)")
    snr, length = eval_family_snr(a, n, _params(building, radio), _table(mech), slots)
    return np.where(np.isfinite(length[:, 0]), snr[:, 0], -np.inf)
