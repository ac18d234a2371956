"""BLAS threads: the README's Python snippet and the filter's products, the library default against 1 and 2 threads.

    python benchmarks/blas_threads.py [--sizes 208 1351 5335] [--repeat 3] [--no-fit] [--quick]

Product benchmark (ratios against a baseline measured in the same run). Two tables:

* the README's snippet (``pinned_benchmark(seed=0)``, ``benchmark_model(bench, "joint_ekf")``,
  filterpy's EKF driven by hand, ``cyclic_estimate``, ``IteratedSmoother().run``): wall time
  with the library's default (``sfem_filters.resources.DEFAULT_BLAS_THREADS`` inside the
  estimators' entry points; the hand-driven EKF loop runs at whatever BLAS threads the process
  has), with ``blas_threads(1)`` and with ``blas_threads(2)`` around all of it, each as a ratio
  against the default, and whether each setting's estimates equal the default's to the last bit;
* the filter's products at the state sizes users meet (208: the pinned benchmark; 1351: the
  measured slice's region baseline; 5335: the same subject on a pixel lattice twice as fine,
  ``docs/frozen/large_subject.md``): one step of the smoother's Kalman filter
  (``LinearisedEngine`` predict + update: A P A^T with the sensitivity terms, the gain, the Joseph
  update, 24 parameters and 32 observed rows) on a random model of that size, one n x n product
  and one Cholesky factorisation, best of ``--repeat`` at 1 and at 2 threads; and, unless
  ``--no-fit``, one fit of the measured slice's region baseline (2 iterations of the iterated
  smoother, no covariance pass) at 1 and at 2 threads, where the data set ``subject_a`` is found
  (``sfem_filters.datasets``; else the row says so and is left out).

Every row records ``/proc/loadavg`` (1-minute load) before it: on a machine shared with other
jobs, threads compete with them, so say how loaded it was. The environment may set
``OPENBLAS_CORETYPE`` / ``OPENBLAS_L2_SIZE`` (older OpenBLAS builds need them on some
processors); to benchmark a current numpy without them, unset both in the benchmark command only:
``env -u OPENBLAS_CORETYPE -u OPENBLAS_L2_SIZE python benchmarks/blas_threads.py``.
``--quick``: the smallest setting (size 208, one repeat, the snippet with one cyclic loop and one
smoother iteration, no fit), a smoke test.
"""
from __future__ import annotations

import argparse
import os
import platform
import time
import warnings

import numpy as np
from threadpoolctl import threadpool_info

from sfem_filters import IteratedSmoother, cyclic_estimate
from sfem_filters.benchmark import benchmark_model, pinned_benchmark
from sfem_filters.cardiac import build_model, example_path, load_sequence, prepare
from sfem_filters.filtering.linearised import LinearisedModel
from sfem_filters.filtering.smoother import LinearisedEngine
from sfem_filters.resources import BLAS_THREADS_ENV, DEFAULT_BLAS_THREADS, blas_threads
from sfem_filters.resources import best_of


def load() -> str:
    """The 1-, 5- and 15-minute load averages (``/proc/loadavg``), or "?" where not on Linux."""
    try:
        with open("/proc/loadavg") as f:
            return " ".join(f.read().split()[:3])
    except OSError:
        return "?"


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or "?"



