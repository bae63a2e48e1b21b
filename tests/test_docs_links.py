"""The documentation's own rules (DEVELOPING.md, "Rules"): the README is a front door of at most
``README_MAX_LINES`` lines, and every relative link or image in README.md, DEVELOPING.md,
benchmarks/README.md and docs/ resolves to a file or folder of the repository.

A link is markdown's inline form ``[text](target)`` or ``![alt](target)`` outside code (fenced
blocks and inline code spans are text, not links); web addresses and in-page anchors are not
checked, a ``#fragment`` after a path is dropped.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 250
DOCS = sorted({ROOT / "README.md", ROOT / "DEVELOPING.md", ROOT / "benchmarks" / "README.md",
               *(ROOT / "docs").rglob("*.md")})
LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^\s*(```|~~~)")
CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1")


def links(text: str) -> list[tuple[int, str]]:
    """``(line number, target)`` of every inline link and image outside code."""
    out, fenced = [], False
    for no, line in enumerate(text.splitlines(), 1):
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            out += [(no, m.group(1)) for m in LINK.finditer(CODE_SPAN.sub("", line))]
    return out


def broken(path: Path) -> list[str]:
    """The relative links of one markdown file that name no existing file or folder."""
    bad = []
    for no, target in links(path.read_text(encoding="utf-8")):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I) or target.startswith("#"):
            continue  # a web address (http:, mailto:) or an anchor in the same page
        rel = target.split("#", 1)[0]
        if not (path.parent / rel).exists():
            bad.append(f"{path.relative_to(ROOT)}:{no}: {target}")
    return bad


def test_link_parser_finds_links_and_skips_code():
    text = ("see [a](x.md) and ![img](pics/p.png), [b](https://e.org), [c](#top)\n"
            "`[not](code.md)` [d](y.md#part)\n```\n[fenced](z.md)\n```\n[e](<w.md>)\n")
    assert [t for _, t in links(text)] == ["x.md", "pics/p.png", "https://e.org", "#top",
                                           "y.md#part", "w.md"]


def test_broken_link_is_reported(tmp_path):
    (tmp_path / "there.md").write_text("x")
    page = tmp_path / "page.md"
    page.write_text("[ok](there.md) [ok](there.md#a) [web](http://x) [gone](missing.md)\n")
    global ROOT
    root, ROOT = ROOT, tmp_path
    try:
        assert broken(page) == ["page.md:1: missing.md"]
    finally:
        ROOT = root


@pytest.mark.parametrize("path", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(path):
    bad = broken(path)
    assert not bad, "broken relative links (fix the target or the link):\n" + "\n".join(bad)


def test_readme_is_a_front_door():
    n = len((ROOT / "README.md").read_text(encoding="utf-8").splitlines())
    assert n <= README_MAX_LINES, (
        f"README.md has {n} lines (> {README_MAX_LINES}): move dated measurements, histories "
        "and investigations to docs/ (each figure with its command) and link them")
