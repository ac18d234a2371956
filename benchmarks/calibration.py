"""Calibration of the material posterior (shared/specs/calibration.md): ANEES / p and coverage.

    OPENBLAS_NUM_THREADS=1 python benchmarks/calibration.py [--problems pinned pinned_process_noise annulus]
        [--n 200] [--n-annulus 100] [--estimators cyclic_ekf cyclic_ekf_one_cycle iterated_smoother smoother_estimated_q]
        [--annulus-estimators iterated_smoother] [--json out/calibration.json]

Per problem and estimator: N replicates whose material is drawn from the prior, the average
normalised estimation error squared over the number of parameters with its 95% band for a
calibrated posterior, and the fraction of the N p parameter values inside the 95% intervals with
its Wilson interval; on the annulus also the coverage of the smoothed strain intervals
(:mod:`sfem_filters.benchmark.calibration`). The paper's cyclic EKF costs up to 50 loops per
replicate: on the annulus (about 2 minutes a replicate) it is left out by default.
"""
from __future__ import annotations

import argparse
import time

from sfem_filters._io import write_json
from sfem_filters.benchmark.calibration import ESTIMATORS, PROBLEMS, calibrate, format_calibration


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--problems", nargs="*", choices=PROBLEMS, default=list(PROBLEMS))
    ap.add_argument("--n", type=int, default=200, help="replicates of the pinned problems (spec: 200)")
    ap.add_argument("--n-annulus", type=int, default=100, help="replicates of the annulus problem")
    ap.add_argument("--estimators", nargs="*", choices=ESTIMATORS, default=list(ESTIMATORS))
    ap.add_argument("--annulus-estimators", nargs="*", choices=ESTIMATORS, default=["iterated_smoother"])
    ap.add_argument("--json", help="write the summaries as JSON")
    args = ap.parse_args(argv)
    summaries = []
    for problem in args.problems:
        annulus = problem == "annulus"
        t0 = time.perf_counter()
        res = calibrate(problem, args.annulus_estimators if annulus else args.estimators,
                        n=args.n_annulus if annulus else args.n, progress=True)
        print(format_calibration(res), flush=True)
        print(f"({time.perf_counter() - t0:.0f} s)", flush=True)
        summaries += [c.summary() for c in res.values()]
    if args.json:
        write_json(args.json, summaries)


if __name__ == "__main__":
    main()
