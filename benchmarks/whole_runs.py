"""Wall time of whole cyclic runs, every loop, as the library's commands run them.

    OPENBLAS_NUM_THREADS=1 python benchmarks/whole_runs.py [--cases r3 element region basis]
        [--dense-loops 3] [--basis-loops 50] [--landmarks 8] [--effects NAME,...]

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
import time
import warnings

from sfem_filters.benchmark.comparison import run_strategy
from sfem_filters.benchmark.pinned import STRATEGIES, pinned_benchmark
from sfem_filters.cardiac import measured
from sfem_filters.cardiac.sequence import example_path, load_sequence
from sfem_filters.filtering.cyclic import cyclic_estimate
from sfem_filters.filtering.diagnostics import material_drift

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


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="*", choices=CASES, default=list(CASES))
    ap.add_argument("--dense-loops", type=int, default=3, help="loop limit of the element and region "
                                                               "cases (sfem-filters dense's default: 3)")
    ap.add_argument("--basis-loops", type=int, default=50, help="loop limit of the basis case")
    ap.add_argument("--landmarks", type=int, default=8, help="landmarks per contour (the dense command's default)")
    ap.add_argument("--effects", default="", help="comma-separated effects of the DENSE model (default: none, "
                                                  "the baseline; active_polar: the extended model)")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    effects = tuple(e for e in args.effects.split(",") if e)
    if effects:
        print(f"DENSE model with effects {', '.join(effects)} (+)", flush=True)
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
