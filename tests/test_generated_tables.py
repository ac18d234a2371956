"""Every results table in the README and the docs is a generated file, shown as it was generated.

(a) The README's blocks between ``<!-- generated: PATH -->`` and ``<!-- end generated -->`` are
the files they name, line for line (``python -m validation sync-readme`` rewrites them).
(b) No page (README.md, docs/**/*.md but docs/_generated/, docs/frozen/ and build outputs) holds a
Markdown table with a decimal number in a body cell outside such a block: results come in by an
``{include}`` of a generated file, never pasted.
(c) Every ``{include}`` of a generated file names one that exists, so the pages build.
(d) Every stored result names the commit it was made at, from a clean tree (reproducible).
"""
from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from validation import readme  # noqa: E402

PAGES = readme.checked_pages()
INCLUDE = re.compile(r"^```\{include\}\s+(?P<path>\S+)\s*$", re.M)


def _ids(paths):
    return [str(p.relative_to(ROOT)) for p in paths]


@pytest.mark.parametrize("page", PAGES, ids=_ids(PAGES))
def test_generated_blocks_match_their_files(page):
    assert readme.stale_blocks(page) == []


@pytest.mark.parametrize("page", PAGES, ids=_ids(PAGES))
def test_no_results_table_pasted_by_hand(page):
    found = readme.results_tables(page)
    assert found == [], "results tables not generated (include a docs/_generated/ file instead):\n" + "\n".join(
        f"{page.relative_to(ROOT)}:{line}: {row[:100]}" for line, row in found)


@pytest.mark.parametrize("page", PAGES, ids=_ids(PAGES))
def test_included_generated_files_exist(page):
    for m in INCLUDE.finditer(page.read_text()):
        target = (page.parent / m.group("path")).resolve()
        if "_generated" in target.parts:
            assert target.exists(), f"{page.relative_to(ROOT)} includes {m.group('path')}, which does not exist"


def test_sync_rewrites_a_stale_block_and_leaves_the_rest(tmp_path):
    src = tmp_path / "t.md"
    src.write_text("| a | b |\n|---|---|\n| x | 1.5 |\n")
    text = f"intro\n<!-- generated: {src} -->\nold line\n<!-- end generated -->\noutro\n"
    page = tmp_path / "page.md"
    page.write_text(text)
    assert readme.blocks(text) == [(str(src), 1, 3)]
    assert readme.stale_blocks(page)
    assert readme.rewrite(text) == (f"intro\n<!-- generated: {src} -->\n| a | b |\n|---|---|\n| x | 1.5 |\n"
                                    "<!-- end generated -->\noutro\n")
    page.write_text(readme.rewrite(text))
    assert readme.stale_blocks(page) == [] and readme.results_tables(page) == []


def test_results_table_detection(tmp_path):
    page = tmp_path / "p.md"
    page.write_text("| name | shape |\n|---|---|\n| U | (16, 26) |\n\n"     # names and shapes: allowed
                    "```\n| in | code |\n|---|---|\n| 0.5 | 1.5 |\n```\n\n"     # a fenced block is not a table
                    "| case | RMSE |\n|---|---|\n| a | 0.544 |\n"                # a pasted result
                    "\n| file | what |\n|---|---|\n| `x = 0.5` | section 2.7, Python 3.10 |\n")
    assert [line for line, _ in readme.results_tables(page)] == [13]


def test_an_unterminated_block_is_an_error():
    with pytest.raises(ValueError, match="end generated"):
        readme.blocks("<!-- generated: docs/_generated/table1.md -->\n| a |\n")


STORED = sorted((ROOT / "docs" / "_generated").glob("*.json"))


@pytest.mark.parametrize("path", STORED, ids=_ids(STORED))
def test_stored_results_were_made_from_committed_code(path):
    """(d) Each stored claim names the commit it ran at, with a clean tree that stayed so: anyone can rerun it."""
    import json
    prov = json.loads(path.read_text())["provenance"]
    assert isinstance(prov.get("git_commit"), str) and len(prov["git_commit"]) == 40, prov.get("git_commit")
    assert prov.get("git_dirty") is False, f"{path.name}: made with uncommitted changes; rerun it at a commit"
    assert not prov.get("git_changed_during_run"), f"{path.name}: the code changed during its run; rerun it"


def test_the_index_of_claims_is_the_one_their_stored_results_give(tmp_path):
    """docs/_generated/claims.md (the validation index's table: each claim's last full run) is what
    claims_index renders from the stored JSON now, so a claim rerun without it is caught; a claim with no stored
    full run is listed as not run, and the durations are read from the provenance, not typed."""
    import json
    from validation import CLAIMS
    from validation.claims_index import INDEX_NAME, claims_table
    generated = ROOT / "docs" / "_generated"
    assert (generated / INDEX_NAME).read_text() == claims_table(generated), \
        "run `python -m validation render NAME` (or write_claims_table) after a claim's full run"
    (tmp_path / "table1.json").write_text(json.dumps({"provenance": {"tier": "full", "wall_seconds": 1740.0,
                                                                      "date_utc": "2026-01-02 03:04 UTC"}}))
    (tmp_path / "laplace.json").write_text(json.dumps({"provenance": {"tier": "quick", "wall_seconds": 5.0}}))
    rows = {line.split("|")[2].strip(" `"): line for line in claims_table(tmp_path).splitlines()[2:len(CLAIMS) + 2]}
    assert set(rows) == set(CLAIMS)
    assert "| 29 min, 2026-01-02 |" in rows["table1"] and "| not run |" in rows["laplace"]
    assert "| not run |" in rows["search"]
