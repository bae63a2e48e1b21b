"""``diffpos replay --shards N`` (the replay core's ``shards`` what-if) through the CLI: the
option reaches the replay (the report's cores are N per live shard) and the text report prints
the shards note; out-of-range counts are an options error (exit 2)."""

from __future__ import annotations

import json

import pytest
from diffpos_services.cli.main import main as cli_main
from diffpos_services.replay.synthetic import write_late_recording


@pytest.fixture(scope="module")
def sharded(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli-shards") / "sharded.mcap"
    write_late_recording(path, n_anchors=4, n_nodes=4, duration_s=2.0, late_fraction=0.1,
                         seed=3, shards=2)
    return path


def _json_report(capsys, *argv: str) -> dict:
    assert cli_main(["replay", *argv, "--no-files", "--no-progress", "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_shards_option_reaches_the_replay(sharded, capsys):
    default = _json_report(capsys, str(sharded))["shards"]
    assert (default["live"], default["replayed"], default["note"]) == (2, 2, None)
    assert default["cores"] == [["0/2"], ["1/2"]]
    one = _json_report(capsys, str(sharded), "--shards", "1")["shards"]
    assert (one["live"], one["replayed"]) == (2, 1)
    assert one["cores"] == [["0/1"], ["0/1"]]
    three = _json_report(capsys, str(sharded), "--shards", "3")["shards"]
    assert three["cores"] == [["0/3", "1/3", "2/3"]] * 2


def test_text_report_prints_the_shards_note(sharded, capsys):
    assert cli_main(["replay", str(sharded), "--shards", "1", "--no-files",
                     "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "fusion shards: replayed as 1 fusion shard(s) instead of the live 2" in out
    assert cli_main(["replay", str(sharded), "--no-files", "--no-progress"]) == 0
    assert "fusion shards:" not in capsys.readouterr().out  # as live: no note


def test_shards_out_of_range_is_an_options_error(sharded, capsys):
    assert cli_main(["replay", str(sharded), "--shards", "0", "--no-files",
                     "--no-progress"]) == 2
    assert "shards=0" in capsys.readouterr().err
