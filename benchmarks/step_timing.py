"""Seconds per joint-EKF step, split by phase, against a naive baseline and the dense floor.

    python benchmarks/step_timing.py [--refine 1 2 3 4] [--dense] [--repeat 3] [--figure PATH]

For the pinned benchmark at refinement r (per-element E and nu) and for the measured DENSE
mesh (per-element parameters), one step of the joint EKF is timed in four phases:

* discretisation: the eigen-decomposition and modal exponentials for the step's material;
* M_t: the exact sensitivity of the transition to every material parameter (Eq. 33);
* propagation: the rest of the predict: forming A, P <- F P F^T + Q from the Cholesky factor
  of P (structured, block-wise), the state;
* update: Cholesky-based Kalman update with the O(n^2 m) Joseph form, and the Cholesky factor
  of the posterior (the covariance check's, reused by the next predict).

The step is the engine's predict plus update as a cyclic run calls them.

Ratios printed against figures measured in the same run:

* naive: ``scipy.linalg.expm_frechet`` once per parameter for M_t (timed on 8 parameters and
  scaled to all of them) plus filterpy's generic update with ``inv(S)`` and the full
  ``(I - KH) P (I - KH)^T``; only where it is feasible (r <= 2);
* floor: one dense n x n matrix product at the augmented dimension n, the least any dense
  covariance propagation pays.

Peak memory is the tracemalloc peak of one step (numpy allocations included).
"""
from __future__ import annotations

import argparse
import time
import tracemalloc
import warnings

import numpy as np
from _timing import best_of

from sfem_filters.benchmark.pinned import benchmark_model, pinned_benchmark
from sfem_filters.cardiac import measured
from sfem_filters.cardiac.sequence import example_path, load_sequence
from sfem_filters.fem.statespace import reference_sensitivity
from sfem_filters.filtering.structured import StructuredEngine


def time_step(model, y, repeat=3):
    """Phase timings (s) of one step from frame 1 to 2, with a fresh material each repeat.

    The step is what a cyclic run pays per frame: the engine's predict (which discretises and
    differentiates for the new material, forms F and propagates the factored covariance) and
    its update, plus the Cholesky factor of the posterior (the covariance check's, which the
    next predict reuses). The discretisation (``model.system`` for a new material) and M_t
    (``model.sensitivity``, the discretisation cached) are timed on their own, best of
    ``repeat`` each; ``propagation`` is the rest of the predict (best of ``repeat``, a new
    material each time): forming A and the time update of P and of the state.
    """
    eng = StructuredEngine(model)
    eng.update(y[0], 0, np.ones(model.dim_obs, bool))
    z, P = eng.x.copy(), eng.P.copy()
    L = eng.cholesky()
    nr = model.n_restart
    rng = np.random.default_rng(0)

    def fresh():
        zz = z.copy()
        zz[nr:] += 1e-6 * rng.standard_normal(model.dim_theta)   # a new material: no cache hit
        return zz

    t_disc = best_of(lambda: model.system(model.theta_of(fresh())), repeat)
    model.system(model.theta_of(z))
    t_mt = best_of(lambda: model.sensitivity(z, 1), repeat)
    t_pred = np.inf
    for _ in range(repeat):
        eng.reset(fresh(), P)
        eng._L = L                    # as after the covariance check of the previous step
        t0 = time.perf_counter()
        eng.predict(1)
        t_pred = min(t_pred, time.perf_counter() - t0)
    P_prior, x_prior = eng.P.copy(), eng.x.copy()

    def update():
        eng.reset(x_prior, P_prior)
        eng.update(y[2], 2, np.ones(model.dim_obs, bool))
        eng.cholesky()

    t_upd = best_of(update, repeat)
    tracemalloc.start()
    eng.reset(fresh(), P)
    eng.predict(1)
    eng.update(y[2], 2, np.ones(model.dim_obs, bool))
    eng.cholesky()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return {"discretisation": t_disc, "M_t": t_mt, "propagation": t_pred - t_disc - t_mt,
            "update": t_upd, "step": t_pred + t_upd, "peak_MB": peak / 2 ** 20}


