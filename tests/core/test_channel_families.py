"""The emulated channel's higher-order families (``Radio.channel_max_order`` 3, 4).

* The compiled kernel (:mod:`diffpos.channel.families_nb`, behind
  :func:`diffpos.channel.emulator.pair_first_arrival`) against the numpy emulator
  (:func:`diffpos.channel.emulator.emulate_channel`, :func:`diffpos.channel.slots.family_slot`):
  the same ``-inf`` pattern and SNRs within 1e-7 dB (the operations are not in the reference's
  order: rounding, ~1e-12 dB measured; a modelling difference, e.g. a 0.1 dB loss, is far
  larger), on buildings with partitions, glass loss, patterns and another polarisation.
* The amplitude of a ceiling-floor-ceiling path against its closed form: the ray in the
  y-z plane and the polarisation along x make every slab reflection pure TE, so ``|g| =
  lambda / (4 pi L) |Gamma_TE(cos theta)|^3`` over the unfolded length ``L``.
* The generic diffraction builder against the 18's own one where both apply.
* A link whose first arrival is a third-order path (diffraction then two slab bounces): a
  strong triple bounce lifts the threshold over the order-2 first arrival; the third-order
  path is well above the threshold and every shorter path below it.
* The setting: parsed, validated, in the scenario's round trip (so recorded with it); the
  default keeps the 18.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from diffpos.channel.emulator import (
    _detect,
    _family_snr_length,
    emulate_channel,
    first_arrival,
    pair_first_arrival,
)
from diffpos.channel.linkbudget import noise_floor_dbm
from diffpos.channel.slots import (
    _Ctx,
    _diffracted,
    _diffracted_family,
    _slots,
    fresnel_coefficients,
    itu_permittivity,
)
from diffpos.constants import SPEED_OF_LIGHT_M_S
from diffpos.paths.mechanisms import FAMILIES, Recipe, label_family, mechanism_set
from diffpos.paths.model import first_arrival_paths
from diffpos.scenario import Building, Partition, Radio, Scenario, ScenarioError, default_scenario

ATOL_DB = 1e-7

BUILDINGS = {
    "default": Building(),
    "parts_glass": Building(width_m=25.0, center_x_m=4.0, depth_m=12.0, n_floors=3,
                            floor_height_m=4.2, first_floor_z_m=0.5, sill_height_m=1.1,
                            window_height_m=2.3, windows="glass", glass_loss_db=4.0,
                            partitions=(Partition("x", 3.0, (2.0, 11.0)),
                                        Partition("y", 6.0, (-10.0, 8.0), loss_db=9.0))),
    "slit": Building(width_m=60.0, center_x_m=-7.5, depth_m=30.0, n_floors=8,
                     floor_height_m=2.8, first_floor_z_m=6.0, sill_height_m=0.3,
                     window_height_m=0.6, windows="open", interior_material="plasterboard",
                     ground_material="brick"),
}
RADIOS = {
    "isotropic": Radio(),
    "patterns_zpol": Radio(frequency_hz=60e9, polarization=(0.0, 0.6, 0.8), tx_hpbw_deg=40.0,
                           rx_hpbw_deg=90.0, tx_peak_deg=100.0, rx_peak_deg=80.0),
}


def _pairs(b: Building, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` (anchor, node) pairs: nodes anywhere in the floors, anchors in front of and
    beyond the facade, below and above every window band."""
    x0, x1 = b.edge_x_m
    w = x1 - x0
    k = rng.integers(0, b.n_floors, n)
    nodes = np.stack([rng.uniform(x0 + 0.01, x1 - 0.01, n), rng.uniform(0.01, b.depth_m - 0.01, n),
                      b.floor_z_m(k) + rng.uniform(0.02, b.floor_height_m - 0.02, n)], axis=-1)
    anchors = np.stack([rng.uniform(x0 - 0.3 * w, x1 + 0.3 * w, n), -rng.uniform(0.5, 35.0, n),
                        rng.uniform(0.3, b.top_z_m + 15.0, n)], axis=-1)
    return anchors, nodes


