"""A verb's jobs run as a batch (``--scheduler``, ``--workers``, ``--batch-dir``): one job per seed
or file, results kept per job so that a rerun resumes."""
from __future__ import annotations

import hashlib
import json
import os
import sys

from .. import batch
from ._common import _progress


def _batch_mode(args, n_jobs: int) -> bool:
    if args.workers is not None and args.scheduler not in (None, "local"):
        raise ValueError(f"--workers: only applies to --scheduler local, got --scheduler {args.scheduler}")
    return n_jobs > 1 or args.scheduler is not None or args.batch_dir is not None


def _run_batch(args, jobs, command: str):
    directory = args.batch_dir
    if directory is None:
        configs = json.dumps([{k: v for k, v in j.config.items() if k != "seed"} for j in jobs[:1]], sort_keys=True)
        directory = os.path.join("out", "batch", f"{command}-{hashlib.sha256(configs.encode()).hexdigest()[:10]}")
    args.kept_in = directory                            # for an interruption's message
    scheduler = args.scheduler or ("local" if len(jobs) > 1 else "serial")
    report = batch.run_batch(jobs, directory, scheduler=scheduler, workers=args.workers,
                                       progress=_progress(args))
    print(report.summary_line(), file=sys.stderr)
    for name, message in report.failed.items():
        print(f"sfem-filters {command}: job {name} failed: {message} (traceback in "
              f"{os.path.join(report.directory, name + '.error.json')})", file=sys.stderr)
    print(f"wrote {report.table}", file=sys.stderr)
    return report
