"""How far the Gauss-Newton curvature is from the exact one on the measured slice.

    OPENBLAS_NUM_THREADS=1 python benchmarks/hessian_check.py [--parameterisation region]
        [--effects NAME,...] [--landmarks 8] [--at 10] [--step-sd 0.1]

The iterated smoother steps with, and reports the inverse of, the Gauss-Newton Hessian of the
profile cost J_p(theta) (:mod:`sfem_filters.filtering.curvature`). This script takes the exact
Hessian by central differences of the exact gradient (2 p gradient passes) at two points of the
``dense`` command's smoother run on the shipped DENSE slice (subject_a, its model and split):

* after ``--at`` iterations (the issue's budget is 10), where the run still has far to go;
* at the mode (the run to its stop rule, resumed from the first point's checkpoint).

Printed per point: the MAP cost, the gradient's size (max over parameters of |g| times the
Gauss-Newton sd: nats per sd), the eigenvalues of the exact Hessian relative to Gauss-Newton's
(1 where Gauss-Newton is exact, below 0 along a direction of negative curvature, which no
Gauss-Newton model can represent), the parameter that dominates the lowest one, the Newton
decrements of both models (the decrease each predicts to its own stationary point) and the
differencing asymmetry. At the mode also the marginal sds of the exact Laplace covariance over the
Gauss-Newton ones, for the stiffness (relative log E) and Poisson (nu) parameters apart.
About 15 minutes for the 23-parameter region map on one BLAS thread.
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
import warnings

import numpy as np
import scipy.linalg as sla

from sfem_filters.cardiac import measured
from sfem_filters.cardiac.sequence import example_path, load_sequence
from sfem_filters.filtering import IteratedSmoother, profile_hessian


def _decrement(H, g) -> float:
    """The decrease the quadratic model with Hessian H predicts to its stationary point (nats);
    NaN where H is not positive definite (no minimum)."""
    try:
        return float(0.5 * g @ sla.cho_solve(sla.cho_factor(H), g))
    except np.linalg.LinAlgError:
        return float("nan")


def _point(label, model, y, result, step_sd, names):
    t0 = time.perf_counter()
    curv = profile_hessian(model, y, result.states, step_sd=step_sd, progress=True)
    seconds = time.perf_counter() - t0
    w, V = sla.eigh(curv.hessian, curv.gauss_newton)
    sd = np.sqrt(np.diag(sla.inv(curv.gauss_newton)))
    lowest = V[:, 0] / np.abs(V[:, 0]).max()
    k = int(np.argmax(np.abs(lowest)))
    print(f"{label:<14}{result.iterations:>5}{result.cost:>11.3f}{np.abs(curv.gradient * sd).max():>9.3f}"
          f"{w[0]:>9.3f}{w[-1]:>8.3f}{int(np.sum(w < 0)):>5}  {names[k]:<10}{_decrement(curv.gauss_newton, curv.gradient):>9.3f}"
          f"{_decrement(curv.hessian, curv.gradient):>9.3f}{curv.asymmetry:>10.1e}{seconds:>8.0f}", flush=True)
    return curv


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--parameterisation", default="region", choices=("region", "basis"))
    ap.add_argument("--effects", default="", help="comma-separated effects of the model (default: none, the baseline)")
    ap.add_argument("--landmarks", type=int, default=8)
    ap.add_argument("--at", type=int, default=10, help="iterations before the first point (default 10)")
    ap.add_argument("--step-sd", type=float, default=0.1, help="difference step in Gauss-Newton sds")
    args = ap.parse_args(argv)
    effects = tuple(e for e in args.effects.split(",") if e)
    setup = measured.prepare(load_sequence(example_path()), args.landmarks)
    model, y = measured.build_model(setup, effects, "penalty", args.parameterisation)
    p = model.dim_theta
    n_log_e = model.parameterisation.basis_E.shape[1]           # theta = [log E modes; logit(2 nu) modes]
    names = [f"logE[{i}]" for i in range(n_log_e)] + [f"nu[{i}]" for i in range(p - n_log_e)]
    print(f"DENSE subject_a, {args.parameterisation}{'+' + '+'.join(effects) if effects else ''}, "
          f"{args.landmarks} landmarks, p = {p}; exact Hessian by central differences ({2 * p + 1} gradient passes, "
          f"step {args.step_sd:g} sd)")
    print(f"{'point':<14}{'iter':>5}{'MAP cost':>11}{'|g| sd':>9}{'eig min':>9}{'max':>8}{'neg':>5}  "
          f"{'lowest on':<10}{'dec GN':>9}{'dec ex':>9}{'asym':>10}{'s':>8}")
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="iterated smoother: stopped by")
        warnings.filterwarnings("ignore", message="filter inconsistent")
        cp = os.path.join(tmp, "run.npz")
        early = IteratedSmoother(max_iterations=args.at, covariance=False).run(model, y, checkpoint=cp)
        _point(f"after {args.at}", model, y, early, args.step_sd, names)
        mode = IteratedSmoother(max_iterations=100, covariance=False).run(model, y, checkpoint=cp)
        curv = _point(f"mode ({mode.stop_reason})", model, y, mode, args.step_sd, names)
    if curv.positive_definite():
        ratio = curv.sd_ratio()
        print("exact Laplace sd / Gauss-Newton sd, per parameter:", " ".join(f"{r:.2f}" for r in ratio))
        print(f"  stiffness (log E, {n_log_e}): {ratio[:n_log_e].min():.2f}-{ratio[:n_log_e].max():.2f}; "
              f"Poisson (logit 2 nu, {p - n_log_e}): {ratio[n_log_e:].min():.2f}-{ratio[n_log_e:].max():.2f}")
    else:
        print("the exact Hessian at the mode is not positive definite: no exact Laplace covariance")


if __name__ == "__main__":
    main()
