"""Wall time of the measured-data rounds with their fits side by side, against one after the other.

    python benchmarks/rounds_parallel.py [--subject slice|annulus] [--workers 2] [--max-iterations 6]
        [--max-rounds 2] [--landmarks 8] [--frames 24]

:func:`sfem_filters.cardiac.closing_the_loop` on the shipped slice (``--subject slice``, the `dense`
command's settings with ``--max-iterations`` and ``--max-rounds`` as given; needs the data set, see
:mod:`sfem_filters.datasets`) or on a synthetic annulus (``--subject annulus``, ``--frames``
frames), twice in the same run: one fit at a time (``workers=1``, the baseline) and ``--workers``
fits side by side, each in its own process on one BLAS thread. Printed: both wall times, their
ratio, the fits made, the rounds' path, and whether the two reports agree to the last bit (every
figure but the wall times; exit status 1 if not). What one BLAS thread costs a fit is
``benchmarks/blas_threads.py``'s to say. Only public names of :mod:`sfem_filters` are used
(``tests/test_benchmarks.py`` runs it with ``--subject annulus --frames 6 --max-iterations 1
--max-rounds 1``).
"""
from __future__ import annotations

import argparse
import json
import sys
import time

from sfem_filters.batch import split_timing
from sfem_filters.cardiac import (EstimatorSettings, LoopSettings, ModelSpec, annulus_sequence, closing_the_loop,
                                  example_path, load_sequence)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subject", choices=("slice", "annulus"), default="slice")
    ap.add_argument("--frames", type=int, default=24, help="frames of the synthetic annulus (default 24)")
    ap.add_argument("--workers", type=int, default=2, help="fits side by side (default 2)")
    ap.add_argument("--max-iterations", type=int, default=6, help="smoother iterations per fit (default 6)")
    ap.add_argument("--max-rounds", type=int, default=2, help="forward rounds (default 2)")
    ap.add_argument("--landmarks", type=int, default=8, help="landmarks per contour (default 8)")
    args = ap.parse_args(argv)
    seq = (load_sequence(example_path()) if args.subject == "slice"
           else annulus_sequence("active_polar", n_frames=args.frames, landmarks=args.landmarks))
    specs = (ModelSpec(landmarks=args.landmarks), EstimatorSettings(max_iterations=args.max_iterations),
             LoopSettings(max_rounds=args.max_rounds))
    reports, wall = [], []
    for workers in (1, args.workers):
        t0 = time.perf_counter()
        out = closing_the_loop(seq, *specs, workers=workers)
        wall.append(time.perf_counter() - t0)
        reports.append(split_timing(json.loads(json.dumps(out.as_json(), default=str)))[0])
        fits = 1 + sum(len(r.tried) + len(r.backward) for r in out.rounds) + len(out.last_attempt.get("tried", []))
        path = " -> ".join(str(r.added or ("-" + str(r.removed) if r.removed else "baseline")) for r in out.rounds)
        label = f"{workers} worker{'s' if workers > 1 else ' '}"
        print(f"rounds, {label} {wall[-1]:8.1f} s   ratio {wall[-1] / wall[0]:.2f}"
              f"   {fits} fits, path {path}, stop: {out.stop_reason}", flush=True)
    same = reports[0] == reports[1]
    print(f"rounds: the two reports identical but for wall times: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