@pytest.mark.parametrize("bname", list(BUILDINGS))
@pytest.mark.parametrize("rname", list(RADIOS))
def test_family_kernel_matches_numpy_emulator(bname: str, rname: str) -> None:
    b = BUILDINGS[bname]
    radio = dataclasses.replace(RADIOS[rname], channel_max_order=4)
    anchors, nodes = _pairs(b, np.random.default_rng(5), 600)
    extra = mechanism_set(4, partitions=True).recipes[18:]
    # the numpy emulator on pairs: anchor p -> node p (per-node anchors (N, 1, 3))
    length_r, _, _, _, valid_r, _, snr_r = _slots(_Ctx(b, radio, nodes, anchors[:, None, :]),
                                                  radio, extra)
    ref_snr, ref_len = snr_r[:, 0, 18:], length_r[:, 0, 18:]
    snr, length = _family_snr_length(anchors, nodes, b, radio)
    assert snr.shape == ref_snr.shape == (600, len(extra))
    fin = np.isfinite(ref_snr)
    assert np.array_equal(np.isfinite(snr), fin)
    assert fin.sum() > 2000  # the families exist on many links
    assert np.max(np.abs(snr[fin] - ref_snr[fin])) <= ATOL_DB
    assert np.array_equal(np.isfinite(length), np.isfinite(ref_len))
    ok = np.isfinite(ref_len)
    assert np.allclose(length[ok], ref_len[ok], rtol=1e-12, atol=0)
    # and the path model's geometry (what M-NLS fits): same existence, same lengths
    geo = first_arrival_paths(nodes, anchors, b, mechanisms=mechanism_set(4, partitions=True)).length_m[:, 18:]
    assert np.array_equal(np.isfinite(geo), ok)
    assert np.allclose(geo[ok], length[ok], rtol=1e-12, atol=0)
    # the compiled first arrival equals the numpy emulator's detector on the same slots
    _, true_ref, snr_fr, _, _, det_ref = _detect(valid_r[:, 0], snr_r[:, 0],
                                                 length_r[:, 0] / SPEED_OF_LIGHT_M_S, length_r[:, 0],
                                                 radio, None)
    _, _, snr_f, true_path, det = pair_first_arrival(anchors, nodes, building=b, radio=radio)
    assert np.array_equal(det, det_ref)
    assert np.allclose(true_path[det], true_ref[det], rtol=1e-12, atol=0)
    assert np.max(np.abs(snr_f[det] - snr_fr[det])) <= ATOL_DB


def test_ceiling_floor_ceiling_amplitude_closed_form() -> None:
    """Paper building, floor 0 (z 4..7, window 4.75..6.25): anchor (0, -5, 3), node
    (0, 20, 4.2). Node imaged in the ceiling, the floor, the ceiling (last plane first):
    z = 14 - 4.2 -> 8 - 9.8 -> 14 + 1.8 = 15.8; the unfolded ray enters at z = 5.56."""
    b = Building()
    radio = dataclasses.replace(Radio(), channel_max_order=3)
    anchor = np.array([[0.0, -5.0, 3.0]])
    node = np.array([[0.0, 20.0, 4.2]])
    labels = mechanism_set(3).labels
    s = labels.index("Tx-R(ceiling)-R(floor)-R(ceiling)-Rx")
    length = np.hypot(25.0, 15.8 - 3.0)
    cos_t = (15.8 - 3.0) / length
    gs, _ = fresnel_coefficients(cos_t, itu_permittivity(b.interior_material, radio.frequency_hz))
    gain = radio.wavelength_m / (4 * np.pi * length) * abs(complex(gs)) ** 3
    n0 = float(noise_floor_dbm(radio.bandwidth_hz, temperature_k=radio.noise_temperature_k,
                               noise_figure_db=radio.noise_figure_db))
    want = radio.tx_power_dbm + 20 * np.log10(gain) + radio.processing_gain_db - n0
    ch = emulate_channel(anchor, node, building=b, radio=radio)
    assert ch.valid[0, 0, s]
    assert ch.length_m[0, 0, s] == pytest.approx(length, rel=1e-12)
    assert ch.snr_db[0, 0, s] == pytest.approx(want, abs=1e-9)
    snr, _ = _family_snr_length(anchor, node, b, radio)
    assert snr[0, s - 18] == pytest.approx(want, abs=1e-9)


