"""Batch on Dask against the serial loop, in one run: wall time ratio and byte-identical results.

    python benchmarks/batch.py [--seeds 0-19] [--workers 2] [--refine 1] [--keep DIR]

Runs the synthetic comparison over the seeds twice from empty result folders: first serially in
this process (``scheduler="serial"``, the loop ``sfem-filters compare --scheduler serial``
runs), then on a ``LocalCluster`` with ``--workers`` worker processes (``--scheduler local``),
the cluster's start-up and the workers' imports included in its wall time. Prints both wall
times, their ratio (local / serial; the target of issue #15 on 2 cores is <= 0.6), the sum of
the jobs' own run times in each (from the ``.run.json`` records: how much slower a job runs
inside a Dask worker than in the serial loop), and whether every per-job result file of the two
runs is the same byte for byte (exit status 1 if not).
"""
from __future__ import annotations

import argparse
import filecmp
import json
import os
import sys
import tempfile
import time

from sfem_filters.batch import compare_jobs, run_batch


def seeds(text: str) -> list:
    """``0``, ``0,1,2`` or ``0-4`` (as ``sfem-filters compare --seed`` reads them)."""
    out = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    if not out or min(out) < 0:
        raise argparse.ArgumentTypeError(f"expected seeds such as 0, 0,1,2 or 0-4, got {text!r}")
    return out


def _job_seconds(folder: str, jobs) -> float:
    """Sum of the jobs' wall times (s) as their run records give them."""
    total = 0.0
    for j in jobs:
        with open(os.path.join(folder, f"{j.name}.run.json")) as f:
            total += json.load(f)["wall_seconds"]
    return total


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=seeds, default=list(range(20)))
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--refine", type=int, default=1)
    p.add_argument("--keep", help="keep the two result folders under this directory")
    args = p.parse_args(argv)
    root = args.keep or tempfile.mkdtemp(prefix="sfem-batch-bench-")
    jobs = compare_jobs(args.seeds, refine=args.refine)
    t0 = time.perf_counter()
    serial = run_batch(jobs, os.path.join(root, "serial"), scheduler="serial", progress=False)
    t_serial = time.perf_counter() - t0
    t0 = time.perf_counter()
    local = run_batch(jobs, os.path.join(root, "local"), scheduler="local", workers=args.workers, progress=False)
    t_local = time.perf_counter() - t0
    same = [filecmp.cmp(os.path.join(root, "serial", f"{j.name}.json"), os.path.join(root, "local", f"{j.name}.json"),
                        shallow=False) for j in jobs]
    print(f"{len(jobs)} comparison jobs (seeds {args.seeds[0]}-{args.seeds[-1]}, r = {args.refine}) on "
          f"{os.cpu_count()} cores")
    print(f"serial loop in one process:           {t_serial:8.1f} s  (failed: {len(serial.failed)})")
    print(f"Dask LocalCluster, {args.workers} workers x 1 thread: {t_local:8.1f} s  (failed: {len(local.failed)}; "
          "cluster start included)")
    print(f"ratio local / serial: {t_local / t_serial:.2f}")
    js, jl = _job_seconds(os.path.join(root, "serial"), jobs), _job_seconds(os.path.join(root, "local"), jobs)
    print(f"sum of the jobs' own run times: serial {js:.1f} s, in the workers {jl:.1f} s (ratio {jl / js:.2f})")
    print(f"per-job result files identical byte for byte: {sum(same)}/{len(same)}")
    if args.keep:
        print(f"results kept in {root}")
    return 0 if all(same) and not serial.failed and not local.failed else 1


if __name__ == "__main__":
    sys.exit(main())
