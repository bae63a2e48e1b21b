"""The import graph of both packages, checked on the source (DEVELOPING.md, "The house rules").

* no import loop (lazy imports inside functions count: a loop hidden in a function is still one);
* the core's import graph is at most ``MAX_CORE_DEPTH`` modules deep;
* no underscore name is imported from another package (``from a.b import _x``, or ``mod._x``
  through an imported module): a name used across packages is public, and named so;
* one import path per name: ``from M import n`` names the module that defines ``n`` (no
  re-exports, no shims), or a submodule of a package;
* no function over ``MAX_FUNCTION_LINES`` lines of code in the core (services: test_import_rules).

A package is a folder with an ``__init__.py``; modules of one package share its private names.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TREES = {"diffpos": ROOT / "diffpos", "diffpos_services": ROOT / "services" / "diffpos_services"}
MAX_CORE_DEPTH = 6
MAX_FUNCTION_LINES = 80


@dataclass
class Mod:
    name: str
    path: Path
    is_pkg: bool
    tree: ast.Module
    lines: list[str]
    defs: set[str] = field(default_factory=set)

    @property
    def package(self) -> str:
        return self.name if self.is_pkg else self.name.rpartition(".")[0]


def top_level_defs(body: list[ast.stmt]) -> set[str]:
    """The names a module body binds at its top level (also inside if/try/with/for blocks)."""
    out: set[str] = set()
    for n in body:
        if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            out.add(n.name)
        elif isinstance(n, ast.Assign):
            out.update(x.id for t in n.targets for x in ast.walk(t) if isinstance(x, ast.Name))
        elif isinstance(n, ast.AnnAssign | ast.AugAssign) and isinstance(n.target, ast.Name):
            out.add(n.target.id)
        elif isinstance(n, ast.If | ast.Try | ast.With | ast.For):
            out |= top_level_defs(n.body) | top_level_defs(getattr(n, "orelse", []))
            out |= top_level_defs(getattr(n, "finalbody", []))
            for h in getattr(n, "handlers", []):
                out |= top_level_defs(h.body)
    return out


def _load(trees: dict[str, Path]) -> dict[str, Mod]:
    mods = {}
    for top, root in trees.items():
        for path in sorted(root.rglob("*.py")):
            rel = path.relative_to(root).with_suffix("")
            is_pkg = rel.name == "__init__"
            parts = [top, *(rel.parts[:-1] if is_pkg else rel.parts)]
            src = path.read_text()
            tree = ast.parse(src, filename=str(path))
            mods[".".join(parts)] = Mod(".".join(parts), path, is_pkg, tree, src.splitlines(),
                                        top_level_defs(tree.body))
    return mods


MODS = _load(TREES)


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def _absolute(mod: Mod, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = mod.package.split(".")
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, *([node.module] if node.module else [])])


def _imports(mod: Mod, mods: dict[str, Mod]):
    """(line, target module, imported name or None) for every import, lazy ones included."""
    for node in ast.walk(mod.tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name in mods:
                    yield node.lineno, a.name, None
        elif isinstance(node, ast.ImportFrom):
            src = _absolute(mod, node)
            for a in node.names:
                if f"{src}.{a.name}" in mods:
                    yield node.lineno, f"{src}.{a.name}", None
                elif src in mods:
                    yield node.lineno, src, a.name


def _graph(mods: dict[str, Mod]) -> dict[str, set[str]]:
    return {m.name: {t for _, t, _ in _imports(m, mods) if t != m.name} for m in mods.values()}


def _loops(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            nxt = next(it, None)
            if nxt is not None:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter[0]
                    counter[0] += 1
                    stack.append(nxt)
                    on.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                elif nxt in on:
                    low[v] = min(low[v], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def _depth(graph: dict[str, set[str]], prefix: str) -> tuple[int, list[str]]:
    """The longest chain of imports among the modules under ``prefix`` (a module alone = 1)."""
    memo: dict[str, list[str]] = {}

    def chain(m: str) -> list[str]:
        if m not in memo:
            memo[m] = [m]
            best = max((chain(t) for t in graph[m] if t.startswith(prefix)), key=len, default=[])
            memo[m] = [m, *best]
        return memo[m]
    longest = max((chain(m) for m in graph if m.startswith(prefix)), key=len)
    return len(longest), longest


def private_imports(mods: dict[str, Mod]) -> list[str]:
    bad = []
    for mod in mods.values():
        aliases = {}
        for line, target, name in _imports(mod, mods):
            if (name is not None and name.startswith("_")
                    and mods[target].package != mod.package):
                bad.append(f"{_rel(mod.path)}:{line}: {target}.{name}")
        for node in ast.walk(mod.tree):
            if isinstance(node, ast.ImportFrom):
                src = _absolute(mod, node)
                for a in node.names:
                    if f"{src}.{a.name}" in mods:
                        aliases[a.asname or a.name] = f"{src}.{a.name}"
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.asname and a.name in mods:
                        aliases[a.asname] = a.name
        for node in ast.walk(mod.tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and node.value.id in aliases and node.attr.startswith("_")
                    and not node.attr.startswith("__")):
                target = mods[aliases[node.value.id]]
                if target.package != mod.package and target.name != mod.name:
                    bad.append(f"{_rel(mod.path)}:{node.lineno}: "
                               f"{target.name}.{node.attr}")
    return bad


def reexports(mods: dict[str, Mod]) -> list[str]:
    bad = []
    for mod in mods.values():
        for line, target, name in _imports(mod, mods):
            if name is not None and name != "*" and name not in mods[target].defs:
                bad.append(f"{_rel(mod.path)}:{line}: {name} from {target}, "
                           "which does not define it")
    return bad


def long_functions(mods: dict[str, Mod], prefix: str) -> list[str]:
    bad = []
    for mod in mods.values():
        if not mod.name.startswith(prefix):
            continue
        for node in ast.walk(mod.tree):
            if not isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            skip = set()
            if ast.get_docstring(node, clean=False) is not None:
                skip = set(range(node.body[0].lineno, node.body[0].end_lineno + 1))
            n = sum(1 for i in range(node.lineno, node.end_lineno + 1)
                    if i not in skip and mod.lines[i - 1].strip()
                    and not mod.lines[i - 1].strip().startswith("#"))
            if n > MAX_FUNCTION_LINES:
                bad.append(f"{_rel(mod.path)}:{node.lineno}: {node.name} ({n} lines)")
    return bad


def test_no_import_loop() -> None:
    loops = _loops(_graph(MODS))
    assert not loops, "import loops (lazy imports count):\n" + "\n".join(map(" <-> ".join, loops))


def test_core_import_depth() -> None:
    depth, chain = _depth(_graph(MODS), "diffpos.")
    assert depth <= MAX_CORE_DEPTH, f"core import depth {depth}: " + " -> ".join(chain)


def test_no_private_name_imported_across_packages() -> None:
    bad = private_imports(MODS)
    assert not bad, "underscore names imported across packages:\n" + "\n".join(bad)


def test_one_import_path_per_name() -> None:
    bad = reexports(MODS)
    assert not bad, "names imported from a module that only re-exports them:\n" + "\n".join(bad)


def test_core_functions_are_short() -> None:
    bad = long_functions(MODS, "diffpos.")
    assert not bad, f"core functions over {MAX_FUNCTION_LINES} lines of code:\n" + "\n".join(bad)


@pytest.mark.parametrize("check", ["loop", "private", "reexport", "depth"])
def test_checks_catch_a_planted_violation(check: str, tmp_path: Path) -> None:
    """Each checker fails on a small planted tree (so a silent checker cannot pass)."""
    pkg = tmp_path / "p"
    for sub in ("a", "b"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    files = {
        "loop": {"a/x.py": "from p.b import y\n", "b/y.py": "def f():\n    from p.a import x\n"},
        "private": {"a/x.py": "_hidden = 1\n", "b/y.py": "from p.a.x import _hidden\n"},
        "reexport": {"a/x.py": "def f(): pass\n", "a/y.py": "from p.a.x import f\n",
                     "b/z.py": "from p.a.y import f\n"},
        "depth": {f"a/m{i}.py": (f"from p.a import m{i + 1}\n" if i < 7 else "") for i in range(8)},
    }[check]
    for rel, src in files.items():
        (pkg / rel).write_text(src)
    mods = _load({"p": pkg})
    if check == "loop":
        assert _loops(_graph(mods))
    elif check == "private":
        assert private_imports(mods)
    elif check == "reexport":
        assert reexports(mods)
    else:
        assert _depth(_graph(mods), "p.")[0] > MAX_CORE_DEPTH
