"""Issue 14's bar on geometries that are not in scenarios/: a lockstep `diffpos emulate` of
the default fusion gives a position for >= 90 % of the node-epochs after the first 2 s and
the right floor for >= 80 % of ALL of them (the summary's scorer, `diffpos.metrics`).

The geometries: samples of the seeded held-out generator (`benchmarks/heldout.py`, seed 2,
not one of the seeds the README's sweep reports, not tuned for; rand-2-0: a 7-floor building
with the paper's four UAVs, all below its windows; rand-2-2: only three UAVs, one beyond a
facade end), a one-floor building and a building off the origin with UAVs beyond both facade
ends. Lockstep runs are seeded, but the start-up's order of events can move one by a point or
two (README, What to expect). Measured (2026-11-28 02:52 and 03:21 UTC, the same both times):
availability 100 % in all four, floor 100 % in three and 84.2 % in rand-2-0 (the cause-1
geometry of docs/heldout_geo14.md: 15 node-epochs of 360 above the bar); rand-2-0 alone 16
more times, 10 of them two at once beside two busy loops: 83.3-84.2 %. A failure there may
still be a start-up order rather than a change: check its log before blaming the change."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import bench_accuracy
import heldout

pytestmark = pytest.mark.slow

PAPER = Path(__file__).resolve().parents[2] / "scenarios" / "paper.toml"


def _one_floor() -> str:
    return re.sub(r"(?m)^n_floors = 5.*$", "n_floors = 1", PAPER.read_text())


def _offset() -> str:
    """The paper's building centred at x = 30 m, its walls and UAVs moved with it, and two
    more UAVs beyond the facade ends (x = 30 -/+ 26 m)."""
    d = bench_accuracy.variants()["anchors-beyond-ends"]
    d = json.loads(json.dumps(d))
    d["name"] = "offset"
    d["building"]["center_x_m"] = 30.0
    for p in d["building"]["partitions"]:
        if p["axis"] == "x":
            p["position_m"] += 30.0
        else:
            p["span_m"] = [s + 30.0 for s in p["span_m"]]
    for a in d["anchors"]:
        a["position_m"][0] += 30.0
    return heldout.to_toml(d)


CASES = {
    "rand-2-0": lambda: heldout.to_toml(heldout.random_scenario(2, 0)),
    "rand-2-2": lambda: heldout.to_toml(heldout.random_scenario(2, 2)),
    "one-floor": _one_floor,
    "offset-beyond-ends": _offset,
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_default_fusion_on_a_held_out_geometry(services, tmp_path, name):
    scenario = tmp_path / f"{name}.toml"
    scenario.write_text(CASES[name]())
    summary_path = tmp_path / "summary.json"
    p = services.start("emulate", "emulate", str(scenario), "--duration", "8", "--speed", "0",
                       "--record", "off", "--dashboard", "off", "--json", str(summary_path),
                       "--no-progress", "--log-dir", str(tmp_path / "logs"))
    rc = p.wait(timeout=240)  # inside the suite's 300 s per-test timeout
    assert rc == 0, services.log("emulate")[-3000:]
    s = json.loads(summary_path.read_text())
    assert s["node_epochs"] == s["nodes"] * 60  # 8 s at 10 Hz, the first 2 s skipped
    assert s["availability"] >= 0.9, s
    assert s["floor_accuracy"] >= 0.8, s
