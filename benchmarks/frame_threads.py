"""Wall time of a fit made in the rounds' own process, its frames on two threads against one.

    python benchmarks/frame_threads.py [--subject slice|annulus] [--threads 2] [--max-iterations N]
        [--landmarks 8] [--frames 24] [--repeat 1]

The baseline fit of :func:`sfem_filters.cardiac.closing_the_loop` (``LoopSettings(effects="none")``:
the baseline alone) with the ``dense`` command's default search (``SEARCHES["coarse"]``: its mesh,
element size and iteration limit) on the shipped slice (``--subject slice``; needs the data set, see
:mod:`sfem_filters.datasets`) or on a synthetic annulus (``--subject annulus``, ``--frames``
frames), in the same run with ``workers=1`` (the baseline: every linearisation's frames
one after the other) and ``workers=--threads`` (the frames' sensitivities side by side on that many
threads, :class:`sfem_filters.resources.frame_threads`; the baseline is one fit, so no worker process
starts). Printed: the best wall time of each over ``--repeat`` runs, their ratio, and whether the two
reports agree to the last bit (every figure but the wall times; exit status 1 if not). Only public
names of :mod:`sfem_filters` are used (``tests/test_benchmarks.py`` runs it with ``--subject annulus
--frames 6 --max-iterations 2``).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

from sfem_filters.batch import split_timing
from sfem_filters.cardiac import (EstimatorSettings, LoopSettings, ModelSpec, annulus_sequence, closing_the_loop,
                                  example_path, load_sequence)
from sfem_filters.cardiac.closing import SEARCHES


def _load() -> float:
    try:
        with open("/proc/loadavg") as fh:
            return float(fh.read().split()[0])
    except OSError:
        return float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subject", choices=("slice", "annulus"), default="slice")
    ap.add_argument("--frames", type=int, default=24, help="frames of the synthetic annulus (default 24)")
    ap.add_argument("--threads", type=int, default=2, help="threads of the second setting (default 2)")
    ap.add_argument("--max-iterations", type=int, default=None,
                    help="smoother iterations of the fit (default: the search's limit)")
    ap.add_argument("--landmarks", type=int, default=8, help="landmarks per contour (default 8)")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each setting, the best kept (default 1)")
    args = ap.parse_args(argv)
    seq = (load_sequence(example_path()) if args.subject == "slice"
           else annulus_sequence("active_polar", n_frames=args.frames, landmarks=args.landmarks))
    search = SEARCHES["coarse"]
    specs = (ModelSpec(landmarks=args.landmarks, mesh=search.mesh, element_px=search.element_px),
             EstimatorSettings(max_iterations=args.max_iterations or search.max_iterations("penalty")),
             LoopSettings(effects="none"))
    print(f"baseline fit of {args.subject} ({seq.n_points} points x {seq.n_frames} frames), "
          f"{os.cpu_count()} cores, best of {args.repeat}", flush=True)
    reports, best = [], []
    for workers in (1, args.threads):
        times = []
        for _ in range(max(args.repeat, 1)):
            load = _load()
            t0 = time.perf_counter()
            out = closing_the_loop(seq, *specs, workers=workers)
            times.append(time.perf_counter() - t0)
        best.append(min(times))
        reports.append(split_timing(json.loads(json.dumps(out.as_json(), default=str)))[0])
        iterations = out.rounds[0].run.metrics.get("iterations")
        print(f"frame threads {workers}: {best[-1]:8.2f} s   ratio {best[-1] / best[0]:.2f}   "
              f"{len(iterations) if iterations else '?'} iterations   load before {load:.2f}", flush=True)
    same = reports[0] == reports[1]
    print(f"baseline fit: the two reports identical but for wall times: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
