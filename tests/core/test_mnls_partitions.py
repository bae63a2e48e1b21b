"""M-NLS with the partition-reflection families (``mnls(max_order >= 3)`` on a building with
interior partitions: ``mechanism_set(max_order, partitions=True)``).

* The compiled LM steps (the path kernel with the building's partitions inside) equal the
  numpy/numba reference steps, with partition families chosen.
* The SNR of a partition reflection (diffpos.estimators.mnls.power: the emulated channel's
  physics) against a hand computation from the image geometry: Friis over the length, the
  dipole's transverse field and the TM Fresnel coefficient of the partition the path reflects
  on (the nearer of two, different materials) at its incidence (anchor and nodes at one
  height: the ray and the x-polarised field lie in the plane of incidence).
* Nodes whose first arrival on some link is a partition reflection: the partition families
  explain those links (fewer excluded links, no fewer floors right) where the same building
  without partitions (no such families) cannot.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from mnls_cases import ANCHORS
from mnls_cases import random_nodes as _nodes

from diffpos.channel.linkbudget import snr_db
from diffpos.channel.slots import fresnel_coefficients, itu_permittivity
from diffpos.estimators.mnls.power import family_snr_db
from diffpos.estimators.mnls.solver import mnls
from diffpos.paths.mechanisms import mechanism_set
from diffpos.paths.model import first_arrival_paths
from diffpos.scenario import Building, Partition, Radio

B = Building(width_m=30.0, center_x_m=5.0, depth_m=15.0, n_floors=4, floor_height_m=3.5,
             first_floor_z_m=2.0, sill_height_m=1.0, window_height_m=1.2,
             partitions=(Partition("x", 2.0, (3.0, 15.0)), Partition("y", 9.0, (-10.0, 20.0)),
                         Partition("x", 12.0, (0.0, 9.0))))
MECH = mechanism_set(3, partitions=True)
N_PLAIN = len(mechanism_set(3))


def _partition_first(rng, n: int):
    """Nodes whose shortest existing specular path of ``MECH`` (the diffracted ones below
    detection) is a partition reflection on some link, with >= 4 such ranges; the ranges."""
    nodes = _nodes(B, n, rng)
    ps = first_arrival_paths(nodes[:, None], ANCHORS[None], B, mechanisms=MECH)
    spec = np.isin(np.arange(len(MECH)), MECH.specular)
    lm = np.where(ps.valid & spec, ps.length_m, np.inf)
    r = np.min(lm, axis=-1)
    part = (np.argmin(lm, axis=-1) >= N_PLAIN) & np.isfinite(r)
    pick = np.flatnonzero(part.any(axis=1) & (np.isfinite(r).sum(axis=1) >= 4))
    return nodes[pick], r[pick], part[pick]


def test_compiled_lm_equals_reference_steps_with_partition_families():
    rng = np.random.default_rng(11)
    nodes, r, _ = _partition_first(rng, 300)
    nodes, r = nodes[:12], r[:12]
    mask = np.isfinite(r)
    rr = np.where(mask, r + rng.normal(0, 0.02, r.shape), 0.0)
    a = np.broadcast_to(ANCHORS, (len(nodes), *ANCHORS.shape))
    radio = Radio()
    snr = np.where(mask, rng.uniform(0, 30, r.shape), np.nan)
    kw = {"mask": mask, "building": B, "snr_db": snr, "radio": radio, "max_order": 3}
    got, ref = mnls(a, rr, 0.02, **kw), mnls(a, rr, 0.02, kernel=False, **kw)
    for k in ("floor", "mechanism", "status", "used", "excluded"):
        np.testing.assert_array_equal(getattr(got, k), getattr(ref, k), err_msg=k)
    np.testing.assert_allclose(got.position_m, ref.position_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got.floor_probability, ref.floor_probability, atol=1e-9)
    assert (got.mechanism >= N_PLAIN).any()  # partition families are chosen


def test_partition_reflection_snr_by_hand():
    """``Tx-R(partition)-Rx`` between two x-partitions of different materials: the path
    reflects on the nearer one (the shortest existing path); anchor and nodes at one height,
    so the ray stays horizontal and the x dipole's transverse field ``x - (x.d) d`` lies in
    the plane of incidence (TM): SNR = link budget of ``|x - (x.d) d| |Gamma_TM(cos)|
    lambda / (4 pi L)``, ``cos`` the anchor -> image ray's cosine along x."""
    radio = Radio()
    b = Building(width_m=30.0, center_x_m=0.0, depth_m=15.0, n_floors=2, floor_height_m=3.0,
                 first_floor_z_m=0.0, sill_height_m=0.75, window_height_m=1.5,
                 partitions=(Partition("x", 9.0, (0.0, 15.0), material="concrete"),
                             Partition("x", 5.0, (0.0, 15.0), material="wood")))
    anchor = np.array([-2.0, -8.0, 1.5])
    nodes = np.array([[1.0, 6.0, 1.5], [3.0, 4.0, 1.5], [-1.0, 10.0, 1.5]])
    s = MECH.labels.index("Tx-R(partition)-Rx")
    ps = first_arrival_paths(nodes, anchor[None], b, floor=0, slots=[s], mechanisms=MECH)
    assert ps.valid.all()
    img = nodes.copy()
    img[:, 0] = 2 * 5.0 - nodes[:, 0]  # imaged in the nearer partition (x = 5, wood)
    d = img - anchor
    length = np.linalg.norm(d, axis=-1)
    np.testing.assert_allclose(ps.length_m[:, 0], length, rtol=1e-12)
    cos = np.abs(d[:, 0]) / length
    _, gp = fresnel_coefficients(cos, itu_permittivity("wood", radio.frequency_hz))
    amp = np.sqrt(1 - cos**2) * np.abs(gp)
    p_rx = (radio.tx_power_dbm + radio.tx_gain_dbi + radio.rx_gain_dbi
            + 20 * np.log10(amp * radio.wavelength_m / (4 * np.pi * length)))
    want = snr_db(p_rx, bandwidth_hz=radio.bandwidth_hz,
                  processing_gain_db=radio.processing_gain_db,
                  temperature_k=radio.noise_temperature_k, noise_figure_db=radio.noise_figure_db)
    got = family_snr_db(np.broadcast_to(anchor, nodes.shape), nodes, b, radio, MECH, [s])
    np.testing.assert_allclose(got[:, 0], want, rtol=0, atol=1e-6)


def test_partition_first_arrivals_are_explained():
    """Ranges (2 cm noise, ranges only) whose first arrival on some link is a partition
    reflection: with the partition families those links are explained, not excluded; the
    same building without partitions (no such families) excludes them."""
    rng = np.random.default_rng(3)
    nodes, r, part = _partition_first(rng, 400)
    assert len(nodes) >= 10
    mask = np.isfinite(r)
    rr = np.where(mask, r + rng.normal(0, 0.02, r.shape), 0.0)
    a = np.broadcast_to(ANCHORS, (len(nodes), *ANCHORS.shape))
    with_p = mnls(a, rr, 0.02, mask=mask, building=B, max_order=3)
    without = mnls(a, rr, 0.02, mask=mask,
                   building=dataclasses.replace(B, partitions=()), max_order=3)
    right = lambda res: np.mean(res.floor == B.floor_index(nodes[:, 2]))  # noqa: E731
    assert with_p.excluded[part].mean() <= 0.5 * without.excluded[part].mean()
    assert without.excluded[part].mean() >= 0.3
    assert right(with_p) >= right(without)
