"""The smoother's posterior against the exact marginal posterior of the material (2-region map).

Given the material, the pinned benchmark's kinematics are linear-Gaussian, so one Kalman pass gives
the exact log p(y | theta); its maximum with the prior (the marginal MAP) and the inverse Hessian
there are compared with the iterated smoother's joint mode and Gauss-Newton covariance by
:func:`sfem_filters.filtering.laplace_check`: the distance of the modes in marginal sd, the ratio
of the sds and the KL divergence.
"""
from __future__ import annotations

import numpy as np

from sfem_filters import Parameterisation
from sfem_filters.benchmark import benchmark_model, pinned_benchmark
from sfem_filters.filtering import IteratedSmoother, laplace_check

from ._core import md_table

NAME = "laplace"
TITLE = "The smoother's Laplace posterior against the exact marginal posterior"
FULL_COST = "under a minute"
TIERS = {"quick": {"seeds": [0]}, "full": {"seeds": [0, 1, 2, 3, 4]}}
#: The marginal's own evaluations depend on round-off in its line search; the figures do not.
TOLERANCES = {"*": (1e-3, 1e-5), "evaluations": None}


def compute(settings: dict, out_dir) -> dict:
    rows = []
    for seed in settings["seeds"]:
        bench = pinned_benchmark(seed)
        model = benchmark_model(bench, "joint_ekf", parameterisation=Parameterisation.per_region(bench.middle))
        res = IteratedSmoother().run(model, bench.observations)
        c = laplace_check(model, bench.observations, res.theta, res.P_theta)
        rows.append({"seed": seed, "iterations": int(res.iterations), "max_abs_z_mode": float(np.abs(c.z_mode).max()),
                     "sd_ratio_min": float(c.sd_ratio.min()), "sd_ratio_max": float(c.sd_ratio.max()),
                     "kl_nats": float(c.kl), "evaluations": int(c.evaluations)})
    return {"rows": rows}


def markdown(results: dict) -> str:
    cols = ["seed", "iterations", "max abs mode difference / sd", "sd ratio min-max", "KL [nats]", "passes"]
    body = [[r["seed"], r["iterations"], f"{r['max_abs_z_mode']:.4f}",
             f"{r['sd_ratio_min']:.3f}-{r['sd_ratio_max']:.3f}", f"{r['kl_nats']:.5f}", r["evaluations"]]
            for r in results["rows"]]
    return (md_table(cols, body) + "\n\nMode difference: smoother's mode minus the marginal MAP, in marginal sd; "
            "sd ratio: smoother sd over marginal sd, per parameter; passes: the exact marginal's evaluations.")


def check(results: dict, tier: str) -> list:
    """The modes within 0.05 marginal sd and the sds within 10% of each other, KL below 0.01 nats."""
    problems = []
    for r in results["rows"]:
        if not r["max_abs_z_mode"] < 0.05:
            problems.append(f"seed {r['seed']}: modes {r['max_abs_z_mode']} sd apart")
        if not 0.9 < r["sd_ratio_min"] <= r["sd_ratio_max"] < 1.1:
            problems.append(f"seed {r['seed']}: sd ratio {r['sd_ratio_min']}-{r['sd_ratio_max']}")
        if not 0 <= r["kl_nats"] < 0.01:
            problems.append(f"seed {r['seed']}: KL {r['kl_nats']}")
    return problems