def test_generic_diffraction_builder_matches_the_18s() -> None:
    """``_diffracted_family`` (any planes, a ground bounce) on a one-plane recipe equals the
    18's ``_diffracted`` (gain and validity) on the same sheet (a family's edge is a dielectric
    sheet of the walls' material), on random links of two buildings."""
    for b in (BUILDINGS["default"], BUILDINGS["parts_glass"]):
        anchors, nodes = _pairs(b, np.random.default_rng(9), 300)
        c = _Ctx(b, RADIOS["patterns_zpol"], nodes, anchors[:, None, :])
        for edge in ("upper", "lower"):
            for plane in ("floor", "ceiling", "back"):
                ref = _diffracted(c, edge, plane, sheet=c.eta_wall)
                got = _diffracted_family(c, Recipe("diff", edge=edge, planes=(plane,)))
                assert np.array_equal(got[4], ref[4])
                ok = ref[4]
                assert ok.sum() > 100
                assert np.allclose(np.abs(got[1][ok]), np.abs(ref[1][ok]), rtol=1e-9, atol=0)


def test_third_order_path_arrives_first() -> None:
    """Paper scenario, anchor (0, -15, 0), node (-4.5, 21.6, 5.5): with the families of order
    3 the strongest path is the ceiling-floor-ceiling triple bounce; it lifts the threshold
    ``P_max - 15 dB`` above the order-2 first arrival (a weak lower-edge diffraction), and the
    first arrival becomes the lower-edge diffraction then a ceiling and a floor bounce, 12 dB
    above the threshold and 1 m later: what Sionna shows on such links, and what the 18
    cannot produce."""
    sc = default_scenario()
    anchor = np.array([[0.0, -15.0, 0.0]])
    node = np.array([[-4.5, 21.6, 5.5]])
    r2 = sc.radio
    r3 = dataclasses.replace(sc.radio, channel_max_order=3)
    ch2 = emulate_channel(anchor, node, building=sc.building, radio=r2)
    fa2 = first_arrival(ch2, radio=r2)
    ch3 = emulate_channel(anchor, node, building=sc.building, radio=r3)
    fa3 = first_arrival(ch3, radio=r3)
    snr3 = ch3.snr_db[0, 0]
    thr3 = snr3.max() - r3.fap_threshold_db
    assert ch3.mechanism[int(np.argmax(snr3))] == "Tx-R(ceiling)-R(floor)-R(ceiling)-Rx"
    assert ch2.mechanism[fa2.slot[0, 0]] == "Tx-D(lower)-Rx"
    assert fa2.snr_db[0, 0] < thr3 - 3.0
    label = ch3.mechanism[fa3.slot[0, 0]]
    assert label == "Tx-D(lower)-R(ceiling)-R(floor)-Rx"
    assert fa3.snr_db[0, 0] >= thr3 + 10.0
    assert fa3.true_path_m[0, 0] > fa2.true_path_m[0, 0] + 0.5
    # every shorter path of the order-3 channel is below the threshold
    shorter = ch3.valid[0, 0] & (ch3.length_m[0, 0] < fa3.true_path_m[0, 0])
    assert shorter.any() and np.all(snr3[shorter] < thr3)
    mset = mechanism_set(3)
    geo = first_arrival_paths(node, anchor, sc.building, mechanisms=mset)
    assert geo.length_m[0, mset.labels.index(label)] == pytest.approx(fa3.true_path_m[0, 0],
                                                                        rel=1e-12)
    _, _, _, true_path, det = pair_first_arrival(anchor, node, building=sc.building, radio=r3)
    assert det[0] and true_path[0] == pytest.approx(fa3.true_path_m[0, 0], rel=1e-12)


