"""``diffpos emulate --tracker KEY=VALUE`` with real processes (issue 33, item 3): the fusion
process runs the given tracker settings, the recording's fusion settings hold every tracker
setting under ``tracker``, a replay of it runs that tracker (every live position reproduced
bit for bit, by the live fusion's decision record) and ``--set tracker.KEY=VALUE`` back to
the default changes the estimates. The in-process checks: tests/services/test_tracker_settings.py.
"""

from __future__ import annotations

import dataclasses
import json

import pytest
from diffpos_services.recording.reader import side_records
from diffpos_services.replay.run import replay

from diffpos.tracking.state import TrackerConfig

pytestmark = pytest.mark.slow

DEFAULTS = dataclasses.asdict(TrackerConfig())


def test_emulate_records_its_tracker_settings_and_replay_runs_them(services, tmp_path):
    mcap = tmp_path / "run.mcap"
    p = services.start("emulate", "emulate", "--duration", "3", "--speed", "0",
                       "--record", str(mcap), "--dashboard", "off", "--no-progress",
                       "--tracker", "sigma_model_m=0.1", "--tracker", "nis_limit=12")
    assert p.wait(timeout=600) == 0, services.log("emulate")[-3000:]
    md = {m.name: m.metadata for m in side_records(mcap).metadata}
    recorded = json.loads(md["run_config"]["fusion"])
    assert recorded["method"] == "mnls" and recorded["tracking"] is True
    assert recorded["tracker"] == {**DEFAULTS, "sigma_model_m": 0.1, "nis_limit": 12.0}

    r = replay(mcap, keep_estimates=False)
    assert r.report["settings"]["tracker"] == recorded["tracker"]
    assert r.report["tracker_settings"] is None
    c = r.report["compare"]
    assert c["only_live"] == c["only_replayed"] == 0
    assert c["with_positions"] >= 0.8 * c["matched"] > 0
    assert c["identical_positions"] == c["with_positions"], c

    what_if = replay(mcap, keep_estimates=False,
                     overrides={"tracker": {"sigma_model_m": DEFAULTS["sigma_model_m"]}})
    assert what_if.report["settings"]["tracker"] == DEFAULTS | {"nis_limit": 12.0}
    w = what_if.report["compare"]
    assert w["identical_positions"] < 0.5 * w["with_positions"], w
