"""benchmarks/bench_channel_mix.py --live's scenario copies: a shipped scenario (by name) and a
file with explicit moving nodes written back with only ``radio.channel_max_order`` changed
(the loader's own parse of the copy against the original), and never over an existing file."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import pytest
from diffpos_services.scenario_io import load_scenario, resolve_scenario

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import bench_channel_mix as B


@pytest.mark.parametrize("name", ["paper", "large"])
@pytest.mark.parametrize("order", [2, 3, 4])
def test_order_copy_changes_only_the_channel_order(tmp_path, name, order):
    src = load_scenario(resolve_scenario(name))
    path = B.order_copy(name, order, tmp_path)
    assert path == tmp_path / f"{name}-o{order}.toml"
    got = load_scenario(path)
    assert got.radio.channel_max_order == order
    assert got.radio == dataclasses.replace(src.radio, channel_max_order=order)
    assert (got.building, got.anchors, got.nodes, got.node_grid) == (
        src.building, src.anchors, src.nodes, src.node_grid)


def test_order_copy_never_writes_over_a_file(tmp_path):
    path = tmp_path / "paper-o3.toml"
    path.write_text("keep me")
    with pytest.raises(FileExistsError, match=r"paper-o3\.toml exists"):
        B.order_copy("paper", 3, tmp_path)
    assert path.read_text() == "keep me"
