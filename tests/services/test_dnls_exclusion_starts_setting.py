"""The starts of a cold D-NLS fix's exclusion candidates are a recorded fusion setting
(``dnls_exclusion_starts``): ``diffpos fusion --dnls-exclusion-starts`` and ``diffpos replay
--set dnls_exclusion_starts=...`` set it, the recording's settings keep it, a replay runs the
value that ran live; new runs use ``"local"`` (since 2026-12-07), recordings made before the
setting replay with ``"grid"``."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
from diffpos_services.cli import fusion as cmd_fusion
from diffpos_services.cli.main import main
from diffpos_services.fusion.config import (
    DEFAULT_DNLS_EXCLUSION_STARTS,
    LEGACY_DNLS_EXCLUSION_STARTS,
    FusionConfig,
    with_legacy_defaults,
)
from diffpos_services.recording.reader import side_records
from diffpos_services.replay import synthetic
from diffpos_services.replay.run import replay

from diffpos.scenario import default_scenario


def test_default_legacy_value_and_fusion_option():
    assert FusionConfig().dnls_exclusion_starts == DEFAULT_DNLS_EXCLUSION_STARTS == "local"
    old = with_legacy_defaults({"method": "dnls", "gating": True})
    assert old["dnls_exclusion_starts"] == LEGACY_DNLS_EXCLUSION_STARTS == "grid"
    kept = with_legacy_defaults({"method": "dnls", "dnls_exclusion_starts": "local"})
    assert kept["dnls_exclusion_starts"] == "local"
    # a recording without stored settings was made before the setting: grid
    derived = FusionConfig.from_recording({"site": "demo"}, default_scenario())
    assert derived.dnls_exclusion_starts == "grid"
    p = argparse.ArgumentParser()
    cmd_fusion.add_arguments(p)
    cfg = cmd_fusion.config_from_args(p.parse_args(["--method", "dnls", "--dnls-exclusion-starts",
                                                    "local"]), default_scenario())
    assert cfg.dnls_exclusion_starts == "local"
    default = cmd_fusion.config_from_args(p.parse_args([]), default_scenario())
    assert default.dnls_exclusion_starts == "local"
    with pytest.raises(SystemExit):
        p.parse_args(["--dnls-exclusion-starts", "grid2"])
    help_text = p.format_help()
    assert "--dnls-exclusion-starts" in help_text and "default" in help_text


def _write(path, monkeypatch, starts: str):
    """5 anchors, 3 nodes, 3 s, 15 % outliers (cold fixes with exclusion candidates); the live
    fusion runs with ``starts`` and the recording keeps its settings."""
    with monkeypatch.context() as m:
        m.setitem(synthetic.SYNTHETIC_FUSION, "dnls_exclusion_starts", starts)
        synthetic.write_synthetic_recording(path, n_anchors=5, n_nodes=3, duration_s=3.0,
                                            outlier_probability=0.15, seed=3, flush_every=200)


def _fixes(r):
    return {(e.node_id, e.epoch): (e.status, tuple(e.used_anchors or ()), e.position_m)
            for e in r.estimates}


def _moved(a, b):
    assert a.keys() == b.keys()
    return [float(np.linalg.norm(np.subtract(a[k][2], b[k][2]))) for k in a
            if a[k][2] is not None and b[k][2] is not None]


def test_a_live_run_with_local_replays_with_it(tmp_path, monkeypatch):
    rec = tmp_path / "local.mcap"
    _write(rec, monkeypatch, "local")
    md = {m.name: m.metadata for m in side_records(rec).metadata}
    assert md["fusion_config"]["dnls_exclusion_starts"] == "local"
    same = replay(rec, out_mcap=None)
    assert same.report["settings"]["dnls_exclusion_starts"] == "local"
    assert same.report["compare"]["position_diff_m"]["max"] == 0.0  # live ran the same
    grid = replay(rec, out_mcap=None, overrides={"dnls_exclusion_starts": "grid"})
    assert grid.report["settings"]["dnls_exclusion_starts"] == "grid"
    moved = _moved(_fixes(same), _fixes(grid))
    # the candidates' starts differ, the anchors they exclude do not on this data: the same
    # fixes within 1 mm, but not the same bits (the value reached the solver)
    assert 0.0 < max(moved) < 1e-3


def test_replay_set_runs_it_and_the_written_mcap_records_it(tmp_path, monkeypatch, capsys):
    rec = tmp_path / "grid.mcap"
    _write(rec, monkeypatch, "grid")
    out = tmp_path / "replayed.mcap"
    assert main(["replay", str(rec), "--no-files", "--no-progress", "--set",
                 "dnls_exclusion_starts=local", "--write-mcap", str(out)]) == 0
    capsys.readouterr()
    md = {m.name: m.metadata for m in side_records(out).metadata}
    settings = json.loads(md["replay"]["settings"])
    assert settings["dnls_exclusion_starts"] == "local"
    # the written copy keeps what ran live beside it
    assert md["fusion_config"]["dnls_exclusion_starts"] == "grid"
    # the replay of the written settings (read back from the MCAP) is the replay with --set
    local = replay(rec, out_mcap=None, overrides=settings)
    by_set = replay(rec, out_mcap=None, overrides={"dnls_exclusion_starts": "local"})
    assert _fixes(local) == _fixes(by_set)
    live = replay(rec, out_mcap=None)
    assert max(_moved(_fixes(by_set), _fixes(live))) > 0.0

