"""`diffpos solve`: JSON Lines in/out, order, schemas, invalid lines, --strict, Python entry.

Everything runs the verb in this process (``cli.main.main`` with stdin replaced); the real
``diffpos solve`` process (a pipe, --batch 1 answering line by line) is
tests/system/test_solve_process.py."""

from __future__ import annotations

import io
import json
import sys
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from diffpos_services.cli import main as cli
from diffpos_services.scenario_io import load_scenario
from diffpos_services.solve import solve_records
from diffpos_services.wire.solve_io import DEFAULT_LIMITS, decode_line, parse_problem
from diffpos_services.wire.solve_line import parse_line

from diffpos.estimators.mnls.solver import mnls
from diffpos.geometry import los_path, window_edge_path
from diffpos.paths.model import first_arrival_paths

ROOT = Path(__file__).resolve().parents[2]
PROBLEM_SCHEMA = json.loads((ROOT / "schemas" / "solve_problem.v1.json").read_text())
RESULT_SCHEMA = json.loads((ROOT / "schemas" / "solve_result.v1.json").read_text())
ANCHORS = [
    [-15.0, -20.0, 1.0],
    [0.0, -15.0, 0.0],
    [0.0, -7.0, 4.0],
    [15.0, -20.0, 1.0],
    [5.0, -30.0, 20.0],
]


def _problem(node, **extra):
    r = window_edge_path(np.array(ANCHORS), np.array(node), window_height_m=1.0).length_m
    prob = {"anchors_m": ANCHORS, "ranges_m": r.tolist(), "sigmas_m": 0.01, "window_height_m": 1.0}
    prob.update(extra)
    return prob


def _run(lines, argv=(), monkeypatch=None, capsys=None):
    monkeypatch.setattr(sys, "stdin", io.StringIO("".join(line + "\n" for line in lines)))
    rc = cli.main(["solve", *argv])
    out, err = capsys.readouterr()
    return rc, [json.loads(x) for x in out.splitlines()], err


def test_valid_problems_in_order_and_schema_valid(monkeypatch, capsys):
    nodes = [[2.0, 5.0, 10.5], [-4.0, 3.0, 1.5], [6.0, 8.0, 22.5]]
    lines = [json.dumps(_problem(n, id=f"n{k}")) for k, n in enumerate(nodes)]
    rc, recs, _ = _run(lines, ["--batch", "2"], monkeypatch, capsys)
    assert rc == 0 and len(recs) == 3
    for k, (rec, node) in enumerate(zip(recs, nodes, strict=True)):
        jsonschema.validate(rec, RESULT_SCHEMA)
        assert rec["line"] == k + 1 and rec["id"] == f"n{k}"
        assert rec["status"] == "ok" and rec["method"] == "dnls"
        assert np.allclose(rec["position_m"], node, atol=1e-6)
        assert rec["used_anchors"] == [0, 1, 2, 3, 4]
        assert rec["covariance_model"] == "diffraction FIM"
    for line in lines:
        jsonschema.validate(json.loads(line), PROBLEM_SCHEMA)


