"""Command line: ``sfem-filters compare | dense | observe``.

The choices of every option come from the modules' own constants (engines, drives,
parameterisations, effects), so the command line cannot drift from the library.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import warnings

from ._io import write_json
from .cardiac.closing import CRITERIA, LAPLACE, SEARCHES, SELECTIONS, not_converged_note
from .cardiac.effects import CATALOGUE, EXPLICIT_ONLY
from .cardiac.measured import DRIVES, ELEMENT_PX, ESTIMATORS, MESHES, OBSERVE, PARAMETERISATIONS, default_max_iterations
from .filtering.engines import ENGINES
from .filtering.smoother import MEMORY_ADVICE, InsufficientMemory
from .filtering.iterated import NOISE_LEVELS
from .resources import blas_threads


def _integer(text: str, expected: str) -> int:
    """``int(text)``, or an argparse error saying what was expected (never argparse's
    "invalid <function name> value", which names our internals)."""
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None


def _seeds(text: str) -> list:
    expected = "seeds like 0 or 0,1,2 or 0-4 (non-negative integers)"
    out = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part[1:]:
            a, b = part.split("-", 1)
            out.extend(range(_integer(a, expected), _integer(b, expected) + 1))
        else:
            out.append(_integer(part, expected))
    if not out or min(out) < 0:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return out


def _number(text: str, ok, expected: str) -> float:
    """``float(text)`` if it is finite and ``ok(value)``, else an argparse error saying what was expected."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not math.isfinite(value) or not ok(value):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def _positive_float(text: str) -> float:
    return _number(text, lambda v: v > 0, "a positive number")


def _finite_float(text: str) -> float:
    return _number(text, lambda v: True, "a finite number")


def _non_negative_float(text: str) -> float:
    return _number(text, lambda v: v >= 0, "a number >= 0")


def _non_negative_int(text: str) -> int:
    v = _integer(text, "an integer >= 0")
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return v


def _positive_int(text: str) -> int:
    v = _integer(text, "an integer >= 1")
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return v


def _landmarks(text: str) -> int:
    v = _integer(text, "an integer >= 3 (landmarks per contour)")
    if v < 3:
        raise argparse.ArgumentTypeError(f"expected an integer >= 3 (landmarks per contour), got {text!r}")
    return v


def _folds(text: str) -> int:
    v = _integer(text, "an integer >= 2")
    if v < 2:
        raise argparse.ArgumentTypeError(f"expected an integer >= 2, got {text!r}")
    return v


def _names(text: str) -> list:
    """A comma list of catalogue effects."""
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in CATALOGUE]
    if not names or unknown:
        raise argparse.ArgumentTypeError(f"expected a comma list of effects from {sorted(CATALOGUE)}, got {text!r}")
    return names


