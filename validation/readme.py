"""Generated blocks in Markdown files, and results tables that are not generated.

A page shows a generated table either with MyST's ``{include}`` directive (the docs) or, where
Markdown has no includes (the README), between the lines ``<!-- generated: PATH -->`` and
``<!-- end generated -->``, PATH relative to the repository root: :func:`sync` rewrites every
such block from its file, :func:`stale_blocks` lists the ones that differ.
:func:`results_tables` finds the Markdown tables with a decimal number in a body cell outside
those blocks: a results table pasted by hand.
"""
from __future__ import annotations

import re
from pathlib import Path

from ._core import ROOT

BEGIN = re.compile(r"^<!-- generated: (?P<path>\S+) -->\s*$")
END = "<!-- end generated -->"
DECIMAL = re.compile(r"\d\.\d")
#: Not results: inline code (names, keys, options) and references to sections, equations, versions.
NOT_RESULTS = re.compile(r"`[^`]*`|\b(?:[Ss]ections?|Eqs?\.|[Ee]quations?|[Vv]ersion|Python|v)\s*\d+(?:\.\d+)+")
#: Folders of docs/ whose pages are not checked for pasted results: the generated tables
#: themselves, the frozen results of past investigations and the build outputs.
EXCLUDED = ("_generated", "frozen", "_build", "build", "auto_examples", "generated")


def blocks(text: str):
    """``(path, start, end)`` of every generated block: lines ``start`` (the marker) to ``end``
    (the end marker), 0-based."""
    lines = text.splitlines()
    out, i = [], 0
    while i < len(lines):
        m = BEGIN.match(lines[i])
        if m:
            for j in range(i + 1, len(lines)):
                if lines[j].strip() == END:
                    out.append((m.group("path"), i, j))
                    i = j
                    break
            else:
                raise ValueError(f"generated block of {m.group('path')} at line {i + 1} has no {END!r}")
        i += 1
    return out


def _content(path: str) -> list:
    """The lines of ``path`` (relative to the repository root, or absolute)."""
    return (ROOT / path).read_text().rstrip("\n").splitlines()


def rewrite(text: str) -> str:
    """``text`` with every generated block's lines replaced by its file's."""
    lines = text.splitlines()
    for path, start, end in reversed(blocks(text)):
        lines[start + 1:end] = _content(path)
    return "\n".join(lines) + ("\n" if text.endswith("\n") else "")


def sync(paths=None) -> list:
    """Rewrite the generated blocks of ``paths`` (default: README.md); returns the files changed."""
    changed = []
    for p in paths or [ROOT / "README.md"]:
        p = Path(p)
        if not p.exists():
            continue
        old = p.read_text()
        new = rewrite(old)
        if new != old:
            p.write_text(new)
            changed.append(str(p))
    return changed


def stale_blocks(path) -> list:
    """The generated blocks of ``path`` that differ from their file (or whose file is missing)."""
    text = Path(path).read_text()
    stale = []
    for src, start, end in blocks(text):
        if not (ROOT / src).exists():
            stale.append(f"{path}:{start + 1}: {src} does not exist")
        elif text.splitlines()[start + 1:end] != _content(src):
            stale.append(f"{path}:{start + 1}: differs from {src} (run python -m validation sync-readme)")
    return stale


def _cells(line: str) -> list:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def results_tables(path) -> list:
    """``(line, row)`` of every Markdown table body row with a decimal number in a cell, outside the
    generated blocks and fenced code (a table of names, shapes or keys has none; inline code and
    references such as "section 2.7" or "Python 3.10" do not count)."""
    text = Path(path).read_text()
    inside = set()
    for _, start, end in blocks(text):
        inside.update(range(start, end + 1))
    lines = text.splitlines()
    found, fence, i = [], None, 0
    while i < len(lines):
        s = lines[i].strip()
        if s.startswith(("```", "~~~")):
            mark = s[:3]
            fence = None if fence == mark else (fence or mark)
            i += 1
            continue
        is_table = (fence is None and i not in inside and s.startswith("|") and i + 1 < len(lines)
                    and re.match(r"^\|?\s*:?-{3,}", lines[i + 1].strip()))
        if not is_table:
            i += 1
            continue
        j = i + 2
        while j < len(lines) and lines[j].strip().startswith("|"):
            if any(DECIMAL.search(NOT_RESULTS.sub("", c)) for c in _cells(lines[j])):
                found.append((j + 1, lines[j].strip()))
            j += 1
        i = j
    return found


def checked_pages() -> list:
    """README.md and every Markdown page of docs/ but the excluded folders."""
    pages = [ROOT / "README.md"] if (ROOT / "README.md").exists() else []
    docs = ROOT / "docs"
    if docs.exists():
        pages += sorted(p for p in docs.rglob("*.md")
                        if not set(p.relative_to(docs).parts[:-1]) & set(EXCLUDED))
    return pages
