"""Run a list of jobs serially or on Dask, writing each result as it finishes.

>>> report = run_batch(compare_jobs(range(20)), "out/batch", scheduler="local", workers=2)  # doctest: +SKIP

``scheduler``: ``"serial"`` (this process, one job after the other), ``"local"`` (a
``dask.distributed.LocalCluster`` on this machine: one worker process per core unless
``workers`` says otherwise, one thread per worker, BLAS held to one thread) or the address of a
running Dask scheduler (``tcp://host:8786``: a cluster started by hand, or by dask-jobqueue on
SLURM / PBS). Jobs whose result already exists for the same fingerprint are skipped, so an
interrupted batch resumes where it stopped; a job that fails is recorded with its error and
the others go on.
"""
from __future__ import annotations

import logging
import os
import time
import traceback as tb
from dataclasses import dataclass, field

from tqdm.auto import tqdm

from .jobs import Job, run_job
from .store import ResultStore

__all__ = ["BatchReport", "run_batch", "SCHEDULERS"]

#: Named schedulers; anything else is taken as the address of a Dask scheduler.
SCHEDULERS = ("serial", "local")


@dataclass
class BatchReport:
    """Outcome of :func:`run_batch`.

    Attributes
    ----------
    directory : str
        The result folder (:class:`~sfem_filters.batch.store.ResultStore`).
    ran, skipped : list of str
        Names of the jobs run now, and of those whose result already existed.
    failed : dict
        Name -> error message of the jobs that failed.
    table : str
        Path of the combined CSV table.
    seconds : float
        Wall time of the batch (s), cluster start included.
    scheduler : str
    records : dict
        Name -> stored record (``{"job", "result"}``) of every job that has a result.
    timings : dict
        Name -> timing of that result.
    """

    directory: str
    ran: list
    skipped: list
    failed: dict
    table: str
    seconds: float
    scheduler: str
    records: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)

    def summary_line(self) -> str:
        """One line for the log: jobs run, skipped and failed, the result folder, wall time (s) and scheduler."""
        out = f"{len(self.ran)} run, {len(self.skipped)} skipped (result exists), {len(self.failed)} failed"
        return f"{out}; results in {self.directory} ({self.seconds:.1f} s, scheduler {self.scheduler})"


def _check(jobs, scheduler, workers) -> list:
    jobs = list(jobs)
    if not jobs or not all(isinstance(j, Job) for j in jobs):
        raise ValueError("jobs: expected a non-empty list of sfem_filters.batch.Job")
    names = [j.name for j in jobs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"jobs: names must be unique within a batch, repeated: {dup}")
    if not isinstance(scheduler, str) or not scheduler:
        raise ValueError(f"scheduler: expected 'serial', 'local' or a scheduler address, got {scheduler!r}")
    if scheduler not in SCHEDULERS and ":" not in scheduler:
        raise ValueError(f"scheduler: expected 'serial', 'local' or an address like tcp://host:8786, got {scheduler!r}")
    if workers is not None and (isinstance(workers, bool) or int(workers) != workers or workers < 1):
        raise ValueError(f"workers: expected an integer >= 1, got {workers!r}")
    if workers is not None and scheduler not in ("local",):
        raise ValueError(f"workers: only applies to scheduler 'local' (got scheduler {scheduler!r})")
    return jobs


def _failure(exc: BaseException, trace) -> tuple:
    message = f"{type(exc).__name__}: {exc}"
    text = "".join(tb.format_exception(type(exc), exc, trace)) if trace is not None else message
    return message, text


#: Dask settings of the local cluster, both measured with ``benchmarks/batch.py``:
#:
#: - the workers' statistical profiler samples every task's stack every 10 ms under the GIL,
#:   which slowed these Python-heavy jobs by about a tenth; the batch does not use its output;
#: - the nanny starts workers with ``MALLOC_TRIM_THRESHOLD_=65536``, which makes glibc hand
#:   freed memory back to the system after every large temporary array and fault it in again on
#:   the next: the same jobs spent 1.0-1.5 s of system time per 12 seeds instead of 0.1 s and ran
#:   5-15% slower than in the serial loop. The jobs hold little memory, so glibc's own threshold
#:   is kept (``None`` removes the variable);
#: - the scheduler hands a one-thread worker two tasks at a time (``worker-saturation`` 1.1,
#:   rounded up), so at the end of a batch one worker can sit idle while the other still holds a
#:   queued job; one task per free thread keeps the last jobs on both workers.
LOCAL_CONFIG = {"distributed.worker.profile.enabled": False,
                "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                "distributed.scheduler.worker-saturation": 1.0}


def _distributed():
    """``dask`` and ``dask.distributed``, imported when a batch first needs a scheduler: they take
    about 0.8 s to import (``python -X importtime``), which a serial batch, ``import sfem_filters``
    and every ``sfem-filters ... --help`` do not need (a third-party import, not a sibling's)."""
    import dask
    import dask.distributed
    return dask, dask.distributed


def _client(scheduler: str, workers):
    dask, distributed = _distributed()
    Client, LocalCluster = distributed.Client, distributed.LocalCluster
    if scheduler == "local":
        n = workers or os.cpu_count() or 1
        with dask.config.set(LOCAL_CONFIG):
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                                   silence_logs=logging.ERROR)
        return Client(cluster), cluster
    return Client(scheduler), None