BAD_LINES = [
    ("{not json", "invalid JSON"),
    ("[1, 2]", "JSON object"),
    (json.dumps({"ranges_m": [1, 2, 3]}), "anchors_m"),
    (
        json.dumps({"anchors_m": ANCHORS[:3], "ranges_m": [1, 2], "window_height_m": 1}),
        "ranges_m must have 3 entries",
    ),
    (
        '{"anchors_m": [[0,-5,0],[1,-5,0],[2,-6,1]], "ranges_m": [1, NaN, 3], '
        '"window_height_m": 1}',
        "ranges_m[1] must be finite",
    ),
    (
        '{"anchors_m": [[0,-5,0],[1,-5,Infinity],[2,-6,1]], "ranges_m": [1, 2, 3], '
        '"window_height_m": 1}',
        "anchors_m[1][2] must be finite",
    ),
    (
        json.dumps({"anchors_m": ANCHORS[:3], "ranges_m": [1, -2, 3], "window_height_m": 1}),
        "ranges_m[1] is negative",
    ),
    (
        json.dumps({"anchors_m": ANCHORS[:3], "ranges_m": [1, None, 3], "window_height_m": 1}),
        "fewer than 3 anchors",
    ),
    (
        json.dumps({"anchors_m": ANCHORS[:2], "ranges_m": [1, 2], "window_height_m": 1}),
        "fewer than 3 anchors",
    ),
    (
        json.dumps({"anchors_m": [[0, -5]] * 3, "ranges_m": [1, 2, 3], "window_height_m": 1}),
        "anchors_m[0] must have 3 entries",
    ),
    (json.dumps({"anchors_m": ANCHORS[:3], "ranges_m": [1, 2, 3]}), "window_height_m"),
    (
        json.dumps(
            {"anchors_m": ANCHORS[:3], "ranges_m": [1, 2, 3], "window_height_m": 1, "sigma_m": 0.1}
        ),
        "did you mean 'sigmas_m'",
    ),
    (
        json.dumps(
            {
                "anchors_m": ANCHORS[:3],
                "ranges_m": [1, 2, 3],
                "window_height_m": 1,
                "sigmas_m": [0.1, 0, 0.1],
            }
        ),
        "sigmas_m[1]",
    ),
    (
        json.dumps(
            {"anchors_m": ANCHORS[:3], "ranges_m": [1, 2, 3], "window_height_m": 1, "method": "gps"}
        ),
        "method",
    ),
    (
        json.dumps(
            {
                "anchors_m": ANCHORS[:3],
                "ranges_m": [1, 2, 3],
                "window_height_m": 1,
                "gating": {"false_alarm_probability": 2},
            }
        ),
        "gating.false_alarm_probability",
    ),
]


@pytest.mark.parametrize(("line", "needle"), BAD_LINES, ids=[n for _, n in BAD_LINES])
def test_bad_line_gives_invalid_input_and_filter_continues(line, needle, monkeypatch, capsys):
    good = json.dumps(_problem([1.0, 4.0, 7.5]))
    rc, recs, err = _run([good, line, good], [], monkeypatch, capsys)
    assert rc == 0
    assert [r["status"] for r in recs] == ["ok", "invalid_input", "ok"]
    assert needle in recs[1]["message"], recs[1]["message"]
    assert recs[1]["line"] == 2
    jsonschema.validate(recs[1], RESULT_SCHEMA)
    assert "1 invalid line" in err
    rc, recs, _ = _run([good, line, good], ["--strict"], monkeypatch, capsys)
    assert rc == 1 and len(recs) == 3


def test_problem_schema_rejects_what_it_can_express():
    for bad in (
        {"ranges_m": [1, 2, 3]},
        {"anchors_m": ANCHORS[:3], "ranges_m": [1, -2, 3]},
        {"anchors_m": ANCHORS[:3], "ranges_m": [1, 2, 3], "sigma_m": 1},
        {"anchors_m": [[0, 1]] * 3, "ranges_m": [1, 2, 3]},
    ):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(bad, PROBLEM_SCHEMA)


def test_methods_mixed_in_one_batch_match_single_solves():
    node = [1.0, 4.0, 7.5]
    los = los_path(np.array(ANCHORS), np.array(node))[0].tolist()
    probs = [
        _problem(node),
        {"anchors_m": ANCHORS, "ranges_m": los, "method": "lls"},
        _problem([3.0, 6.0, 13.5], delta_m=0.0, gating=False),
        {"anchors_m": ANCHORS[:4], "ranges_m": los[:4], "method": "ippa", "nlos": False},
        _problem(node, ranges_m=[*_problem(node)["ranges_m"][:4], None]),
    ]
    together = solve_records(probs)
    alone = [solve_records([p])[0] for p in probs]
    for t, a in zip(together, alone, strict=True):
        assert t["status"] == a["status"]
        if t["status"] in ("ok", "ok_unverified"):
            assert np.allclose(t["position_m"], a["position_m"], atol=1e-9)
        else:  # no trustworthy position, none published
            assert t["position_m"] is None and a["position_m"] is None
    assert together[1]["method"] == "lls"
    assert np.allclose(together[1]["position_m"], node, atol=1e-8)
    assert together[2]["status"] == "ok_unverified"
    assert together[4]["used_anchors"] == [0, 1, 2, 3]
    assert together[4]["residuals_m"][4] is None
    assert [r["line"] for r in together] == [1, 2, 3, 4, 5]


