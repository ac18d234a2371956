"""``sfem-filters dense``: close the loop on measured point-wise motion (DENSE, tagging, tracking):
a baseline, then rounds adding the missing effects the innovations point to; several files as a batch."""
from __future__ import annotations

import argparse
import sys

from .. import batch
from ..cardiac import closing, sequence     # closing.closing_the_loop, sequence.load_sequence: looked up when run
from ..cardiac.closing import CRITERIA, LAPLACE, SEARCHES, SELECTIONS, STIFF_SPRINGS, not_converged_note
from ..cardiac.effects import CATALOGUE, EXPLICIT_ONLY
from ..cardiac.measured import DRIVES, ELEMENT_PX, ESTIMATORS, MESHES, OBSERVE, PARAMETERISATIONS
from ..cardiac.myocardium import NotStarShapedError
from ..cardiac.specs import EstimatorSettings, LoopSettings, ModelSpec
from ..export import export_dense
from ..filtering.iterated import NOISE_LEVELS
from ..plotting.measured import dense_figures
from ._batch import _batch_mode, _run_batch
from ._common import (_batch_options, _finite_float, _folds, _landmarks, _names, _non_negative_int, _positive_float,
                      _positive_int, _progress, _progress_options, _write_json)


def add_parser(sub) -> None:
    """The ``dense`` subcommand and its options, on the subparsers ``sub``."""
    d = sub.add_parser("dense", help="close the loop on measured point-wise motion (DENSE, tagging, tracking)",
                       description="Baseline run on a sequence file, then rounds: rank the candidate missing "
                                   "effects on the current innovations, add the best while it is significant and "
                                   "log p(y) rises; held-out errors of every round beside a thin-plate spline's.")
    d.add_argument("path", nargs="+", help="sequence .npz file(s): keys points (P, 2) and displacement (F, P, 2) "
                                           "in pixels, optional sigma, confidence, point_kind, frame_interval, "
                                           "pixel_spacing, pressure, frame_masks, ... (the docs' how-to page "
                                           "'Formats and readers' lists every key); 'example' for the measured DENSE "
                                           "slice subject_a (not shipped: read from the data directory "
                                           "$SFEM_FILTERS_DATA or the download cache; --download fetches it); several "
                                           "files run as a batch, one job each")
    d.add_argument("--download", action="store_true",
                   help="with 'example': download the slice from its original repository (checksum verified) "
                        "when it is in neither the data directory nor the cache")
    d.add_argument("--effects", default="auto",
                   help="none, auto (rounds of ranking and adding effects) or a comma list of: "
                        + ", ".join(sorted(CATALOGUE)) + " (default auto)")
    d.add_argument("--candidates", type=_names, default=None, metavar="NAME,...",
                   help="the catalogue effects the rounds of --effects auto may add (default: all but "
                        + ", ".join(EXPLICIT_ONLY) + ", which are tried only when named here)")
    d.add_argument("--drive", choices=DRIVES, default="penalty",
                   help="what drives the model besides its effects (default penalty)")
    d.add_argument("--landmarks", type=_landmarks, default=8, help="observed landmarks per contour (default 8)")
    d.add_argument("--observe", choices=OBSERVE, default="boundary",
                   help="observe the landmarks only, or also a seeded half of the mid-wall points")
    d.add_argument("--holdout-seed", type=int, default=0, help="seed of the mid-wall split (default 0)")
    d.add_argument("--parameterisation", choices=PARAMETERISATIONS, default="region",
                   help="material parameterisation: 12 regions (default), a smooth basis (6 relative "
                        "log E modes, 3 nu modes), per element, or none (material fixed)")
    d.add_argument("--estimator", choices=ESTIMATORS, default="smoother",
                   help="smoother (default): the iterated smoother, the MAP of one cycle with its data counted once "
                        "and a Laplace posterior; cyclic: the paper's cyclic joint EKF, reported with the covariance "
                        "of one cycle; roukf: Moireau & Chapelle's reduced-order UKF (p + 1 simplex sigma points on "
                        "the material, no tangent operator, no process noise) in the same cyclic driver")
    d.add_argument("--max-iterations", type=_positive_int, default=None,
                   help="Gauss-Newton iteration limit of the smoother (default 20; 80 with --drive pressure, where "
                        "the stiffness level is estimated and takes longer to converge)")
    d.add_argument("--max-loops", type=_positive_int, default=3, help="loop limit of the cyclic estimator (default 3)")
    d.add_argument("--max-rounds", type=_positive_int, default=5,
                   help="most rounds (effects or corrections added) of --effects auto (default 5)")
    d.add_argument("--alpha", type=_positive_float, default=0.01,
                   help="family-wise level of the candidates' score tests, Bonferroni-corrected (default 0.01)")
    d.add_argument("--criterion", choices=CRITERIA, default="evidence",
                   help="what a candidate must improve to be kept: evidence, log p(y) of the observed points "
                        "(default); cv, the K-fold cross-validation error over the observed points (each fold "
                        "neither drives nor is observed)")
    d.add_argument("--selection", choices=SELECTIONS, default="best",
                   help="how a round picks among significant candidates: best, fit them (at most --max-tries) and "
                        "keep the one that improves the criterion most (default); first, the first by score that "
                        "improves it")
    d.add_argument("--max-tries", type=_positive_int, default=3,
                   help="most significant candidates fitted per round (default 3)")
    d.add_argument("--no-prune", action="store_true",
                   help="no backward steps: after a round adds a term, do not try taking earlier terms out "
                        "(by default the one whose removal improves the criterion most is taken out, while one does)")
    d.add_argument("--folds", type=_folds, default=4,
                   help="folds of the cross-validation over the observed points, reported for every round "
                        "(default 4, at least 2)")
    d.add_argument("--laplace", choices=LAPLACE, default="gauss-newton",
                   help="the final model's material covariance: gauss-newton, the smoother's inverse Gauss-Newton "
                        "Hessian (default, free); exact, the inverse exact Hessian of the MAP cost at the final mode "
                        "(2 p + 1 gradient passes more, about 5 min for the 23-parameter region map: the Laplace "
                        "approximation proper where the model misfits its data); smoother only")
    d.add_argument("--measurement-noise", choices=NOISE_LEVELS, default="fixed",
                   help="fixed: the measurement noise at the data's noise floor (default); estimate: every fit "
                        "chooses its level by type-II maximum likelihood (about 3-5 fits each; smoother and the "
                        "evidence criterion only)")
    d.add_argument("--search", choices=tuple(SEARCHES), default="coarse",
                   help="coarse (default): on a mesh of the wall apart from the points (--mesh polar, 2-pixel "
                        "edges; the points' own mesh where the wall is not star-shaped about its centre), every fit "
                        "of a round started from the current model's mode (--warm-start) and screened with 3 "
                        "iterations, only the one kept fitted to the end (--screen-iterations 3), at most 40 "
                        "iterations; fast: the same on the node-per-point mesh, a few times slower; full: every fit "
                        "to the end from the prior on the node-per-point mesh (--no-warm-start --screen-iterations "
                        "0, 20 iterations). The options below override the search's values; the docs' validation "
                        "page 'Closing the loop: the coarse and fast searches' measures what each finds and costs")
    d.add_argument("--mesh", choices=MESHES, default=None,
                   help="delaunay: Delaunay triangles, whose diagonal in each full pixel cell Qhull picks by the "
                        "coordinates (--search fast, full); radial: every diagonal towards the cavity "
                        "centre, the same mesh wherever the heart lies in the image (pixel lattices only); polar: "
                        "a mesh of the wall apart from the points (rings at equal angles, layers across the wall, "
                        "edges of --element-px), the points observed through its shape functions: the cost is set "
                        "by the element size, not by the points (--search coarse)")
    d.add_argument("--element-px", type=_positive_float, default=None, metavar="PX",
                   help=f"element edge of --mesh polar, in the points' spacings (pixels; default {ELEMENT_PX:g})")
    d.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=None,
                   help="start each fit of a round from the material mode of the model it extends or prunes, not "
                        "from the prior mean (the same cost and mode, fewer iterations; --search fast, coarse)")
    d.add_argument("--screen-iterations", type=_non_negative_int, default=None, metavar="N",
                   help="screen every fit of a round with at most N Gauss-Newton iterations and fit only the one "
                        "that would be kept to the end (--search fast: 3; 0: every fit to the end, --search full)")
    d.add_argument("--stiff-springs", choices=STIFF_SPRINGS, default="contour",
                   help="which drives the rounds' correction springs:x10 (springs ten times stiffer) is offered to: "
                        "contour (default), only springs spread along the whole contour (--drive contour); any, "
                        "the isolated landmarks' springs of --drive penalty too, which pull tents in the wall (what "
                        "the rounds did before; the docs' validation page 'Stiff springs only along the contours')")
    d.add_argument("--angle-origin", type=_finite_float, default=0.0, metavar="DEG",
                   help="where landmark 0, sector 0 of the regional map and segment 0 start: the angle about the "
                        "cavity centre in degrees from the image's +x axis towards +y (down), for example the "
                        "anterior RV insertion (default 0)")
    d.add_argument("--json", metavar="PATH", help="write the report as JSON")
    d.add_argument("--figures", metavar="DIR", help="write the figures (PNG) into DIR")
    d.add_argument("--export", metavar="DIR", help="write ParaView time series (.pvd + .vtu) into DIR")
    _progress_options(d, "a line as the baseline and each round end: what was tried and kept, the held-out error "
                         "against the spline's, the elapsed time, an upper bound of the time left; and each fit's "
                         "bar: iterations, cost, time")
    _batch_options(d, "file", "; with one file, the fits of each round made side by side, one process each on one "
                              "BLAS thread, the same figures whatever the number (default: one per core, as far as "
                              "the memory holds them)")


