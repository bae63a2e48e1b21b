"""The layout's rules, checked on the source (DEVELOPING.md, "Layout and import rules").

Each rule is a function over the parsed modules of ``diffpos_services``; a violation names the
file, the line and the rule. The pure-core rule itself is in ``test_layout.py``.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
from dataclasses import dataclass
from pathlib import Path

import diffpos_services
import pytest
from diffpos_services.errors import DiffposError

PKG = Path(diffpos_services.__file__).resolve().parent
CORE = PKG.parents[1] / "diffpos"

#: Service modules (one role each) -> service name. They may import the shared layers (errors,
#: config, logs, shutdown, processes, wire, bus, resources, scenario_io, reports, and recording:
#: the MCAP file format), and each other only where listed in ALLOWED_SERVICE_IMPORTS.
SERVICES = {
    "anchor": "anchor", "fusion": "fusion", "recorder": "recorder", "dashboard": "dashboard",
    "emulate": "emulate", "raytrace": "raytrace", "replay": "replay",
}
ALLOWED_SERVICE_IMPORTS = {
    ("replay", "fusion"),  # replay re-runs the fusion core offline
    ("emulate", "fusion"),  # emulate builds the fusion's config to start and score it
}
#: Where ``import zenoh`` may appear: the bus layer and the process entry points.
ZENOH_ALLOWED = ("bus", "anchor.service", "fusion.service", "recorder", "dashboard.service",
                 "emulate", "cli.router")
#: Plot/terminal libraries: only reports and the CLI.
PRESENTATION = ("matplotlib", "rich")
PRESENTATION_ALLOWED = ("reports", "cli")
#: Imports allowed inside functions: optional extras (not installed by default: sionna and
#: its JIT, cryptography, jsonschema of the test extra) and the Rerun viewer stack (rerun-sdk
#: and the dashboard modules that import it at module level: ~1 s that a run without a
#: dashboard must not pay), the compiled kernels where a process prepares them on purpose
#: (importing them compiles them on a fresh machine: emulate says so first), and replay's plot
#: (matplotlib, ~0.35 s that `diffpos replay --no-files` must not pay). Besides these, a verb
#: module (cli/<verb>.py) imports its service inside its functions, never in add_arguments
#: or what it calls (:func:`_verb_lazy_lines`): `diffpos VERB --help` imports the parser only.
#: And the M-NLS + tracker stack (its kernels: M-NLS starts, tracker, channel SNR, paths),
#: imported where a process runs the ``mnls`` method, so a D-NLS process (replay, the fusion
#: service, ``emulate --method dnls``) loads and, on a fresh machine, compiles none of it
#: (issue 37 item 3; tests/services/test_startup_loads.py checks that it loads none).
METHOD_LAZY = ("diffpos.estimators.mnls", "diffpos.tracking.tracker", "diffpos.tracking.families",
               "diffpos.channel.emulator", "diffpos_services.fusion.tracked",
               "diffpos_services.fusion.estimates_v2", "diffpos_services.fusion.warm",
               "diffpos_services.fusion.rows", "diffpos_services.fusion.workers")
LAZY_ALLOWED = ("sionna", "drjit", "mitsuba", "cryptography", "jsonschema", "rerun", "pyarrow",
                "diffpos_services.dashboard", "diffpos_services.reports.replay", *METHOD_LAZY)
MAX_FUNCTION_LINES = 80


@dataclass(frozen=True)
class Module:
    name: str  # dotted, relative to diffpos_services ("fusion.core")
    path: Path
    tree: ast.Module
    lines: list[str]


def _modules() -> list[Module]:
    out = []
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        name = ".".join(parts) or "__init__"
        src = path.read_text()
        out.append(Module(name, path, ast.parse(src, filename=str(path)), src.splitlines()))
    assert out, "no service modules found"
    return out


MODULES = _modules()


def _in(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == p or name.startswith(p + ".") for p in prefixes)


def _imports(mod: Module):
    """(line, absolute dotted module, inside a function?) for every import of ``mod``."""
    func_ranges = [(n.lineno, n.end_lineno) for n in ast.walk(mod.tree)
                   if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)]
    for node in ast.walk(mod.tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = mod.name.split(".")[: -node.level or None] if mod.path.name != "__init__.py" \
                    else mod.name.split(".")[: len(mod.name.split(".")) - node.level + 1]
                names = ["diffpos_services." + ".".join([*base, node.module or ""]).strip(".")]
            else:
                names = [node.module or ""]
                names += [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        inside = any(a <= node.lineno <= b for a, b in func_ranges)
        for n in names:
            yield node.lineno, n, inside


def _service_of(name: str) -> str | None:
    """The service a ``diffpos_services``-relative module belongs to, or None (shared/cli)."""
    for prefix, service in SERVICES.items():
        if _in(name, (prefix,)):
            return service
    return None


def _violations(rule) -> list[str]:
    return [f"{m.path.relative_to(PKG.parents[1])}:{line}: {msg}"
            for m in MODULES for line, msg in rule(m)]


def rule_nothing_imports_cli(m: Module):
    if _in(m.name, ("cli",)):
        return
    for line, name, _ in _imports(m):
        if _in(name, ("diffpos_services.cli",)):
            yield line, f"imports {name} (nothing outside cli/ imports the CLI)"


def rule_services_stay_apart(m: Module):
    mine = _service_of(m.name)
    if mine is None:
        return
    for line, name, _ in _imports(m):
        if not name.startswith("diffpos_services."):
            continue
        other = _service_of(name.removeprefix("diffpos_services."))
        if other and other != mine and (mine, other) not in ALLOWED_SERVICE_IMPORTS:
            yield line, f"service {mine} imports service {other} ({name})"


def rule_zenoh_only_in_bus_and_entry_points(m: Module):
    if _in(m.name, ZENOH_ALLOWED):
        return
    for line, name, _ in _imports(m):
        if name.split(".")[0] == "zenoh":
            yield line, "imports zenoh outside bus/ and the process entry points"


def rule_presentation_only_in_reports_and_cli(m: Module):
    if _in(m.name, PRESENTATION_ALLOWED):
        return
    for line, name, _ in _imports(m):
        if name.split(".")[0] in PRESENTATION:
            yield line, f"imports {name.split('.')[0]} outside reports/ and cli/"


def _verb_lazy_lines(m: Module) -> set[int]:
    """The lines of a verb module (``cli/<verb>.py``) where an import may be lazy: its top-level
    functions but ``add_arguments`` and the functions it calls (the parser's path)."""
    if not m.name.startswith("cli.") or m.name == "cli.main":
        return set()
    funcs = {n.name: n for n in m.tree.body if isinstance(n, ast.FunctionDef)}
    parser, todo = set(), ["add_arguments"]
    while todo:
        f = todo.pop()
        if f in parser or f not in funcs:
            continue
        parser.add(f)
        todo += [x.id for x in ast.walk(funcs[f]) if isinstance(x, ast.Name) and x.id in funcs]
    return {i for name, f in funcs.items() if name not in parser
            for i in range(f.lineno, f.end_lineno + 1)}


def rule_no_imports_inside_functions(m: Module):
    verb_lazy = _verb_lazy_lines(m)
    for line, name, inside in _imports(m):
        kernel = name.startswith("diffpos.") and name.endswith("_nb")  # compiled kernels
        if inside and not kernel and line not in verb_lazy and not any(
                name == p or name.startswith(p + ".") for p in LAZY_ALLOWED):
            yield line, (f"imports {name} inside a function (module level, unless an optional "
                         "extra or a verb's service outside its add_arguments)")


def rule_key_strings_in_keys(m: Module):
    if m.name == "wire.keys":
        return
    docs = {id(n.value) for n in ast.walk(m.tree)
            if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)}
    for node in ast.walk(m.tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs:
            s = node.value
            if s.startswith("diffpos/") or "/alive/" in s or s.endswith("/**"):
                yield node.lineno, f"key string {s!r} outside wire/keys.py"


def rule_short_functions(m: Module):
    """No function over MAX_FUNCTION_LINES lines of code (a file holds one role, no line limit)."""
    for node in ast.walk(m.tree):
        if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            continue
        doc = ast.get_docstring(node, clean=False)
        skip = set()
        if doc is not None:
            d = node.body[0]
            skip = set(range(d.lineno, d.end_lineno + 1))
        n = sum(1 for i in range(node.lineno, node.end_lineno + 1)
                if i not in skip and m.lines[i - 1].strip()
                and not m.lines[i - 1].strip().startswith("#"))
        if n > MAX_FUNCTION_LINES:
            yield node.lineno, f"function {node.name} has {n} lines of code (> {MAX_FUNCTION_LINES})"


RULES = [rule_nothing_imports_cli, rule_services_stay_apart, rule_zenoh_only_in_bus_and_entry_points,
         rule_presentation_only_in_reports_and_cli, rule_no_imports_inside_functions,
         rule_key_strings_in_keys, rule_short_functions]


@pytest.mark.parametrize("rule", RULES, ids=lambda r: r.__name__.removeprefix("rule_"))
def test_layout_rule(rule) -> None:
    bad = _violations(rule)
    assert not bad, f"{rule.__doc__ or rule.__name__}:\n" + "\n".join(bad)


def test_core_never_imports_services() -> None:
    bad = []
    for path in sorted(CORE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            bad += [f"{path}:{node.lineno}: {n}" for n in names if n.startswith("diffpos_services")]
    assert not bad, "the core imports services:\n" + "\n".join(bad)


def test_every_error_class_derives_from_the_one_base() -> None:
    bad = []
    for info in pkgutil.walk_packages(diffpos_services.__path__, "diffpos_services."):
        if ".raytrace" in info.name and "sionna" in info.name:
            continue
        module = importlib.import_module(info.name)
        for _, cls in inspect.getmembers(module, inspect.isclass):
            if (cls.__module__ == module.__name__ and issubclass(cls, Exception)
                    and not issubclass(cls, DiffposError)):
                bad.append(f"{info.name}.{cls.__name__}")
    assert not bad, "error classes not derived from errors.DiffposError: " + ", ".join(bad)


@pytest.mark.parametrize("rule", [rule_no_imports_inside_functions, rule_services_stay_apart],
                         ids=["lazy_import", "service_import"])
def test_rules_catch_a_violation(rule, tmp_path) -> None:
    """The checker itself fails on a planted violation (so a silent checker cannot pass)."""
    src = ("from diffpos_services.dashboard import stream\n"
           "def f():\n    import json\n    return json\n")
    planted = Module("fusion.core", tmp_path / "x.py", ast.parse(src), src.splitlines())
    assert list(rule(planted)), f"{rule.__name__} missed a planted violation"


def test_a_verb_imports_its_service_lazily_only_off_its_parser_path(tmp_path) -> None:
    """In cli/<verb>.py an import inside run() (or a helper of run) passes; one inside
    add_arguments, or a function add_arguments calls, is a violation."""
    src = ("import argparse\n"
           "def _opts(p):\n    from diffpos_services.fusion.config import METHODS\n"
           "def add_arguments(p):\n    _opts(p)\n"
           "def _helper():\n    from diffpos_services.replay.run import replay\n"
           "def run(args):\n    from diffpos_services.fusion.service import run_fusion\n")
    planted = Module("cli.fusion", tmp_path / "x.py", ast.parse(src), src.splitlines())
    assert {line for line, _ in rule_no_imports_inside_functions(planted)} == {3}
