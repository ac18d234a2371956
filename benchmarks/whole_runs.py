"""Wall time of whole runs, every loop or iteration, as the library's commands run them.

    OPENBLAS_NUM_THREADS=1 python benchmarks/whole_runs.py [--cases r3 element region basis]
        [--dense-loops 3] [--basis-loops 50] [--landmarks 8] [--effects NAME,...]
        [--estimator cyclic|smoother] [--max-iterations 20] [--start prior|ekf]

With ``--estimator smoother`` the DENSE cases run the iterated smoother (the ``dense`` command's
default) instead: iterations against the limit, the stop reason, the MAP cost, seconds (the final
covariance pass included), seconds per iteration, and the process's peak resident memory (MB,
``ru_maxrss``, which only grows: run one case per process to read it per case).

Cases (each one cyclic estimation, timed from the first loop to the stop, model set-up excluded):

* ``r3``: the pinned synthetic benchmark at refinement 3 (247 nodes, 864 per-element
  parameters), seed 0, all three strategies with the spec's loop schedule (until the relative
  material change is below 1e-3, at most 50 loops), as ``sfem-filters compare --refine 3``;
* ``element``, ``region``: the measured DENSE slice (``sfem-filters dense example``, baseline
  run) with per-element parameters or the 12-region relative map, with the command's loop
  limit ``--dense-loops`` (its default: 3) and tolerance 1e-3;
* ``basis``: the DENSE slice with the smooth basis (``--parameterisation basis``: 6 relative log E
  modes, 3 nu modes), with the limit ``--basis-loops``.

``--effects active_polar`` runs the DENSE cases on the extended model of the closing-the-loop
workflow (``sfem-filters dense example`` adds that effect) instead of the baseline.

Printed per case: state size, loops run against the limit, whether the material converged,
the last relative change, seconds and seconds per loop; for DENSE, each loop's relative change and
its material step against the carried posterior sd (max over parameters,
:func:`sfem_filters.filtering.diagnostics.material_drift`). ``OPENBLAS_NUM_THREADS=1`` is how to
time on this shared 2-core machine: there two BLAS threads are slower than one.
"""
from __future__ import annotations

import argparse
import resource
import time
import warnings

import numpy as np

from sfem_filters.benchmark.comparison import run_strategy
from sfem_filters.benchmark.pinned import STRATEGIES, pinned_benchmark
from sfem_filters.cardiac import measured
from sfem_filters.cardiac.sequence import example_path, load_sequence
from sfem_filters.filtering.cyclic import cyclic_estimate
from sfem_filters.filtering.diagnostics import material_drift
from sfem_filters.filtering.iterated import IteratedSmoother

CASES = ("r3", "element", "region", "basis")


def _row(name, model, result, seconds, limit):
    last = result.rel_changes[-1] if result.rel_changes else float("nan")
    return (f"{name:<26}{model.mesh.n_nodes:>6}{model.dim_theta:>7}{model.dim_state:>7}"
            f"{result.loops:>6}{limit:>6}{'yes' if result.converged else 'no':>6}{last:>11.2e}"
            f"{seconds:>9.1f}{seconds / result.loops:>9.2f}")


def dense_case(parameterisation, loops, landmarks, effects=()):
    setup = measured.prepare(load_sequence(example_path()), landmarks)
    model, y = measured.build_model(setup, effects, "penalty", parameterisation)
    t0 = time.perf_counter()
    result = cyclic_estimate(model, y, max_loops=loops, tol=1e-3, description=parameterisation)
    return model, result, time.perf_counter() - t0


