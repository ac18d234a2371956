"""``sfem-filters compare``: the paper's three-way synthetic comparison (Table 1, Figs. 1-5), with the
joint smoother as a fourth row; one seed here, several as a batch."""
from __future__ import annotations

import os
import sys

from .. import batch
from ..benchmark import comparison          # comparison.run_comparison: looked up when the verb runs
from ..benchmark.summary import format_summary, summarise
from ..export import export_comparison
from ..filtering.engines import ENGINES
from ..plotting.comparison import comparison_figures, summary_figure
from ._batch import _batch_mode, _run_batch
from ._common import _batch_options, _positive_float, _positive_int, _progress, _progress_options, _seeds, _write_json


def add_parser(sub) -> None:
    """The ``compare`` subcommand and its options, on the subparsers ``sub``."""
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
                        "median and quartiles of D, p, errors, loops and time; with --figures DIR: "
                        "DIR/batch_summary.png (the distributions of D and p) instead of each seed's figures")


def cmd_compare(args) -> int:
    failed = False
    if _batch_mode(args, len(args.seed)):
        jobs = batch.compare_jobs(args.seed, refine=args.refine, noise_mm=args.noise_mm, engine=args.engine,
                            max_loops=args.max_loops, tol=args.tol, figures=None if args.summary else args.figures,
                            export=args.export,
                            checkpoint_dir=args.checkpoint_dir)
        report = _run_batch(args, jobs, "compare")
        results = [batch.merge_timing(report.records[j.name]["result"], report.timings[j.name])
                   for j in jobs if j.name in report.records]
        failed = bool(report.failed)
        if not results:
            print("sfem-filters compare: error: no job produced a result", file=sys.stderr)
            return 1
    else:
        comp = comparison.run_comparison(args.seed[0], args.refine, args.noise_mm, engine=args.engine,
                                         max_loops=args.max_loops, tol=args.tol, progress=_progress(args),
                                         checkpoint_dir=args.checkpoint_dir)
        if args.figures:
            for path in comparison_figures(comp, args.figures, ekf_tol=args.tol):
                print(f"wrote {path}", file=sys.stderr)
        if args.export:
            for path in export_comparison(comp, args.export):
                print(f"wrote {path}", file=sys.stderr)
        results = [comp.as_json()]
    print(comparison.format_table(results))
    if args.summary:
        summary = summarise(results)
        print()
        print(format_summary(summary))
        if args.figures:
            print(f"wrote {summary_figure(summary, os.path.join(args.figures, 'batch_summary.png'))}", file=sys.stderr)
    if args.json:
        _write_json(args.json, results[0] if len(args.seed) == 1 and len(results) == 1 else results)
    return 1 if failed else 0