def _batch_options(p, unit: str, workers_help: str = "") -> None:
    p.add_argument("--scheduler", metavar="local|serial|ADDRESS",
                   help=f"run the {unit}s as a batch: 'local' (default with more than one {unit}: a Dask LocalCluster, "
                        "one worker process per core, one thread each), 'serial' (this process) or the address of a "
                        "running Dask scheduler, e.g. tcp://host:8786 (a cluster, or SLURM through dask-jobqueue)")
    p.add_argument("--workers", type=_positive_int,
                   help="worker processes of --scheduler local (default: one per core)" + workers_help)
    p.add_argument("--batch-dir", metavar="DIR",
                   help="result folder of a batch: a JSON per job and table.csv; jobs with a result there for the "
                        "same configuration are skipped, so a rerun resumes (default out/batch/<command>-<config hash>)")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="sfem-filters", description=(
        "Stochastic finite-element filters for cardiac kinematics and material (Shi & Liu 2003)."))
    p.add_argument("--blas-threads", type=_positive_int, metavar="N",
                   help="BLAS threads of this run (default: the library's measured best, 1, or the environment "
                        "variable SFEM_FILTERS_BLAS_THREADS)")
    sub = p.add_subparsers(dest="command", required=True)
    c = sub.add_parser("compare", help="the paper's three-way synthetic comparison (Table 1, Figs. 1-5), with the "
                                       "joint smoother as a fourth row",
                       description="Run the uniform-material KF, the perfect-material KF and the joint EKF "
                                   "on the pinned synthetic benchmark, and the joint iterated smoother on the joint "
                                   "EKF's model, and print a Table-1 style table.")
    c.add_argument("--seed", type=_seeds, default=[0], help="noise seed(s): 0, 0,1,2 or 0-4 (default 0)")
    c.add_argument("--refine", type=_positive_int, default=1, help="mesh refinement factor r (default 1)")
    c.add_argument("--noise-mm", type=_positive_float, default=0.1,
                   help="observation noise standard deviation in mm (default 0.1)")
    c.add_argument("--json", metavar="PATH", help="write the measured numbers as JSON")
    c.add_argument("--figures", metavar="DIR", help="write the figures (PNG) into DIR")
    c.add_argument("--export", metavar="DIR", help="write ParaView time series (.pvd + .vtu) into DIR")
    c.add_argument("--engine", choices=tuple(e for e in ENGINES if e != "roukf"), default="structured",
                   help="filter implementation: structured (default), filterpy (the reference), ud "
                        "(Bierman-Thornton U-D factorised, for ill-conditioned covariances) or ukf (filterpy's "
                        "UnscentedKalmanFilter on the full state: slow). Moireau & Chapelle's reduced-order UKF "
                        "estimates parameters only, so it has no fixed-material rows: 'dense --estimator roukf' "
                        "and the validation suite's peers claim run it")
    c.add_argument("--max-loops", type=_positive_int, default=50, help="cyclic loop limit (default 50)")
    c.add_argument("--tol", type=_positive_float, default=1e-3,
                   help="relative material change that ends the loops (default 1e-3)")
    c.add_argument("--checkpoint-dir", metavar="DIR",
                   help="save the joint EKF after every loop and resume from there if interrupted")
    _progress_options(c, "the per-loop and per-iteration bars of the joint estimators")
    _batch_options(c, "seed")
    c.add_argument("--summary", action="store_true",
                   help="Table 1 over the seeds: per strategy the rejection rate at 5%% with its 95%% Wilson interval, "
                        "median and quartiles of D, p, errors, loops and time; with --figures DIR: DIR/batch_summary.png "
                        "(the distributions of D and p) instead of each seed's figures")

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
    d.add_argument("--search", choices=tuple(SEARCHES), default="fast",
                   help="fast (default): every fit of a round started from the current model's mode "
                        "(--warm-start) and screened with 3 iterations, only the one kept fitted to the end "
                        "(--screen-iterations 3), at most 40 iterations; coarse: the same on a mesh of the wall "
                        "apart from the points (--mesh polar), faster, another discretisation; full: every fit to "
                        "the end from the prior (--no-warm-start --screen-iterations 0, 20 iterations). The options "
                        "below override the search's values; the docs' validation page 'Closing the loop: fast and "
                        "full search' measures what each finds and costs")
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

    o = sub.add_parser("observe", help="images or masks -> confidence-weighted observation sequence",
                       description="Shape-track the myocardial borders of a mask (or segmented image) sequence "
                                   "(Eqs. 35-37), sample phase-contrast velocities at mid-wall with their local "
                                   "phase coherence (Eqs. 38-39), and write a sequence file with confidences.")
    o.add_argument("path", help="images: a DICOM directory, .nii/.nii.gz, .npz (keys magnitude, velocity, masks, "
                                "pixel_spacing, frame_interval, venc) or .npy; or a sequence .npz with frame_masks")
    o.add_argument("--out", required=True, metavar="PATH", help="sequence .npz to write")
    o.add_argument("--pixel-spacing", type=_positive_float, help="pixel size in m (overrides the file)")
    o.add_argument("--frame-interval", type=_positive_float, help="time between frames in s (overrides the file)")
    o.add_argument("--venc", type=_positive_float, help="velocity encoding in m/s (overrides the file)")
    o.add_argument("--window", type=_positive_int, default=2, help="search window, contour points (default 2)")
    o.add_argument("--figures", metavar="DIR", help="write the figures (PNG) into DIR")
    o.add_argument("-q", "--quiet", action="store_true",
                   help="for scripts: no progress output (observe shows no bars; accepted as by every verb); "
                        "the results, errors and warnings are still printed")
    s = sub.add_parser("strain", help="DENSE images -> Green-Lagrange strain of every reference pixel, with sd and "
                                      "95%% bands, beside the conventional analysis",
                       description="Phase to Lagrangian displacement of every reference myocardial pixel, the "
                                   "finite-element smoother on a mesh chosen apart from the pixels, Green-Lagrange "
                                   "strain (radial and circumferential about the reference myocardium's centre of "
                                   "mass) with its sd, global and six-segment curves with 95% bands; the "
                                   "conventional analysis (finite differences) and the thin-plate spline through "
                                   "the same observed points in the same run. JSON keys: points, frame_times_s, "
                                   "strain, global, segments, conventional, spline, truth (when the case has one), "
                                   "peaks, seconds, route, settings "
                                   "(the docs' validation page 'Strain against DENSE-Sim's ground truth' scores it).")
    s.add_argument("path", help="a DENSE-Sim case folder (phase_x.npy, phase_y.npy, magnitude.npy, "
                                "LV_mask_time_lowres.npy, config.yaml); DICOM folders and sequence files are not "
                                "read by this verb yet")
    s.add_argument("--json", required=True, metavar="OUT", help="write the strain report (JSON) to OUT")
    s.add_argument("--route", choices=("dense", "contours"), default="dense",
                   help="dense (default): from the DENSE phase; contours: from the masks alone (tracked "
                        "endo- and epicardial borders, the interior from the physics; no phase)")
    s.add_argument("--segment-start", type=_finite_float, default=0.0, metavar="DEG",
                   help="start of segment 0: degrees about the centre from the image's +x axis towards +y "
                        "(default 0; the anterior RV insertion when you know it)")
    s.add_argument("--conventional-sigma", type=_non_negative_float, default=1.0, metavar="PX",
                   help="Gaussian smoothing (pixels, inside the mask) of the conventional analysis beside ours "
                        "(default 1; 0 none)")
    s.add_argument("--snr", type=_positive_float, metavar="SNR",
                   help="add complex Gaussian noise first (SNR = mean myocardial magnitude / noise sd), as the "
                        "validation does; default none")
    s.add_argument("--seed", type=_non_negative_int, default=0, help="seed of --snr's noise (default 0)")
    s.add_argument("--csv", metavar="PATH",
                   help="also write the report as one tidy CSV table (one row per method, region = pixel, global "
                        "or segment, frame and component; PATH ending .gz is compressed); see the how-to page "
                        "'Command-line recipes'")
    s.add_argument("--figures", metavar="DIR",
                   help="write the figures (PNG) into DIR: segment and global curves with 95%% bands against "
                        "the conventional analysis, the spline (and the ground truth when the case has one), "
                        "rings of peak strain and time to peak")
    _progress_options(s, "a line per step of the route")
    return p


