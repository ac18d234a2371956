"""Which drive lets the physics predict the measured slice's held-out points: the issue-14 candidates.

    OPENBLAS_NUM_THREADS=1 python benchmarks/dense_drives.py [--landmarks 8 16] [--effects active_polar]

On the shipped DENSE slice, the iterated smoother (region map, at most 20 iterations) with each
drive of :func:`sfem_filters.cardiac.measured.build_model`: springs on the isolated landmarks
(``penalty``) or on the whole contour interpolated between them (``contour``), each pulling
toward the previous frame's data (lag 1, causal: the innovations stay one-step-ahead prediction
errors and ``log p(y)`` is a likelihood of the data), toward its linear extrapolation from the
two previous frames (``trend``, still causal), or toward the same frame's data (lag 0: the
observed landmarks then enter twice, as drive and as data, so NIS and ``log p(y)`` are not
comparable with the causal rows'; the held-out points are untouched either way). Beside them the thin-plate spline
through the same observed points. Prints held-out RMSE (total, radial, circumferential), NIS/dof,
lag-1 autocorrelation, log p(y), iterations and wall time.
"""
from __future__ import annotations

import argparse
import time
import warnings

from sfem_filters.cardiac import example_path, load_sequence, measured, prepare
from sfem_filters.cardiac.reference import spline_reference
from sfem_filters.filtering import IteratedSmoother


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--landmarks", type=int, nargs="*", default=[8, 16])
    ap.add_argument("--effects", default="active_polar", help="comma list of effects in every model")
    ap.add_argument("--max-iterations", type=int, default=20)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    seq = load_sequence(example_path())
    effects = tuple(e for e in args.effects.split(",") if e)
    print(f"effects: {','.join(effects) or 'none'}; region map; iterated smoother")
    print(f"{'landmarks':>9} {'drive':<9}{'lag':>5}{'held-out':>9}{'radial':>8}{'circ.':>8}{'NIS/dof':>9}{'lag-1':>7}"
          f"{'log p(y)':>10}{'it':>4}{'s':>6}", flush=True)
    rows = (("penalty", 1, False), ("penalty", 1, True), ("contour", 1, False), ("contour", 1, True),
            ("penalty", 0, False), ("contour", 0, False))
    for n in args.landmarks:
        su = prepare(seq, n)
        held = su.node_of_point[su.heldout]
        ref = spline_reference(seq.points, seq.displacement, su.observed, su.heldout, su.geometry.radial[held],
                               su.geometry.circumferential[held])
        for drive, lag, trend in rows:
            t0 = time.perf_counter()
            model, y = measured.build_model(su, effects, drive, "region", drive_lag=lag, drive_trend=trend)
            res = IteratedSmoother(max_iterations=args.max_iterations, covariance=False).run(model, y)
            _, m = measured.evaluate(su, model, res, observations=y)
            print(f"{n:>9} {drive:<9}{'trend' if trend else lag:>5}{m['heldout_rmse_px']:>9.3f}{m['heldout_rmse_radial_px']:>8.3f}"
                  f"{m['heldout_rmse_circumferential_px']:>8.3f}{m['nis_mean_over_dof']:>9.3f}"
                  f"{m['innovation_lag1_autocorrelation']:>7.3f}{m['log_evidence']:>10.1f}{res.iterations:>4}"
                  f"{time.perf_counter() - t0:>6.0f}", flush=True)
        print(f"{n:>9} {'spline':<9}{'':>5}{ref['heldout_rmse_px']:>9.3f}{ref['heldout_rmse_radial_px']:>8.3f}"
              f"{ref['heldout_rmse_circumferential_px']:>8.3f}", flush=True)


if __name__ == "__main__":
    main()
