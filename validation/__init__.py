"""The validation suite: one module per claim the docs make, each regenerating its numbers.

Run from the repository root (the package is not installed with the wheel)::

    python -m validation list
    python -m validation run table1 --full          # writes docs/_generated/table1.json and .md
    python -m validation run --all --quick --out /tmp/quick
    python -m validation sync-readme                # README.md's generated blocks from their files

Each claim has a quick tier (seconds to a minute; the default test suite runs it as a subprocess,
``tests/test_validation_suite.py``) and a full tier, whose outputs are the files committed under
``docs/_generated/`` and shown by the pages of ``docs/validation/``; the slow tests rerun a full
tier and compare it with the stored JSON within the module's ``TOLERANCES``. Every output carries
its provenance (:func:`validation._core.provenance`). The modules use only the public names of
:mod:`sfem_filters` (those in some ``__all__``), so a rename breaks the suite's tests, not a user.
"""
from __future__ import annotations

import importlib

__all__ = ["CLAIMS", "claim"]

#: Claim name -> module (``validation.<module>``), in the order ``run --all`` runs them.
CLAIMS = {name: name for name in ("table1", "calibration", "calibration_annulus", "laplace", "peers", "peers_measured",
                                   "whole_runs", "whole_runs_smoother", "speed", "closing_loop", "rounds_synthetic",
                                   "search", "springs", "strain_dense_sim", "strain_contours", "border_views",
                                   "first_run", "strain_budget", "strain_variants", "strain_bands",
                                   "strain_resolution", "strain_draws")}


def claim(name: str):
    """The module of claim ``name``."""
    if name not in CLAIMS:
        raise ValueError(f"name: expected one of {list(CLAIMS)}, got {name!r}")
    return importlib.import_module(f"validation.{CLAIMS[name]}")