def test_gated_exclusion_is_reported(monkeypatch, capsys):
    prob = _problem([2.0, 5.0, 10.5])
    prob["ranges_m"][2] += 1.0  # 100 sigma
    rc, recs, _ = _run([json.dumps(prob)], [], monkeypatch, capsys)
    assert rc == 0
    assert recs[0]["excluded_anchors"] == [{"index": 2, "reason": "raim"}]
    assert recs[0]["residuals_m"][2] is None
    assert np.allclose(recs[0]["position_m"], [2.0, 5.0, 10.5], atol=0.05)


def test_input_file_and_missing_file(tmp_path, capsys):
    path = tmp_path / "p.jsonl"
    path.write_text(json.dumps(_problem([2.0, 5.0, 10.5])) + "\n\n" + "oops\n")
    rc = cli.main(["solve", "--input", str(path)])
    out, _ = capsys.readouterr()
    recs = [json.loads(x) for x in out.splitlines()]
    assert rc == 0 and [r["line"] for r in recs] == [1, 3]  # blank line skipped but counted
    rc = cli.main(["solve", "--input", str(tmp_path / "missing.jsonl")])
    _, err = capsys.readouterr()
    assert rc == 2 and "cannot read --input" in err


def test_gating_height_range_and_multistart_options(monkeypatch, capsys):
    """gating.z_range_m flags an implausible height; bad values name the field."""
    node = [2.0, 5.0, 10.5]
    default = _problem(node, id="default")
    narrow = _problem(node, id="narrow", gating={"z_range_m": [12.0, 30.0],
                                                 "multistart_exclusion": False})
    off = _problem(node, id="off", gating={"z_range_m": None})
    bad = _problem(node, id="bad", gating={"z_range_m": [5.0]})
    bad2 = _problem(node, id="bad2", gating={"multistart_exclusion": "yes"})
    for p in (default, narrow, off):
        jsonschema.validate(p, PROBLEM_SCHEMA)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(bad, PROBLEM_SCHEMA)
    rc, recs, _ = _run([json.dumps(p) for p in (default, narrow, off, bad, bad2)], (),
                       monkeypatch, capsys)
    assert rc == 0
    by_id = {r["id"]: r for r in recs}
    assert by_id["default"]["status"] == "ok" and by_id["off"]["status"] == "ok"
    assert by_id["narrow"]["status"] == "gating_failed"  # z = 10.5 m is outside [12, 30]
    assert by_id["narrow"]["position_m"] is None  # gating_failed publishes no position
    assert by_id["bad"]["status"] == "invalid_input" and "z_range_m" in by_id["bad"]["message"]
    assert (by_id["bad2"]["status"] == "invalid_input"
            and "multistart_exclusion" in by_id["bad2"]["message"])
    for r in recs:
        jsonschema.validate(r, RESULT_SCHEMA)


# ----------------------------------------------------------------------------- issue 15, item 11
@pytest.mark.parametrize(("y", "where"), [(5.0, "inside the building (y = 5 > 0)"),
                                          (0.0, "on the facade (y = 0)")])
def test_anchor_not_outside_is_invalid_naming_the_anchor(y, where, monkeypatch, capsys):
    """An anchor at y >= 0 is not where an anchor can be: before, the line was solved (ok)."""
    node = [2.0, 5.0, 10.5]
    prob = _problem(node)
    prob["anchors_m"] = [list(a) for a in ANCHORS]
    prob["anchors_m"][2][1] = y
    good = json.dumps(_problem(node))
    rc, recs, _ = _run([good, json.dumps(prob), good], [], monkeypatch, capsys)
    assert rc == 0 and [r["status"] for r in recs] == ["ok", "invalid_input", "ok"]
    msg = recs[1]["message"]
    assert msg.startswith(f"anchors_m[2] = [0.0, {y}, 4.0] is {where}"), msg
    assert "anchors must be outside, y < 0" in msg
    for method in ("lls", "ippa"):  # every method uses the building frame
        (rec,) = solve_records([dict(prob, method=method)])
        assert rec["status"] == "invalid_input" and rec["message"] == msg


def _unidentifiable():
    # four anchors at one point: the diffraction geometry constrains one direction only
    return {"anchors_m": [[0.0, -5.0, 1.0]] * 4, "ranges_m": [10.0] * 4, "sigmas_m": 0.01,
            "window_height_m": 1.0, "id": "same-point"}


