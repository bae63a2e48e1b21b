"""The anchor publishes its ranges as one RangeBatch per epoch when it ranges many nodes.

Per-range messages cost the fusion ~11 us of CPU more per range than the same range in a
batch (benchmarks/bench_latency.py, docstring of BATCH_MIN_NODES), so an anchor ranging more
than ``BATCH_MIN_NODES`` nodes batches by default; ``range_batch`` True/False forces either.
"""

from __future__ import annotations

import numpy as np
import pytest
from diffpos_services.anchor.service import BATCH_MIN_NODES, AnchorConfig, AnchorEmulator
from diffpos_services.cli.anchor import config_from_args
from diffpos_services.cli.main import build_parser
from diffpos_services.scenario_io import load_scenario_option

from diffpos.emulation import TimeBase


def _scenario(tmp_path, n_nodes: int):
    lines = ['name = "batching"', "[building]", "first_floor_z_m = 4.0", "floor_height_m = 3.0",
             "n_floors = 3", "sill_height_m = 0.75", "window_height_m = 1.5",
             "[[anchors]]", 'id = "uav1"', "position_m = [0.0, -12.0, 2.0]"]
    for i in range(n_nodes):
        lines += ["[[nodes.list]]", f'id = "n{i}"',
                  f"position_m = [{-10.0 + i * 0.5:.2f}, 6.0, 5.5]"]
    path = tmp_path / f"s{n_nodes}.toml"
    path.write_text("\n".join(lines) + "\n")
    return load_scenario_option(str(path))


@pytest.mark.parametrize(("n_nodes", "setting", "batched"), [
    (BATCH_MIN_NODES, None, False),
    (BATCH_MIN_NODES + 1, None, True),
    (BATCH_MIN_NODES + 1, False, False),
    (2, True, True),
])
def test_anchors_batch_by_default_above_the_node_threshold(tmp_path, n_nodes, setting, batched):
    emu = AnchorEmulator(_scenario(tmp_path, n_nodes),
                         AnchorConfig(anchor_id="uav1", channel="ideal", range_batch=setting))
    assert len(emu.nodes) == n_nodes
    assert emu.batched is batched


@pytest.mark.parametrize(("flag", "value"), [([], None), (["--range-batch"], True),
                                             (["--no-range-batch"], False)])
def test_cli_range_batch_flag_is_tristate(flag, value):
    args = build_parser("anchor").parse_args(["--id", "uav1", *flag])
    assert config_from_args(args).range_batch is value


def test_static_nodes_cached_give_the_same_measurements_as_evaluating_every_node():
    """The emulator takes static nodes' positions once (not one trajectory call per node and
    epoch): the measurements equal those with every node's trajectory evaluated, bit for bit
    (large scenario: static and moving nodes, emulator channel, same seed)."""
    sc = load_scenario_option("scenarios/large.toml")
    cfg = AnchorConfig(anchor_id=sc.anchors[0].id, seed=3)
    fast, slow = AnchorEmulator(sc, cfg), AnchorEmulator(sc, cfg)
    assert 0 < len(fast._moving) < len(fast.nodes)  # both kinds present
    slow._moving = list(range(len(slow.nodes)))  # every node evaluated (the reference)
    tb = TimeBase.free_running(1_800_000_000_000_000_000)
    for k in range(3):
        _, a = fast.measure_block(k, 1, tb)
        _, b = slow.measure_block(k, 1, tb)
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)
