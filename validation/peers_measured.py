"""The same model in the peers' filters, on the measured DENSE slice.

The shipped slice (subject_a, 8 landmarks per contour, penalty drive), baseline (no effect) and
extended (``active_polar``), with the region and basis maps: the paper's cyclic EKF and the
reduced-order UKF with the ``dense`` command's 3 loops, and the iterated smoother; held-out RMSE
(px), NIS / dof, loops or iterations, seconds and peak traced memory. filterpy's full UKF does not
fit there (a state of about 1350 entries), so it has no row.
"""
from __future__ import annotations

from sfem_filters.cardiac import example_path, load_sequence, prepare, run

from ._core import fmt, md_table
from .peers import measure

NAME = "peers_measured"
TITLE = "The model in the peers' filters: the measured DENSE slice"
#: Needs the measured slice (``sfem_filters.datasets``: set SFEM_FILTERS_DATA).
NEEDS_DATA = True
FULL_COST = "about 30-40 min"
ESTIMATOR = {"cyclic_ekf": "cyclic", "smoother": "smoother", "roukf": "roukf"}
TIERS = {"quick": {"cases": [["baseline", "region"]], "methods": ["cyclic_ekf"], "loops": 1,
                   "max_iterations": 1},
         "full": {"cases": [["baseline", "region"], ["baseline", "basis"], ["extended", "region"],
                            ["extended", "basis"]],
                  "methods": ["cyclic_ekf", "smoother", "roukf"], "loops": 3, "max_iterations": None}}
TOLERANCES = {"*": (1e-4, 1e-6), "seconds": None, "peak_MB": None, "failed": None}


def compute(settings: dict, out_dir) -> dict:
    setup = prepare(load_sequence(example_path()), 8)
    rows = []
    for model_name, param in settings["cases"]:
        effects = ("active_polar",) if model_name == "extended" else ()
        for method in settings["methods"]:
            r, sec, peak, err = measure(lambda: run(setup, effects, "penalty", param, max_loops=settings["loops"],
                                                    estimator=ESTIMATOR[method],
                                                    max_iterations=settings["max_iterations"]))
            row = {"model": model_name, "map": param, "method": method, "seconds": sec, "peak_MB": peak}
            if err is not None:
                rows.append({**row, "failed": err})
                continue
            row.update({"heldout_rmse_px": r.metrics["heldout_rmse_px"], "nis_over_dof": r.metrics["nis_mean_over_dof"],
                        "loops": int(r.result.loops), "converged": bool(r.result.converged)})
            rows.append(row)
    return {"rows": rows}


def markdown(results: dict) -> str:
    cols = ["model", "map", "method", "held-out RMSE [px]", "NIS / dof", "loops or iterations", "seconds", "peak MB"]
    body = []
    for r in results["rows"]:
        if "failed" in r:
            body.append([r["model"], r["map"], r["method"], "failed: " + r["failed"].replace("|", "/"), "", "",
                         fmt(r["seconds"], ".0f"), ""])
        else:
            body.append([r["model"], r["map"], r["method"], fmt(r["heldout_rmse_px"], ".3f"),
                         fmt(r["nis_over_dof"], ".2f"), f"{r['loops']}{'' if r['converged'] else ' (limit)'}",
                         fmt(r["seconds"], ".0f"), fmt(r["peak_MB"], ".0f")])
    return md_table(cols, body) + "\n\nExtended: the baseline plus the `active_polar` effect."


def check(results: dict, tier: str) -> list:
    """Held-out RMSE finite and between 0.05 and 2 px, NIS / dof positive, for every method that ran;
    the cyclic EKF and the smoother run everywhere."""
    problems = []
    for r in results["rows"]:
        if "failed" in r:
            if r["method"] != "roukf":
                problems.append(f"{r['model']} {r['map']} {r['method']} failed: {r['failed']}")
            continue
        if not (r["heldout_rmse_px"] is not None and 0.05 < r["heldout_rmse_px"] < 2):
            problems.append(f"{r['model']} {r['map']} {r['method']}: held-out RMSE {r['heldout_rmse_px']}")
        if not (r["nis_over_dof"] is not None and r["nis_over_dof"] > 0):
            problems.append(f"{r['model']} {r['map']} {r['method']}: NIS / dof {r['nis_over_dof']}")
    return problems
