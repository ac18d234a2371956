"""The same model in the peers' filters, side by side in one run (issue #16).

    OPENBLAS_NUM_THREADS=1 python benchmarks/peers.py [--seeds 0-4] [--max-loops 50]
        [--methods cyclic_ekf smoother ukf roukf] [--ukf-max-dim 400] [--ukf-max-loops 5]
        [--roukf-max-loops 20] [--measured] [--dense-loops 3]
        [--json out/peers.json]

Methods, all on one model object:

* ``cyclic_ekf``: the paper's cyclic joint EKF (structured engine), until the relative material
  change is below 1e-3 or ``--max-loops``;
* ``smoother``: the iterated smoother (Gauss-Newton on the MAP of one cycle, Laplace posterior);
* ``ukf``: filterpy's ``UnscentedKalmanFilter`` (Merwe points, 2n + 1 of them) in the same
  cyclic driver (``engine="ukf"``), only where the state has at most ``--ukf-max-dim`` entries,
  and at most ``--ukf-max-loops`` loops (a loop of the per-element map took 20-40 s here);
* ``roukf``: Moireau & Chapelle's reduced-order UKF (p + 1 simplex points on the parameters)
  in the same cyclic driver (``engine="roukf"``), at most ``--roukf-max-loops`` loops.

Synthetic: the pinned benchmark, seeds ``--seeds``, r = 1, with the per-element map (p = 96, the
paper's) and the 2-region map (middle / rest, p = 4). Per method and map, over the seeds:
mean absolute relative E error in the middle and outside, ANEES / p of theta against the truth
(the cyclic methods with their carried covariance and with the covariance of one cycle), loops
or iterations, seconds and peak traced memory (MB, tracemalloc: numpy's arrays included).

``--measured``: the shipped DENSE slice (8 landmarks, penalty drive), baseline (no effect) and
extended (``active_polar``), with the region and basis maps: held-out RMSE (px), NIS / dof,
loops or iterations, seconds, peak memory; the cyclic methods with ``--dense-loops`` loops.
"""
from __future__ import annotations

import argparse
import time
import tracemalloc
import warnings

import numpy as np
import scipy.linalg as sla

from sfem_filters._io import write_json
from sfem_filters.benchmark import benchmark_model, pinned_benchmark
from sfem_filters.cardiac import measured
from sfem_filters.cardiac.sequence import example_path, load_sequence
from sfem_filters.cli import _seeds
from sfem_filters.fem.material import Parameterisation
from sfem_filters.filtering import CyclicEKF, IteratedSmoother

METHODS = ("cyclic_ekf", "smoother", "ukf", "roukf")
ENGINE = {"cyclic_ekf": "structured", "ukf": "ukf", "roukf": "roukf"}


def _estimate(method, model, y, limits):
    if method == "smoother":
        return IteratedSmoother().run(model, y)
    loops = limits[method]
    return CyclicEKF(engine=ENGINE[method], max_loops=loops).run(model, y, progress=True, description=method)


def _measure(fn):
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


def _nees(theta, theta_true, P):
    d = theta - theta_true
    return float(d @ sla.cho_solve(sla.cho_factor(P), d)) / len(d)


def synthetic(seeds, methods, limits, ukf_max_dim):
    rows = []
    for seed in seeds:
        bench = pinned_benchmark(seed)
        maps = {"element": None, "2 regions": Parameterisation.per_region(bench.middle)}
        for map_name, param in maps.items():
            model = benchmark_model(bench, "joint_ekf", parameterisation=param)
            theta_true = model.parameterisation.theta_of(bench.true_material)
            for method in methods:
                if method == "ukf" and model.dim_state > ukf_max_dim:
                    rows.append({"seed": seed, "map": map_name, "method": method, "skipped":
                                 f"state of {model.dim_state} > --ukf-max-dim {ukf_max_dim}"})
                    continue
                res, sec, peak, err = _measure(lambda: _estimate(method, model, bench.observations, limits))
                if err is not None:
                    rows.append({"seed": seed, "map": map_name, "method": method, "skipped": f"failed after "
                                 f"{sec:.0f} s: {err}"})
                    print(_fmt_synthetic(rows[-1]), flush=True)
                    continue
                mat = model.material_of_theta(res.theta)
                eE = np.abs(mat.E - bench.true_material.E) / bench.true_material.E
                row = {"seed": seed, "map": map_name, "method": method, "p": model.dim_theta,
                       "E_err_middle": float(eE[bench.middle].mean()), "E_err_outside": float(eE[~bench.middle].mean()),
                       "nees_over_p": _nees(res.theta, theta_true, res.posterior_cov),
                       "loops": int(res.loops),
                       "converged": bool(res.converged), "seconds": sec, "peak_MB": peak}
                if method != "smoother":
                    row["nees_over_p_carried"] = _nees(res.theta, theta_true, res.P_theta)
                rows.append(row)
                print(_fmt_synthetic(row), flush=True)
    return rows


