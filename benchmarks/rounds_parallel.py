"""Wall time of the measured-data rounds: variances only for the fits kept, fits side by side.

    python benchmarks/rounds_parallel.py [--workers 2] [--max-iterations 6] [--max-rounds 2] [--landmarks 8]

Figures as ratios against a baseline measured in the same run:

* **BLAS threads.** One smoother fit of the shipped slice (subject_a, the `dense` command's
  region map, `active_polar`, ``--max-iterations`` Gauss-Newton steps) on one BLAS thread and
  on as many as the machine has. ``closing_the_loop`` holds every fit to one thread, so that a
  fit's figures do not depend on how many run at once; this line says what that costs.
* **Rounds.** ``closing_the_loop`` on the shipped slice (the `dense` command's settings, with
  ``--max-iterations`` and ``--max-rounds`` as given) three ways: every fit with the variances of
  its kinematics and strains, one after the other (the baseline: how the rounds ran before);
  the variances made only for the fits kept, one after the other; the same with ``--workers``
  fits side by side. The wall time of each, its ratio to the baseline, and whether the three
  reports agree to the last bit (every figure but the wall times).
"""
from __future__ import annotations

import argparse
import json
import time

from threadpoolctl import threadpool_info, threadpool_limits

from sfem_filters.batch import split_timing
from sfem_filters.cardiac import closing, measured
from sfem_filters.cardiac.sequence import example_path, load_sequence


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2, help="fits side by side (default 2)")
    ap.add_argument("--max-iterations", type=int, default=6, help="smoother iterations per fit (default 6)")
    ap.add_argument("--max-rounds", type=int, default=2, help="forward rounds (default 2)")
    ap.add_argument("--landmarks", type=int, default=8, help="landmarks per contour (default 8)")
    args = ap.parse_args()
    seq = load_sequence(example_path())

    setup = measured.prepare(seq, args.landmarks)
    blas = max((p.get("num_threads", 1) for p in threadpool_info() if p.get("user_api") == "blas"), default=1)
    seconds = {}
    for threads in sorted({1, blas}):
        with threadpool_limits(limits=threads):
            t0 = time.perf_counter()
            measured.run(setup, ("active_polar",), "penalty", max_iterations=args.max_iterations)
            seconds[threads] = time.perf_counter() - t0
    print(f"one fit (subject_a, region map, active_polar, {args.max_iterations} iterations):")
    for threads, s in seconds.items():
        print(f"  {threads} BLAS thread{'s' if threads > 1 else ' '}  {s:7.1f} s   ratio {s / seconds[1]:.2f}")

    kw = dict(landmarks=args.landmarks, max_iterations=args.max_iterations, max_rounds=args.max_rounds)
    lean_run = closing.run

    def every_fit_with_variances(*a, covariance=True, **options):
        return lean_run(*a, **options)

    ways = (("every fit with its variances, 1 worker", 1, every_fit_with_variances),
            ("variances for the fits kept, 1 worker", 1, lean_run),
            (f"variances for the fits kept, {args.workers} workers", args.workers, lean_run))
    reports, wall = [], []
    for label, workers, fit in ways:
        closing.run = fit                   # the baseline's fits all make their variances
        try:
            t0 = time.perf_counter()
            out = closing.closing_the_loop(seq, workers=workers, **kw)
            wall.append(time.perf_counter() - t0)
        finally:
            closing.run = lean_run
        reports.append(split_timing(json.loads(json.dumps(out.as_json(), default=str)))[0])
        fits = 1 + sum(len(r.tried) + len(r.backward) for r in out.rounds) + len(out.last_attempt.get("tried", []))
        print(f"rounds, {label:<42s} {wall[-1]:7.1f} s   ratio {wall[-1] / wall[0]:.2f}   {fits} fits, "
              f"path {' -> '.join(str(r.added or ('-' + str(r.removed) if r.removed else 'baseline')) for r in out.rounds)}"
              f", stop: {out.stop_reason}")
    same = all(r == reports[0] for r in reports[1:])
    print(f"rounds: the three reports identical but for wall times: {same}")
    if not same:
        raise SystemExit("the reports differ")


if __name__ == "__main__":
    main()
