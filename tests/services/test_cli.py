"""Every registered subcommand has a working, teaching --help, and unknown ones fail clearly."""

from __future__ import annotations

import logging

import pytest
from diffpos_services.cli import main as cli


@pytest.mark.parametrize("name", list(cli.COMMANDS))
def test_subcommand_help(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main([name, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith(f"usage: diffpos {name}")
    module = cli._load(name)
    first_line = (module.__doc__ or "").strip().splitlines()[0]
    assert first_line and first_line in out, "the module docstring is the help text"


def test_top_level_help_lists_every_subcommand(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in cli.COMMANDS:
        assert f"  {name} " in out


def test_unknown_subcommand_is_a_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["bouns"]) == 2
    err = capsys.readouterr().err
    assert "unknown subcommand 'bouns'" in err and "bounds" in err


def test_a_service_verb_run_in_process_leaves_root_logging_as_it_found_it(capsys) -> None:
    """``fusion`` configures the root logger (level info, a stderr handler) before its config
    error; run through ``cli.main`` in-process (as tests do) the root logger gets its level and
    handlers back, so later caplog assertions do not depend on test order."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    root.setLevel(logging.ERROR)
    try:
        assert cli.main(["fusion", "--deadline-s", "100", "--log-level", "debug"]) == 2
        assert "deadline_s" in capsys.readouterr().err
        assert root.level == logging.ERROR and root.handlers == handlers
    finally:
        root.setLevel(level)


#: unit suffixes of option names and how their help may state the unit (or the metavar)
_UNITS = {
    "_s": ("[s]", "second"), "_m": ("[m]",), "_hz": ("[hz]",), "_ms": ("[ms]", "ms"),
    "_us": ("[us]",), "_db": ("[db]",), "_ns": ("[ns]",), "_m2": ("[m^2]",),
}


def _renderings(value) -> set[str]:
    """How a default value may be written in a help text."""
    if isinstance(value, bool | str | int):
        return {str(value)}
    if isinstance(value, float):
        out = {str(value), f"{value:g}"}
        for e in range(13):  # 28e9, 1e5
            m = value / 10**e
            if m == int(m) and abs(m) < 1000:
                out.add(f"{int(m)}e{e}")
        return out | ({str(int(value))} if value.is_integer() else set())
    if isinstance(value, list | tuple):
        return {" ".join(" ".join(sorted(_renderings(v), key=len)[:1]) for v in value)}
    return {str(value)}


def _options(name: str):
    import argparse

    parser = cli.build_parser(name)
    fmt = parser._get_formatter()
    skip = (argparse._HelpAction, argparse._VersionAction, argparse._StoreTrueAction,
            argparse._StoreFalseAction, argparse._AppendConstAction, argparse._CountAction)
    return [(a, fmt._expand_help(a) if a.help else "") for a in parser._actions
            if a.option_strings and not isinstance(a, skip)]


@pytest.mark.parametrize("name", list(cli.COMMANDS))
def test_every_option_shows_its_default_and_unit(name: str) -> None:
    """Every option has a help text; an option with a default says "default" and the value;
    an option whose name carries a unit (``--deadline-s``, ``--rate-hz``) states it."""
    problems = []
    for a, text in _options(name):
        opt = a.option_strings[-1]
        if not text:
            problems.append(f"{opt}: no help")
            continue
        low = (text + " " + str(a.metavar or "")).lower()
        if a.default is not None and a.default != [] and not a.required:
            if "default" not in text.lower() or not any(
                    r.lower() in text.lower() for r in _renderings(a.default)):
                problems.append(f"{opt}: default {a.default!r} not shown in {text!r}")
        for suffix, words in _UNITS.items():
            if a.dest.endswith(suffix) and not any(w in low for w in words):
                problems.append(f"{opt}: unit {suffix[1:]} not stated in {text!r}")
    assert not problems, f"diffpos {name}: " + "; ".join(problems)