def _progress_options(p, what: str) -> None:
    """``--quiet`` and ``--no-progress`` of a verb that shows progress on stderr (``what``)."""
    p.add_argument("-q", "--quiet", action="store_true",
                   help=f"for scripts: no progress on stderr ({what}); the results, errors and warnings are still "
                        "printed. Implies --no-progress")
    p.add_argument("--no-progress", action="store_true", help="no progress on stderr: the same as --quiet")


def _progress(args) -> bool:
    """Whether the verb shows its progress on stderr: not with ``--quiet`` nor ``--no-progress``."""
    return not (getattr(args, "quiet", False) or getattr(args, "no_progress", False))


def _message(command: str, kind: str, text: str) -> None:
    """One line of the command line's own on stderr: ``sfem-filters COMMAND: KIND: TEXT``."""
    print(f"sfem-filters {command}: {kind}: {text}", file=sys.stderr)


def _interrupted(args, exc) -> str:
    """What an interrupted verb (Ctrl-C) had finished and where it is kept."""
    if getattr(exc, "message", None):                   # the rounds say it themselves (RoundsInterrupted)
        return exc.message
    kept = getattr(args, "kept_in", None)
    if kept is not None:
        return f"interrupted; the finished jobs are kept in {kept} (the same command resumes from them)"
    if getattr(args, "checkpoint_dir", None):
        return (f"interrupted; the joint estimators' checkpoints are kept in {args.checkpoint_dir} (the same command "
                "resumes from them)")
    return "interrupted; nothing is kept" + (" (--checkpoint-dir DIR keeps the joint estimators' progress)"
                                             if args.command == "compare" else "")


