"""Publishers say what happens under congestion (issue 15: tests that must not flake).

Zenoh's default congestion control is DROP: a publisher that outruns the link or a busy
subscriber silently loses messages (3 of 10 runs of a dashboard test lost 19 of 264 under
CPU load). Every publisher in the services, the tests and the benchmarks therefore names its
congestion control: ``declare_publisher(key, congestion_control=...)``, and a one-shot
``session.put(key, payload, congestion_control=...)``. What must arrive uses BLOCK; a DROP
is a visible choice in the code, never the silent default.

The rule is checked on the source (like ``test_import_rules.py``); a violation names the
file and the line.
"""

from __future__ import annotations

import ast
from pathlib import Path

import diffpos_services
import pytest

ROOT = Path(__file__).resolve().parents[1]
SERVICES = Path(diffpos_services.__file__).resolve().parent
#: (directory, also check session.put) - in the services a two-argument ``.put`` is mostly
#: numpy's ``ndarray.put``; their one-shot puts are reviewed by hand (fusion, emulate).
TREES = ((ROOT / "tests", True), (ROOT / "benchmarks", True), (SERVICES, False))


def _calls(path: Path):
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            yield node


def _violations(path: Path, *, check_put: bool) -> list[str]:
    """``file:line: what`` for each publisher without an explicit congestion control."""
    out = []
    rel = path.relative_to(ROOT) if ROOT in path.parents else path
    for call in _calls(path):
        kws = {k.arg for k in call.keywords}
        if "congestion_control" in kws or None in kws:  # None: **options
            continue
        name = call.func.attr
        if name == "declare_publisher":
            out.append(f"{rel}:{call.lineno}: declare_publisher without congestion_control")
        elif check_put and name == "put" and (len(call.args) >= 2 or "encoding" in kws):
            # session.put(key, payload): a queue's put takes one item
            out.append(f"{rel}:{call.lineno}: session.put without congestion_control")
    return out


def _sources():
    for top, check_put in TREES:
        for path in sorted(top.rglob("*.py")):
            yield path, check_put


def test_every_publisher_names_its_congestion_control():
    bad = [v for path, check_put in _sources() for v in _violations(path, check_put=check_put)]
    assert not bad, ("publishers on Zenoh's default (DROP, silent loss under load); pass "
                     "congestion_control=zenoh.CongestionControl.BLOCK for what must arrive:\n"
                     + "\n".join(bad))


@pytest.mark.parametrize(("code", "n"), [
    ("s.declare_publisher(k)", 1),
    ("s.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)", 0),
    ("s.put(k, b'x')", 1),
    ("s.put(k, b'x', congestion_control=zenoh.CongestionControl.BLOCK)", 0),
    ("q.put((k, b'x'))", 0),
    ("pub.put(b'x')", 0),  # a declared publisher's put: checked at its declaration
])
def test_the_rule_sees_default_publishers(tmp_path, code, n):
    f = tmp_path / "probe.py"
    f.write_text(code + "\n")
    assert len(_violations(f, check_put=True)) == n
