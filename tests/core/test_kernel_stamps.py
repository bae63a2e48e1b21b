"""numba keys a kernel's on-disk cache (the ``__pycache__`` beside it) on the stamp (mtime,
size) of the kernel's OWN source file, not on the files of the functions it compiles in: after
an edit of ``paths/model_nb.py`` a developer's warm cache would keep serving the tracker's,
M-NLS's and the SNR prediction's kernels with the old path code (a fresh clone
cannot be stale). So every kernel module that imports another ``*_nb`` module at its top
carries ``CALLEES_SHA256``: a digest of the code (the AST, comments and the stamp line itself
left out) of every ``*_nb`` module it compiles in, transitively. This test recomputes them
and names the value to write: editing a callee fails it until each dependant's stamp is
updated, and that edit of the dependant is what invalidates its cache."""

from __future__ import annotations

import ast
import hashlib
from pathlib import Path

import diffpos

CORE = Path(diffpos.__file__).parent
STAMP = "CALLEES_SHA256"
#: Every compiled kernel module of the core, by dotted name (they live beside their references).
KERNELS = {".".join(("diffpos", *p.relative_to(CORE).with_suffix("").parts)): p
           for p in sorted(CORE.rglob("*_nb.py"))}


def _tree(name: str) -> ast.Module:
    return ast.parse(KERNELS[name].read_text(), filename=str(KERNELS[name]))


def _callees(name: str) -> set[str]:
    """The ``*_nb`` modules ``name`` imports at module level (an import inside a function is
    a Python call, not compiled in)."""
    return {n.module for n in _tree(name).body
            if isinstance(n, ast.ImportFrom) and n.level == 0 and n.module in KERNELS}


def _closure(name: str) -> list[str]:
    seen: set[str] = set()
    todo = list(_callees(name))
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(_callees(m))
    return sorted(seen - {name})


def _code(name: str) -> str:
    """The module's AST without its stamp assignment (comments are not in the AST)."""
    tree = _tree(name)
    tree.body = [n for n in tree.body if not (
        isinstance(n, ast.Assign) and any(getattr(t, "id", None) == STAMP for t in n.targets))]
    return ast.dump(tree)


def digest(name: str) -> str:
    h = hashlib.sha256()
    for m in _closure(name):
        h.update(m.encode() + b"\0" + _code(m).encode() + b"\0")
    return h.hexdigest()[:16]


def _stamp(name: str) -> str | None:
    for n in _tree(name).body:
        if isinstance(n, ast.Assign) and any(getattr(t, "id", None) == STAMP for t in n.targets):
            return ast.literal_eval(n.value)
    return None


PATHS, TRACKER, IEKF, DNLS = ("diffpos.paths.model_nb", "diffpos.tracking.model_nb",
                              "diffpos.tracking.iekf_nb", "diffpos.estimators.dnls.fit_nb")


def test_every_kernel_module_stamps_the_code_it_compiles_in():
    dependants = sorted(m for m in KERNELS if _callees(m))
    assert {"diffpos.channel.snr_nb", IEKF, "diffpos.estimators.mnls.solver_nb",
            TRACKER} <= set(dependants)
    wrong = {m: digest(m) for m in dependants if _stamp(m) != digest(m)}
    assert not wrong, ("a callee changed (or a stamp is missing): set these in the module "
                       f"({STAMP} = \"...\"): {wrong}")


def test_the_digest_follows_a_callee_edit_only(monkeypatch):
    """A code edit of the path kernel changes the digest of its dependants (the tracker's
    model kernel directly, the IEKF through it too), a comment does not, an unrelated module
    is unchanged."""
    before = {m: digest(m) for m in (TRACKER, IEKF, DNLS)}
    src = KERNELS[PATHS].read_text()

    def patched(text):
        def tree(name):
            s = text if name == PATHS else KERNELS[name].read_text()
            return ast.parse(s)
        return tree

    monkeypatch.setitem(globals(), "_tree", patched(src + "\n# a comment\n"))
    assert {m: digest(m) for m in before} == before
    monkeypatch.setitem(globals(), "_tree", patched(src + "\n_X = 1\n"))
    after = {m: digest(m) for m in before}
    assert after[TRACKER] != before[TRACKER]
    assert after[IEKF] != before[IEKF]
    assert after[DNLS] == before[DNLS]
