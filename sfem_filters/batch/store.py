"""Where a batch keeps its results: one folder, a JSON file per job, written atomically.

``<name>.json``
    ``{"job": {kind, name, config, inputs, fingerprint}, "result": ...}``: depends only on the
    job (byte for byte the same from any scheduler and worker count).
``<name>.run.json``
    How that result was obtained: timing (s), warnings, worker, files written, when. Written
    before the result, so every result has one; a job counts as done only once its result is.
``<name>.error.json``
    The error of a job that failed (removed once the job succeeds).
``table.csv``
    One row per job and strategy (or round), rebuilt from the result files after every batch.

A result whose fingerprint differs from the job's (another configuration, input or version)
is not reused; when the job reruns, the old file is kept as ``<name>.<fingerprint[:12]>.json``.
"""
from __future__ import annotations

import csv
import datetime
import json
import os
import socket
import tempfile

from .._io import json_safe, write_json
from .jobs import Job, JobOutcome, table_rows

__all__ = ["ResultStore"]


def _atomic_write(path: str, text: str) -> str:
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=".json")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    return path


def _dumps(payload) -> str:
    return json.dumps(json_safe(payload), indent=2, allow_nan=False) + "\n"


class ResultStore:
    """The result folder of a batch (module docstring).

    Parameters
    ----------
    directory : str or path
        Created if missing.
    """

    def __init__(self, directory):
        self.directory = os.fspath(directory)
        os.makedirs(self.directory, exist_ok=True)
        self._fingerprints = {}

    def path(self, job: Job, suffix: str = "") -> str:
        """``<directory>/<name><suffix>.json``."""
        return os.path.join(self.directory, f"{job.name}{suffix}.json")

    def fingerprint(self, job: Job) -> str:
        """The job's fingerprint (hashed once per store)."""
        key = id(job)
        if key not in self._fingerprints:
            self._fingerprints[key] = (job, job.fingerprint())
        return self._fingerprints[key][1]

    def _read(self, path):
        try:
            with open(path) as f:
                return json.load(f)
        except (OSError, ValueError):
            return None

    def load(self, job: Job):
        """The stored record of this job with this fingerprint, or None."""
        rec = self._read(self.path(job))
        if rec is None or rec.get("job", {}).get("fingerprint") != self.fingerprint(job):
            return None
        return rec

    def timing(self, job: Job) -> dict:
        """The stored timing of the job's result (empty when unknown)."""
        run = self._read(self.path(job, ".run"))
        if run is None or run.get("fingerprint") != self.fingerprint(job):
            return {}
        return run.get("timing", {})

    def save(self, job: Job, outcome: JobOutcome, worker: str = "") -> str:
        """Write the job's result and run record; keep a result of another fingerprint aside."""
        fp = self.fingerprint(job)
        path = self.path(job)
        old = self._read(path)
        if old is not None and old.get("job", {}).get("fingerprint") not in (None, fp):
            os.replace(path, self.path(job, "." + old["job"]["fingerprint"][:12]))
        # the run record first, the result last: the result file is the commit point, so a
        # process killed between the two writes leaves a job that reruns, never a result
        # without its run record
        _atomic_write(self.path(job, ".run"), _dumps({
            "fingerprint": fp, "timing": outcome.timing, "wall_seconds": outcome.wall_seconds,
            "warnings": outcome.warnings, "written": outcome.written, "worker": worker or socket.gethostname(),
            "finished": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")}))
        _atomic_write(path, _dumps({"job": job.describe(fp), "result": outcome.result}))
        if os.path.exists(self.path(job, ".error")):
            os.remove(self.path(job, ".error"))
        return path

    def save_error(self, job: Job, error: str, traceback: str = "") -> str:
        """Record the failure of a job (its previous result, if any, is left alone)."""
        return write_json(self.path(job, ".error"), {
            "fingerprint": self.fingerprint(job), "error": error, "traceback": traceback,
            "finished": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")})

    def write_table(self, jobs, records=None, timings=None, name: str = "table.csv") -> str:
        """Rebuild the combined CSV from the stored results of ``jobs`` (in their order);
        ``records`` and ``timings`` (name -> stored record / timing) when already loaded."""
        if records is None:
            records = {j.name: rec for j in jobs if (rec := self.load(j)) is not None}
            timings = {j.name: self.timing(j) for j in jobs if j.name in records}
        rows = []
        for job in jobs:
            if job.name in records:
                rows.extend(table_rows(records[job.name], timings[job.name]))
        columns = []
        for r in rows:
            columns.extend(k for k in r if k not in columns)
        if "seconds" in columns:
            columns.remove("seconds")
            columns.append("seconds")
        path = os.path.join(self.directory, name)
        fd, tmp = tempfile.mkstemp(dir=self.directory, prefix=".tmp-", suffix=".csv")
        with os.fdopen(fd, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=columns, restval="")
            w.writeheader()
            w.writerows(rows)
        os.replace(tmp, path)
        return path
