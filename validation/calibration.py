"""Calibration of the material posterior (the pinned check of simulation-based calibration).

Material drawn from the prior, N replicates (``numpy.random.default_rng(1000 + i)``), per estimator:
ANEES / p (1 when calibrated, with its 95% band for N p) and the coverage of the 95% intervals
(with its Wilson interval), by :func:`sfem_filters.benchmark.calibration.calibrate`. Problems:
``pinned`` (the spec's: the truth moves without process noise) and ``pinned_process_noise`` (the
truth moves with the process noise the filter assumes). The annulus problem is its own claim,
``calibration_annulus``.
"""
from __future__ import annotations

import math

from sfem_filters.benchmark.calibration import ESTIMATORS, calibrate

from ._core import fmt, md_table

NAME = "calibration"
TITLE = "Calibration of the material posterior (ANEES and coverage)"
FULL_COST = "10-25 min"
TIERS = {"quick": {"problems": ["pinned"], "n": 5,
                   "estimators": ["cyclic_ekf", "cyclic_ekf_one_cycle", "iterated_smoother"]},
         "full": {"problems": ["pinned", "pinned_process_noise"], "n": 200, "estimators": list(ESTIMATORS)}}
TOLERANCES = {"*": (1e-6, 1e-9), "seconds_median": None}


def compute(settings: dict, out_dir) -> dict:
    rows = []
    for problem in settings["problems"]:
        for cal in calibrate(problem, settings["estimators"], n=settings["n"]).values():
            rows.append(cal.summary())
    return {"rows": rows}


def markdown(results: dict) -> str:
    cols = ["problem", "estimator", "N", "p", "ANEES / p", "95% band", "coverage", "Wilson 95%", "converged",
            "s / run", "Q factor (median)", "prior check chi2 / dof"]
    body = [[r["problem"], r["estimator"], r["n"], r["p"], fmt(r["anees_over_p"], ".3f"),
             f"{r['anees_band'][0]:.2f}-{r['anees_band'][1]:.2f}", fmt(r["coverage"], ".3f"),
             f"{r['coverage_interval'][0]:.3f}-{r['coverage_interval'][1]:.3f}", f"{r['converged']}/{r['n']}",
             fmt(r["seconds_median"], ".2f"), fmt(r["process_noise_scale_median"], ".3g"),
             fmt(r.get("prior_check_chi2_over_dof"), ".3f")] for r in results["rows"]]
    return (md_table(cols, body) + "\n\nANEES / p: mean normalised estimation error squared of theta over p; "
            "calibrated: inside the band. Coverage: fraction of the N p parameter values inside the 95% "
            "intervals. `_one_cycle`: the cyclic filter's carried covariance corrected to one cycle's information.")


def check(results: dict, tier: str) -> list:
    """ANEES / p finite and positive, coverage in [0, 1]; in the full tier, the spec's cyclic EKF
    overconfident (ANEES / p above its band) and the smoother with Q estimated inside 0.8-1.25."""
    problems = []
    for r in results["rows"]:
        a, c = r["anees_over_p"], r["coverage"]
        if a is None or not (math.isfinite(a) and a > 0):
            problems.append(f"{r['problem']} {r['estimator']}: ANEES / p {a}")
        if c is None or not 0 <= c <= 1:
            problems.append(f"{r['problem']} {r['estimator']}: coverage {c}")
    if tier == "full":
        by = {(r["problem"], r["estimator"]): r for r in results["rows"]}
        ekf = by.get(("pinned", "cyclic_ekf"))
        if ekf and not ekf["anees_over_p"] > ekf["anees_band"][1]:
            problems.append("pinned cyclic_ekf: not overconfident")
        for problem in ("pinned", "pinned_process_noise"):
            q = by.get((problem, "smoother_estimated_q"))
            if q and not 0.8 <= q["anees_over_p"] <= 1.25:
                problems.append(f"{problem} smoother_estimated_q: ANEES / p {q['anees_over_p']}")
    return problems
