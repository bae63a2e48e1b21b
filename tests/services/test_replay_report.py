"""What an analyst reads in ``diffpos replay``'s report (issue 35): units on every column,
explained names, one way of writing percentages, times into the recording instead of raw epoch
numbers, "no track yet" apart from RAIM exclusions, a loud warning when a what-if drops an
anchor or a node, plots that name the what-if, count fixes without a position and show (or
say they cut) the worst error, and ``--start/--end``.

Recordings are written without Zenoh by ``write_synthetic_recording`` (5 anchors, 3 nodes,
3 s at 10 Hz, D-NLS live fusion recorded).
"""

from __future__ import annotations

import json
import re
from types import SimpleNamespace

import numpy as np
import pytest
from diffpos_services.cli.main import main as cli_main
from diffpos_services.replay.evaluate import gating_counts
from diffpos_services.replay.report_stream import FixStream, SlimEstimate, SlimExclusion, TruthBook
from diffpos_services.replay.run import replay
from diffpos_services.replay.synthetic import write_synthetic_recording
from diffpos_services.reports.replay import CUT_FACTOR, cdf_figure


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    path = tmp_path_factory.mktemp("report") / "synthetic.mcap"
    write_synthetic_recording(path, n_anchors=5, n_nodes=3, duration_s=3.0,
                              outlier_probability=0.08, seed=11, flush_every=200)
    return path


def _cli(capsys, *argv: str) -> tuple[int, str, str]:
    rc = cli_main(["replay", *argv, "--no-progress"])
    out = capsys.readouterr()
    return rc, out.out, out.err


def _table(text: str) -> tuple[list[str], list[str]]:
    """The per-node table's header and unit rows (split on runs of spaces)."""
    lines = text.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.startswith("node "))
    return lines[i].split(), lines[i + 1].split()


def test_every_column_has_a_unit_and_every_name_is_explained(rec, capsys):
    rc, text, _ = _cli(capsys, str(rec), "--no-files")
    assert rc == 0
    header, units = _table(text)
    columns = ["fixes", "scored", "3D p50", "p67", "p90", "p95", "max", "z p50", "z p90",
               "floor", "PEB p50", "in 2 PEB"]
    assert " ".join(header) == "node " + " ".join(columns)
    assert len(units) == len(columns)  # a unit under every column but the node's name
    assert all(re.fullmatch(r"\[(m|%|n)\]", u) for u in units), units
    assert "eval" not in header and "<=2PEB" not in text
    for name in ("scored:", "PEB: position error bound", "in 2 PEB:", "floor:"):
        assert name in text, name


def test_percentages_are_written_one_way(rec, capsys):
    """Shares are percent numbers under a [%] unit or followed by " %"; never "94%" or a
    0.998 share."""
    rc, text, _ = _cli(capsys, str(rec), "--no-files", "--compare")
    assert rc == 0
    assert not re.search(r"\d%", text), [ln for ln in text.splitlines() if re.search(r"\d%", ln)]
    rep = replay(rec, keep_estimates=False).report
    lo, ro = rep["live"]["accuracy"]["overall"], rep["accuracy"]["overall"]
    row = next(ln for ln in text.splitlines() if ln.startswith("  on the true floor [%]"))
    assert row.split()[-2:] == [f"{100 * lo['floor_accuracy']:.1f}",
                                f"{100 * ro['floor_accuracy']:.1f}"]


def test_differences_are_named_by_time_into_the_recording(rec, capsys):
    rc, text, _ = _cli(capsys, str(rec), "--no-files", "--compare",
                       "--set", "motion_compensation=false")
    assert rc == 0
    assert not re.search(r"epoch \d", text)
    times = [float(t) for t in re.findall(r"^\s+n\d+ at (\d+\.\d) s: ", text, re.M)]
    assert times and all(0.0 <= t <= 3.5 for t in times)  # a 3 s recording


def _est(node: str, status: str, raim: list[str], used: list[str]) -> SlimEstimate:
    pos = None if status in ("UNINITIALISED", "LOST") else (0.0, 0.0, 1.0)
    return SlimEstimate(schema="diffpos.estimate.v2", node_id=node, t_ns=0, epoch=0,
                        status=status, position_m=pos, used_anchors=used,
                        excluded=[SlimExclusion(a, "RAIM") for a in raim])


def test_gating_separates_no_track_yet_from_raim_exclusions():
    """A tracker fix without a track lists every measured anchor as "RAIM": those are counted
    as "no track", the RAIM of a tracked fix as an exclusion (streamed and list versions)."""
    ests = [_est("n1", "UNINITIALISED", ["a", "b"], []),
            _est("n1", "UNINITIALISED", ["a", "b"], []),
            _est("n1", "INITIALISING", ["b"], ["a"]),
            _est("n2", "TRACKING", [], ["a", "b"]),
            _est("n2", "LOST", ["a"], [])]
    want = {"a": {"used": 2, "no_track": 3, "excluded": {}},
            "b": {"used": 1, "no_track": 2, "excluded": {"RAIM": 1}}}
    fs = FixStream(TruthBook(10**10), max_truth_gap_ns=10**9, window_ns=10**10)
    for e in ests:
        fs.add(e)
    assert fs.gating() == want
    assert gating_counts(ests) == want


