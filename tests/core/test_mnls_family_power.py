"""M-NLS's SNR of the families beyond the 18 (diffpos.estimators.mnls.power): the emulated
channel's physics, which agrees with Sionna RT's traced first arrivals (docs/raytrace_study.md
section 3a), not the former closed form (unpolarised Fresnel per reflection, knife edge).

* Equal to the numpy emulator (diffpos.channel.emulator.emulate_channel at
  ``channel_max_order`` 4: an independent implementation of the same physics) on every family
  of ``mechanism_set(4, partitions=True)``, two partitions of different materials: the
  kernel's constants built here from the building are the emulator's.
* A ceiling-floor-ceiling triple bounce by hand: anchor and node in one plane x = const, so
  the x-polarised dipole's field is perpendicular to every plane of incidence (pure TE):
  ``|Gamma_TE(cos)|^3 lambda / (4 pi L)``. The unpolarised average ``(|G_s|^2 + |G_p|^2) / 2``
  per reflection, what M-NLS used before, is several dB weaker there (asserted, so the test
  separates the two).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from diffpos.channel.emulator import emulate_channel
from diffpos.channel.linkbudget import snr_db
from diffpos.channel.slots import fresnel_coefficients, itu_permittivity
from diffpos.estimators.mnls.power import family_snr_db
from diffpos.paths.mechanisms import mechanism_set
from diffpos.paths.model import first_arrival_paths
from diffpos.scenario import Building, Partition, Radio

B = Building(width_m=30.0, center_x_m=5.0, depth_m=15.0, n_floors=3, floor_height_m=3.2,
             first_floor_z_m=1.0, sill_height_m=0.8, window_height_m=1.4,
             interior_material="concrete",
             partitions=(Partition("x", 9.0, (2.0, 15.0), material="wood"),
                         Partition("y", 8.0, (-10.0, 20.0), material="plasterboard")))


def _budget(radio: Radio, amp: np.ndarray, length: np.ndarray) -> np.ndarray:
    p_rx = (radio.tx_power_dbm + radio.tx_gain_dbi + radio.rx_gain_dbi
            + 20 * np.log10(amp * radio.wavelength_m / (4 * np.pi * length)))
    return snr_db(p_rx, bandwidth_hz=radio.bandwidth_hz,
                  processing_gain_db=radio.processing_gain_db,
                  temperature_k=radio.noise_temperature_k, noise_figure_db=radio.noise_figure_db)


def test_family_snr_equals_the_numpy_emulator():
    radio = dataclasses.replace(Radio(), channel_max_order=4)
    mech = mechanism_set(4, partitions=True)
    rng = np.random.default_rng(11)
    n = 60
    x0, x1 = B.edge_x_m
    k = rng.integers(0, B.n_floors, n)
    nodes = np.column_stack([rng.uniform(x0 + 0.5, x1 - 0.5, n), rng.uniform(0.5, 14.5, n),
                             B.floor_z_m(k) + rng.uniform(0.3, 2.9, n)])
    anchors = np.array([[-16.0, -12.0, 1.0], [3.0, -20.0, 0.5], [8.0, -9.0, 6.2],
                        [26.0, -10.0, 2.0]])
    ch = emulate_channel(anchors, nodes, building=B, radio=radio)
    assert ch.snr_db.shape[-1] == len(mech)
    extra = np.arange(18, len(mech))
    p = np.broadcast_to(anchors[None], (n, 4, 3)).reshape(-1, 3)
    q = np.broadcast_to(nodes[:, None], (n, 4, 3)).reshape(-1, 3)
    got = family_snr_db(p, q, B, radio, mech, extra).reshape(n, 4, -1)
    want = ch.snr_db[..., 18:]
    fin = np.isfinite(want)
    np.testing.assert_array_equal(np.isfinite(got), fin)
    assert fin.sum() >= 2000 and fin[..., [mech.labels.index(lb) - 18 for lb in mech.labels
                                          if "partition" in lb]].sum() >= 100
    np.testing.assert_allclose(got[fin], want[fin], rtol=0, atol=1e-6)


def test_triple_bounce_is_te_by_hand():
    radio = Radio()
    b = dataclasses.replace(B, partitions=())
    mech = mechanism_set(3)
    s = mech.labels.index("Tx-R(ceiling)-R(floor)-R(ceiling)-Rx")
    anchor = np.array([4.0, -9.0, 1.0])
    rng = np.random.default_rng(2)
    k = rng.integers(0, b.n_floors, 200)
    nodes = np.column_stack([np.full(200, 4.0), rng.uniform(0.5, 14.5, 200),
                             b.floor_z_m(k) + rng.uniform(0.3, 2.9, 200)])
    ps = first_arrival_paths(nodes, anchor[None], b, floor=k, slots=[s], mechanisms=mech)
    nodes = nodes[ps.valid[:, 0]]  # where the triple bounce enters through the window
    assert len(nodes) >= 10
    ps = first_arrival_paths(nodes, anchor[None], b, floor=b.floor_index(nodes[:, 2]),
                             slots=[s], mechanisms=mech)
    assert ps.valid.all()
    length = ps.length_m[:, 0]
    cos = np.abs(ps.jacobian[:, 0, 2])  # the unfolded ray's cosine along the slabs' normal
    gs, gp = fresnel_coefficients(cos, itu_permittivity(b.interior_material, radio.frequency_hz))
    want = _budget(radio, np.abs(gs) ** 3, length)
    got = family_snr_db(np.broadcast_to(anchor, nodes.shape), nodes, b, radio, mech, [s])[:, 0]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    unpolarised = _budget(radio, (0.5 * (np.abs(gs) ** 2 + np.abs(gp) ** 2)) ** 1.5, length)
    assert np.all(got - unpolarised >= 2.0), got - unpolarised