def _batch_mode(args, n_jobs: int) -> bool:
    if args.workers is not None and args.scheduler not in (None, "local"):
        raise ValueError(f"--workers: only applies to --scheduler local, got --scheduler {args.scheduler}")
    return n_jobs > 1 or args.scheduler is not None or args.batch_dir is not None


def _run_batch(args, jobs, command: str):
    import hashlib
    import json

    from .batch import run_batch
    directory = args.batch_dir
    if directory is None:
        configs = json.dumps([{k: v for k, v in j.config.items() if k != "seed"} for j in jobs[:1]], sort_keys=True)
        directory = os.path.join("out", "batch", f"{command}-{hashlib.sha256(configs.encode()).hexdigest()[:10]}")
    args.kept_in = directory                            # for an interruption's message
    report = run_batch(jobs, directory, scheduler=args.scheduler or ("local" if len(jobs) > 1 else "serial"),
                       workers=args.workers, progress=_progress(args))
    print(report.summary_line(), file=sys.stderr)
    for name, message in report.failed.items():
        print(f"sfem-filters {command}: job {name} failed: {message} (traceback in "
              f"{os.path.join(report.directory, name + '.error.json')})", file=sys.stderr)
    print(f"wrote {report.table}", file=sys.stderr)
    return report


def cmd_compare(args) -> int:
    from .benchmark.comparison import format_table, run_comparison
    from .benchmark.summary import format_summary, summarise
    failed = False
    if _batch_mode(args, len(args.seed)):
        from .batch import compare_jobs, merge_timing
        jobs = compare_jobs(args.seed, refine=args.refine, noise_mm=args.noise_mm, engine=args.engine,
                            max_loops=args.max_loops, tol=args.tol, figures=None if args.summary else args.figures,
                            export=args.export,
                            checkpoint_dir=args.checkpoint_dir)
        report = _run_batch(args, jobs, "compare")
        results = [merge_timing(report.records[j.name]["result"], report.timings[j.name])
                   for j in jobs if j.name in report.records]
        failed = bool(report.failed)
        if not results:
            print("sfem-filters compare: error: no job produced a result", file=sys.stderr)
            return 1
    else:
        comp = run_comparison(args.seed[0], args.refine, args.noise_mm, engine=args.engine, max_loops=args.max_loops,
                              tol=args.tol, progress=_progress(args), checkpoint_dir=args.checkpoint_dir)
        if args.figures:
            from .plotting.comparison import comparison_figures
            for path in comparison_figures(comp, args.figures, ekf_tol=args.tol):
                print(f"wrote {path}", file=sys.stderr)
        if args.export:
            from .export import export_comparison
            for path in export_comparison(comp, args.export):
                print(f"wrote {path}", file=sys.stderr)
        results = [comp.as_json()]
    print(format_table(results))
    if args.summary:
        summary = summarise(results)
        print()
        print(format_summary(summary))
        if args.figures:
            from .plotting.comparison import summary_figure
            print(f"wrote {summary_figure(summary, os.path.join(args.figures, 'batch_summary.png'))}", file=sys.stderr)
    if args.json:
        _write_json(args.json, results[0] if len(args.seed) == 1 and len(results) == 1 else results)
    return 1 if failed else 0


