"""Which model interpolates the measured slice: held-out error against cross-validation (issue 14).

Fixed-material variants of the ``dense`` model (uniform nominal E and nu, so that every row is one
linear smoother pass and the comparison is about the drive and the effects, not the material
estimate) on the shipped slice, 8 and 16 landmarks per contour: held-out RMSE (the points no
model sees) beside the K-fold cross-validation RMSE over the observed landmarks
(:mod:`sfem_filters.cardiac.crossval`) and, for the same split and folds, the thin-plate spline's.
Whether the observed-data criterion ranks the variants as the held-out points do is what decides
if it can stand in for them.

    OPENBLAS_NUM_THREADS=1 python benchmarks/dense_variants.py [--landmarks 8 16] [--folds 4]
        [--observe boundary|boundary+midwall] [--only NAME ...] [--material none region basis]

With ``--observe boundary+midwall`` a seeded half of the mid-wall points is observed too (and
dealt to the folds), so that both the model and its cross-validation see the inside of the wall.
The ``+spline`` columns are the same held-out and CV errors of the model plus a thin-plate
spline of its residual at the observed points
(:func:`sfem_filters.cardiac.reference.residual_spline`), and the next the held-out RMSE of the
model plus the spline minus the spline's, with its 95% interval (delete-one-sector jackknife over
as many angular sectors of the held-out points as landmarks per contour,
:func:`sfem_filters.cardiac.closing.versus_spline`; negative: the physics adds to the spline).
The last gives the model's own held-out RMSE minus the spline's, with the same interval
(negative: the model beats the spline).
``--only`` runs the named rows alone (the rank correlation then needs at least 3 of them).
``--material`` runs every row with each material map named (``none``: fixed uniform nominal, the
default; ``region``, ``basis``: the ``dense`` command's maps, estimated by the iterated smoother
with the CV at the estimate), and the column ``log p(y)`` gives each model's log evidence (nats,
the rounds' default criterion), so that the map the evidence prefers can be set beside the one
the held-out points prefer.
"""
from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from scipy.stats import spearmanr

from sfem_filters.cardiac import (OBSERVE, example_path, load_sequence, prepare, run, spline_cross_validation,
                                  spline_reference)
from sfem_filters.cardiac.closing import Variant, round_cross_validation, versus_spline

VARIANTS = (
    ("penalty", Variant()),
    ("contour+trend", Variant(drive="contour", drive_trend=True)),
    ("contour+trend, springs x10", Variant(drive="contour", drive_trend=True, spring_scale=10.0)),
    ("penalty, active_polar", Variant(effects=("active_polar",))),
    ("contour+trend, active_polar", Variant(("active_polar",), "contour", True)),
    ("contour+trend, active_polar, springs x10", Variant(("active_polar",), "contour", True, spring_scale=10.0)),
    ("contour+trend, active_polar + active_helical", Variant(("active_polar", "active_helical"), "contour", True)),
    ("contour+trend, active_polar + active_transmural", Variant(("active_polar", "active_transmural"), "contour", True)),
    ("contour+trend, active_segments", Variant(("active_segments",), "contour", True)),
    ("contour+trend, active_harmonic", Variant(("active_harmonic",), "contour", True)),
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--landmarks", type=int, nargs="+", default=[8, 16])
    ap.add_argument("--folds", type=int, default=4)
    ap.add_argument("--observe", choices=OBSERVE, default="boundary")
    ap.add_argument("--only", nargs="+", metavar="NAME", choices=[n for n, _ in VARIANTS],
                    help="run only these rows (names as printed)")
    ap.add_argument("--material", nargs="+", choices=("none", "region", "basis"), default=["none"],
                    help="material maps to run every row with (none: fixed uniform nominal)")
    args = ap.parse_args(argv)
    variants = [(n if m == "none" else f"{n} [{m}]", v, m)           # no tag: material fixed
                for n, v in VARIANTS if args.only is None or n in args.only for m in args.material]
    seq = load_sequence(example_path())
    print(f"observe {args.observe}, {args.folds} folds")
    title = "model (material fixed: uniform nominal)" if args.material == ["none"] else "model [material map]"
    print(f"{'landmarks':>9}  {title:<56}{'held-out':>9}{'CV':>8}{'NIS/dof':>9}"
          f"{'s':>6}{'+spline':>9}{'CV':>8}  {'+spline - spline (95%)':<24}{'log p(y)':>10}  {'model - spline (95%)':<24}")
    for L in args.landmarks:
        setup = prepare(seq, L, observe=args.observe)
        g, held = setup.geometry, setup.node_of_point[setup.heldout]
        reference = spline_reference(seq.points, seq.displacement, setup.observed, setup.heldout, g.radial[held],
                                     g.circumferential[held])
        spline = reference["heldout_rmse_px"]
        spline_cv = spline_cross_validation(setup, args.folds)["rmse_px"]
        rows = []
        for name, v, material in variants:
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)          # the baseline's NIS safeguard
                r = run(setup, v.effects, v.drive, material, drive_trend=v.drive_trend, spring_scale=v.spring_scale,
                        effect_rates=v.effect_rates, process_scale=v.process_scale)
                cvs = round_cross_validation(setup, v, r, args.folds)
            cv = cvs["rmse_px"]
            vs = versus_spline(setup, r.U, reference["U"])
            gap, own = ("-", "-") if vs is None else ("{difference:+.3f} ({low:+.3f}, {high:+.3f})".format(**vs[k])
                                                      for k in ("model_plus_spline", "model"))
            rows.append((r.metrics["heldout_rmse_px"], cv))
            print(f"{L:>9}  {name:<56}{rows[-1][0]:>9.3f}{cv:>8.3f}{r.metrics['nis_mean_over_dof']:>9.3f}"
                  f"{time.perf_counter() - t0:>6.0f}{r.metrics['residual_spline']['heldout_rmse_px']:>9.3f}"
                  f"{cvs['residual_spline']['rmse_px']:>8.3f}  {gap:<24}{r.metrics['log_evidence']:>10.1f}  {own:<24}", flush=True)
        print(f"{L:>9}  {'thin-plate spline, no physics':<56}{spline:>9.3f}{spline_cv:>8.3f}")
        h, c = np.array(rows).T
        if len(rows) < 3:
            continue
        print(f"{L:>9}  Spearman rank correlation of CV with held-out over the models: {spearmanr(h, c)[0]:.2f}; "
              f"best by CV: {variants[int(np.argmin(c))][0]} ({h[np.argmin(c)]:.3f} held-out), "
              f"best held-out {h.min():.3f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
