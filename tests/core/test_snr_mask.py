"""The tracker's SNR cost with partial predictions (only the slots that are used).

* :func:`diffpos.channel.snr_nb.channel_snr_masked_kernel` (``pair_snr_db(need=...)``)
  against the unmasked kernel: every needed slot bit for bit (the same per-slot function), NaN
  elsewhere.
* :func:`diffpos.channel.snr_nb.snr_cost_kernel` against its numpy reference
  (``tracking_snr._snr_cost_of_numpy``): bit for bit (no transcendental function), with
  unknown SNRs, slots without power, NaN predictions and a given threshold.
* :func:`diffpos.tracking.model.snr_cost_near` against a brute-force reference that predicts
  all 18 slots of every link at the hypothesis and at both shifted heights (the algorithm
  before the masks): bit for bit with the shifted point's threshold; with the prior's
  threshold (``HOLE_THRESHOLD_AT_PRIOR``) the hole slots equal the brute force given that
  threshold, every other slot is unchanged.

Geometries (fixed seeds): the default building and variants not in scenarios/ (tall floors
with a high sill and short windows, wide windows, a deep off-centre building), UAVs below, at
and above the window bands (up to 15 m above the roof) and beyond the facade ends; the
hypotheses on every floor, a third of them within a few cm of a window-band edge (where the
relax "holes" are).
"""

from __future__ import annotations

import numpy as np
import pytest

import diffpos.tracking.model as tm
from diffpos.channel.emulator import pair_snr_db
from diffpos.scenario import Building, Radio
from diffpos.tracking.links import K_SLOTS, Links, _relax, all_paths

BUILDINGS = [
    Building(),
    Building(width_m=30.0, depth_m=15.0, n_floors=4, floor_height_m=3.6, first_floor_z_m=2.5,
             sill_height_m=1.0, window_height_m=1.2),
    Building(n_floors=3, floor_height_m=3.2, first_floor_z_m=1.0, sill_height_m=0.4,
             window_height_m=2.4),
    Building(width_m=50.0, center_x_m=-6.0, depth_m=25.0, n_floors=6, floor_height_m=2.9,
             first_floor_z_m=5.0, sill_height_m=0.8, window_height_m=1.4),
]
RADIO = Radio()


def _case(b: Building, seed: int, n: int = 12, h: int = 3, m: int = 6, unknown: float = 0.2):
    """Hypotheses (N, H, 3) on random floors (a third near a window-band edge), per-node
    anchors in front of, above and beyond the facade, measured SNRs (a fraction ``unknown``
    of them unknown)."""
    rng = np.random.default_rng(seed)
    x0, x1 = b.edge_x_m
    w = x1 - x0
    floor = rng.integers(0, b.n_floors, (n, h))
    z = b.floor_z_m(floor) + rng.uniform(0.05, b.floor_height_m - 0.05, (n, h))
    lo, hi = b.window_z_m(floor)
    edge = np.where(rng.random((n, h)) < 0.5, lo, hi) + rng.uniform(-0.05, 0.05, (n, h))
    z = np.where(rng.random((n, h)) < 1 / 3, edge, z)
    pos = np.stack([rng.uniform(x0 + 0.1, x1 - 0.1, (n, h)),
                    rng.uniform(0.1, b.depth_m - 0.1, (n, h)), z], axis=-1)
    ax = rng.uniform(x0 - 0.4 * w, x1 + 0.4 * w, (n, m))
    ay = -rng.uniform(0.5, 35.0, (n, m))
    az = rng.uniform(0.3, b.top_z_m + 15.0, (n, m))
    anchors = np.stack([ax, ay, az], axis=-1)
    rho = np.linalg.norm(pos[:, :1, None, :] - anchors[:, None], axis=-1)[:, 0] + 1.0
    snr = np.where(rng.random((n, m)) < unknown, np.nan, rng.uniform(-10.0, 45.0, (n, m)))
    links = Links.from_arrays(anchors, rho, np.full((n, m), 0.1), np.ones((n, m), bool), 0.1,
                              snr_db=snr, radio=RADIO)
    relax = rng.uniform(0.2, 0.6, (n, h))  # one existence margin per hypothesis
    return pos, links, floor, relax