def cmd_dense(args) -> int:
    from .cardiac.closing import closing_the_loop, format_report
    from .cardiac.sequence import example_path, load_sequence
    search = SEARCHES[args.search]
    config = dict(effects=args.effects, drive=args.drive, landmarks=args.landmarks, observe=args.observe,
                  holdout_seed=args.holdout_seed, parameterisation=args.parameterisation, max_loops=args.max_loops,
                  estimator=args.estimator,
                  max_iterations=(search.max_iterations(args.drive) if args.max_iterations is None
                                  else args.max_iterations), max_rounds=args.max_rounds,
                  alpha=args.alpha, criterion=args.criterion, folds=args.folds,
                  # always in the configuration (and a batch job's fingerprint): the default changed
                  # from "first" to "best", and a result of the one must not be reused for the other
                  selection=args.selection, max_tries=args.max_tries,
                  # likewise: the backward steps are new, and a result without them is not one with them
                  prune=not args.no_prune)
    if args.laplace != "gauss-newton":      # only when asked: batch fingerprints of earlier results stay valid
        config["laplace"] = args.laplace
    if args.measurement_noise != "fixed":   # likewise
        config["measurement_noise"] = args.measurement_noise
    mesh = search.mesh if args.mesh is None else args.mesh
    if mesh != "delaunay":                  # likewise
        config["mesh"] = mesh
        if mesh == "polar":
            config["element_px"] = search.element_px if args.element_px is None else args.element_px
    if (search.warm_start if args.warm_start is None else args.warm_start) and args.estimator == "smoother":
        config["warm_start"] = True         # likewise
    screen = search.screen_iterations if args.screen_iterations is None else (args.screen_iterations or None)
    if screen is not None and args.estimator == "smoother":
        config["screen_iterations"] = screen
    if args.angle_origin != 0.0:            # likewise
        config["angle_origin_deg"] = args.angle_origin
    if args.candidates is not None:
        config["candidates"] = args.candidates
    if _batch_mode(args, len(args.path)):
        from .batch import dense_jobs, describe_record, merge_timing
        jobs = dense_jobs(args.path, figures=args.figures, export=args.export, **config)
        report = _run_batch(args, jobs, "dense")
        for j in jobs:
            if j.name in report.records:
                print(describe_record(report.records[j.name]))
        if args.json:
            _write_json(args.json, [merge_timing(report.records[j.name]["result"], report.timings[j.name])
                                    for j in jobs if j.name in report.records])
        return 1 if report.failed or not report.records else 0
    path = args.path[0]
    seq = load_sequence(example_path(download=args.download) if path == "example" else path)
    # --workers changes how fast, not what: it is not part of the configuration (nor a batch fingerprint)
    out = closing_the_loop(seq, progress=_progress(args), workers=args.workers, **config)
    print(format_report(out))
    note = not_converged_note(out.as_json())
    if note:
        print(f"sfem-filters dense: warning: {note}", file=sys.stderr)
    if args.figures:
        from .plotting.measured import dense_figures
        for p in dense_figures(out, args.figures):
            print(f"wrote {p}", file=sys.stderr)
    if args.export:
        from .export import export_dense
        for p in export_dense(out, args.export):
            print(f"wrote {p}", file=sys.stderr)
    if args.json:
        _write_json(args.json, out.as_json())
    return 0


def cmd_observe(args) -> int:
    from dataclasses import replace

    import numpy as np

    from .cardiac.frontend import observe
    from .cardiac.sequence import save_sequence
    from .imaging.readers import make_image_series, read_images
    from .imaging.tracking import TrackingOptions

    path = args.path
    series = None
    if path.endswith(".npz") and os.path.isfile(path):
        try:
            with np.load(path, allow_pickle=False) as f:
                keys = set(f.files)
                if "frame_masks" in keys and not keys & {"masks", "magnitude"}:
                    series = make_image_series(masks=f["frame_masks"], provenance=path,
                                               pixel_spacing=f["pixel_spacing"] if "pixel_spacing" in keys else None,
                                               frame_interval=f["frame_interval"] if "frame_interval" in keys else None)
        except (OSError, EOFError) as exc:
            raise ValueError(f"{path}: not a readable .npz file ({exc})") from None
    if series is None:
        series = read_images(path)
    over = {k: v for k, v in (("pixel_spacing", args.pixel_spacing), ("frame_interval", args.frame_interval),
                              ("venc", args.venc)) if v is not None}
    if over:
        series = replace(series, **over)
    seq, tracks, vel, masks = observe(series, TrackingOptions(window=args.window))
    save_sequence(seq, args.out)
    c = tracks.step_confidence[1:]
    print(f"frames {seq.n_frames}; border points {len(tracks.points)} (endo {int((tracks.contour == 0).sum())}, "
          f"epi {int((tracks.contour == 1).sum())}); match confidence c median {np.median(c):.2f} "
          f"(5-95%: {np.percentile(c, 5):.2f}-{np.percentile(c, 95):.2f}); tracking sd at the last frame "
          f"median {np.median(tracks.sigma[-1]):.2f} px")
    if vel is not None:
        print(f"velocity points {len(vel.points)}; LPC median {np.median(vel.lpc):.2f} "
              f"(5-95%: {np.percentile(vel.lpc, 5):.2f}-{np.percentile(vel.lpc, 95):.2f})")
    print(f"wrote {args.out}", file=sys.stderr)
    if args.figures:
        from .plotting.frontend import observe_figures
        for p in observe_figures({"tracks": tracks, "masks": masks, "velocity": vel}, args.figures):
            print(f"wrote {p}", file=sys.stderr)
    return 0


