"""Many runs at once: a batch of jobs on Dask (or serially), results written as they finish.

A job is one seed of the synthetic comparison or one sequence file of the measured-data
workflow with its configuration; :func:`run_batch` runs a list of them on a scheduler and
keeps one result file per job in a folder:

>>> import tempfile
>>> from sfem_filters.batch import compare_jobs, run_batch
>>> jobs = compare_jobs(range(100), refine=1, noise_mm=0.1)          # one job per noise seed
>>> folder = tempfile.mkdtemp()
>>> report = run_batch(jobs[:1], folder, scheduler="serial", progress=False)  # one seed, here
>>> print(report.summary_line())
1 run, 0 skipped (result exists), 0 failed; results in ... (... s, scheduler serial)
>>> run_batch(jobs[:1], folder, scheduler="serial", progress=False).skipped == report.ran   # a rerun skips it
True
>>> # all 100 on a local cluster of two workers (100 fits: not run here)
>>> report = run_batch(jobs, "out/batch", scheduler="local", workers=2)   # doctest: +SKIP

``scheduler="serial"`` runs in this process, ``"local"`` on a ``LocalCluster`` (one worker
process per core, one thread each), an address such as ``"tcp://10.0.0.5:8786"`` on a running
Dask cluster (by hand or dask-jobqueue). Results do not depend on the scheduler: the same job
gives the same bytes. Rerunning skips jobs whose result exists for the same fingerprint
(configuration, inputs' contents, version), so a killed batch resumes; a failing job is
recorded in ``<name>.error.json`` and the others finish. ``report.records`` are the stored
results; :func:`sfem_filters.benchmark.summarise` turns those of the comparison into Table 1
over many draws.

Modules: :mod:`~sfem_filters.batch.jobs` (what a job is and runs),
:mod:`~sfem_filters.batch.store` (the result folder), :mod:`~sfem_filters.batch.runner`.
"""
from .jobs import (KINDS, Job, JobOutcome, compare_jobs, dense_config, dense_jobs, dense_specs, describe_record,
                   merge_timing, run_job, split_timing, table_rows)
from .runner import SCHEDULERS, BatchReport, run_batch
from .store import ResultStore

__all__ = ["Job", "JobOutcome", "KINDS", "compare_jobs", "dense_jobs", "run_job", "split_timing", "merge_timing",
           "table_rows", "describe_record", "dense_config", "dense_specs", "ResultStore", "run_batch", "BatchReport",
           "SCHEDULERS"]
