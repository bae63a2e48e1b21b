"""A scenario file is bounded in size and nesting before the TOML parser sees it (issue 36,
item 5: a TOML nested 100,000 deep gave a RecursionError traceback, a dotted key 100,000
parts long took 75 s in tomllib, 10^6 anchors reached 23.7 GB)."""

from __future__ import annotations

import pytest
from diffpos_services.errors import ConfigError
from diffpos_services.scenario_io import (
    MAX_NESTING,
    MAX_SCENARIO_BYTES,
    SCENARIO_DIR,
    load_scenario,
    load_scenario_option,
    scenario_from_toml,
)

from diffpos.scenario import ScenarioError

PAPER = (SCENARIO_DIR / "paper.toml").read_text()


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("a = " + "[" * 100_000 + "]" * 100_000, "line 1: arrays or inline tables nested more "
         f"than {MAX_NESTING} deep (scenario_io.MAX_NESTING)"),
        ("a = " + "{b=" * 100_000 + "}" * 100_000, "nested more than 32 deep"),
        ("x = 1\n[" + "a." * 1000 + "b]\n", f"line 2: a dotted key of more than {MAX_NESTING} "
         "parts"),
        ("x = [\n" + "[\n" * 40 + "]\n" * 41, "line 33: arrays or inline tables nested"),
    ],
)
def test_deep_nesting_is_refused_naming_the_limit(text, fragment):
    with pytest.raises(ScenarioError) as ei:
        scenario_from_toml(text, source="deep.toml")
    msg = str(ei.value)
    assert msg.startswith("deep.toml: "), msg
    assert fragment in msg, msg


def test_brackets_and_dots_in_strings_and_comments_are_text():
    text = PAPER.replace('name = "paper"', 'name = "' + "[." * 200 + '" # ' + "{" * 100, 1)
    assert text != PAPER
    s = scenario_from_toml(text, source="x.toml")
    assert s.name == "[." * 200


def test_oversized_file_is_refused_without_reading_it_all(tmp_path):
    p = tmp_path / "big.toml"
    one = '[[anchors]]\nid = "u{i}"\nposition_m = [{i}.0, -20.0, 1.0]\n'
    p.write_text("".join(one.format(i=i) for i in range(1_000_000 // 50)) * 3)
    assert p.stat().st_size > MAX_SCENARIO_BYTES
    with pytest.raises(ConfigError) as ei:
        load_scenario_option(p)
    assert f"larger than {MAX_SCENARIO_BYTES:,} bytes (scenario_io.MAX_SCENARIO_BYTES)" in str(
        ei.value)


def test_five_thousand_anchor_file_names_the_anchor_limit(tmp_path):
    p = tmp_path / "many.toml"
    head = PAPER[: PAPER.index("[[anchors]]")]
    tail = PAPER[PAPER.index("[nodes"):] if "[nodes" in PAPER else ""
    one = '[[anchors]]\nid = "u{i}"\nposition_m = [{i}.0, -20.0, 1.0]\n'
    p.write_text(head + "".join(one.format(i=i) for i in range(5000)) + tail)
    assert p.stat().st_size < MAX_SCENARIO_BYTES
    with pytest.raises(ScenarioError, match=r"anchors: 5,000 anchors; at most 256 are allowed"):
        load_scenario(p)


def test_shipped_scenarios_are_within_the_limits():
    for p in SCENARIO_DIR.glob("*.toml"):
        assert load_scenario(p).anchors
