"""Wall time of whole cyclic runs, every loop, as the library's commands run them.

Cases: the pinned benchmark at refinement 3 (247 nodes, 864 per-element parameters), seed 0, all
three strategies with the spec's loop schedule (relative material change below 1e-3, at most 50
loops), as ``sfem-filters compare --refine 3``; the measured DENSE slice (8 landmarks per
contour, penalty drive; the ``dense`` command's baseline, ``+`` with the ``active_polar`` effect)
with the per-element map and the 12-region map (3 loops, the command's default) and the smooth
basis (at most 50 loops). Per case: state size, loops against the limit, convergence, the last
relative change, seconds and seconds per loop, and for DENSE each loop's material step against
its posterior sd (:func:`sfem_filters.filtering.diagnostics.material_drift`). The smoother's
whole runs are :mod:`validation.whole_runs_smoother`.
"""
from __future__ import annotations

import time
import warnings

from sfem_filters.benchmark import STRATEGIES, pinned_benchmark, run_strategy
from sfem_filters.cardiac import build_model, example_path, load_sequence, prepare
from sfem_filters.filtering import cyclic_estimate
from sfem_filters.filtering.diagnostics import material_drift

from ._core import fmt, md_table

NAME = "whole_runs"
TITLE = "Whole cyclic runs: loops and wall time"
#: Needs the measured slice (``sfem_filters.datasets``: set SFEM_FILTERS_DATA).
NEEDS_DATA = True
FULL_COST = "about 15-25 min"
TIERS = {"quick": {"benchmark_refine": 1, "dense": [["region", [], 1]]},
         "full": {"benchmark_refine": 3,
                  "dense": [["element", [], 3], ["region", [], 3], ["basis", [], 50],
                            ["element", ["active_polar"], 3], ["region", ["active_polar"], 3],
                            ["basis", ["active_polar"], 50]]}}
#: Loops, convergence and the relative changes are deterministic; the seconds are not compared.
TOLERANCES = {"*": (1e-6, 1e-12), "seconds": None, "seconds_per_loop": None}


def _row(name, model, result, seconds, limit) -> dict:
    return {"case": name, "nodes": int(model.mesh.n_nodes), "params": int(model.dim_theta),
            "state": int(model.dim_state), "loops": int(result.loops), "limit": int(limit),
            "converged": bool(result.converged), "rel_changes": [float(r) for r in result.rel_changes],
            "seconds": float(seconds), "seconds_per_loop": float(seconds / max(result.loops, 1))}


def compute(settings: dict, out_dir) -> dict:
    warnings.simplefilter("ignore", RuntimeWarning)
    rows = []
    r = settings["benchmark_refine"]
    bench = pinned_benchmark(0, refine=r)
    for s in STRATEGIES:
        run = run_strategy(bench, s)
        rows.append(_row(f"benchmark r={r} {s}", run.model, run.result, run.metrics["seconds"], 50))
    setup = prepare(load_sequence(example_path()), 8)
    for param, effects, loops in settings["dense"]:
        model, y = build_model(setup, tuple(effects), "penalty", param)
        t0 = time.perf_counter()
        result = cyclic_estimate(model, y, max_loops=loops, tol=1e-3, description=param)
        row = _row(f"DENSE subject_a {param}{'+' if effects else ''}", model, result, time.perf_counter() - t0,
                   loops)
        row["step_over_sd"] = [float(d) for d in material_drift(model, result.history)["max_sd"]]
        rows.append(row)
    return {"rows": rows}


def _series(values, head=6, tail=3) -> str:
    txt = [f"{v:.2e}" for v in values]
    return ", ".join(txt if len(txt) <= head + tail else txt[:head] + ["..."] + txt[-tail:])


def markdown(results: dict) -> str:
    cols = ["case", "nodes", "params", "state n", "loops", "limit", "converged", "last rel. change", "wall s",
            "s / loop"]
    body = [[r["case"], r["nodes"], r["params"], r["state"], r["loops"], r["limit"], "yes" if r["converged"] else "no",
             fmt(r["rel_changes"][-1] if r["rel_changes"] else None, ".2e"), fmt(r["seconds"], ".1f"),
             fmt(r["seconds_per_loop"], ".2f")] for r in results["rows"]]
    dense = [r for r in results["rows"] if "step_over_sd" in r]
    drift = md_table(["case", "relative change per loop", "material step / posterior sd per loop"],
                     [[r["case"], _series(r["rel_changes"]), _series(r["step_over_sd"])] for r in dense])
    return (md_table(cols, body) + "\n\n`+`: with the `active_polar` effect. Model set-up excluded from the "
            "seconds.\n\n" + drift)


def check(results: dict, tier: str) -> list:
    """Every run made at least one loop and at most its limit; a converged run's last relative
    change is below 1e-3 and an unconverged one ran to its limit; the material steps are finite."""
    problems = []
    for r in results["rows"]:
        if not 1 <= r["loops"] <= r["limit"]:
            problems.append(f"{r['case']}: {r['loops']} loops, limit {r['limit']}")
        if r["converged"] and r["rel_changes"] and not r["rel_changes"][-1] < 1e-3:
            problems.append(f"{r['case']}: converged with a last change of {r['rel_changes'][-1]}")
        if not r["converged"] and r["loops"] != r["limit"]:
            problems.append(f"{r['case']}: stopped unconverged before its limit")
        if any(v is None for v in r.get("step_over_sd", [])):
            problems.append(f"{r['case']}: a material step is not finite")
    return problems
