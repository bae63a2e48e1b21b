"""Tracker settings are fusion settings (issue 33, item 3).

``FusionConfig.tracker`` carries every field of :class:`diffpos.tracking.state.TrackerConfig`;
``diffpos fusion`` / ``diffpos emulate`` take ``--tracker KEY=VALUE``, ``diffpos replay`` takes
``--set tracker.KEY=VALUE``; the recorded fusion settings hold them under ``tracker``, so a
replay runs the tracker that ran live, and a recording made before they were recorded
replays with the defaults it ran with, which the report says.

The live runs here are in-process: the seeded synthetic inputs of
:func:`~diffpos_services.replay.synthetic.synthetic_run` (5 hovering anchors, 3 walkers,
3 s) through a :class:`FusionCore` with mnls + tracking, written like the recorder does (run
metadata with ``started_ns``, ``fusion_config``, liveliness, inputs). The same with real
processes (``diffpos emulate --tracker``): tests/system/test_tracker_settings_emulate.py.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import logging
import threading

import msgspec
import pytest
from diffpos_services.cli import emulate as cli_emulate
from diffpos_services.cli import fusion as cli_fusion
from diffpos_services.cli import main as cli
from diffpos_services.cli import replay as cli_replay
from diffpos_services.config import build_config
from diffpos_services.emulate.options import EmulationOptions
from diffpos_services.emulate.orchestrator import Emulation
from diffpos_services.errors import ConfigError
from diffpos_services.fusion.config import (
    TRACKER_KEYS,
    FusionConfig,
    complete_tracker,
    legacy_tracker_settings,
    parse_tracker_items,
)
from diffpos_services.fusion.core import FusionCore
from diffpos_services.recording.reader import side_records
from diffpos_services.recording.topics import parse_topic
from diffpos_services.recording.writer import McapSink
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import (
    FUSION_INPUT_KINDS,
    quiet_logger,
    synthetic_run,
    write_synthetic_recording,
)
from diffpos_services.scenario_io import load_scenario_option
from diffpos_services.wire import messages as M
from diffpos_services.wire.keys import Keys

from diffpos.tracking.state import TrackerConfig

DEFAULTS = dataclasses.asdict(TrackerConfig())
UTC = datetime.UTC
#: recording times after the tracker's last change of a default (30c1dda, 2026-11-27 13:36
#: UTC) and before it (and after 73459d9 / 2f23e13: SNR reuse, tempering, dormant added)
AFTER_NS = int(datetime.datetime(2026, 12, 1, tzinfo=UTC).timestamp()) * 10**9
BEFORE_NS = int(datetime.datetime(2026, 11, 25, tzinfo=UTC).timestamp()) * 10**9
#: the tracker defaults before 2026-11-27 08:17 UTC that a setting of today reproduces
THEN = {"snr_reuse_m": 0.0, "snr_reuse_anchor_m": 0.0, "floor_evidence_lag1_corr": 0.0,
        "dormant": False}
#: the tracker's evidence settings before ab8d4d9 (2026-12-06 07:51 UTC: learned link weights)
#: and its re-entry rules before d3f1e35 (2026-12-06 08:09 UTC: a stale track re-initialised,
#: fewer than 3 ranges not TRACKING)
#: and the published floor probabilities before f926bf5 (2026-12-06 10:19 UTC: the model doubt)
#: and the higher-order families before 431695e (2026-12-06 12:31 UTC: max_order 3, the
#: families as candidate mechanisms of the misfit links) and their gate before 182c287
#: (2026-12-06 15:30 UTC: a fit history, four ranges) and their first-arrival condition before
#: e94ad45 (2026-12-06 15:58 UTC; on by default only until 384cae1, 16:05 UTC); max_order 2
#: again from 7858211 (2026-12-06 17:06 UTC), 3 with the families' minority rule from c77e4db
#: (2026-12-06 18:23 UTC), five ranges for a family from 7103507 (2026-12-06 19:37 UTC), four
#: again where the track learned its channel has them from 52c5723 (2026-12-06 20:57 UTC)
#: the re-seed defaults before 208fb2e (2026-12-07 03:24 UTC: reseed_max 2, reseed_min_links 4)
#: the contest rule before 617a6ba (2026-12-07 04:54 UTC: floor_contest_s 3 s)
#: the detector's skipped paths before 6f921de (2026-12-07 07:58 UTC: first_arrival_prior
#: 0.8)
#: the edge retry and the persistent mechanism prior before dd88bf2 (2026-12-07 11:48 UTC:
#: edge_retry_margin_m 0.4, edge_retry_node, mechanism_prior_min_links 4, mechanism_switch_p
#: 0.3)
#: the burst re-seed and the published covariance's floor weights before 0164933 (2026-12-07
#: 14:54 UTC: reseed_outliers 2, cov_published_floors credible); every set of older defaults
#: below includes it
#: the diffraction SNR slack before 424510e (2026-12-07 17:20 UTC: snr_diffraction_slack_db 6,
#: snr_slack_max_links 3); every set of older defaults below includes it
#: the worst link's families before 2ac62e4 (2026-12-07 20:27 UTC: family_worst_min_links 4);
#: every set of older defaults below includes it
#: the floor hold of few-range nodes before 76801b1 (2026-12-07 23:50 UTC:
#: floor_hold_max_links 2); every set of older defaults below includes it
#: the family-explained link fitted at three ranges before 4c798f4 (2026-12-08 02:23 UTC:
#: family_few_links 3, family_fit_links 3, cov_few_floors temper); every set below includes it
#: the floor hypotheses following their leader before 3c15012 (2026-12-08 02:53 UTC:
#: stairs_follow 3, _settled_s 1, _m 1, _min_links 4); every set below includes it
STAIRS_OFF = {"stairs_follow": 0, "stairs_follow_settled_s": 0.0, "stairs_follow_m": 0.0,
              "stairs_follow_min_links": 0}
FIT_OFF = {"family_few_links": 0, "family_fit_links": 0, "cov_few_floors": "off",
           **STAIRS_OFF}
HOLD_OFF = {"floor_hold_max_links": 0, **FIT_OFF}
WORST_OFF = {"family_worst_min_links": 0, **HOLD_OFF}
SLACK_OFF = {"snr_diffraction_slack_db": 0.0, "snr_slack_max_links": 0, **WORST_OFF}
BURST_OFF = {"reseed_outliers": 0, "cov_published_floors": "off", **SLACK_OFF}
EDGE_OFF = {"edge_retry_margin_m": 0.0, "edge_retry_node": False,
            "mechanism_prior_min_links": 0, "mechanism_switch_p": 0.0, **BURST_OFF}
SKIP_OFF = {"first_arrival_prior": 0.0, **EDGE_OFF}
CONTEST_OFF = {"floor_contest_s": 0.0, **SKIP_OFF}
RESEED_OFF = {"reseed_max": 0, "reseed_min_links": 0, **CONTEST_OFF}
LINK_OFF = {"link_learn": False, "snr_cost_cap_nats": 0.0, "lost_on_gap": False,
            "min_anchors_tracking": 0, "floor_model_doubt": False, "max_order": 2,
            "family_weight": "outlier", "family_gate": "outlier", "family_history": 0,
            "family_min_links": 0, "family_first": False, "family_minority": False,
            "family_learned_links": 0, **RESEED_OFF}
#: the defaults before 431695e only (a recording made between f926bf5 and it); between it and
#: 2fd5568 (2026-12-06 14:17 UTC: max_order back to 2) max_order was 3, the families' gate
#: without a fit history or a minimum of ranges until 182c287 (2026-12-06 15:30 UTC: max_order
#: 3 again, with them)
GATE_OFF = {"family_history": 0, "family_min_links": 0, "family_first": False,
            "family_minority": False, "family_learned_links": 0, **RESEED_OFF}
#: the defaults before 52c5723 only (no learned family prior)
LEARNED_OFF = {"family_learned_links": 0, **RESEED_OFF}
FAMILIES_OFF = {"max_order": 2, "family_weight": "outlier", "family_gate": "outlier",
                **GATE_OFF}
#: a recording made after every change of a default
NOW_NS = int(datetime.datetime(2026, 12, 8, 2, 54, tzinfo=UTC).timestamp()) * 10**9
#: a key that must change the estimates: the model error added to every range sigma [m]
WHAT_IF = {"sigma_model_m": 0.3}


def _live(path, *, tracker=None, started_ns: int | None = AFTER_NS, record_tracker=True):
    """Run the live fusion (mnls + tracking, ``tracker`` settings) over the synthetic inputs,
    write them as the recorder would; returns the live estimates by (node, epoch)."""
    run = synthetic_run(n_anchors=5, n_nodes=3, duration_s=3.0, seed=7)
    cfg = build_config(FusionConfig, {**msgspec.to_builtins(run.config), "method": "mnls",
                                      "tracking": True, "tracker": tracker or {}})
    settings = msgspec.to_builtins(cfg)
    if not record_tracker:  # as every recording made before the settings were recorded
        del settings["tracker"]
    core, keys, out = FusionCore(cfg, logger=quiet_logger()), Keys(cfg.site), []
    with McapSink(path, library="test") as sink:
        sink.add_metadata("run", {"site": cfg.site} if started_ns is None
                          else {"site": cfg.site, "started_ns": started_ns})
        sink.add_metadata("fusion_config", settings)
        for a in run.anchor_ids:
            sink.write_liveliness(cfg.site, keys.alive_anchor(a), True, run.t0_ns - 10**7)
            core.on_liveliness(a, True, run.t0_ns - 10**7)
        last = run.t0_ns
        for items in run.epochs:
            for rx, key, payload in items:
                sink.write(key, payload, rx)
                if parse_topic(key)[0] in FUSION_INPUT_KINDS:
                    core.on_sample(key, payload, rx)
                    out += core.step(rx)
                last = rx
    out += core.step(last + 10**12) + core.flush(last)
    return _by_key(out)


def _by_key(ests) -> dict:
    """(node, epoch) -> encoded estimate without the publish-order fields."""
    return {(e.node_id, e.epoch): M.encode(msgspec.structs.replace(e, seq=0, t_pub_wall_ns=0))
            for e in ests}


def _positions(by_key: dict) -> dict:
    dec = M.estimate_decoder()
    return {k: dec(v).position_m for k, v in by_key.items()}


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    """A live run with the default tracker settings, recorded with them."""
    path = tmp_path_factory.mktemp("trk") / "default.mcap"
    return path, _live(path)


# ------------------------------------------------------------------ config and recording
def test_fusion_config_carries_every_tracker_field_with_its_default():
    cfg = FusionConfig()
    assert TRACKER_KEYS == tuple(f.name for f in dataclasses.fields(TrackerConfig))
    assert msgspec.to_builtins(cfg)["tracker"] == DEFAULTS
    assert cfg.tracker_config() == TrackerConfig()
    changed = build_config(FusionConfig, {"tracker": {"nis_limit": 12, "mixing": "imm"}})
    assert changed.tracker_config() == TrackerConfig(nis_limit=12.0, mixing="imm")
    assert msgspec.to_builtins(changed)["tracker"] == {**DEFAULTS, "nis_limit": 12.0,
                                                      "mixing": "imm"}


def test_the_synthetic_recording_helper_records_every_tracker_setting(tmp_path):
    """The repo's recording helper stores the fusion settings as the recorder does: metadata
    ``fusion_config`` (one JSON value per setting) holds ``tracker`` with every key."""
    path = tmp_path / "synth.mcap"
    write_synthetic_recording(path, n_anchors=4, n_nodes=2, duration_s=0.5, seed=1)
    md = {m.name: m.metadata for m in side_records(path).metadata}
    assert json.loads(md["fusion_config"]["tracker"]) == DEFAULTS


def test_the_live_fusion_runs_the_configured_tracker(tmp_path, default_run):
    """FusionCore runs ``FusionConfig.tracker``: a changed setting changes the live estimates
    (the check that WHAT_IF is a key that must change them)."""
    _, live = default_run
    other = _live(tmp_path / "other.mcap", tracker=WHAT_IF)
    assert other.keys() == live.keys()
    pos, pos_other = _positions(live), _positions(other)
    assert sum(p is not None for p in pos.values()) >= 0.8 * len(pos)
    assert sum(pos[k] != pos_other[k] for k in pos) >= 0.5 * len(pos)


# ------------------------------------------------------------------ replay
def test_replay_runs_the_recorded_tracker_and_a_what_if_changes_it(tmp_path, default_run):
    """A recording made with non-default tracker settings replays to its live estimates bit
    for bit (the recorded settings, not today's defaults); ``--set tracker.KEY=VALUE`` back
    to the default gives the default live run's estimates; the default recording replays
    unchanged and its what-if changes the estimates."""
    path, live = default_run
    changed_path = tmp_path / "changed.mcap"
    changed_live = _live(changed_path, tracker=WHAT_IF)
    r = replay(changed_path)
    assert r.report["settings"]["tracker"] == {**DEFAULTS, **WHAT_IF}
    assert r.report["tracker_settings"] is None  # recorded: nothing to say
    assert _by_key(r.estimates) == changed_live
    back = replay(changed_path, overrides={"tracker": {"sigma_model_m": DEFAULTS["sigma_model_m"]}})
    assert _by_key(back.estimates) == live
    assert _by_key(replay(path).estimates) == live
    what_if = replay(path, overrides={"tracker": dict(WHAT_IF)})
    assert what_if.report["settings"]["tracker"] == {**DEFAULTS, **WHAT_IF}
    assert _by_key(what_if.estimates) == changed_live != live


def test_cli_set_tracker_key_changes_only_that_setting(tmp_path, default_run, capsys):
    path, _ = default_run
    out = tmp_path / "out"
    assert cli.main(["replay", str(path), "--no-progress", "--out", str(out),
                     "--set", "tracker.sigma_model_m=0.3", "--set", "tracker.dormant=false",
                     "--set", "deadline_s=0.3"]) == 0
    settings = json.loads((out / "report.json").read_text())["settings"]
    assert settings["tracker"] == {**DEFAULTS, "sigma_model_m": 0.3, "dormant": False}
    assert "changed: tracker.sigma_model_m=0.3, tracker.dormant=False, deadline_s=0.3" in \
        capsys.readouterr().out
    # --config FILE.json: a "tracker" object merged into the recorded settings, --set on top
    conf = tmp_path / "what_if.json"
    conf.write_text(json.dumps({"tracker": {"nis_limit": 12, "sigma_model_m": 0.1}}))
    assert cli.main(["replay", str(path), "--no-progress", "--out", str(out), "--config",
                     str(conf), "--set", "tracker.sigma_model_m=0.3"]) == 0
    settings = json.loads((out / "report.json").read_text())["settings"]
    assert settings["tracker"] == {**DEFAULTS, "sigma_model_m": 0.3, "nis_limit": 12.0}


@pytest.mark.parametrize(("started_ns", "want", "line"), [
    (NOW_NS, {}, "today's defaults, which it ran with (unchanged since 2026-12-08 02:53 UTC"),
    (AFTER_NS, LINK_OFF, "the defaults of then (stairs_follow=0, "
                         "stairs_follow_settled_s=0.0, stairs_follow_m=0.0, "
                         "stairs_follow_min_links=0, family_few_links=0, "
                         "family_fit_links=0, cov_few_floors=off, floor_hold_max_links=0, "
                         "family_worst_min_links=0, "
                         "snr_diffraction_slack_db=0.0, "
                         "snr_slack_max_links=0, reseed_outliers=0, "
                         "cov_published_floors=off, edge_retry_margin_m=0.0, "
                         "edge_retry_node=false, mechanism_prior_min_links=0, "
                         "mechanism_switch_p=0.0, first_arrival_prior=0.0, "
                         "floor_contest_s=0.0, reseed_max=0, "
                         "reseed_min_links=0, "
                         "family_learned_links=0, family_min_links=0, "
                         "max_order=2, "
                         "family_minority=false, family_history=0, "
                         "family_weight=outlier, family_gate=outlier, "
                         "floor_model_doubt=false, lost_on_gap=false, "
                         "min_anchors_tracking=0, link_learn=false, snr_cost_cap_nats=0.0)"),
    (BEFORE_NS, {**THEN, **LINK_OFF}, "snr_reuse_m=0.0, snr_reuse_anchor_m=0.0, "
                                      "floor_evidence_lag1_corr=0.0, dormant=false)"),
    (None, {}, "recording time unknown: today's defaults"),
])
def test_an_older_recording_replays_with_the_defaults_it_ran_with(tmp_path, capsys, started_ns,
                                                                  want, line):
    """A recording whose fusion settings have no ``tracker`` (made before they were
    recorded) replays with the tracker defaults of when it was made (its ``run`` metadata's
    ``started_ns``), reproducing a live run with those settings bit for bit, and the report
    (JSON and printed) says which defaults it used."""
    path = tmp_path / "old.mcap"
    live = _live(path, tracker=want, started_ns=started_ns, record_tracker=False)
    r = replay(path)
    assert r.report["settings"]["tracker"] == {**DEFAULTS, **want}
    assert line in r.report["tracker_settings"]
    assert _by_key(r.estimates) == live
    assert cli.main(["replay", str(path), "--no-files", "--no-progress"]) == 0
    printed = [s for s in capsys.readouterr().out.splitlines() if "tracker settings:" in s]
    assert len(printed) == 1 and line in printed[0]


def test_legacy_tracker_settings_follow_the_history_of_the_defaults():
    """The defaults of a time (git log -p of diffpos/tracking.py, tracking_state.py,
    tracking/state.py): each change applies to recordings made before it."""
    at = lambda *d: int(datetime.datetime(*d, tzinfo=UTC).timestamp()) * 10**9  # noqa: E731
    mnls = {"method": "mnls", "tracking": True}
    assert legacy_tracker_settings(mnls, at(2026, 12, 8, 2, 54))[0] == DEFAULTS
    assert legacy_tracker_settings(mnls, at(2026, 12, 8, 2, 24))[0] == {**DEFAULTS,
                                                                       **STAIRS_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 7, 23, 51))[0] == {**DEFAULTS,
                                                                         **FIT_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 7, 20, 28))[0] == {**DEFAULTS,
                                                                         **HOLD_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 7, 17, 21))[0] == {**DEFAULTS,
                                                                         **WORST_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 7, 14, 55))[0] == {**DEFAULTS,
                                                                         **SLACK_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 7, 11, 49))[0] == {**DEFAULTS,
                                                                         **BURST_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 7, 7, 59))[0] == {**DEFAULTS,
                                                                        **EDGE_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 7, 4, 55))[0] == {**DEFAULTS,
                                                                        **SKIP_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 7, 3, 25))[0] == {**DEFAULTS,
                                                                        **CONTEST_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 6, 20, 58))[0] == {**DEFAULTS,
                                                                         **RESEED_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 6, 19, 38))[0] == {
        **DEFAULTS, **LEARNED_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 6, 18, 24))[0] == {
        **DEFAULTS, **LEARNED_OFF, "family_min_links": 4}
    assert legacy_tracker_settings(mnls, at(2026, 12, 6, 17, 7))[0] == {
        **DEFAULTS, **LEARNED_OFF, "max_order": 2, "family_minority": False,
        "family_min_links": 4}
    assert legacy_tracker_settings(mnls, at(2026, 12, 6, 16, 6))[0] == {
        **DEFAULTS, **LEARNED_OFF, "max_order": 3, "family_minority": False,
        "family_min_links": 4}
    assert legacy_tracker_settings(mnls, at(2026, 12, 6, 16, 1))[0] == {
        **DEFAULTS, **LEARNED_OFF, "max_order": 3, "family_first": True,
        "family_minority": False, "family_min_links": 4}
    assert legacy_tracker_settings(mnls, at(2026, 12, 6, 15, 45))[0] == {
        **DEFAULTS, **LEARNED_OFF, "max_order": 3, "family_first": False,
        "family_minority": False, "family_min_links": 4}
    assert legacy_tracker_settings(mnls, at(2026, 12, 6, 15))[0] == {
        **DEFAULTS, "max_order": 2, **GATE_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 6, 13))[0] == {
        **DEFAULTS, "max_order": 3, **GATE_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 6, 11))[0] == {**DEFAULTS, **FAMILIES_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 12, 6, 9))[0] == {
        **DEFAULTS, **FAMILIES_OFF, "floor_model_doubt": False}
    assert legacy_tracker_settings(mnls, at(2026, 11, 27, 14))[0] == {**DEFAULTS, **LINK_OFF}
    assert legacy_tracker_settings(mnls, at(2026, 11, 27, 12))[0] == {
        **DEFAULTS, **LINK_OFF, "snr_reuse_m": 0.0, "snr_reuse_anchor_m": 0.0}
    assert legacy_tracker_settings(mnls, at(2026, 11, 27, 8, 52))[0] == {
        **DEFAULTS, **LINK_OFF, "snr_reuse_m": 0.0, "snr_reuse_anchor_m": 0.0,
        "floor_evidence_lag1_corr": 0.0, "dormant_floor_p": 0.99}
    assert legacy_tracker_settings(mnls, at(2026, 11, 23, 18))[0] == {
        **DEFAULTS, **THEN, **LINK_OFF, "init_grid_m": 1.0, "init_starts": 2}


def test_recorded_tracker_settings_without_newer_keys_get_the_values_of_their_time():
    """A recording whose tracker table predates a newer setting (made between the recording
    of the table and ab8d4d9) replays that setting at its old value, and the report says so."""
    at = lambda *d: int(datetime.datetime(*d, tzinfo=UTC).timestamp()) * 10**9  # noqa: E731
    table = {k: v for k, v in DEFAULTS.items() if k not in LINK_OFF}
    rec = {"method": "mnls", "tracking": True, "tracker": table}
    got, line = complete_tracker(rec, at(2026, 12, 6, 7))
    assert got == {**DEFAULTS, **LINK_OFF}
    assert "link_learn=false" in line and "snr_cost_cap_nats=0.0" in line
    assert complete_tracker({**rec, "tracker": DEFAULTS}, at(2026, 12, 6, 7)) == (DEFAULTS, None)
    settings, line = legacy_tracker_settings({"method": "dnls"}, at(2026, 11, 23, 18))
    assert settings == DEFAULTS and "no tracker ran live (method dnls)" in line


# ------------------------------------------------------------------ bad keys and values
def _one_line_error(capsys, argv, *needles):
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 1, err
    for n in needles:
        assert n in err, err
    return err


def test_a_bad_key_is_one_clear_line_naming_the_valid_keys(capsys, default_run):
    keys = ", ".join(TRACKER_KEYS)
    _one_line_error(capsys, ["fusion", "--tracker", "nis_limt=12"],
                    "--tracker nis_limt=12: 'nis_limt' is not a tracker setting; valid keys: "
                    + keys)
    _one_line_error(capsys, ["emulate", "--no-progress", "--tracker", "nis_limt=12"],
                    "'nis_limt' is not a tracker setting; valid keys: " + keys)
    path, _ = default_run
    _one_line_error(capsys, ["replay", str(path), "--no-files", "--no-progress",
                             "--set", "tracker.nis_limt=12"],
                    "tracker.nis_limt=12: 'nis_limt' is not a tracker setting; valid keys: "
                    + keys)


@pytest.mark.parametrize(("item", "needle"), [
    ("nis_limit=-1", "nis_limit takes a number > 0 [-], default 9.0"),
    ("mixing=fast", "mixing takes select or imm, default select"),
    ("gn_iterations=2.5", "gn_iterations takes an integer >= 1 [count], default 3"),
    ("dormant=maybe", "dormant takes true or false, default true"),
    ("q_h_m2_s3=abc", "q_h_m2_s3 takes a number >= 0 [m^2/s^3], default 1.5"),
    ("nis_limit", "expected KEY=VALUE"),
])
def test_a_bad_value_is_one_clear_line(capsys, default_run, item, needle):
    _one_line_error(capsys, ["fusion", "--tracker", item], needle)
    path, _ = default_run
    if "=" in item:
        _one_line_error(capsys, ["replay", str(path), "--no-files", "--no-progress",
                                 "--set", f"tracker.{item}"], needle)


# ------------------------------------------------------------------ the verbs
def _help(module) -> str:
    p = argparse.ArgumentParser()
    module.add_arguments(p)
    return " ".join(p.format_help().split())


@pytest.mark.parametrize("module", [cli_fusion, cli_emulate, cli_replay])
def test_help_shows_every_tracker_key_with_default_and_unit(module):
    text = _help(module)
    assert "q_h_m2_s3=1.5 [m^2/s^3]" in text and "jump_rate_hz=0.001 [1/s]" in text
    assert "lost_after_s=5.0 [s]" in text and "mixing=select (select|imm)" in text
    assert "dormant=true (true|false)" in text and "gn_iterations=3 [count]" in text
    assert all(f"{k}=" in text for k in TRACKER_KEYS)


def test_fusion_cli_builds_the_tracker_settings():
    p = argparse.ArgumentParser()
    cli_fusion.add_arguments(p)
    args = p.parse_args(["--tracker", "nis_limit=12", "--tracker", "dormant=false",
                         "--tracker", "mixing=imm"])
    cfg = cli_fusion.config_from_args(args, load_scenario_option(None))
    assert cfg.tracker_config() == TrackerConfig(nis_limit=12.0, dormant=False, mixing="imm")


def test_emulate_passes_the_tracker_settings_to_its_fusion_and_records_them():
    """``diffpos emulate --tracker``: the fusion process gets ``--tracker KEY=VALUE`` (floats
    exactly), and the config the real fusion CLI parses from it is the one emulate records
    for replay."""
    tracker = parse_tracker_items(["nis_limit=12", "dormant=false",
                                   f"sigma_model_m={0.1 + 0.2!r}"])
    emu = Emulation(EmulationOptions(record="off", dashboard=["off"], tracker=tracker),
                    logging.getLogger("test"), threading.Event())
    ap = argparse.ArgumentParser()
    cli_fusion.add_arguments(ap)
    args = ap.parse_args(emu.fusion_args)
    assert cli_fusion.config_from_args(args, load_scenario_option(args.scenario)) == \
        emu.fusion_config
    assert msgspec.to_builtins(emu.fusion_config)["tracker"] == {
        **DEFAULTS, "nis_limit": 12.0, "dormant": False, "sigma_model_m": 0.1 + 0.2}
    with pytest.raises(ConfigError, match="nis_limit takes a number > 0"):
        EmulationOptions(tracker={"nis_limit": -1}).check()
