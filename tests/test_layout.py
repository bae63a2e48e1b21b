"""The core package `diffpos` must stay pure: numpy/scipy only, no I/O, no bus, no viewer.

Checked two ways: statically (no forbidden import or builtin ``open``/``print`` call anywhere in
``diffpos/``) and dynamically (importing every core module in a fresh interpreter pulls in none
of the forbidden packages).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

CORE = Path(__file__).resolve().parents[1] / "diffpos"  # tests/ is one level below the repo

FORBIDDEN_MODULES = {
    "zenoh", "mcap", "rerun", "matplotlib", "rich", "msgspec", "pyarrow",
    "tomllib", "pathlib", "io", "os", "shutil", "subprocess", "socket", "threading",
    "asyncio", "logging", "pickle", "csv", "sqlite3", "urllib", "http", "concurrent",
    "multiprocessing",
}
FORBIDDEN_CALLS = {"open", "print", "input"}
#: Chosen exceptions, each with its reason. diffpos/_kernels/pool.py runs the compiled kernels'
#: row chunks on a small thread pool (threading and concurrent.futures' ThreadPoolExecutor:
#: threads only, no I/O, no process; 1 thread until a service or replay sets
#: FusionConfig.kernel_threads).
ALLOWED_IMPORTS = {"_kernels/pool.py": {"threading", "concurrent"}}


def _core_files() -> list[Path]:
    files = sorted(CORE.rglob("*.py"))
    assert files, "no core modules found"
    return files


@pytest.mark.parametrize("path", _core_files(), ids=lambda p: str(p.relative_to(CORE)))
def test_no_forbidden_imports_or_io_calls(path: Path) -> None:
    tree = ast.parse(path.read_text(), filename=str(path))
    problems = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [node.module or ""] if node.level == 0 else []
        else:
            names = []
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id in FORBIDDEN_CALLS
            ):
                problems.append(f"line {node.lineno}: call to {node.func.id}()")
        allowed = ALLOWED_IMPORTS.get(path.relative_to(CORE).as_posix(), set())
        for name in names:
            if name.split(".")[0] in FORBIDDEN_MODULES - allowed:
                problems.append(f"line {node.lineno}: import {name}")
    assert not problems, f"{path.name} breaks the pure-core rule:\n" + "\n".join(problems)


def test_importing_core_loads_no_forbidden_package() -> None:
    modules = [
        "diffpos." + ".".join(p.relative_to(CORE).with_suffix("").parts)
        for p in _core_files()
        if p.name != "__init__.py"
    ]
    code = (
        "import importlib, json, sys\n"
        "import diffpos\n"
        f"for m in {modules!r}: importlib.import_module(m)\n"
        "print(json.dumps(sorted(sys.modules)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    loaded = {m.split(".")[0] for m in json.loads(out.stdout)}
    heavy = {"zenoh", "mcap", "rerun", "matplotlib", "rich", "msgspec", "pyarrow"}
    assert not (loaded & heavy), f"importing the core loaded {sorted(loaded & heavy)}"