def _specs(args) -> tuple:
    """``(ModelSpec, EstimatorSettings, LoopSettings)`` of the command's options: the search's values
    (``--search``) where an option is not given; warm starts and screening for the smoother only."""
    search = SEARCHES[args.search]
    smoother = args.estimator == "smoother"
    model = ModelSpec(drive=args.drive, parameterisation=args.parameterisation, landmarks=args.landmarks,
                      observe=args.observe, holdout_seed=args.holdout_seed,
                      mesh=search.mesh if args.mesh is None else args.mesh,
                      element_px=search.element_px if args.element_px is None else args.element_px,
                      angle_origin_deg=args.angle_origin)
    estimator = EstimatorSettings(estimator=args.estimator, max_loops=args.max_loops, laplace=args.laplace,
                                  measurement_noise=args.measurement_noise,
                                  max_iterations=(search.max_iterations(args.drive) if args.max_iterations is None
                                                  else args.max_iterations))
    loop = LoopSettings(effects=args.effects, candidates=args.candidates, max_rounds=args.max_rounds,
                        alpha=args.alpha, criterion=args.criterion, folds=args.folds, selection=args.selection,
                        max_tries=args.max_tries, prune=not args.no_prune, stiff_springs=args.stiff_springs,
                        warm_start=bool(search.warm_start if args.warm_start is None else args.warm_start)
                        and smoother,
                        screen_iterations=((search.screen_iterations if args.screen_iterations is None
                                            else args.screen_iterations or None) if smoother else None))
    return model, estimator, loop


