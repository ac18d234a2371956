"""Held-out error on the measured slice: the paper's 3-loop cyclic filter against the iterated smoother.

    OPENBLAS_NUM_THREADS=1 python benchmarks/dense_heldout.py [--landmarks 8 16] [--json out/dense_heldout.json]

``sfem-filters dense example --landmarks N`` with each estimator (``--estimator cyclic``, the
previous default, 3 loops; ``--estimator smoother``, the default now): the baseline and the
extended model (one round: of the effects the score test ranks best, the one the round keeps,
by default the largest evidence gain of the three best-ranked), held-out RMSE with its radial and
circumferential parts, NIS / dof and the lag-1 autocorrelation of the innovations, loops or
iterations, wall time.
"""
from __future__ import annotations

import argparse
import warnings

from sfem_filters._io import write_json
from sfem_filters.cardiac import closing_the_loop, example_path, load_sequence


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--landmarks", type=int, nargs="*", default=[8, 16])
    ap.add_argument("--json", help="write the rows as JSON")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    seq = load_sequence(example_path())
    rows = []
    print(f"{'landmarks':>9} {'estimator':<10}{'model':<22}{'held-out':>9}{'radial':>8}{'circ.':>8}{'NIS/dof':>9}"
          f"{'lag-1':>7}{'loops/it':>9}{'s':>7}", flush=True)
    for n in args.landmarks:
        for estimator in ("cyclic", "smoother"):
            out = closing_the_loop(seq, effects="auto", landmarks=n, estimator=estimator, max_loops=3, max_rounds=1,
                                   corrections=False)
            for label, run in (("baseline", out.baseline), ("+ " + ",".join(out.effects), out.extended)):
                m = run.metrics
                row = {"landmarks": n, "estimator": estimator, "model": label, **{k: m[k] for k in (
                    "heldout_rmse_px", "heldout_rmse_radial_px", "heldout_rmse_circumferential_px",
                    "nis_mean_over_dof", "innovation_lag1_autocorrelation", "loops", "converged", "seconds")}}
                rows.append(row)
                print(f"{n:>9} {estimator:<10}{label:<22}{m['heldout_rmse_px']:>9.3f}{m['heldout_rmse_radial_px']:>8.3f}"
                      f"{m['heldout_rmse_circumferential_px']:>8.3f}{m['nis_mean_over_dof']:>9.3f}"
                      f"{m['innovation_lag1_autocorrelation']:>7.3f}"
                      f"{str(m['loops']) + ('' if m['converged'] else '*'):>9}{m['seconds']:>7.0f}", flush=True)
    print("* not converged within the limit (cyclic: 3 loops, the dense command's default; smoother: 20 iterations)")
    if args.json:
        write_json(args.json, rows)


if __name__ == "__main__":
    main()
