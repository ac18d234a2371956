"""The smoother's posterior against the exact marginal posterior of the material (2-region map).

    OPENBLAS_NUM_THREADS=1 python benchmarks/laplace_check.py [--seeds 0 1 2 3 4]

Given the material, the pinned benchmark's kinematics are linear-Gaussian, so one Kalman pass
gives the exact log-likelihood log p(y | theta); its maximum with the prior (the marginal MAP)
and the inverse Hessian there (the Laplace covariance) are compared with the iterated smoother's
joint mode and Gauss-Newton covariance (:func:`sfem_filters.filtering.marginal.laplace_check`):
the distance of the modes in marginal sd, the ratio of the sds, and the KL divergence.
"""
from __future__ import annotations

import argparse

import numpy as np

from sfem_filters.benchmark.pinned import benchmark_model, pinned_benchmark
from sfem_filters.fem.material import Parameterisation
from sfem_filters.filtering import IteratedSmoother, laplace_check


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2, 3, 4])
    args = ap.parse_args(argv)
    print(f"{'seed':>4}{'iterations':>11}{'max |mode difference| / sd':>28}{'sd ratio min-max':>18}{'KL [nats]':>11}"
          f"{'passes':>8}")
    for seed in args.seeds:
        bench = pinned_benchmark(seed)
        model = benchmark_model(bench, "joint_ekf", parameterisation=Parameterisation.per_region(bench.middle))
        res = IteratedSmoother().run(model, bench.observations)
        c = laplace_check(model, bench.observations, res.theta, res.P_theta)
        print(f"{seed:>4}{res.iterations:>11}{np.abs(c.z_mode).max():>28.4f}"
              f"{c.sd_ratio.min():>10.3f}-{c.sd_ratio.max():<7.3f}{c.kl:>11.5f}{c.evaluations:>8}", flush=True)


if __name__ == "__main__":
    main()
