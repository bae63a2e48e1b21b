"""Bad options of ``diffpos emulate`` / ``diffpos anchor`` (issue 15, item 12): one line naming
the option, exit 2, no traceback, nothing started.

In this process (``cli.main.main``); the same as real ``diffpos`` processes, the anchor's
unreachable router and the dashboard's liveliness token on a real Zenoh bus are
tests/system/test_emulate_options_process.py."""

from __future__ import annotations

import argparse
import logging
import threading
from pathlib import Path

import pytest
from diffpos_services.bus.commands import recorder_args
from diffpos_services.cli import fusion as cli_fusion
from diffpos_services.cli import main as cli
from diffpos_services.cli import recorder as cli_recorder
from diffpos_services.emulate.options import EmulationOptions, recorder_argv
from diffpos_services.emulate.orchestrator import Emulation
from diffpos_services.errors import ConfigError
from diffpos_services.recorder import build_command
from diffpos_services.scenario_io import load_scenario_option


@pytest.mark.parametrize(("dashboard", "names"), [
    (["save"], "--dashboard save"),
    (["save", "a.rrd", "b.rrd"], "--dashboard save a.rrd b.rrd"),
    (["serve", "x.rrd"], "--dashboard serve x.rrd"),
    (["sve"], "--dashboard sve"),
])
def test_dashboard_option_checked_before_anything_starts(dashboard, names):
    with pytest.raises(ConfigError, match=names):
        EmulationOptions(dashboard=dashboard).check()


def test_dashboard_save_to_a_directory_refused(tmp_path):
    with pytest.raises(ConfigError, match="is a directory"):
        EmulationOptions(dashboard=["save", str(tmp_path)]).check()


