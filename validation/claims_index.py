"""The validation index's table of claims, generated from each claim's stored results.

:func:`claims_table` lists every claim of :data:`validation.CLAIMS` (its page, its name) with the wall
time and date of the full tier's last run, read from the provenance of ``docs/_generated/<name>.json``,
so that the cost a reader sees is the one measured, not one typed by hand. ``python -m validation
run`` and ``render`` rewrite ``docs/_generated/claims.md`` (:func:`write_claims_table`) whenever they
write into ``docs/_generated/``; the docs' validation index includes it.
"""
from __future__ import annotations

import json
from pathlib import Path

from . import CLAIMS, claim
from ._core import GENERATED

__all__ = ["claims_table", "last_full_run", "write_claims_table", "INDEX_NAME"]

#: The generated table's file name under ``docs/_generated/``.
INDEX_NAME = "claims.md"


def _duration(seconds: float) -> str:
    """``"14 s"`` below two minutes, else ``"29 min"`` (rounded)."""
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def last_full_run(name: str, folder: Path = GENERATED) -> str | None:
    """``"29 min, 2026-11-27"``: the wall time and date of claim ``name``'s last full run, from its stored
    provenance in ``folder``; None where no full run is stored."""
    path = Path(folder) / f"{name}.json"
    if not path.is_file():
        return None
    prov = json.loads(path.read_text()).get("provenance", {})
    if prov.get("tier") != "full" or prov.get("wall_seconds") is None:
        return None
    return f"{_duration(float(prov['wall_seconds']))}, {str(prov.get('date_utc', ''))[:10]}"


def claims_table(folder: Path = GENERATED) -> str:
    """The Markdown table of every claim: page link, name, the last full run's wall time and date (from the
    stored JSON's provenance in ``folder``), or "not run" where no full run is stored."""
    rows = ["| claim | name | last full run |", "|---|---|---|"]
    for name in CLAIMS:
        took = last_full_run(name, folder) or "not run"
        rows.append(f"| [{claim(name).TITLE}]({name}.md) | `{name}` | {took} |")
    return "\n".join(rows) + ("\n\nLast full run: the wall time of the claim's full tier as its stored provenance "
                              "records it, on the machine and at the load its page's header names.\n")


def write_claims_table(folder: Path = GENERATED) -> Path:
    """Write :func:`claims_table` to ``folder / INDEX_NAME``; returns the path."""
    out = Path(folder) / INDEX_NAME
    out.write_text(claims_table(folder))
    return out
