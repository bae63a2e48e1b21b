"""benchmarks/common.py score_recording on a ``diffpos replay --write-mcap`` output: that file
holds the input's live estimates (copied) and the replay's own (``replay/node/*/estimate``);
``replayed=True`` scores the replay's, the default the live ones. A replay with another method
(LLS on a recording made with D-NLS) must show the replay's figures, not the live run's."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
from common import score_recording  # noqa: E402


def test_replayed_estimates_are_scored_apart_from_the_live_ones(tmp_path):
    src = ROOT / "recordings" / "sample.mcap"
    out = tmp_path / "replay.mcap"
    subprocess.run([sys.executable, "-m", "diffpos_services.cli.main", "replay", str(src),
                    "--no-files", "--no-progress", "--method", "lls", "--write-mcap", str(out)],
                   check=True, capture_output=True)
    live_in, live_out = score_recording(src), score_recording(out)
    rep = score_recording(out, replayed=True)
    assert live_out == {**live_in, "latency_ms": live_out["latency_ms"]}
    assert rep["node_epochs"] == live_in["node_epochs"]
    # the replayed estimates are LLS fixes (every one OK_UNVERIFIED: no gating), the live
    # ones D-NLS (OK / GATING_FAILED); their floors differ by tens of points
    assert set(rep["status"]) == {"OK_UNVERIFIED"}
    assert "OK_UNVERIFIED" not in live_in["status"]
    assert abs(rep["floor"] - live_in["floor"]) > 0.2