def _near_reference(pos, links, floor, b, relax, pe, thr_from_prior: bool):
    """snr_cost_near by brute force: all 18 slots of every link at the hypothesis and at both
    shifted heights, the numpy cost."""
    n, h = pos.shape[:2]
    m = links.rho.shape[-1]
    anc = np.broadcast_to(links.anchors, (n, h, m, 3)).reshape(-1, 3)
    p = np.broadcast_to(pos[:, :, None, :], (n, h, m, 3)).reshape(-1, 3)
    meas = np.broadcast_to(links.snr, (n, h, m)).reshape(-1)
    sure = pe.sure.reshape(-1, K_SLOTS)
    pred = pair_snr_db(anc[:, None, :], p, building=b, radio=links.radio)[:, 0]
    c, thr = tm._snr_cost_of_numpy(pred, meas, links.radio, sure)
    hole = ~np.isfinite(c) & pe.loose.reshape(-1, K_SLOTS)
    dz = np.broadcast_to(_relax(relax, (n, h))[..., None], (n, h, m)).reshape(-1)
    zf = b.floor_z_m(np.broadcast_to(floor[..., None], (n, h, m)).reshape(-1))
    best = np.full(c.shape, np.inf)
    powered = 0
    for sign in (-1.0, 1.0):
        q = p.copy()
        q[:, 2] = np.clip(q[:, 2] + sign * dz, zf + 0.01, zf + b.floor_height_m - 0.01)
        pq = pair_snr_db(anc[:, None, :], q, building=b, radio=links.radio)[:, 0]
        powered += int(np.sum(hole & np.isfinite(pq)))
        cs = tm._snr_cost_of_numpy(pq, meas, links.radio, sure,
                                   thr=thr if thr_from_prior else None)[0]
        best = np.minimum(best, cs)
    out = np.where(hole, best, c).reshape(n, h, m, K_SLOTS)
    return out, hole.reshape(n, h, m, K_SLOTS), powered


@pytest.mark.parametrize("bi", range(len(BUILDINGS)))
def test_masked_kernel_equals_unmasked_on_needed_slots(bi):
    """Every needed slot of the masked kernel is the unmasked kernel's value bit for bit
    (-inf where not valid), every other one NaN; random masks and the tracker's own masks
    (the slots that may exist within the margin, those that surely exist); also through the
    numpy reference (a non-finite coordinate)."""
    b = BUILDINGS[bi]
    for seed in range(3):
        pos, links, floor, relax = _case(b, 100 * bi + seed)
        n, h, m = pos.shape[0], pos.shape[1], links.rho.shape[-1]
        anc = np.ascontiguousarray(np.broadcast_to(links.anchors, (n, h, m, 3)).reshape(-1, 1, 3))
        p = np.broadcast_to(pos[:, :, None, :], (n, h, m, 3)).reshape(-1, 3)
        full = pair_snr_db(anc, p, building=b, radio=RADIO)
        assert np.all(np.isfinite(full) | (full == -np.inf))
        assert np.any(np.isfinite(full)) and np.any(full == -np.inf)
        pe = all_paths(pos, links, floor, b, relax)
        rng = np.random.default_rng(seed)
        for need in (rng.random(full.shape) < 0.3, pe.loose.reshape(full.shape),
                     pe.sure.reshape(full.shape), np.zeros(full.shape, bool)):
            got = pair_snr_db(anc, p, building=b, radio=RADIO, need=need)
            np.testing.assert_array_equal(got[need], full[need])
            assert np.all(np.isnan(got[~need]))
    # the numpy reference path (a non-finite coordinate) honours the mask the same way
    p_bad = p.copy()
    p_bad[0, 0] = np.nan
    need = np.random.default_rng(9).random(full.shape) < 0.5
    with np.errstate(invalid="ignore", divide="ignore"):
        ref = pair_snr_db(anc, p_bad, building=b, radio=RADIO)
        got = pair_snr_db(anc, p_bad, building=b, radio=RADIO, need=need)
    np.testing.assert_array_equal(got[need], ref[need])
    assert np.all(np.isnan(got[~need]))


def test_snr_cost_kernel_bit_identical_to_numpy():
    """The compiled cost equals the numpy reference exactly: costs and thresholds, with
    unknown SNRs, slots without power, a NaN prediction among the trusted slots (the
    threshold becomes NaN as numpy's max makes it), no trusted slot (the detection floor),
    and a given threshold."""
    rng = np.random.default_rng(3)
    p, k = 400, K_SLOTS
    pred = rng.uniform(-40.0, 60.0, (p, k))
    pred[rng.random((p, k)) < 0.3] = -np.inf
    pred[rng.random((p, k)) < 0.01] = np.nan
    meas = rng.uniform(-15.0, 50.0, p)
    meas[rng.random(p) < 0.1] = np.nan
    trust = rng.random((p, k)) < 0.6
    trust[:20] = False
    for tr in (trust, None):
        got = tm._snr_cost_of(pred, meas, RADIO, tr)
        ref = tm._snr_cost_of_numpy(pred, meas, RADIO, tr)
        for g, r in zip(got, ref, strict=True):
            np.testing.assert_array_equal(g, r)
    thr = tm._snr_cost_of_numpy(pred, meas, RADIO, trust)[1]
    assert np.any(np.isnan(thr) & np.isfinite(meas))  # the NaN prediction case is exercised
    assert np.all(thr[:20][np.isfinite(meas[:20])] == RADIO.detection_snr_db)
    thr_given = rng.uniform(-10.0, 40.0, p)
    got = tm._snr_cost_of(pred, meas, RADIO, thr=thr_given)[0]
    ref = tm._snr_cost_of_numpy(pred, meas, RADIO, thr=thr_given)[0]
    np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("bi", range(len(BUILDINGS)))
