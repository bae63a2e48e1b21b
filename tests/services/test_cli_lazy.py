"""The CLI loads lazily: ``diffpos --help`` imports no verb, ``diffpos VERB --help`` imports
that verb's parser only and never numba or a compiled kernel (``diffpos.*_nb``): on a fresh
machine importing a kernel module compiles it (71 s for ``replay --help`` before, issue 33).

Each verb runs in a fresh interpreter (``sys.modules`` of this one is full of everything).
Not timed: benchmarks/bench_cli_help.py measures the seconds.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest
from diffpos_services.cli import main as cli

CLI = Path(cli.__file__).resolve().parent

#: what ``diffpos VERB --help`` (or ``diffpos --help``) left in ``sys.modules``: numba, the
#: kernel modules and the verb modules of the CLI
PROBE = """
import contextlib, io, json, sys
from diffpos_services.cli import main as cli
with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
    cli.main(sys.argv[1:])
mods = sorted(sys.modules)
print(json.dumps({
    "numba": [m for m in mods if m == "numba" or m.startswith("numba.")][:3],
    "kernels": [m for m in mods if m.startswith("diffpos.") and m.rsplit(".", 1)[-1].endswith("_nb")],
    "verbs": [m for m in mods if m.startswith("diffpos_services.cli.")
              and m not in ("diffpos_services.cli.main", "diffpos_services.cli.raytrace_options")],
}))
"""


def _imported(*argv: str) -> dict[str, list[str]]:
    out = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True, text=True,
                         timeout=120, check=False)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_the_verb_table_matches_each_modules_docstring() -> None:
    """``COMMANDS``' one-line help is the first line of the verb module's docstring (read from
    the source, as before the static table), and every verb module is listed."""
    for name, (module, help_) in cli.COMMANDS.items():
        tree = ast.parse((CLI / f"{module}.py").read_text(encoding="utf-8"))
        first = (ast.get_docstring(tree) or "").strip().splitlines()[0]
        assert help_ == first, f"{name}: the table says {help_!r}, {module}.py says {first!r}"
    modules = {p.stem for p in CLI.glob("*.py")} - {"__init__", "main", "raytrace_options"}
    assert modules == {m for m, _ in cli.COMMANDS.values()}


def test_top_level_help_imports_no_verb() -> None:
    got = _imported("--help")
    assert got == {"numba": [], "kernels": [], "verbs": []}, got


@pytest.mark.parametrize("name", list(cli.COMMANDS))
def test_verb_help_imports_its_parser_only_and_no_kernel(name: str) -> None:
    got = _imported(name, "--help")
    assert not got["numba"] and not got["kernels"], (
        f"diffpos {name} --help imports numba / kernels: {got}")
    assert got["verbs"] == [f"diffpos_services.cli.{cli.COMMANDS[name][0]}"], got["verbs"]

