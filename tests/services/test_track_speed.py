"""A wrong fix must not turn later ranges negative through motion compensation (issue 15,
item 14).

``diffpos replay recordings/sample.mcap --no-gating --pfa 1e-4 --method lls`` marked 40 of
720 fixes INVALID_INPUT "ranges_m contains a negative range" although the smallest recorded
range is 10.74 m: an unverified LLS fix of node r05 ~1.4 km off gave its track a velocity of
4.4 km/s; ``fusion.step.prepare`` compensated the next epochs' ranges with it
(``r - (J . v) dt``, 110 m at dt = 25 ms), and the track, never updated by the INVALID_INPUT
fixes, kept that velocity. The fix (fusion/step.py): a track velocity above
``MAX_TRACK_SPEED_M_S`` is neither extrapolated nor used for compensation.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from diffpos_services.fusion import step
from diffpos_services.fusion.config import FusionConfig
from diffpos_services.fusion.ingest import Track
from diffpos_services.replay.run import replay

from diffpos.alignment import PendingEpoch

SAMPLE = Path(__file__).resolve().parents[2] / "recordings" / "sample.mcap"
_PENDING = ("needs the fusion/step.py diff of issue 15 item 14 (MAX_TRACK_SPEED_M_S); "
            "remove this marker when it is applied")
_HAS_FIX = hasattr(step, "MAX_TRACK_SPEED_M_S")


@pytest.mark.xfail(not _HAS_FIX, reason=_PENDING, strict=True)
def test_an_absurd_track_velocity_is_not_used():
    tr = Track()
    tr.update(1_000_000_000, [0.0, 5.0, 6.0])
    tr.update(1_100_000_000, [-18.0, -92.0, 443.0])  # a fix 440 m off: 4.4 km/s
    assert tr.vel is not None
    cfg = FusionConfig()
    epochs = [PendingEpoch("r05", 12, 0)]
    x0, vel, has_vel = step._start_points(epochs, {"r05": tr}, np.array([1_200_000_000]), cfg)
    assert not has_vel[0], vel
    assert np.all(vel == 0.0)
    assert x0[0].tolist() == [-18.0, -92.0, 443.0]  # warm start: the last fix, not extrapolated


def test_a_plausible_track_velocity_is_still_used():
    tr = Track()
    tr.update(1_000_000_000, [0.0, 5.0, 6.0])
    tr.update(1_100_000_000, [0.1, 5.0, 6.0])  # 1 m/s
    x0, vel, has_vel = step._start_points([PendingEpoch("n", 12, 0)], {"n": tr},
                                           np.array([1_200_000_000]), FusionConfig())
    assert has_vel[0]
    assert vel[0] == pytest.approx([1.0, 0.0, 0.0])
    assert x0[0] == pytest.approx([0.2, 5.0, 6.0])


@pytest.mark.xfail(not _HAS_FIX, reason=_PENDING, strict=True)
def test_replay_of_the_sample_with_lls_has_no_negative_ranges():
    assert SAMPLE.is_file(), SAMPLE
    res = replay(SAMPLE, overrides={"gating": False, "false_alarm_probability": 1e-4},
                 method="lls")
    status = [e.status for e in res.estimates]
    assert len(status) == 720
    assert "INVALID_INPUT" not in status, sorted(set(status))