def smoother_case(parameterisation, max_iterations, landmarks, effects=(), start="prior"):
    """The smoother from the prior's material (its default), or with ``start="ekf"`` from the
    material of one pass of the paper's joint EKF (its seconds counted in the run's)."""
    setup = measured.prepare(load_sequence(example_path()), landmarks)
    model, y = measured.build_model(setup, effects, "penalty", parameterisation)
    t0 = time.perf_counter()
    first = None
    if start == "ekf":
        ekf = cyclic_estimate(model, y, max_loops=1, tol=1e-3, description="one EKF pass")
        first = np.array(ekf.states, float)
        first[:, model.n_restart:] = ekf.theta
    result = IteratedSmoother(max_iterations=max_iterations).run(model, y, start=first, description=parameterisation)
    return model, result, time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="*", choices=CASES, default=list(CASES))
    ap.add_argument("--dense-loops", type=int, default=3, help="loop limit of the element and region "
                                                               "cases (sfem-filters dense's default: 3)")
    ap.add_argument("--basis-loops", type=int, default=50, help="loop limit of the basis case")
    ap.add_argument("--landmarks", type=int, default=8, help="landmarks per contour (the dense command's default)")
    ap.add_argument("--effects", default="", help="comma-separated effects of the DENSE model (default: none, "
                                                  "the baseline; active_polar: the extended model)")
    ap.add_argument("--estimator", choices=("cyclic", "smoother"), default="cyclic",
                    help="the DENSE cases' estimator (default cyclic, the paper's)")
    ap.add_argument("--max-iterations", type=int, default=20, help="iteration limit of the smoother")
    ap.add_argument("--start", choices=("prior", "ekf"), default="prior",
                    help="the smoother's first material: the prior mean (default, the library's), or the "
                         "estimate after one pass of the paper's joint EKF (its seconds included)")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    effects = tuple(e for e in args.effects.split(",") if e)
    if effects:
        print(f"DENSE model with effects {', '.join(effects)} (+)", flush=True)
    if args.estimator == "smoother":
        print(f"{'case':<26}{'nodes':>6}{'params':>7}{'aug n':>7}{'iter':>6}{'limit':>6}{'stop':>6}"
              f"{'MAP cost':>12}{'wall s':>9}{'s/iter':>9}{'peak MB':>9}", flush=True)
        for case in ("element", "region", "basis"):
            if case in args.cases:
                model, res, sec = smoother_case(case, args.max_iterations, args.landmarks, effects, args.start)
                peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
                stop = {"max_iterations": "limit"}.get(res.stop_reason, res.stop_reason)
                print(f"{'DENSE subject_a ' + case + ('+' if effects else ''):<26}{model.mesh.n_nodes:>6}"
                      f"{model.dim_theta:>7}{model.dim_state:>7}{res.iterations:>6}{args.max_iterations:>6}"
                      f"{stop:>6}{res.cost:>12.3f}{sec:>9.1f}{sec / max(res.iterations, 1):>9.2f}"
                      f"{peak:>9.0f}", flush=True)
                print("  cost:    " + ", ".join(f"{r['cost']:.3f}" for r in res.records), flush=True)
                print("  step/sd: " + ", ".join(f"{r['step_sd']:.2e}" for r in res.records), flush=True)
        return
    print(f"{'case':<26}{'nodes':>6}{'params':>7}{'aug n':>7}{'loops':>6}{'limit':>6}{'conv':>6}"
          f"{'last rel':>11}{'wall s':>9}{'s/loop':>9}", flush=True)
    if "r3" in args.cases:
        bench = pinned_benchmark(0, refine=3)
        total = 0.0
        for s in STRATEGIES:
            run = run_strategy(bench, s)
            total += run.metrics["seconds"]
            print(_row(f"benchmark r=3 {s}", run.model, run.result, run.metrics["seconds"], 50), flush=True)
        print(f"{'benchmark r=3, all three':<26}{'':>51}{total:>9.1f}", flush=True)
    for case, loops in (("element", args.dense_loops), ("region", args.dense_loops), ("basis", args.basis_loops)):
        if case in args.cases:
            model, result, seconds = dense_case(case, loops, args.landmarks, effects)
            print(_row(f"DENSE subject_a {case}{'+' if effects else ''}", model, result, seconds, loops), flush=True)
            if result.rel_changes:
                print(f"  relative changes: {', '.join(f'{r:.2e}' for r in result.rel_changes)}", flush=True)
                drift = material_drift(model, result.history)["max_sd"]
                print(f"  step / sd:        {', '.join(f'{d:.2e}' for d in drift)}", flush=True)


if __name__ == "__main__":
    main()