def cmd_dense(args) -> int:
    model, estimator, loop = _specs(args)
    # every setting in the specs, defaults included (a batch job's fingerprint hashes them whole)
    if _batch_mode(args, len(args.path)):
        jobs = batch.dense_jobs(args.path, model, estimator, loop, figures=args.figures, export=args.export)
        report = _run_batch(args, jobs, "dense")
        for j in jobs:
            if j.name in report.records:
                print(batch.describe_record(report.records[j.name]))
        if args.json:
            _write_json(args.json, [batch.merge_timing(report.records[j.name]["result"], report.timings[j.name])
                                    for j in jobs if j.name in report.records])
        return 1 if report.failed or not report.records else 0
    path = args.path[0]
    seq = sequence.load_sequence(sequence.example_path(download=args.download) if path == "example" else path)
    # --workers changes how fast, not what: it is not part of the specs (nor a batch fingerprint)
    try:
        out = closing.closing_the_loop(seq, model, estimator, loop, progress=_progress(args), workers=args.workers)
    except NotStarShapedError as exc:
        if args.mesh is not None:           # asked for by name: the error stands
            raise
        # the search's polar mesh cannot follow this wall: the mesh through the points instead
        print(f"sfem-filters dense: warning: --search {args.search}: {exc}; meshing through the points "
              f"(--mesh delaunay) instead", file=sys.stderr)
        model = model.with_(mesh="delaunay")
        out = closing.closing_the_loop(seq, model, estimator, loop, progress=_progress(args), workers=args.workers)
    print(closing.format_report(out))
    note = not_converged_note(out.as_json())
    if note:
        print(f"sfem-filters dense: warning: {note}", file=sys.stderr)
    if args.figures:
        for p in dense_figures(out, args.figures):
            print(f"wrote {p}", file=sys.stderr)
    if args.export:
        for p in export_dense(out, args.export):
            print(f"wrote {p}", file=sys.stderr)
    if args.json:
        _write_json(args.json, out.as_json())
    return 0
