"""No facades: a module's ``__all__`` lists only names the module defines (DEVELOPING.md, "one
import path per public name").

``tests/test_import_graph.py`` catches ``from M import n`` where ``M`` does not define ``n``; a
facade module (``from .a import x, y`` + ``__all__ = ["x", "y"]``) used as ``import facade as
f; f.x`` slips past it and gives ``x`` two import paths. This checks the facade itself: every
name in a module's ``__all__`` is defined there (a def, a class or an assignment at module
level, also inside ``if``/``try``), not imported. Checked on the source of both packages.
"""

from __future__ import annotations

import ast
from pathlib import Path

from test_import_graph import top_level_defs

ROOT = Path(__file__).resolve().parents[1]
TREES = (ROOT / "diffpos", ROOT / "services" / "diffpos_services")

#: modules of other owners still listing imported names (to be emptied by them; an entry that
#: no longer applies fails the test, so this list only shrinks)
PENDING: dict[str, set[str]] = {
    "diffpos/paths/model.py": {"DIFFRACTION_SLOTS", "MECHANISMS", "SPECULAR_SLOTS"},
    "services/diffpos_services/fusion/core.py": {"BEHIND_KEEP_EPOCHS", "FusionConfig"},
    "services/diffpos_services/replay/run.py": {"live_fusion_settings"},
}


def _exported(tree: ast.Module) -> list[str]:
    for n in tree.body:
        if (isinstance(n, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__"
                                              for t in n.targets)):
            return [e.value for e in n.value.elts if isinstance(e, ast.Constant)]
    return []


def facade_names(src: str) -> set[str]:
    """The names a module's ``__all__`` lists without defining them."""
    tree = ast.parse(src)
    return set(_exported(tree)) - top_level_defs(tree.body)


def test_every_name_in_all_is_defined_where_it_is_listed() -> None:
    found: dict[str, set[str]] = {}
    for top in TREES:
        for path in sorted(top.rglob("*.py")):
            bad = facade_names(path.read_text(encoding="utf-8"))
            if bad:
                found[str(path.relative_to(ROOT))] = bad
    new = {p: sorted(n - PENDING.get(p, set())) for p, n in found.items()
           if n - PENDING.get(p, set())}
    assert not new, f"modules listing imported names in __all__ (facades): {new}"
    stale = {p: sorted(n - found.get(p, set())) for p, n in PENDING.items()
             if n - found.get(p, set())}
    assert not stale, f"PENDING entries that no longer apply (remove them): {stale}"


def test_the_check_catches_a_facade_and_passes_a_definition() -> None:
    facade = "from p.a import f\nfrom p.b import G\n__all__ = ['G', 'f']\n"
    assert facade_names(facade) == {"G", "f"}
    own = ("try:\n    import x\n    OK = True\nexcept ImportError:\n    OK = False\n"
           "def f():\n    pass\nclass G:\n    pass\n__all__ = ['G', 'OK', 'f']\n")
    assert facade_names(own) == set()
