"""Whole runs of the iterated smoother on the measured DENSE slice: iterations, cost and wall time.

The ``dense`` command's model (8 landmarks per contour, penalty drive; ``+`` with the
``active_polar`` effect) with the 12-region map, the smooth basis and the per-element map, the
smoother from the prior's material with at most ``max_iterations`` Gauss-Newton iterations, its
final covariance pass included. Each case runs in a fresh process (so its peak resident memory,
``ru_maxrss``, is its own): iterations, the stop reason, the MAP cost at the end and after every
iteration, each iteration's material step in posterior sd, seconds and peak MB.
"""
from __future__ import annotations

import concurrent.futures
import multiprocessing
import time
import warnings

from ._core import MIB, fmt, md_table, peak_rss_bytes

NAME = "whole_runs_smoother"
TITLE = "Whole smoother runs on the measured slice: iterations, MAP cost, time, memory"
#: Needs the measured slice (``sfem_filters.datasets``: set SFEM_FILTERS_DATA).
NEEDS_DATA = True
FULL_COST = "about 10-20 min"
TIERS = {"quick": {"cases": [["basis", []]], "max_iterations": 1},
         "full": {"cases": [["region", []], ["basis", []], ["element", []], ["region", ["active_polar"]],
                            ["basis", ["active_polar"]], ["element", ["active_polar"]]], "max_iterations": 40}}
TOLERANCES = {"*": (1e-6, 1e-9), "seconds": None, "seconds_per_iteration": None, "peak_MB": None}


def one_case(param: str, effects: list, max_iterations: int) -> dict:
    """One smoother run in this process (a fresh one: its peak memory is the case's)."""
    from sfem_filters.cardiac import build_model, example_path, load_sequence, prepare
    from sfem_filters.filtering import IteratedSmoother
    warnings.simplefilter("ignore", RuntimeWarning)
    setup = prepare(load_sequence(example_path()), 8)
    model, y = build_model(setup, tuple(effects), "penalty", param)
    t0 = time.perf_counter()
    res = IteratedSmoother(max_iterations=max_iterations).run(model, y, description=param)
    sec = time.perf_counter() - t0
    return {"case": f"DENSE subject_a {param}{'+' if effects else ''}", "nodes": int(model.mesh.n_nodes),
            "params": int(model.dim_theta), "state": int(model.dim_state), "iterations": int(res.iterations),
            "limit": int(max_iterations), "stop": str(res.stop_reason), "cost": float(res.cost),
            "costs": [float(r["cost"]) for r in res.records], "step_sd": [float(r["step_sd"]) for r in res.records],
            "seconds": sec, "seconds_per_iteration": sec / max(res.iterations, 1),
            "peak_MB": peak_rss_bytes() / MIB}


def compute(settings: dict, out_dir) -> dict:
    rows = []
    ctx = multiprocessing.get_context("spawn")
    for param, effects in settings["cases"]:
        with concurrent.futures.ProcessPoolExecutor(1, mp_context=ctx) as pool:
            rows.append(pool.submit(one_case, param, effects, settings["max_iterations"]).result())
    return {"rows": rows}


def markdown(results: dict) -> str:
    cols = ["case", "nodes", "params", "state n", "iterations", "limit", "stop", "MAP cost", "wall s", "s / iteration",
            "peak MiB"]
    body = [[r["case"], r["nodes"], r["params"], r["state"], r["iterations"], r["limit"], r["stop"],
             fmt(r["cost"], ".3f"), fmt(r["seconds"], ".1f"), fmt(r["seconds_per_iteration"], ".2f"),
             fmt(r["peak_MB"], ".0f")] for r in results["rows"]]
    path = md_table(["case", "MAP cost after each iteration", "material step / sd"],
                    [[r["case"], ", ".join(f"{c:.3f}" for c in r["costs"]), ", ".join(f"{s:.2e}" for s in r["step_sd"])]
                     for r in results["rows"]])
    return (md_table(cols, body) + "\n\n`+`: with the `active_polar` effect; peak MiB: the case's process's peak "
            "resident memory in mebibytes (2**20 bytes).\n\n" + path)


def check(results: dict, tier: str) -> list:
    """The MAP cost never rises from one iteration to the next; iterations within the limit; the
    cost finite."""
    problems = []
    for r in results["rows"]:
        if not 1 <= r["iterations"] <= r["limit"]:
            problems.append(f"{r['case']}: {r['iterations']} iterations, limit {r['limit']}")
        if r["cost"] is None:
            problems.append(f"{r['case']}: cost not finite")
        if any(b > a + 1e-9 * abs(a) for a, b in zip(r["costs"], r["costs"][1:])):
            problems.append(f"{r['case']}: the MAP cost rose")
    return problems
