"""The SNR term's window edge as Sionna RT traces it (``TrackerConfig.snr_edge_model``;
:func:`diffpos.channel.emulator.pair_snr_db`'s ``edge_model``).

* ``with_wedge_edges(pair_snr_db(...))``: every slot but the window-edge slots 7-13 is bit for
  bit the half-plane's; ``Tx-D(upper)-Rx`` / ``Tx-D(lower)-Rx`` differ from the half-plane's
  by ``20 log10(|wedge field| / |half-plane field|)`` computed here from the two fields at the
  Fermat point (:func:`diffpos.channel.wedge.wedge_field`, whose values are held to Sionna
  RT's own diffraction matrix in tests/core/test_channel_wedge.py), 1e-9 dB; with ``need``
  the needed slots equal the unmasked ones bit for bit, the rest NaN.
* The tracker's SNR term with the setting equals the term computed with every prediction of
  ``pair_snr_db`` made by the wedge (the function swapped in), bit for bit, and the setting
  moves some slot by more than 0.1 nats (fails with the tracker ignoring it); the default is
  the half-plane's term bit for bit.
Fixed seeds."""

from __future__ import annotations

import dataclasses

import numpy as np

import diffpos.tracking.model as tm
from diffpos.channel.edge_snr import with_wedge_edges
from diffpos.channel.emulator import pair_snr_db
from diffpos.channel.gtd_halfplane import edge_frame, field_from_frame
from diffpos.channel.slots import itu_permittivity
from diffpos.channel.wedge import wedge_field
from diffpos.paths.model import FloorFrame, diffracted_path
from diffpos.scenario import Building, Radio
from diffpos.tracking.links import Links, all_paths
from diffpos.tracking.state import TrackerConfig

EDGE = np.zeros(18, bool)
EDGE[7:14] = True


def _points(seed: int, n: int = 40, m: int = 4):
    rng = np.random.default_rng(seed)
    b = Building()
    x0, x1 = b.edge_x_m
    floor = rng.integers(0, b.n_floors, n)
    z = b.floor_z_m(floor) + rng.uniform(0.3, b.floor_height_m - 0.3, n)
    nodes = np.stack([rng.uniform(x0 + 0.5, x1 - 0.5, n), rng.uniform(0.5, b.depth_m - 0.5, n),
                      z], -1)
    anchors = np.stack([rng.uniform(x0 - 15.0, x1 + 15.0, (n, m)),
                        -rng.uniform(3.0, 30.0, (n, m)), rng.uniform(0.3, 8.0, (n, m))], -1)
    return b, nodes, anchors


def test_with_wedge_edges_replaces_only_the_window_edge_slots() -> None:
    b, nodes, anchors = _points(0)
    r = Radio()
    half = pair_snr_db(anchors, nodes, building=b, radio=r)
    wed = with_wedge_edges(pair_snr_db(anchors, nodes, building=b, radio=r), anchors, nodes,
                           building=b, radio=r)
    with np.errstate(invalid="ignore"):  # -inf - -inf where a slot has no power
        diff = wed - half
    assert np.array_equal(half[..., ~EDGE], wed[..., ~EDGE])
    assert np.array_equal(np.isfinite(half), np.isfinite(wed))
    eta = itu_permittivity(b.wall_material, r.frequency_hz)
    fr = FloorFrame.from_building(b, b.floor_index(nodes[:, 2])[:, None])
    nb = np.broadcast_to(nodes[:, None], anchors.shape)
    for k, edge, e_dir, face in ((7, "upper", [1.0, 0, 0], [0, 0, 1.0]),
                                 (8, "lower", [-1.0, 0, 0], [0, 0, -1.0])):
        q = diffracted_path(anchors, nb, fr, edge).points[0]
        frame = edge_frame(anchors, nb, q, e_dir, face)
        e0 = np.asarray(r.polarization, float)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = 20 * np.log10(
                np.linalg.norm(wedge_field(frame, e0, frequency_hz=r.frequency_hz,
                                           permittivity=eta, thickness_m=b.wall_thickness_m),
                               axis=-1)
                / np.linalg.norm(field_from_frame(frame, e0, frequency_hz=r.frequency_hz),
                                 axis=-1))
        ok = np.isfinite(half[..., k])
        assert ok.sum() > 40
        np.testing.assert_allclose(diff[..., k][ok], ratio[ok], atol=1e-9, rtol=0)
    assert np.nanmax(np.abs(np.where(np.isfinite(half), diff, 0.0))) > 3.0
    need = np.random.default_rng(1).random(half.shape) < 0.3
    masked = with_wedge_edges(pair_snr_db(anchors, nodes, building=b, radio=r, need=need),
                              anchors, nodes, building=b, radio=r, need=need)
    assert np.array_equal(masked[need], wed[need])
    assert np.all(np.isnan(masked[~need]))


def _case(seed: int):
    b, nodes, anchors = _points(seed, n=12)
    rng = np.random.default_rng(seed + 10)
    n, h, m = 12, 3, 4
    floor = rng.integers(0, b.n_floors, (n, h))
    floor[:, 0] = b.floor_index(nodes[:, 2])
    pos = np.repeat(nodes[:, None], h, axis=1)
    pos[:, 1:, 2] = b.floor_z_m(floor[:, 1:]) + rng.uniform(0.4, 2.6, (n, h - 1))
    mask = np.ones((n, m), bool)
    mask[: n // 2, 3] = False
    pred = with_wedge_edges(pair_snr_db(anchors, nodes, building=b, radio=Radio()), anchors,
                            nodes, building=b, radio=Radio())
    snr = np.max(np.where(np.isfinite(pred), pred, -np.inf), axis=-1)
    snr = np.where(np.isfinite(snr), snr, 0.0) + rng.normal(0.0, 3.0, (n, m))
    rho = np.linalg.norm(pos[:, :1] - anchors, axis=-1) + 0.3
    links = Links.from_arrays(anchors, rho, np.full((n, m), 0.1), mask, 0.03, snr_db=snr,
                              radio=Radio())
    return b, pos, floor, links


def test_the_tracker_snr_term_uses_the_wedge(monkeypatch) -> None:
    b, pos, floor, links = _case(3)
    base = TrackerConfig(snr_reuse_m=0.0, snr_reuse_anchor_m=0.0, snr_diffraction_slack_db=0.0)
    on = dataclasses.replace(base, snr_edge_model="wedge")
    relax = np.full(pos.shape[:2], 0.2)
    pe = all_paths(pos, links, floor, b, relax)
    c0 = tm.snr_term(pos, links, floor, b, relax, pe, base)
    c1 = tm.snr_term(pos, links, floor, b, relax, pe, on)
    orig = tm.pair_snr_db

    def wedge_everywhere(anchors, nodes, **kw):
        return with_wedge_edges(orig(anchors, nodes, **kw), anchors, nodes, **kw)

    monkeypatch.setattr(tm, "pair_snr_db", wedge_everywhere)
    ref = tm.snr_term(pos, links, floor, b, relax, pe, base)
    assert np.array_equal(c1, ref, equal_nan=True)
    fin = np.isfinite(c0) & np.isfinite(c1)
    assert np.max(np.abs(c1[fin] - c0[fin])) > 0.1
    monkeypatch.setattr(tm, "pair_snr_db", orig)
    assert np.array_equal(tm.snr_term(pos, links, floor, b, relax, pe, base), c0,
                          equal_nan=True)