def test_default_channel_keeps_the_18() -> None:
    sc = default_scenario()
    assert sc.radio.channel_max_order == 2
    ch = emulate_channel(sc.anchor_positions_m(), np.array([[0.0, 5.0, 5.5]]),
                         building=sc.building, radio=sc.radio)
    assert ch.snr_db.shape[-1] == 18 and len(ch.mechanism) == 18
    ch4 = emulate_channel(sc.anchor_positions_m(), np.array([[0.0, 5.0, 5.5]]),
                          building=sc.building,
                          radio=dataclasses.replace(sc.radio, channel_max_order=4))
    assert ch4.mechanism == mechanism_set(4, partitions=True).labels
    # the 18 keep their slots; at order >= 3 their window edges are a dielectric sheet of
    # the walls' material (order 2: perfect conductors), everything else is unchanged
    diff = np.array([r.kind == "diff" for r in mechanism_set(2).recipes])
    assert np.array_equal(ch4.snr_db[..., :18][..., ~diff], ch.snr_db[..., ~diff])
    assert np.array_equal(np.isfinite(ch4.snr_db[..., :18]), np.isfinite(ch.snr_db))
    fin = np.isfinite(ch.snr_db) & diff
    assert fin.sum() >= 3 and np.all(ch4.snr_db[..., :18][fin] != ch.snr_db[fin])
    assert set(ch4.mpc_class[18:].tolist()) <= {2, 3, 4}
    # class 2 (one specular reflection) among the added: only the partition reflection
    assert {ch4.mechanism[i] for i in range(18, len(ch4.mechanism))
            if ch4.mpc_class[i] == 2} == {"Tx-R(partition)-Rx"}


def test_channel_max_order_is_parsed_and_round_trips() -> None:
    d = default_scenario().to_dict()
    d["radio"]["channel_max_order"] = 3
    sc = Scenario.from_dict(d)
    assert sc.radio.channel_max_order == 3
    assert sc.to_dict()["radio"]["channel_max_order"] == 3
    assert Scenario.from_dict(sc.to_dict()).radio == sc.radio
    for bad in (1, 5, 3.0, "3", True):
        d["radio"]["channel_max_order"] = bad
        with pytest.raises(ScenarioError, match=r"radio\.channel_max_order"):
            Scenario.from_dict(d)


@pytest.mark.parametrize(("label", "family"), [
    ("Tx-Rx", "direct"),
    ("Tx-R(ceiling)-Rx", "R x1"),
    ("Tx-R(ground)-R(ceiling)-Rx", "R x2"),
    ("Tx-R(ceiling)-R(floor)-R(ceiling)-R(floor)-Rx", "R x3+"),
    ("Tx-D(lower)-Rx", "D"),
    ("Tx-D(upper)-R(floor)-Rx", "D+R"),
    ("Tx-D(lower)-R(ceiling)-R(floor)-Rx", "D+RR+"),
    ("Tx-R(ground)-D(lower)-R(ceiling)-Rx", "ground+D"),
    ("Tx-D(lower)-R(partition)-Rx", "wall/partition"),
    ("Tx-R(ceiling)-R(back)-Rx", "wall/partition"),
    ("Tx-D(vertical)-R(ceiling)-Rx", "vertical D"),
    ("Tx-R(ground)-D(vertical x2)-R(floor)-Rx", "vertical D"),
    ("Tx-D(vertical)-R(partition)-Rx", "wall/partition"),
    ("Tx-D(lower floor+1)-Rx", "other"),
    ("none", "none"),
    ("", "none"),
])
def test_label_family(label: str, family: str) -> None:
    assert label_family(label) == family
    assert family in FAMILIES


def test_every_recipe_has_a_family() -> None:
    fams = {label_family(r.label) for r in mechanism_set(4).recipes}
    assert "other" not in fams and "none" not in fams