def cmd_strain(args) -> int:
    import time

    import numpy as np

    from .cardiac import StrainRouteSettings, dense_strain
    from .imaging import add_complex_noise, conventional_analysis, phase_to_displacement, read_dense_sim

    if not os.path.isfile(os.path.join(args.path, "config.yaml")):
        raise ValueError(f"path: expected a DENSE-Sim case folder with config.yaml, phase_x.npy, phase_y.npy, "
                         f"magnitude.npy and LV_mask_time_lowres.npy, got {args.path!r}")
    say = (lambda m: _message("strain", "progress", m)) if _progress(args) else (lambda m: None)
    t0 = time.perf_counter()
    say(f"reading {args.path}")
    case = read_dense_sim(args.path)
    if args.snr is not None:
        say(f"adding complex noise at SNR {args.snr:g} (seed {args.seed})")
        case = add_complex_noise(case, args.snr, args.seed)
    say("phase to Lagrangian displacement")
    tracks = phase_to_displacement(case)
    if args.route == "contours":       # the masks alone (no phase): tracked borders, interior from the physics
        from .cardiac.contours_route import ContourRouteSettings, contour_spline_strain, contour_strain
        ours = contour_strain(case.masks, case.pixel_size_m, case.frame_times_s,
                              ContourRouteSettings(start_deg=args.segment_start), progress=say)
    else:
        ours = dense_strain(tracks, case.reference_mask, case.pixel_size_m,
                            StrainRouteSettings(start_deg=args.segment_start), progress=say)
    conv = conventional_analysis(case, sigma=args.conventional_sigma, centre=ours.centre,
                                 start_deg=args.segment_start, tracks=tracks)
    out = ours.to_dict()
    if args.route == "contours":
        from .imaging.strain_report import spline_block
        say("thin-plate spline through the same tracked contour landmarks")
        out["spline"] = spline_block(contour_spline_strain(ours), "the tracked contour landmarks (the points the "
                                     "contours route observes, their full tracked displacement), each component "
                                     "with the larger of the landmark's normal and tangential sd")

    def js(a):
        a = np.asarray(a, float)
        return np.where(np.isfinite(a), a.astype(object), None).tolist()
    out["conventional"] = {
        "smoothing_sigma_px": args.conventional_sigma,
        "strain": {k: js(getattr(conv.strain, k)) for k in ("Ecc", "Err", "Ecr")},
        "global": {"Ecc": js(conv.global_Ecc), "Err": js(conv.global_Err)},
        "segments": {"start_deg": conv.start_deg, "Ecc": js(conv.segments_Ecc), "Err": js(conv.segments_Err)}}
    out["settings"] = {**out["settings"], "noise_snr": args.snr, "noise_seed": args.seed if args.snr else None,
                       "untracked_point_frames": int(tracks.n_untracked)}
    if "spline" not in out:
        out["spline"] = _dense_spline(tracks, ours.centre, args.segment_start, say)
    out["seconds"] = time.perf_counter() - t0
    g = ours.global_curves
    peak_cc, peak_rr = int(np.nanargmin(g["Ecc"])), int(np.nanargmax(g["Err"]))
    print(f"{len(ours.points)} reference pixels x {len(ours.frame_times_s)} frames; global peak Ecc "
          f"{100 * g['Ecc'][peak_cc]:.2f}% (95% {100 * g['Ecc_lo'][peak_cc]:.2f} to {100 * g['Ecc_hi'][peak_cc]:.2f}) "
          f"at {ours.frame_times_s[peak_cc]:.3f} s, Err {100 * g['Err'][peak_rr]:.2f}% "
          f"(95% {100 * g['Err_lo'][peak_rr]:.2f} to {100 * g['Err_hi'][peak_rr]:.2f}) at "
          f"{ours.frame_times_s[peak_rr]:.3f} s; conventional (sigma {args.conventional_sigma:g} px) "
          f"{100 * np.nanmin(conv.global_Ecc):.2f}% / {100 * np.nanmax(conv.global_Err):.2f}%; {out['seconds']:.0f} s")
    out = _strain_extras(case, out, say)
    _write_json(args.json, out)
    if args.csv:
        from .imaging.strain_report import strain_csv
        say(f"writing the CSV table {args.csv}")
        print(f"wrote {strain_csv(out, args.csv)}", file=sys.stderr)
    if args.figures:
        from .plotting.strain import strain_figures
        say(f"drawing the figures into {args.figures}")
        for p in strain_figures(out, args.figures):
            print(f"wrote {p}", file=sys.stderr)
        if "material" not in out:
            say("no stiffness figure: the route holds the material fixed (its settings say so), so there is no "
                "stiffness per segment with an sd to draw")
    return 0


