"""The tracker's masked SNR prediction (``channel.snr_nb.eval_snr_masked_kernel``) split over
the kernel threads: every output bit for bit the one-thread call's (raw bytes, NaN of the
slots not needed included), on random pairs of two buildings other than the shipped ones
(anchors above the windows and beyond the facade ends) with random masks, and the call really
split (chunks of at least ``MASKED_MIN_PAIRS`` pairs)."""

from __future__ import annotations

import numpy as np
import pytest
from test_kernel_threads import _BUILDINGS, _RADIO, restore_threads  # noqa: F401 (a fixture)

from diffpos._kernels import pool
from diffpos.channel import snr_nb
from diffpos.channel.emulator import pair_snr_db


def _pairs(b, seed, n):
    rng = np.random.default_rng(seed)
    x0, x1 = b.edge_x_m
    floor = rng.integers(0, b.n_floors, n)
    nodes = np.stack([rng.uniform(x0 + 2, x1 - 2, n), rng.uniform(0.3, b.depth_m - 1, n),
                      b.floor_z_m(floor) + rng.uniform(0.1, b.floor_height_m - 0.1, n)], -1)
    anc = np.stack([rng.uniform(x0 - 15, x1 + 15, (n, 1)), rng.uniform(-40, -2, (n, 1)),
                    rng.uniform(0, b.floor_z_m(b.n_floors - 1) + 8, (n, 1))], -1)
    need = rng.random((n, 1, 18)) < 0.4
    return anc, nodes, need


@pytest.mark.usefixtures("restore_threads")
@pytest.mark.parametrize("bi", [0, 1])
def test_masked_prediction_two_threads_bit_identical(bi, monkeypatch):
    b = _BUILDINGS[bi]
    n = 6 * snr_nb.MASKED_MIN_PAIRS + 37
    anc, nodes, need = _pairs(b, 10 + bi, n)
    pool.set_threads(1)
    ref = pair_snr_db(anc, nodes, building=b, radio=_RADIO, need=need)
    chunks: list[int] = []
    real = snr_nb.run_rows

    def spy(f, n_rows, *, min_rows=1):
        def rec(lo, hi):
            chunks.append(hi - lo)
            f(lo, hi)
        return real(rec, n_rows, min_rows=min_rows)

    monkeypatch.setattr(snr_nb, "run_rows", spy)
    pool.set_threads(2)
    got = pair_snr_db(anc, nodes, building=b, radio=_RADIO, need=need)
    assert len(chunks) >= 2 and min(chunks) >= snr_nb.MASKED_MIN_PAIRS
    assert sum(chunks) == n
    assert got.tobytes() == ref.tobytes()
    assert np.isnan(got[~need]).all() and not np.isnan(got[need]).any()
