"""The tracker's existence margin follows every hypothesis' own height uncertainty.

:func:`diffpos.tracking.model.existence_margin`: a specular mechanism enters through the
window band at the height where the unfolded ray from the anchor to the (mirrored) node
crosses the facade; moving the node by ``dz`` in height moves that entry point by ``t dz``,
``0 < t < 1`` (the fraction of the unfolded ray outside the building). So a hypothesis whose
height is uncertain by ``sigma_z`` may have every specular mechanism whose entry lies within
``2 sigma_z`` of the band: with the fixed margin alone (0.2 m), a track on the stairs with a
loose height called the links of such a mechanism impossible and scored them as outliers, and
a mirror floor that explained every link won (the default scenario's top-floor descent).

Reference: the emulator's own first arrivals (:func:`diffpos.channel.emulator.first_arrival`, its
detected mechanism per link) at the true position, on a building and UAV layout that is not in
scenarios/ (3.3 m floors, 0.8 m sill, 1.3 m windows, 30 x 16 m, one UAV beyond a facade end).
"""

from __future__ import annotations

import numpy as np
from margin_building import ANCHORS, BUILDING, SCENARIO

from diffpos.channel.emulator import emulate_channel, first_arrival
from diffpos.paths.mechanisms import SPECULAR_SLOTS
from diffpos.tracking.links import Links, _all_paths_numpy, all_paths
from diffpos.tracking.model import ENTRY_SIGMAS, existence_margin, snr_cost_near
from diffpos.tracking.state import TrackerConfig

_SC, _B, _ANCHORS = SCENARIO, BUILDING, ANCHORS


def _nodes(rng, n):
    """``n`` true positions anywhere between floor and ceiling (stairs, crouching) and the
    emulator's first arrivals of every anchor at them."""
    x0, x1 = _B.edge_x_m
    floor = rng.integers(0, _B.n_floors, n)
    zf = _B.floor_z_m(floor)
    nodes = np.stack([rng.uniform(x0 + 1.0, x1 - 1.0, n), rng.uniform(1.0, _B.depth_m - 1.0, n),
                      zf + rng.uniform(0.3, _B.floor_height_m - 0.3, n)], axis=-1)
    fa = first_arrival(emulate_channel(_ANCHORS, nodes, building=_B, radio=_SC.radio),
                       radio=_SC.radio, rng=rng)
    return floor, nodes, fa


def test_detected_specular_mechanism_exists_within_two_height_sigmas():
    """A hypothesis displaced from the truth in height only, by up to ``ENTRY_SIGMAS`` of its
    own height standard deviation, grades every detected specular first arrival as possibly
    existing (``loose``): the entry point moves by less than the height. With the fixed margin
    alone some of them are called impossible (the case exercises the band edges)."""
    rng = np.random.default_rng(7)
    cfg = TrackerConfig()
    n = 600
    floor, nodes, fa = _nodes(rng, n)
    sigma_z = rng.uniform(0.1, 0.6, n)
    # the prior: the truth moved in height by |dz| <= ENTRY_SIGMAS sigma_z, kept on its floor
    zf = _B.floor_z_m(floor)
    dz = rng.uniform(-1.0, 1.0, n) * ENTRY_SIGMAS * sigma_z
    z = np.clip(nodes[:, 2] + dz, zf + cfg.z_margin_m, zf + _B.floor_height_m - cfg.z_margin_m)
    prior = np.concatenate([nodes[:, :2], z[:, None]], axis=-1)[:, None]
    cov = np.zeros((n, 1, 6, 6))
    cov[:, 0, 2, 2] = sigma_z**2
    links = Links.from_arrays(np.broadcast_to(_ANCHORS, (n, 4, 3)), fa.range_m, fa.sigma_m,
                              fa.detected, cfg.sigma_model_m)
    spec = fa.detected & np.isin(fa.slot, SPECULAR_SLOTS)
    # the emulator's mechanism exists at the truth in the path model too (same geometry)
    at_truth = all_paths(nodes[:, None], links, floor[:, None], _B, 0.0)
    slot = np.maximum(fa.slot, 0)[:, None, :, None]
    exists = np.take_along_axis(at_truth.strict, slot, axis=-1)[:, 0, :, 0]
    assert np.all(exists[spec])
    margin = existence_margin(cov, cfg)
    np.testing.assert_array_equal(margin, np.maximum(cfg.exist_margin_m,
                                                     ENTRY_SIGMAS * sigma_z)[:, None])
    graded = all_paths(prior, links, floor[:, None], _B, margin)
    loose = np.take_along_axis(graded.loose, slot, axis=-1)[:, 0, :, 0]
    assert spec.sum() > 100
    assert np.all(loose[spec])
    fixed = all_paths(prior, links, floor[:, None], _B, cfg.exist_margin_m)
    assert np.any(~np.take_along_axis(fixed.loose, slot, axis=-1)[:, 0, :, 0][spec])


def test_all_paths_per_hypothesis_margin_bit_identical_to_reference():
    """The compiled pass with one margin per hypothesis (0 included) equals the numpy
    reference exactly, and a constant array equals the scalar margin."""
    rng = np.random.default_rng(11)
    n, h = 40, 6
    floor, nodes, fa = _nodes(rng, n)
    fl = np.broadcast_to(floor[:, None], (n, h))
    pos = nodes[:, None] + rng.normal(0.0, 0.4, (n, h, 3))
    links = Links.from_arrays(np.broadcast_to(_ANCHORS, (n, 4, 3)), fa.range_m, fa.sigma_m,
                              fa.detected, 0.03)
    relax = np.where(rng.random((n, h)) < 0.2, 0.0, rng.uniform(0.0, 1.2, (n, h)))
    got = all_paths(pos, links, fl, _B, relax)
    ref = _all_paths_numpy(pos, links, fl, _B, relax)
    for f in ("length", "jac", "strict", "loose", "sure"):
        np.testing.assert_array_equal(getattr(got, f), getattr(ref, f), err_msg=f)
    assert np.any(ref.loose & ~ref.strict) and np.any(ref.strict & ~ref.sure)
    const = all_paths(pos, links, fl, _B, np.full((n, h), 0.2))
    scalar = all_paths(pos, links, fl, _B, 0.2)
    for f in ("strict", "loose", "sure"):
        np.testing.assert_array_equal(getattr(const, f), getattr(scalar, f), err_msg=f)


def test_snr_near_boundary_scored_at_each_hypothesis_margin():
    """The SNR of a slot that exists only within a hypothesis' margin is scored at the
    hypothesis' own +- margin in height: per-hypothesis margins give, hypothesis by
    hypothesis, the scalar result of that margin."""
    rng = np.random.default_rng(5)
    n = 30
    floor, nodes, fa = _nodes(rng, n)
    links = Links.from_arrays(np.broadcast_to(_ANCHORS, (n, 4, 3)), fa.range_m, fa.sigma_m,
                              fa.detected, 0.03, snr_db=fa.snr_db, radio=_SC.radio)
    pos = np.repeat(nodes[:, None], 2, axis=1) + np.array([0.0, 0.0, 0.3])
    fl = np.broadcast_to(floor[:, None], (n, 2))
    margins = np.array([0.2, 0.6])
    got = snr_cost_near(pos, links, fl, _B, np.broadcast_to(margins, (n, 2)))
    for j, r in enumerate(margins):
        ref = snr_cost_near(pos[:, j:j + 1], links, fl[:, j:j + 1], _B, float(r))
        np.testing.assert_array_equal(got[:, j], ref[:, 0])