def _fmt_synthetic(r):
    if "skipped" in r:
        return f"seed {r['seed']} {r['map']:<10} {r['method']:<11} skipped: {r['skipped']}"
    carried = f" (carried {r['nees_over_p_carried']:.3g})" if "nees_over_p_carried" in r else ""
    return (f"seed {r['seed']} {r['map']:<10} {r['method']:<11} E err mid/out {r['E_err_middle']:.3f}/"
            f"{r['E_err_outside']:.3f}  NEES/p {r['nees_over_p']:.3g}{carried}  loops {r['loops']}"
            f"{'' if r['converged'] else '*'}  {r['seconds']:.1f} s  {r['peak_MB']:.0f} MB")


def summary(rows):
    print("\nover the seeds (mean; ANEES/p = mean NEES/p):")
    print(f"{'map':<10} {'method':<11} {'E err mid':>9} {'E err out':>9} {'ANEES/p':>9} {'carried':>9} "
          f"{'loops':>7} {'seconds':>8} {'peak MB':>8}")
    keys = sorted({(r["map"], r["method"]) for r in rows if "skipped" not in r}, key=lambda k: (k[0], METHODS.index(k[1])))
    for key in keys:
        rs = [r for r in rows if (r["map"], r["method"]) == key and "skipped" not in r]
        carried = np.mean([r["nees_over_p_carried"] for r in rs]) if "nees_over_p_carried" in rs[0] else np.nan
        print(f"{key[0]:<10} {key[1]:<11} {np.mean([r['E_err_middle'] for r in rs]):>9.3f} "
              f"{np.mean([r['E_err_outside'] for r in rs]):>9.3f} {np.mean([r['nees_over_p'] for r in rs]):>9.3g} "
              f"{carried:>9.3g} {np.mean([r['loops'] for r in rs]):>7.1f} {np.mean([r['seconds'] for r in rs]):>8.1f} "
              f"{np.max([r['peak_MB'] for r in rs]):>8.0f}")


def dense(methods, dense_loops, ukf_max_dim):
    seq = load_sequence(example_path())
    setup = measured.prepare(seq, 8)
    rows = []
    for effects in ((), ("active_polar",)):
        for param in ("region", "basis"):
            for method in methods:
                label = f"{'extended' if effects else 'baseline'}/{param}"
                if method == "ukf":
                    model, _ = measured.build_model(setup, effects, "penalty", param)
                    if model.dim_state > ukf_max_dim:
                        rows.append({"case": label, "method": method,
                                     "skipped": f"state of {model.dim_state} > --ukf-max-dim {ukf_max_dim}"})
                        print(f"{label:<18} {method:<11} skipped: {rows[-1]['skipped']}", flush=True)
                        continue
                est = {"smoother": "smoother", "cyclic_ekf": "cyclic", "roukf": "roukf"}[method]
                run, sec, peak, err = _measure(lambda: measured.run(setup, effects, "penalty", param,
                                                                    max_loops=dense_loops, estimator=est))
                if err is not None:
                    rows.append({"case": label, "method": method, "skipped": f"failed after {sec:.0f} s: {err}"})
                    print(f"{label:<18} {method:<11} {rows[-1]['skipped']}", flush=True)
                    continue
                m = run.metrics
                res = run.result
                row = {"case": label, "method": method, "heldout_rmse_px": m["heldout_rmse_px"],
                       "nis_over_dof": m["nis_mean_over_dof"],
                       "loops": int(res.loops),
                       "seconds": sec, "peak_MB": peak}
                rows.append(row)
                print(f"{label:<18} {method:<11} held-out {row['heldout_rmse_px']:.3f} px  NIS/dof "
                      f"{row['nis_over_dof']:.3f}  loops {row['loops']}  {sec:.1f} s  {peak:.0f} MB", flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=_seeds, default=list(range(5)))
    ap.add_argument("--max-loops", type=int, default=50)
    ap.add_argument("--methods", nargs="*", choices=METHODS, default=list(METHODS))
    ap.add_argument("--ukf-max-dim", type=int, default=400)
    ap.add_argument("--ukf-max-loops", type=int, default=5,
                    help="loop limit of the full-state UKF (2n + 1 model runs per frame; default 5)")
    ap.add_argument("--roukf-max-loops", type=int, default=20,
                    help="loop limit of the reduced-order UKF (p + 1 model runs per frame; default 20)")
    ap.add_argument("--measured", action="store_true")
    ap.add_argument("--no-synthetic", action="store_true")
    ap.add_argument("--dense-loops", type=int, default=3)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    out = {}
    if not args.no_synthetic:
        out["synthetic"] = synthetic(args.seeds, args.methods, {"cyclic_ekf": args.max_loops, "ukf": args.ukf_max_loops,
                                                                "roukf": args.roukf_max_loops}, args.ukf_max_dim)
        summary(out["synthetic"])
    if args.measured:
        print()
        out["measured"] = dense(args.methods, args.dense_loops, args.ukf_max_dim)
    if args.json:
        print(f"wrote {write_json(args.json, out)}")


if __name__ == "__main__":
    main()