def _dense_spline(tracks, centre, start_deg: float, say) -> dict:
    """The yardstick of the DENSE route: the thin-plate spline through the same observed points (every
    tracked reference pixel, with the tracks' sd), its strain at the reference pixels, as the ``spline`` block."""
    from .imaging.spline_strain import spline_strain
    from .imaging.strain_report import spline_block

    say("thin-plate spline through the same observed points (the tracked reference pixels)")
    s = spline_strain(tracks.points, tracks.displacement, tracks.points, sd_px=tracks.sd, centre=centre,
                      start_deg=start_deg, frame_times_s=tracks.frame_times_s)
    return spline_block(s, "the tracked reference pixels (every datum the dense route observes), with their sd")


def _strain_extras(case, out: dict, say) -> dict:
    """The strain report with the case's ground truth as a ``truth`` block (when it has one) and the
    peaks and times to peak of every method's curves (``peaks`` in each block)."""
    from .imaging import truth_at_points
    from .imaging.strain_report import truth_block, with_peaks

    if case.has_truth and out.get("centre") is not None:
        say("ground truth of the case at the reference pixels")
        te, tr = truth_at_points(case)
        out["truth"] = truth_block(te, tr, out["points"], out["centre"], out["segments"]["start_deg"],
                                   source="DENSE-Sim GT_Ecc, GT_Err")
    return with_peaks(out)


def _write_json(path, payload):
    print(f"wrote {write_json(path, payload)}", file=sys.stderr)


def _warning_line(message, category, filename, lineno, line=None) -> str:
    """A warning as the command line shows it: one line, what happened, no source path."""
    kind = "warning" if category in (UserWarning, RuntimeWarning) else f"warning ({category.__name__})"
    return f"sfem-filters: {kind}: {' '.join(str(message).split())}\n"


@contextlib.contextmanager
def _warnings_as_lines():
    """Show warnings as :func:`_warning_line` while the command runs (not at import: a library
    user keeps Python's format); recorded warnings (``catch_warnings(record=True)``) stay records."""
    saved = warnings.formatwarning
    warnings.formatwarning = _warning_line
    try:
        yield
    finally:
        warnings.formatwarning = saved


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        # BLAS: --blas-threads, else SFEM_FILTERS_BLAS_THREADS, else the measured default
        with blas_threads(args.blas_threads), _warnings_as_lines():
            return {"compare": cmd_compare, "dense": cmd_dense, "observe": cmd_observe,
                    "strain": cmd_strain}[args.command](args)
    except KeyboardInterrupt as exc:
        # Ctrl-C: the rounds have stopped their workers; one line says what finished and where it is kept
        _message(args.command, "interrupted", _interrupted(args, exc).removeprefix("interrupted").lstrip(" ;,"))
        return 130
    except MemoryError as exc:
        # the smoother's own refusal says what to reduce; an allocation that fails midway does not
        text = str(exc) if isinstance(exc, InsufficientMemory) else (
            "out of memory" + (f" ({exc})" if str(exc) else "") + f"; the run needs more memory than is free here: "
            f"{MEMORY_ADVICE}")
        _message(args.command, "error", text)
        return 2
    except (ValueError, TypeError, OSError, ImportError) as exc:
        _message(args.command, "error", str(exc))
        return 2


if __name__ == "__main__":
    sys.exit(main())