def test_statuses_without_a_trustworthy_position_publish_none(monkeypatch, capsys):
    """Before: not_identifiable carried positions like y = 925 km. Now only ok and
    ok_unverified publish position_m, covariance_m2, peb_m, z_bound_m."""
    node = [1.0, 4.0, 7.5]
    los = los_path(np.array(ANCHORS), np.array(node))[0].tolist()
    far = _problem([2.0, 5.0, 10.5], id="gating", gating={"z_range_m": [12.0, 30.0]})
    ippa_cap = {"anchors_m": ANCHORS[:4], "ranges_m": los[:4], "method": "ippa",
                "nlos": False, "id": "ippa"}
    lines = [json.dumps(p) for p in (_unidentifiable(), far, ippa_cap, _problem(node))]
    rc, recs, _ = _run(lines, [], monkeypatch, capsys)
    assert rc == 0
    by_id = {r["id"]: r for r in recs}
    assert by_id["same-point"]["status"] == "not_identifiable"
    assert by_id["gating"]["status"] == "gating_failed"
    assert by_id["ippa"]["status"] == "not_converged"
    for r in recs:
        jsonschema.validate(r, RESULT_SCHEMA)
        fields = [r[k] for k in ("position_m", "covariance_m2", "peb_m", "z_bound_m")]
        if r["status"] in ("ok", "ok_unverified"):
            assert all(f is not None for f in fields), r
        else:
            assert fields == [None] * 4, r
            assert r["message"]  # the verdict still says why
    assert recs[-1]["status"] == "ok"
    assert np.allclose(recs[-1]["position_m"], node, atol=1e-6)


def test_blank_lines_are_skipped_as_help_and_docs_say(monkeypatch, capsys):
    """Every non-blank line gets exactly one result; blank (whitespace-only) lines get none
    but are counted in "line". --help and docs/bad_input.md say so (they said every line)."""
    good = json.dumps(_problem([2.0, 5.0, 10.5]))
    rc, recs, _ = _run([good, "", "   ", "\t", good, "{}", " "], [], monkeypatch, capsys)
    assert rc == 0
    assert [(r["line"], r["status"]) for r in recs] == [(1, "ok"), (5, "ok"),
                                                        (6, "invalid_input")]
    with pytest.raises(SystemExit) as info:
        cli.main(["solve", "--help"])
    assert info.value.code == 0
    flat = " ".join(capsys.readouterr().out.split())
    assert "exactly one result line (JSON object) to stdout for every input line that is not " \
           "blank" in flat
    assert "Blank (whitespace-only) lines are skipped without a result, but counted in the " \
           "result's \"line\" number." in flat
    doc = " ".join((ROOT / "docs" / "bad_input.md").read_text().split())
    assert "Every line that is not blank gets exactly one result line" in doc
    assert "blank (whitespace-only) lines are skipped without a result" in doc
    assert "Every line gets exactly one result" not in doc


# ----------------------------------------------------------------------------- mnls (issue 13)
HELD_OUT_TOML = """
name = "held-out"
[building]
width_m = 24.0
center_x_m = 3.0
depth_m = 12.0
n_floors = 3
floor_height_m = 3.4
first_floor_z_m = 2.0
sill_height_m = 0.9
window_height_m = 1.2
[[anchors]]
position_m = [-14.0, -9.0, 1.0]
[nodes.grid]
spacing_m = 3.0
y_max_m = 10.0
"""
# 6 UAVs: below, at and above the window bands, one beyond each facade end (x in [-9, 15])
HELD_OUT_ANCHORS = [[-14.0, -9.0, 1.0], [3.0, -6.0, 3.5], [20.0, -10.0, 6.8],
                    [9.0, -4.0, 11.5], [-5.0, -12.0, 0.5], [12.0, -15.0, 2.0]]
HELD_OUT_NODES = [[0.0, 4.0, 3.5], [6.5, 2.0, 7.6], [10.0, 6.0, 4.2], [-2.0, 5.0, 10.9]]


@pytest.fixture
def held_out(tmp_path):
    """A building that is not a shipped scenario, and first-arrival ranges of its nodes: the
    shortest existing mechanism of every link (what arrives first on a noiseless channel)."""
    path = tmp_path / "held_out.toml"
    path.write_text(HELD_OUT_TOML)
    sc = load_scenario(path)
    a = np.array(HELD_OUT_ANCHORS)
    ps = first_arrival_paths(np.array(HELD_OUT_NODES)[:, None, :], a[None], sc.building)
    ranges = np.min(np.where(ps.valid, ps.length_m, np.inf), axis=-1)
    assert np.all(np.isfinite(ranges))
    return path, sc, ranges


