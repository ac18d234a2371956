"""The same model in the peers' filters: filterpy's UKF and the reduced-order UKF, synthetic part.

Four methods on one model object, the pinned benchmark (r = 1) with the per-element map (p = 96)
and the 2-region map (p = 4), per seed: ``cyclic_ekf`` (the paper's cyclic joint EKF, until the
relative material change is below 1e-3 or its loop limit), ``smoother`` (the iterated smoother),
``ukf`` (filterpy's ``UnscentedKalmanFilter`` in the same cyclic driver, ``engine="ukf"``) and
``roukf`` (Moireau & Chapelle's reduced-order UKF, ``engine="roukf"``). Reported over the seeds
(mean): relative E error in the middle part and outside it, ANEES / p of theta against the truth
(with the covariance of one cycle and, for the cyclic methods, the carried one), loops or
iterations, seconds and peak traced memory (tracemalloc, MB).
"""
from __future__ import annotations

import time
import tracemalloc
import warnings

import numpy as np
import scipy.linalg as sla

from sfem_filters import Parameterisation
from sfem_filters.benchmark import benchmark_model, pinned_benchmark
from sfem_filters.filtering import CyclicEKF, IteratedSmoother

from ._core import fmt, md_table

NAME = "peers"
TITLE = "The model in the peers' filters (filterpy's UKF, reduced-order UKF): synthetic"
FULL_COST = "about 15-25 min"
METHODS = ("cyclic_ekf", "smoother", "ukf", "roukf")
ENGINE = {"cyclic_ekf": "structured", "ukf": "ukf", "roukf": "roukf"}
MAPS = ("2 regions", "element")
TIERS = {"quick": {"seeds": [0], "maps": ["2 regions"], "methods": list(METHODS),
                   "max_loops": {"cyclic_ekf": 50, "ukf": 1, "roukf": 3}},
         "full": {"seeds": [0, 1, 2, 3, 4], "maps": list(MAPS), "methods": list(METHODS),
                  "max_loops": {"cyclic_ekf": 50, "ukf": 5, "roukf": 10}}}
TOLERANCES = {"*": (1e-6, 1e-9), "seconds": None, "peak_MB": None}


def measure(fn):
    """``(result or None, seconds, peak MB, error or None)``: a method that fails is a result."""
    tracemalloc.start()
    t0 = time.perf_counter()
    out, err = None, None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            out = fn()
    except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
        err = f"{type(exc).__name__}: {str(exc)[:160]}"
    sec = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    return out, sec, peak, err


def nees_over_p(theta, theta_true, P) -> float:
    d = np.asarray(theta) - theta_true
    return float(d @ sla.cho_solve(sla.cho_factor(P), d)) / len(d)


def estimate(method, model, y, max_loops):
    if method == "smoother":
        return IteratedSmoother().run(model, y)
    return CyclicEKF(engine=ENGINE[method], max_loops=max_loops[method]).run(model, y)


def compute(settings: dict, out_dir) -> dict:
    runs = []
    for seed in settings["seeds"]:
        bench = pinned_benchmark(seed)
        for map_name in settings["maps"]:
            param = Parameterisation.per_region(bench.middle) if map_name == "2 regions" else None
            model = benchmark_model(bench, "joint_ekf", parameterisation=param)
            theta_true = model.parameterisation.theta_of(bench.true_material)
            for method in settings["methods"]:
                res, sec, peak, err = measure(lambda: estimate(method, model, bench.observations,
                                                               settings["max_loops"]))
                row = {"seed": seed, "map": map_name, "method": method, "p": model.dim_theta,
                       "seconds": sec, "peak_MB": peak}
                if err is not None:
                    runs.append({**row, "failed": err})
                    continue
                mat = model.material_of_theta(res.theta)
                eE = np.abs(mat.E - bench.true_material.E) / bench.true_material.E
                row.update({"E_err_middle": float(eE[bench.middle].mean()),
                            "E_err_outside": float(eE[~bench.middle].mean()),
                            "nees_over_p": nees_over_p(res.theta, theta_true, res.posterior_cov),
                            "nees_over_p_carried": (None if method == "smoother" else
                                                    nees_over_p(res.theta, theta_true, res.P_theta)),
                            "loops": int(res.loops), "converged": bool(res.converged)})
                runs.append(row)
    return {"runs": runs, "summary": summarise(runs, settings)}


def summarise(runs, settings) -> list:
    out = []
    for map_name in settings["maps"]:
        for method in settings["methods"]:
            rs = [r for r in runs if r["map"] == map_name and r["method"] == method and "failed" not in r]
            if not rs:
                continue
            carried = [r["nees_over_p_carried"] for r in rs if r["nees_over_p_carried"] is not None]
            out.append({"map": map_name, "method": method, "seeds": len(rs),
                        "E_err_middle": float(np.mean([r["E_err_middle"] for r in rs])),
                        "E_err_outside": float(np.mean([r["E_err_outside"] for r in rs])),
                        "anees_over_p": float(np.mean([r["nees_over_p"] for r in rs])),
                        "anees_over_p_carried": float(np.mean(carried)) if carried else None,
                        "loops": float(np.mean([r["loops"] for r in rs])),
                        "limit": settings["max_loops"].get(method),
                        "seconds": float(np.mean([r["seconds"] for r in rs])),
                        "peak_MB": float(np.max([r["peak_MB"] for r in rs]))})
    return out


def markdown(results: dict) -> str:
    cols = ["map", "method", "E err mid", "E err out", "ANEES / p", "carried", "loops", "loop limit", "seconds",
            "peak MB"]
    body = [[r["map"], r["method"], fmt(r["E_err_middle"], ".3f"), fmt(r["E_err_outside"], ".3f"),
             fmt(r["anees_over_p"], ".3g"), fmt(r["anees_over_p_carried"], ".3g"), fmt(r["loops"], ".1f"),
             r["limit"] if r["limit"] is not None else "-", fmt(r["seconds"], ".1f"), fmt(r["peak_MB"], ".0f")]
            for r in results["summary"]]
    failed = [r for r in results["runs"] if "failed" in r]
    notes = ["Mean over the seeds; ANEES / p of theta against the truth with the covariance of one cycle, "
             "`carried`: the cyclic methods' carried covariance; loops: cyclic loops or the smoother's "
             "Gauss-Newton iterations."]
    notes += [f"Failed: seed {r['seed']} {r['map']} {r['method']}: {r['failed']}" for r in failed]
    return md_table(cols, body) + "\n\n" + "\n".join(notes)


def check(results: dict, tier: str) -> list:
    """Every method ran; on the 2-region map the four E errors within 0.01 of each other and each
    below 0.05; ANEES / p finite and positive."""
    problems = [f"{r['map']} {r['method']} seed {r['seed']} failed: {r['failed']}"
                for r in results["runs"] if "failed" in r]
    two = [r for r in results["summary"] if r["map"] == "2 regions"]
    if two:
        mids = [r["E_err_middle"] for r in two]
        if not (max(mids) < 0.05 and max(mids) - min(mids) < 0.01):
            problems.append(f"2 regions: E errors in the middle {mids}")
    problems += [f"{r['map']} {r['method']}: ANEES / p {r['anees_over_p']}" for r in results["summary"]
                 if not (r["anees_over_p"] is not None and r["anees_over_p"] > 0)]
    return problems
