"""Calibration on the synthetic annulus: a 12-region map (p = 23) moved by the measured-data model.

As :mod:`validation.calibration`, on :func:`sfem_filters.benchmark.calibration.annulus_problem`
with the iterated smoother: ANEES / p, coverage of the material's 95% intervals and of the
smoothed strains' (over every frame, node and component).
"""
from __future__ import annotations

from sfem_filters.benchmark.calibration import calibrate

from . import calibration

NAME = "calibration_annulus"
TITLE = "Calibration on the synthetic annulus (p = 23, strain coverage)"
FULL_COST = "about 15-30 min"
TIERS = {"quick": {"n": 1, "estimators": ["iterated_smoother"]},
         "full": {"n": 100, "estimators": ["iterated_smoother"]}}
TOLERANCES = calibration.TOLERANCES


def compute(settings: dict, out_dir) -> dict:
    cals = calibrate("annulus", settings["estimators"], n=settings["n"])
    return {"rows": [c.summary() for c in cals.values()]}


def markdown(results: dict) -> str:
    return calibration.markdown(results) + " Strain coverage: " + ", ".join(
        f"{r['estimator']} {r['strain_coverage']:.3f}" for r in results["rows"] if r["strain_coverage"] is not None)


def check(results: dict, tier: str) -> list:
    problems = calibration.check(results, "quick")
    for r in results["rows"]:
        sc = r["strain_coverage"]
        if sc is None or not 0 < sc <= 1:
            problems.append(f"{r['estimator']}: strain coverage {sc}")
    if tier == "full":
        problems += [f"{r['estimator']}: ANEES / p {r['anees_over_p']}" for r in results["rows"]
                     if not 0.8 <= r["anees_over_p"] <= 1.25]
    return problems