def test_emulate_dashboard_save_without_path_is_one_line_exit_2_in_process(capsys):
    """Through cli.main in this process; as a real process (and an unreachable router for
    ``diffpos anchor``): tests/system/test_emulate_options_process.py."""
    assert cli.main(["emulate", "--dashboard", "save", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 1, err
    assert "diffpos emulate: error: --dashboard save" in err and "--rerun" not in err, err
    # validated before any process started (no router, no "starting" line)
    assert "starting" not in err and "waiting for the router" not in err


def test_emulate_bad_endpoint_is_one_line_exit_2_in_process(capsys):
    assert cli.main(["emulate", "--endpoint", "foo", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 1, err
    assert "diffpos emulate: error: --endpoint 'foo' is not a Zenoh endpoint" in err, err
    assert "starting" not in err


def test_fusion_started_by_emulate_accepts_only_the_scenarios_anchors_and_emulated_nodes():
    """A foreign anchor (``uav9``) on the emulate bus is rejected by the fusion as an unknown
    anchor: emulate passes the scenario's anchors as its allow-list (and the recorded run
    configuration says so, for replay); likewise the nodes it emulates (``--max-nodes``
    included), whose estimate publishers the fusion then declares before the run."""
    emu = Emulation(EmulationOptions(record="off", dashboard=["off"]),
                    logging.getLogger("test"), threading.Event())
    i = emu.fusion_args.index("--anchors")
    assert emu.fusion_args[i + 1].split(",") == emu.anchor_ids == ["uav1", "uav2", "uav3", "uav4"]
    assert list(emu.fusion_config.anchors) == emu.anchor_ids
    ids = [nid for nid, _ in emu.nodes]
    assert len(ids) == 6 and list(emu.fusion_config.nodes) == ids
    few = Emulation(EmulationOptions(record="off", dashboard=["off"], max_nodes=2),
                    logging.getLogger("test"), threading.Event())
    assert list(few.fusion_config.nodes) == ids[:2]



REPO = Path(__file__).resolve().parents[2]
#: Linux's limit on one argument of a process started (MAX_ARG_STRLEN, with its NUL) [bytes]
_MAX_ARG_BYTES = 32 * 4096


@pytest.mark.parametrize("max_nodes", [0, 2000, 3])
def test_a_node_list_too_long_for_a_command_line_is_not_written_on_it(tmp_path, max_nodes):
    """2,100 nodes with 64-character ids (136,500 characters as a list): a process with that
    argument cannot be started (E2BIG), so emulate's fusion gets ``--nodes scenario`` (all
    of the scenario's nodes emulated), or no allow-list (2,000 of them: still too long), or
    the short list (3); the config the real fusion CLI parses is the one emulate records,
    and its allow-list is exactly the emulated nodes (or none)."""
    text = (REPO / "scenarios" / "large.toml").read_text()
    ids = [f"node-{i:04d}-" + "x" * 54 for i in range(2100)]
    assert {len(i) for i in ids} == {64}
    body = "".join(f'\n[[nodes.list]]\nid = "{nid}"\nposition_m = [{-15 + 0.01 * k:.2f}, 5.0, '
                   f'5.5]\n' for k, nid in enumerate(ids))
    path = tmp_path / "many.toml"
    path.write_text(text[:text.index("[[nodes.list]]")] + body)
    emu = Emulation(EmulationOptions(record="off", dashboard=["off"], scenario=str(path),
                                     max_nodes=max_nodes), logging.getLogger("test"),
                    threading.Event())
    assert all(len(a.encode()) < _MAX_ARG_BYTES for a in emu.fusion_args)
    ap = argparse.ArgumentParser()
    cli_fusion.add_arguments(ap)
    args = ap.parse_args(emu.fusion_args)
    assert cli_fusion.config_from_args(args, load_scenario_option(args.scenario)) == \
        emu.fusion_config
    want = {0: ids, 2000: None, 3: ids[:3]}[max_nodes]
    got = emu.fusion_config.nodes
    assert (None if got is None else list(got)) == want


@pytest.mark.parametrize(("speed", "method", "workers"), [(1.0, None, 1), (0.0, None, 1),
                                                          (0.0, "mnls", 2), (5.0, "dnls", 1),
                                                          (1.0, None, 3)])
def test_the_recorded_fusion_config_is_the_one_the_fusion_parses(speed, method, workers):
    """The run configuration emulate records for replay (``Emulation.fusion_config``) equals
    the config the fusion process builds from emulate's ``fusion_args`` with the real
    ``diffpos fusion`` CLI, lockstep (``--speed 0``: no overload policy) or not: a replay by
    the decision record uses the recorded one, so any difference (e.g. max_backlog_s,
    supersede_after_s) would make it drop other epochs than the live fusion."""
    emu = Emulation(EmulationOptions(record="off", dashboard=["off"], speed=speed,
                                     method=method, fusion_workers=workers),
                    logging.getLogger("test"), threading.Event())
    ap = argparse.ArgumentParser()
    cli_fusion.add_arguments(ap)
    args = ap.parse_args(emu.fusion_args)
    parsed = cli_fusion.config_from_args(args, load_scenario_option(args.scenario))
    assert parsed == emu.fusion_config
    assert (emu.fusion_config.max_backlog_s is None) == (speed == 0)
    assert emu.fusion_config.workers == workers


@pytest.mark.parametrize("workers", [0, -1, 65])
def test_fusion_workers_out_of_range_is_a_config_error(workers):
    """``--fusion-workers`` outside [1, MAX_WORKERS] is refused before anything starts."""
    with pytest.raises(ConfigError, match="--fusion-workers"):
        EmulationOptions(fusion_workers=workers).check()


# ------------------------------------------------------------------ one recorder command line
def test_recorder_command_line_is_built_once():
    """emulate's recorder argv and recorder.build_command are both bus.commands.recorder_args;
    the argv parses with the real recorder CLI into the values given."""
    o = EmulationOptions(record="r.mcap", scenario="scenarios/paper.toml", site="s1")
    argv = recorder_argv(o, "tcp/127.0.0.1:7", "run")
    assert argv == recorder_args(site="s1", out="r.mcap", connect=["tcp/127.0.0.1:7"],
                                 scenario="scenarios/paper.toml")
    cmd = build_command(site="s1", out="r.mcap", connect=["tcp/127.0.0.1:7"],
                        scenario="scenarios/paper.toml", flush_interval_s=0.1,
                        split_duration_s=5, split_size_mb=0, status=True, python="py")
    assert cmd[:3] == ["py", "-m", "diffpos_services.cli.main"]
    assert cmd[3:] == recorder_args(site="s1", out="r.mcap", connect=["tcp/127.0.0.1:7"],
                                    scenario="scenarios/paper.toml", flush_interval_s=0.1,
                                    split_duration_s=5, split_size_mb=0, status=True)
    parser = argparse.ArgumentParser()
    cli_recorder.add_arguments(parser)
    a = parser.parse_args(cmd[4:])
    assert (a.site, a.out, a.connect, a.scenario, a.flush_interval, a.split_duration,
            a.split_size, a.status) == ("s1", "r.mcap", ["tcp/127.0.0.1:7"],
                                        "scenarios/paper.toml", 0.1, 5.0, 0.0, True)
    assert recorder_argv(EmulationOptions(record="off"), "tcp/127.0.0.1:7", "run") is None


# ------------------------------------------------------------------ one scenario loader
@pytest.mark.parametrize(("text", "says"), [
    (None, "no such scenario file"),
    ("[building\n", "TOML syntax error"),
    ("[building]\nwidth_m = -3\n", "building"),
])
def test_scenario_option_errors_are_one_config_error_naming_option_and_file(tmp_path, text, says):
    """anchor, fusion and emulate load --scenario with scenario_io.load_scenario_option: a
    ConfigError (exit 2) naming the option, the file and the problem."""
    path = tmp_path / "s.toml"
    if text is not None:
        path.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_scenario_option(str(path))
    msg = str(exc.value)
    assert msg.startswith("--scenario") and str(path) in msg and says in msg, msg
    assert "\n" not in msg and exc.value.exit_code == 2
    with pytest.raises(ConfigError, match=str(path)):
        Emulation(EmulationOptions(scenario=str(path), record="off", dashboard=["off"]),
                  logging.getLogger("t"), threading.Event())
    assert load_scenario_option(None).anchors  # the built-in paper scenario