def run_batch(jobs, directory, *, scheduler: str = "local", workers=None, progress: bool = True) -> BatchReport:
    """Run ``jobs`` (list of :class:`~sfem_filters.batch.jobs.Job`) into ``directory``.

    Parameters
    ----------
    jobs : list of Job
        Unique names.
    directory : str or path
        Result folder; results already there for the same fingerprint are kept and skipped.
    scheduler : str
        ``"serial"``, ``"local"`` or a Dask scheduler address (module docstring).
    workers : int, optional
        Worker processes of the local cluster (default: one per core).
    progress : bool
        Progress bar over jobs.

    Returns
    -------
    BatchReport
    """
    jobs = _check(jobs, scheduler, workers)
    t0 = time.perf_counter()
    store = ResultStore(directory)
    pending, skipped = [], []
    for j in jobs:
        (skipped if store.load(j) is not None else pending).append(j)
    ran, failed = [], {}
    bar = tqdm(total=len(jobs), initial=len(skipped), desc=f"{jobs[0].kind} jobs", unit="job", disable=not progress)

    def finished(job, outcome=None, exc=None, trace=None, worker=""):
        if exc is None:
            store.save(job, outcome, worker)
            ran.append(job.name)
        else:
            message, text = _failure(exc, trace)
            store.save_error(job, message, text)
            failed[job.name] = message
            bar.write(f"{job.name}: failed: {message}")
        bar.update(1)

    try:
        if pending and scheduler == "serial":
            for j in pending:
                try:
                    outcome = run_job(j)
                except Exception as exc:  # noqa: BLE001 - a failed job is recorded, the others go on
                    finished(j, exc=exc, trace=exc.__traceback__)
                else:
                    finished(j, outcome)
        elif pending:
            environ = dict(os.environ)
            client, cluster = _client(scheduler, workers)
            try:
                futures = {client.submit(run_job, j, key=f"sfem-{j.name}-{store.fingerprint(j)[:16]}", pure=False): j
                           for j in pending}
                for fut in _distributed()[1].as_completed(futures):
                    job = futures[fut]
                    if fut.status == "finished":
                        finished(job, fut.result(), worker=_worker_of(client, fut))
                    else:
                        finished(job, exc=fut.exception(), trace=fut.traceback())
            finally:
                client.close()
                if cluster is not None:
                    cluster.close()
                _restore_environ(environ)
    finally:
        bar.close()
    records = {j.name: rec for j in jobs if (rec := store.load(j)) is not None}
    timings = {j.name: store.timing(j) for j in jobs if j.name in records}
    table = store.write_table(jobs, records, timings)
    return BatchReport(os.fspath(directory), ran, [j.name for j in skipped], failed, table, time.perf_counter() - t0, scheduler,
                       records, timings)


def _restore_environ(saved: dict) -> None:
    """Undo what starting the cluster wrote into this process's environment: Dask's nanny sets
    ``OMP_NUM_THREADS=1``, ``OPENBLAS_NUM_THREADS=1``, ``PYTHONHASHSEED`` ... in ``os.environ``
    before spawning workers and leaves them there, where every later subprocess of the caller
    would inherit them."""
    for key in set(os.environ) - set(saved):
        del os.environ[key]
    for key, value in saved.items():
        if os.environ.get(key) != value:
            os.environ[key] = value


def _worker_of(client, fut) -> str:
    try:
        where = client.who_has([fut]).get(fut.key, ())
        return ",".join(where)
    except Exception:  # noqa: BLE001 - only a label in the run record
        return ""