def test_gating_table_prints_no_track_apart(rec, capsys):
    rc, text, _ = _cli(capsys, str(rec), "--no-files")
    assert rc == 0
    head = next(ln for ln in text.splitlines() if ln.strip().startswith("anchor "))
    assert head.split()[:4] == ["anchor", "used", "no", "track"]


def test_a_what_if_that_drops_an_anchor_or_a_node_warns_loudly(rec, capsys):
    base = replay(rec, keep_estimates=False).report
    anchors, nodes = base["anchors"], base["nodes"]
    assert base["dropped"] == {"anchors": {}, "nodes": {}, "fusion_rejected": {}}
    keep_a = json.dumps(anchors[:-1])
    keep_n = json.dumps(nodes[:-1])
    rc, text, err = _cli(capsys, str(rec), "--no-files", "--set", f"anchors={keep_a}",
                         "--set", f"nodes={keep_n}")
    assert rc == 0
    warn = [ln for ln in text.splitlines() if ln.startswith("WARNING: the replayed fixes lost")]
    assert len(warn) == 2  # at the top and again at the end
    assert "1 anchor(s) and 1 node(s)" in warn[0] and "anchors=" in warn[0]
    assert re.search(rf"anchor {anchors[-1]}: used by 0 replayed fixes \(recorded live: \d+",
                     text)
    assert re.search(rf"node {nodes[-1]}: 0 of \d+ replayed fixes have a position "
                     r"\(recorded live: \d+\)", text)
    assert "WARNING: the replayed fixes lost" in err  # also where a script's log keeps it


def _result(e3, ez, *, evaluated, without_position, what_if="max_speed_m_s=1.0"):
    acc = {"overall": {"evaluated": evaluated, "without_position": without_position}}
    report = {"file": "run.mcap", "method": "mnls", "what_if": what_if, "accuracy": acc,
              "node_epochs": {}, "live": None}
    return SimpleNamespace(report=report, errors={"e3": np.asarray(e3), "ez": np.asarray(ez)},
                           live_errors={})


def test_cdf_names_the_what_if_and_counts_fixes_without_a_position():
    e = np.linspace(0.1, 1.0, 10)
    fig = cdf_figure(_result(e, e / 2, evaluated=10, without_position=5))
    ax = fig.axes[0]
    assert "what-if: max_speed_m_s=1.0" in ax.get_title()
    ys = [line.get_ydata()[-1] for line in ax.get_lines()]
    assert ys == pytest.approx([10 / 15, 10 / 15])  # 5 fixes without a position: misses
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert all("10 with a position / 15 fixes" in lab for lab in labels)
    res = _result(e, e, evaluated=10, without_position=0, what_if="")
    assert "what-if: none" in cdf_figure(res).axes[0].get_title()
    res.report["dropped"] = {"anchors": {"uav8": {}}, "nodes": {}}
    assert "LOST anchor uav8" in cdf_figure(res).axes[0].get_title()


def test_cdf_axis_shows_the_worst_error_or_says_it_cut_it():
    near = np.r_[np.linspace(0.1, 1.0, 99), 2.0]  # worst within CUT_FACTOR x p99: shown
    ax = cdf_figure(_result(near, near / 10, evaluated=100, without_position=0)).axes[0]
    assert ax.get_xlim()[1] >= 2.0 and "worst error 2.00 m" in ax.get_xlabel()
    far = np.r_[np.linspace(0.1, 1.0, 199), 7.0]  # one far outlier: cut, and said
    assert 7.0 > CUT_FACTOR * np.percentile(far, 99)
    ax = cdf_figure(_result(far, far / 10, evaluated=200, without_position=0)).axes[0]
    assert ax.get_xlim()[1] < 7.0
    assert "axis cut at" in ax.get_xlabel() and "worst error 7.00 m, 1 errors beyond" in \
        ax.get_xlabel()


def test_start_and_end_replay_only_that_window(rec, capsys):
    full = replay(rec)
    part = replay(rec, start_s=1.0, end_s=2.0)
    origin = part.report["origin_ns"]
    assert origin == full.report["origin_ns"]
    t = np.array([e.t_pub_wall_ns for e in part.estimates]) - origin
    assert t.min() >= 1.0e9 and t.max() <= 2.0e9
    # 3 nodes at 10 Hz: about 10 epochs each in one second (the first may lack a state)
    assert 3 * 8 <= len(part.estimates) <= 3 * 11 < len(full.estimates)
    assert part.report["window"] == {"start_s": 1.0, "end_s": 2.0}
    assert part.report["recording_s"] <= 1.0
    rc, text, _ = _cli(capsys, str(rec), "--no-files", "--start", "1", "--end", "2")
    assert rc == 0 and "time window: 1 s to 2 s into the recording" in text
    rc, _, err = _cli(capsys, str(rec), "--no-files", "--start", "2", "--end", "1")
    assert rc == 2 and "before it starts" in err


def test_replay_speed_does_not_count_the_kernels(rec, capsys):
    rc, text, _ = _cli(capsys, str(rec), "--no-files", "--json")
    assert rc == 0
    rep = json.loads(text)
    t = rep["timing"]
    assert t["kernels_s"] >= 0 and t["warm_up_s"] >= 0
    assert t["speedup_x"] == pytest.approx(rep["recording_s"] / t["wall_s"])
