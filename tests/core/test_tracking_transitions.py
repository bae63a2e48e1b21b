"""The IMM transitions' floor spread (diffpos.tracking.imm._to_floors) against the einsum it
replaces: every (hypothesis -> floor) probability put on the hypotheses of that floor and mode.

Reference: the product with the floor -> hypothesis indicator matrix, ``einsum("nhf,fk->nhk",
a, to_floor) * same_mode``, built here from the hypothesis layout. Exact equality (bit for bit:
every output is one product ``a * 1`` plus exact zeros) on random inputs (seed 0) and on the
transitions of real prior states; the non-finite case keeps the einsum's values (NaN spread
over every column).
"""

from __future__ import annotations

import numpy as np

from diffpos.scenario import default_scenario
from diffpos.tracking.imm import _layout, _to_floors, _transitions
from diffpos.tracking.state import TrackerConfig, hypothesis_floor, hypothesis_vertical

B = default_scenario().building
CFG = TrackerConfig()


def _reference(a: np.ndarray, nf: int) -> np.ndarray:
    fl, vert = hypothesis_floor(nf), hypothesis_vertical(nf)
    to_floor = (fl[None, :] == np.arange(nf)[:, None]).astype(np.float64)  # (F, H)
    same_mode = (vert[:, None] == vert[None, :]).astype(np.float64)
    return np.einsum("nhf,fk->nhk", a, to_floor) * same_mode


def test_floor_spread_is_the_einsum_bit_for_bit():
    rng = np.random.default_rng(0)
    for nf in (1, 2, 5, 7):
        _, _, same_mode, to_floor, _, _, _, _ = _layout(nf)
        move = rng.random((9, 2 * nf, nf)) * (rng.random((9, 2 * nf, nf)) < 0.5)
        jump = rng.random((9, 2 * nf, nf)) * 1e-5
        cf, cj = _to_floors(move, jump, hypothesis_floor(nf), to_floor, same_mode)
        assert cf.tobytes() == _reference(move, nf).tobytes()
        assert cj.tobytes() == _reference(jump, nf).tobytes()
        move[3, 1, 0] = np.nan  # not finite: the einsum itself (NaN in every column)
        cf, _ = _to_floors(move, jump, hypothesis_floor(nf), to_floor, same_mode)
        ref = _reference(move, nf)
        assert np.array_equal(cf, ref, equal_nan=True)
        assert np.isnan(cf[3, 1]).sum() == np.isnan(ref[3, 1]).sum() > (1 if nf > 1 else 0)


def test_transitions_match_the_einsum_form():
    """The transitions of states at and between floors (heights spread over the building,
    height variances 1e-4..1 m^2, dt 0.05..2 s) equal those of the einsum form: ``pi``,
    ``pi_move`` and the jump part bit for bit."""
    rng = np.random.default_rng(1)
    nf = B.n_floors
    n = 40
    mean = np.zeros((n, 2 * nf, 6))
    mean[..., 2] = rng.uniform(B.first_floor_z_m - 1.0,
                               B.first_floor_z_m + nf * B.floor_height_m + 1.0, (n, 2 * nf))
    cov = np.broadcast_to(np.eye(6), (n, 2 * nf, 6, 6)) * rng.uniform(1e-4, 1.0,
                                                                      (n, 2 * nf, 1, 1))
    dt = rng.uniform(0.05, 2.0, n)
    pi, pi_move, pi_jump = _transitions(mean, cov, dt, B, CFG)
    adj, other, _, _, same_floor, start, _, _ = _layout(nf)
    fl, vert = hypothesis_floor(nf), hypothesis_vertical(nf)
    d = np.maximum(dt, 0.0)[:, None, None]
    zf = B.floor_z_m(np.arange(nf))
    lo, hi = zf + CFG.z_margin_m, zf + B.floor_height_m - CFG.z_margin_m
    z = mean[:, :, None, 2]
    gap = np.maximum(np.maximum(lo[None, None, :] - z, z - hi[None, None, :]), 0.0)
    reach = gap - d * CFG.v_stairs_m_s
    near = np.exp(-0.5 * np.maximum(reach, 0.0) ** 2 / np.maximum(cov[:, :, None, 2, 2], 1e-6))
    move = adj * np.minimum(d * CFG.v_stairs_m_s / B.floor_height_m, 0.45) * near
    jump = other * (np.minimum(d * CFG.jump_rate_hz, 0.05) / max(nf - 1, 1))
    assert pi_jump.tobytes() == _reference(jump, nf).tobytes()
    cross_f = _reference(move, nf)
    assert np.all((pi_move - cross_f)[..., ~np.eye(2 * nf, dtype=bool) & (same_floor == 0)]
                  == 0.0)
    assert np.array_equal(pi[..., fl[None, :] != fl[:, None]],
                          (cross_f + pi_jump)[..., fl[None, :] != fl[:, None]])
    assert np.all(pi_move[:, ~vert][:, :, vert][:, np.eye(nf, dtype=bool)] == 0.0)
    assert start[~vert][:, vert].all()