def snippet(quick: bool) -> tuple:
    """The README's Python snippet: (seconds by part, the estimates it makes)."""
    seconds, t0 = {}, time.perf_counter()
    bench = pinned_benchmark(seed=0)
    model = benchmark_model(bench, "joint_ekf")
    ekf = model.make_ekf()
    for t, y in enumerate(bench.observations):
        if t > 0:
            ekf.predict(u=t - 1)
        ekf.update(y.reshape(-1, 1), model.H_jacobian, model.hx, args=t, hx_args=t)
    seconds["ekf"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    result = cyclic_estimate(model, bench.observations, **({"max_loops": 1} if quick else {}))
    seconds["cyclic"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    mode = IteratedSmoother(**({"max_iterations": 1} if quick else {})).run(model, bench.observations)
    seconds["smoother"] = time.perf_counter() - t0
    estimates = np.concatenate([np.ravel(ekf.x), result.states[-1], mode.theta, np.ravel(mode.P_theta),
                                np.ravel(mode.output_sd["strain"])])
    return seconds, estimates, model.dim_state


def random_linearised(n: int, p: int = 24, m: int = 32, seed: int = 0) -> LinearisedModel:
    """A linearised model of state size n (n - p restart entries, p parameters, m observed rows):
    the shapes of the smoother's products, with random stable numbers."""
    nr, rng = n - p, np.random.default_rng(seed)
    A = 0.99 * np.linalg.qr(rng.standard_normal((nr, nr)))[0]
    B = rng.standard_normal((nr, nr)) / np.sqrt(nr)
    H = np.zeros((m, nr))
    H[np.arange(m), rng.choice(nr, m, replace=False)] = 1.0
    return LinearisedModel(A=A, M=rng.standard_normal((1, nr, p)), c=np.zeros((1, nr)), H=H,
                           R=np.stack([np.eye(m)] * 2), Q=0.01 * np.eye(nr), xi0=np.zeros(nr),
                           P0=B @ B.T + np.eye(nr), theta_bar=np.zeros(p), theta0=np.zeros(p), P_theta0=np.eye(p))


def products(n: int, repeat: int) -> dict:
    """Best-of-``repeat`` seconds of the filter's products at state size n, at 1 and 2 threads."""
    lin = random_linearised(n)
    eng = LinearisedEngine(lin, lin.theta0, lin.P_theta0, store="none")
    x0, P0 = eng.x.copy(), eng.P.copy()
    y, mask = np.random.default_rng(1).standard_normal(lin.dim_obs), np.ones(lin.dim_obs, bool)
    a = np.random.default_rng(2).standard_normal((n, n))

    def step():
        eng.reset(x0, P0)
        eng.predict(0)
        eng.update(y, 1, mask)

    out = {}
    for threads in (1, 2):
        with blas_threads(threads):
            out[threads] = {"load": load(), "step": best_of(step, repeat), "product": best_of(lambda: a @ a, repeat),
                            "cholesky": best_of(lambda: np.linalg.cholesky(P0), repeat)}
    return out


def measured_fit(threads: int) -> tuple:
    """Seconds of 2 iterations of the iterated smoother on the measured slice's region baseline."""
    setup = prepare(load_sequence(example_path()), 8)
    model, y = build_model(setup, (), "penalty", "region")
    with blas_threads(threads):
        t0 = time.perf_counter()
        res = IteratedSmoother(max_iterations=2, covariance=False).run(model, y)
        return time.perf_counter() - t0, model.dim_state, res.theta


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[208, 1351, 5335], help="state sizes of the products")
    ap.add_argument("--repeat", type=int, default=3, help="best of this many calls for each product (default 3)")
    ap.add_argument("--no-fit", action="store_true", help="leave out the measured slice's fit")
    ap.add_argument("--quick", action="store_true", help="the smallest setting, a smoke test")
    args = ap.parse_args(argv)
    if args.quick:
        args.sizes, args.repeat, args.no_fit = [min(args.sizes)], 1, True
    warnings.simplefilter("ignore", RuntimeWarning)
    os.environ.pop(BLAS_THREADS_ENV, None)             # the library's own default in the first row
    blas = [p for p in threadpool_info() if p["user_api"] == "blas"]
    print(f"CPU {cpu_model()}, {os.cpu_count()} cores; BLAS: "
          + ", ".join(f"{p['internal_api']} {p['version']} {p['architecture']} ({p['num_threads']} threads)"
                      for p in blas)
          + f"; OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')} "
            f"OPENBLAS_CORETYPE={os.environ.get('OPENBLAS_CORETYPE')}; library default {DEFAULT_BLAS_THREADS}")
    print(f"load average at start: {load()}  (other processes share the cores: a loaded machine where > 0.5)")

    print(f"\nREADME snippet{' (quick: 1 cyclic loop, 1 smoother iteration)' if args.quick else ''}")
    print(f"{'setting':<18}{'load 1/5/15 min':>18}{'ekf s':>9}{'cyclic s':>10}{'smoother s':>12}{'total s':>10}"
          f"{'/ default':>11}  same numbers")
    rows, reference = {}, None
    for name, threads in (("library default", None), ("1 thread", 1), ("2 threads", 2)):
        before = load()
        if threads is None:
            seconds, estimates, n = snippet(args.quick)
        else:
            with blas_threads(threads):
                seconds, estimates, n = snippet(args.quick)
        total = sum(seconds.values())
        rows[name] = total
        reference = estimates if reference is None else reference
        diff = float(np.abs(estimates - reference).max())
        same = "yes" if np.array_equal(estimates, reference) else f"no (max diff {diff:.1e})"
        print(f"{name:<18}{before:>18}{seconds['ekf']:>9.2f}{seconds['cyclic']:>10.2f}{seconds['smoother']:>12.2f}"
              f"{total:>10.2f}{total / rows['library default']:>11.2f}  {same}", flush=True)
    print(f"(state size {n}; the estimators' entry points run under the default, the hand-driven EKF loop does not)")

    print(f"\nthe filter's products, best of {args.repeat}: seconds at 1 and 2 threads, ratio 2 / 1 "
          "(> 1: two are slower)")
    print(f"{'n':>6}{'load at 1':>16}{'load at 2':>16}{'step 1':>10}{'step 2':>10}{'ratio':>8}{'n x n 1':>10}"
          f"{'n x n 2':>10}{'ratio':>8}{'chol 1':>9}{'chol 2':>9}{'ratio':>8}")
    for n in args.sizes:
        r = products(n, args.repeat)
        one, two = r[1], r[2]
        print(f"{n:>6}{one['load']:>16}{two['load']:>16}"
              + "".join(f"{one[k]:>{w}.4f}{two[k]:>{w}.4f} {two[k] / one[k]:>7.2f}"
                        for k, w in (("step", 10), ("product", 10), ("cholesky", 9))), flush=True)

    if not args.no_fit:
        print("\nmeasured slice, region baseline: 2 iterations of the iterated smoother (no covariance pass)")
        fits = {}
        for threads in (1, 2):
            before = load()
            try:
                fits[threads] = measured_fit(threads)
            except FileNotFoundError as exc:        # the data set is not here
                print(f"  left out: {str(exc).splitlines()[0]}")
                break
            print(f"  {threads} thread{'s' if threads > 1 else ' '}  load {before}  n = {fits[threads][1]}  "
                  f"{fits[threads][0]:7.1f} s  ratio to 1 thread {fits[threads][0] / fits[1][0]:.2f}", flush=True)
        if len(fits) == 2:
            print(f"  same material estimate at 1 and 2 threads: {np.array_equal(fits[1][2], fits[2][2])}")
    print(f"\nload average at the end: {load()}")


if __name__ == "__main__":
    main()