def test_mnls_with_scenario_equals_the_estimator_and_finds_the_floor(held_out, monkeypatch,
                                                                     capsys):
    path, sc, ranges = held_out
    probs = [{"anchors_m": HELD_OUT_ANCHORS, "ranges_m": r.tolist(), "sigmas_m": 0.05,
              "method": "mnls", "id": k} for k, r in enumerate(ranges)]
    lines = [json.dumps(p) for p in probs]
    for p in probs:
        jsonschema.validate(p, PROBLEM_SCHEMA)
    rc, recs, _ = _run(lines, ["--scenario", str(path), "--batch", "3"], monkeypatch, capsys)
    assert rc == 0 and [r["line"] for r in recs] == [1, 2, 3, 4]
    direct = mnls(np.array(HELD_OUT_ANCHORS), ranges, 0.05, building=sc.building,
                  bandwidth_hz=sc.radio.bandwidth_hz, error_floor_m=sc.radio.range_error_floor_m)
    truth_floor = sc.building.floor_index(np.array(HELD_OUT_NODES)[:, 2])
    for i, rec in enumerate(recs):
        jsonschema.validate(rec, RESULT_SCHEMA)
        assert rec["method"] == "mnls" and rec["status"] == "ok", rec["message"]
        assert rec["covariance_model"] == "first-arrival model, floor mixture"
        assert np.allclose(rec["position_m"], direct.position_m[i], atol=1e-9)
        assert np.allclose(rec["floor_probability"], direct.floor_probability[i], atol=1e-12)
        assert rec["floor"] == int(truth_floor[i]) == int(direct.floor[i])
        assert sum(rec["floor_probability"]) == pytest.approx(1.0)
        assert np.linalg.norm(np.subtract(rec["position_m"], HELD_OUT_NODES[i])) < 0.2
    # the default method from the command line, and the Python entry point
    rc, recs2, _ = _run([json.dumps({k: v for k, v in probs[0].items() if k != "method"})],
                        ["--scenario", str(path), "--method", "mnls"], monkeypatch, capsys)
    assert rc == 0 and recs2[0]["position_m"] == recs[0]["position_m"]
    (rec,) = solve_records([probs[0]], scenario=sc)
    assert rec["position_m"] == recs[0]["position_m"]


def test_mnls_without_the_building_is_refused(held_out, tmp_path, monkeypatch, capsys):
    _, _, ranges = held_out
    prob = {"anchors_m": HELD_OUT_ANCHORS, "ranges_m": ranges[0].tolist(), "method": "mnls"}
    good = json.dumps(_problem([1.0, 4.0, 7.5]))
    rc, recs, _ = _run([good, json.dumps(prob), good], [], monkeypatch, capsys)
    assert rc == 0 and [r["status"] for r in recs] == ["ok", "invalid_input", "ok"]
    assert "--scenario" in recs[1]["message"] and "mnls" in recs[1]["message"]
    assert recs[1]["floor"] is None and recs[0]["floor"] is None  # not mnls: no floor
    rc = cli.main(["solve", "--method", "mnls"])
    assert rc == 2 and "--scenario" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text("[building]\nn_floors = 0\n")
    rc = cli.main(["solve", "--scenario", str(bad)])
    err = capsys.readouterr().err
    assert rc == 2 and "building.n_floors" in err and "Traceback" not in err


def test_scenario_gives_dnls_its_window_height_and_edges(held_out, monkeypatch, capsys):
    path, sc, _ = held_out
    node = np.array([4.0, 5.0, 5.3])
    a = np.array(HELD_OUT_ANCHORS)
    r = window_edge_path(a, node, window_height_m=sc.building.window_height_m,
                         edge_x_m=sc.building.edge_x_m).length_m.tolist()
    bare = {"anchors_m": HELD_OUT_ANCHORS, "ranges_m": r, "sigmas_m": 0.01}
    explicit = dict(bare, window_height_m=1.2, edge_x_m=[-9.0, 15.0])
    rc, recs, _ = _run([json.dumps(bare), json.dumps(explicit)], ["--scenario", str(path)],
                       monkeypatch, capsys)
    assert rc == 0 and recs[0]["status"] == recs[1]["status"] == "ok"
    assert recs[0]["position_m"] == recs[1]["position_m"]
    assert np.allclose(recs[0]["position_m"], node, atol=1e-6)
    (rec,) = solve_records([bare])  # without the building, w is required
    assert rec["status"] == "invalid_input" and "window_height_m" in rec["message"]


