"""Every registered subcommand has a working, teaching --help, and unknown ones fail clearly."""

from __future__ import annotations

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