def test_snr_cost_near_equals_brute_force(bi, monkeypatch):
    """snr_cost_near with the masks equals predicting every slot everywhere: bit for bit with
    the shifted point's threshold; with the prior's threshold the hole slots equal the brute
    force given that threshold and every other slot is the exact value. With and without
    unknown SNRs."""
    b = BUILDINGS[bi]
    n_hole = n_powered = 0
    for seed in range(3):
        # seed 0: every SNR known (snr_cost's path without a gather)
        pos, links, floor, relax = _case(b, 1000 + 100 * bi + seed,
                                         unknown=0.0 if seed == 0 else 0.2)
        pe = all_paths(pos, links, floor, b, relax)
        monkeypatch.setattr(tm, "HOLE_THRESHOLD_AT_PRIOR", False)
        got = tm.snr_cost_near(pos, links, floor, b, relax, pe)
        ref, hole, powered = _near_reference(pos, links, floor, b, relax, pe, False)
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_array_equal(tm.snr_cost(pos, links, b, trust=pe.sure)[~hole],
                                      ref[~hole])
        monkeypatch.setattr(tm, "HOLE_THRESHOLD_AT_PRIOR", True)
        got_p = tm.snr_cost_near(pos, links, floor, b, relax, pe)
        ref_p, hole_p, _ = _near_reference(pos, links, floor, b, relax, pe, True)
        np.testing.assert_array_equal(hole_p, hole)
        np.testing.assert_array_equal(got_p, ref_p)
        np.testing.assert_array_equal(got_p[~hole], got[~hole])
        unknown = ~np.isfinite(np.broadcast_to(links.snr, got.shape[:3]))
        assert np.all(got[unknown] == 0.0)
        n_hole += int(hole.sum())
        n_powered += powered
    # the cases hold holes, and holes that carry power at a shifted height (the threshold's
    # slots predicted there)
    assert n_hole > 0 and n_powered > 0


def test_kernels_get_writeable_contiguous_arrays(monkeypatch):
    """numba types a read-only array apart from a writeable one: a contiguous read-only view
    (``broadcast_to`` to its own shape, as snr_cost and snr_cost_near build their inputs)
    would compile a second specialisation of the SNR kernels at its first use, after
    ``warm_channel`` (the live service's first epochs). Every array the tracker's SNR cost
    hands to the kernels is writeable and C-contiguous, and the values are those of plain
    copies."""
    from diffpos.channel import snr_nb as channel_nb

    channel_nb.warm_channel()
    seen = []

    def spy(kernel):
        def call(*args):
            seen.extend(a.flags.writeable and a.flags.c_contiguous
                        for a in args if isinstance(a, np.ndarray))
            return kernel(*args)
        return call

    for name in ("channel_snr_kernel", "channel_snr_masked_kernel"):
        monkeypatch.setattr(channel_nb, name, spy(getattr(channel_nb, name)))
    b = BUILDINGS[1]
    pos, links, floor, relax = _case(b, 77, unknown=0.0)
    pe = all_paths(pos, links, floor, b, relax)
    tm.snr_cost_near(pos, links, floor, b, relax, pe)  # the known-SNR path and the holes
    n, m = links.rho.shape[0], links.rho.shape[-1]
    anc0 = np.ascontiguousarray(np.broadcast_to(links.anchors, (n, 1, m, 3))[:, 0])
    nodes0, need0 = np.ascontiguousarray(pos[:, 0]), np.ascontiguousarray(pe.loose[:, 0])
    anc, nodes, need = (np.broadcast_to(a, a.shape) for a in (anc0, nodes0, need0))
    assert not (anc.flags.writeable or nodes.flags.writeable or need.flags.writeable)
    assert anc.flags.c_contiguous and nodes.flags.c_contiguous and need.flags.c_contiguous
    got = pair_snr_db(anc, nodes, building=b, radio=RADIO, need=need)
    ref = pair_snr_db(anc0, nodes0, building=b, radio=RADIO, need=need0)
    np.testing.assert_array_equal(got, ref)
    assert len(seen) > 6 and all(seen)