def time_naive(model, y, n_params=8):
    """Naive step: expm_frechet per parameter (scaled from n_params) + filterpy-style update."""
    z = model.x0.copy()
    mat = model.material_of(z)
    system, K, _ = model._entry(mat)
    dirs = model._directions(mat)
    dofs = np.concatenate([model._directions_dofs, model._directions_dofs])
    idx = np.linspace(0, len(dirs) - 1, n_params).astype(int)
    dense = [model._scatter(dirs[i], dofs[i]) for i in idx]
    t0 = time.perf_counter()
    reference_sensitivity(model.M, K, model.alpha, model.beta, model.frame_interval, z[:model.dim_x],
                          model.load(z, 1), dense)
    t_mt = (time.perf_counter() - t0) * len(dirs) / n_params
    F = model.F_jacobian(z, 1)
    P = model.P0.copy()
    H, R = model.H_jacobian(z, 1), model.R
    t0 = time.perf_counter()
    P1 = F @ P @ F.T + model.Q
    PHT = P1 @ H.T
    S = H @ PHT + R
    K_ = PHT @ np.linalg.inv(S)
    I_KH = np.eye(len(P1)) - K_ @ H
    I_KH @ P1 @ I_KH.T + K_ @ R @ K_.T
    t_rest = time.perf_counter() - t0
    return t_mt + t_rest


def time_floor(n, repeat=3):
    a = np.random.default_rng(0).standard_normal((n, n))
    return best_of(lambda: a @ a, repeat)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--refine", type=int, nargs="*", default=[1, 2, 3, 4])
    ap.add_argument("--dense", action="store_true", help="also the measured DENSE mesh (per element)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--naive-max-refine", type=int, default=2)
    ap.add_argument("--figure", default=None, help="write a log-log figure of time per step")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    cases = []
    for r in args.refine:
        b = pinned_benchmark(0, refine=r)
        cases.append((f"benchmark r={r}", benchmark_model(b, "joint_ekf"), b.observations, r <= args.naive_max_refine))
    if args.dense:
        su = measured.prepare(load_sequence(example_path()), 8)
        m, y = measured.build_model(su, (), "penalty", "element")
        cases.append(("DENSE subject_a", m, y, False))
    head = (f"{'case':<18}{'nodes':>6}{'params':>7}{'aug n':>7}{'disc s':>9}{'M_t s':>9}{'prop s':>9}{'upd s':>9}"
            f"{'step s':>9}{'peak MB':>9}{'floor s':>9}{'step/floor':>11}{'naive s':>10}{'naive/step':>11}")
    print(head)
    rows = []
    for name, model, y, naive in cases:
        t = time_step(model, y, args.repeat)
        fl = time_floor(model.dim_state, args.repeat)
        nv = time_naive(model, y) if naive else np.nan
        rows.append((model.dim_state, t["step"], nv, fl))
        print(f"{name:<18}{model.mesh.n_nodes:>6}{model.dim_theta:>7}{model.dim_state:>7}{t['discretisation']:>9.4f}"
              f"{t['M_t']:>9.4f}{t['propagation']:>9.4f}{t['update']:>9.4f}{t['step']:>9.4f}{t['peak_MB']:>9.1f}"
              f"{fl:>9.4f}{t['step'] / fl:>11.1f}{nv:>10.2f}{nv / t['step']:>11.1f}", flush=True)
    if args.figure:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        rows = np.array(rows)
        fig, ax = plt.subplots(figsize=(6, 4.2), constrained_layout=True)
        ax.loglog(rows[:, 0], rows[:, 1], "o-", label="this library (structured step)")
        ok = np.isfinite(rows[:, 2])
        ax.loglog(rows[ok, 0], rows[ok, 2], "s--", label="naive (expm_frechet + filterpy update)")
        ax.loglog(rows[:, 0], rows[:, 3], "^:", label="one dense n x n product (floor)")
        ax.set_xlabel("augmented state dimension n")
        ax.set_ylabel("seconds per step")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
        fig.savefig(args.figure, dpi=120)
        print(f"wrote {args.figure}")


if __name__ == "__main__":
    main()