def test_snr_db_is_optional_and_checked(held_out, monkeypatch, capsys):
    path, _, ranges = held_out
    base = {"anchors_m": HELD_OUT_ANCHORS, "ranges_m": ranges[1].tolist(), "method": "mnls"}
    with_snr = dict(base, snr_db=[20.0, None, 35.5, -3.0, 12.0, 8.0])
    short = dict(base, snr_db=[20.0, 30.0])
    jsonschema.validate(with_snr, PROBLEM_SCHEMA)
    rc, recs, _ = _run([json.dumps(p) for p in (base, with_snr, short)],
                       ["--scenario", str(path)], monkeypatch, capsys)
    assert rc == 0
    assert recs[0]["status"] == "ok"
    # made-up SNRs (-3 dB on a link that has a range) may fail the solver's checks; the line
    # is accepted and solved, not rejected as input
    assert recs[1]["status"] in ("ok", "ok_unverified", "gating_failed")
    assert recs[2]["status"] == "invalid_input" and "snr_db" in recs[2]["message"]
    # an earlier v1 result (no floor fields) still validates
    old = {k: v for k, v in recs[0].items() if k not in ("floor", "floor_probability")}
    jsonschema.validate(old, RESULT_SCHEMA)


def _fields_equal(fast, slow) -> None:
    for k in slow.__dataclass_fields__:
        x, y = getattr(fast, k), getattr(slow, k)
        if isinstance(y, np.ndarray):
            assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), k
        else:
            assert x == y and type(x) is type(y), k


def test_fast_line_parser_builds_the_checked_parsers_problem_or_defers_to_it():
    """The typed msgspec decode (wire/solve_line.py) gives the same Problem as the checked
    path on well-formed lines (nulls, per-anchor sigmas, every option) and returns None on
    anything the checked path rejects, so error messages stay the checked path's."""
    rng = np.random.default_rng(11)
    good = [_problem([rng.uniform(-5, 5), rng.uniform(1, 10), 1.5 + 3 * k], id=k)
            for k in range(20)]
    good.append(_problem([1.0, 4.0, 7.5], ranges_m=[20.0, None, 15.0, 21.0, 30.0],
                         sigmas_m=[0.1, None, 0.2, 0.3, 0.1], edge_x_m=[5, -5], x0_m=[1, 2, 3],
                         z_starts_m=[1, 2], gating={"max_exclusions": 1}, loss="huber",
                         delta_m=1, snr_db=[10, None, 20, 30, 25], id={"a": [1, "b"]}))
    good.append(_problem([1.0, 4.0, 7.5], method="ippa", nlos=[True, False, True, True, True],
                         nlos_bias_m=[0.1, 0, 0, 0, 0.2], sigmas_m=0.2, gating=False))
    for prob in good:
        line = json.dumps(prob)
        fast = parse_line(line, default_method="dnls", limits=DEFAULT_LIMITS)
        assert fast is not None and fast[0] == prob.get("id")
        _fields_equal(fast[1], parse_problem(decode_line(line), limits=DEFAULT_LIMITS))
    bad = [dict(good[0], anchors_m=[[0.0, 1.0, 2.0], *ANCHORS[1:]]),
           dict(good[0], ranges_m=[1.0, 2.0, True, 3.0, 4.0]),
           dict(good[0], ranges_m=[1.0, None, None, None, 4.0]),
           dict(good[0], ranges_m=[1.0, 2.0, -3.0, 3.0, 4.0]),
           dict(good[0], sigmas_m=0), dict(good[0], delta_m=None), dict(good[0], unknown=1),
           dict(good[0], window_height_m=None), dict(good[0], ranges_m=[1.0, 2.0, 3.0]),
           dict(good[0], anchors_m=[[0.0, -1.0], *ANCHORS[1:]]),
           dict(good[0], ranges_m=[1e8, 2.0, 3.0, 3.0, 4.0]), dict(good[0], method="mnls")]
    for prob in bad:
        assert parse_line(json.dumps(prob), default_method="dnls", limits=DEFAULT_LIMITS) is None
    assert parse_line('{"anchors_m": NaN}', default_method="dnls", limits=DEFAULT_LIMITS) is None
