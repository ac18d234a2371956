"""Jobs of a batch: one noise seed of the synthetic comparison, or one sequence file of the
measured-data workflow, each with its configuration.

A :class:`Job` is plain data (it crosses to Dask workers by pickling); :func:`run_job` runs one
anywhere and returns a :class:`JobOutcome`. The result is split from its timing
(:func:`split_timing`): the result depends only on the job, the timing on the machine, so the
per-job result files of a batch are byte for byte those of a serial run. BLAS is held to one
thread inside a job (:func:`~sfem_filters.resources.blas_threads`): a different thread count
changes the order of floating-point sums, and so the last bits of the numbers.
"""
from __future__ import annotations

import copy
import functools
import hashlib
import json
import os
import time
import warnings
from dataclasses import dataclass, field
from importlib import metadata

from .._io import json_safe
from ..benchmark.comparison import LABELS, run_comparison
from ..cardiac.closing import closing_the_loop, length_display
from ..cardiac.sequence import example_path, load_sequence
from ..cardiac.specs import EstimatorSettings, LoopSettings, ModelSpec, check_specs
from ..export import export_comparison, export_dense
from ..plotting import comparison_figures, dense_figures
from ..resources import blas_threads

__all__ = ["Job", "JobOutcome", "KINDS", "compare_jobs", "dense_jobs", "run_job", "split_timing", "merge_timing",
           "table_rows", "describe_record", "dense_config", "dense_specs"]

KINDS = ("compare", "dense")
#: Keys of a job's ``outputs``: where the job also writes figures, ParaView files and filter
#: checkpoints. They are not part of its fingerprint (they do not change its numbers).
OUTPUTS = ("figures", "export", "checkpoint_dir")
_TIMING_KEYS = ("seconds",)
#: What a result holds for a given configuration, input and version; raised whenever the same job
#: would now compute something else, so that a resumed batch does not mix old results with new
#: (2: the innovations' whiteness with the symmetric root of S instead of its Cholesky factor; 3: what
#: the data say computed from the data only, no longer from the drive's filled-in values, and no
#: landmark on a point without data; 4: every keyword of the run in the configuration, its
#: defaults included, so that no key is there only when it differs from a default, and the rounds'
#: springs:x10 offered only to contour springs by default; 5: a dense job's configuration is the
#: three settings specs' full JSON, :func:`dense_config`, the same results under new keys).
RESULTS_SCHEMA = 5


def dense_config(model: ModelSpec = ModelSpec(), estimator: EstimatorSettings = EstimatorSettings(),
                 loop: LoopSettings = LoopSettings()) -> dict:
    """A dense job's configuration: the specs of :func:`~sfem_filters.cardiac.closing_the_loop`, each
    as its full JSON (``to_json``: every field, defaults included, no key that is there only when it
    differs from a default), with the iteration limit the run will use (the default depends on the
    drive). A job's fingerprint hashes it whole with :data:`RESULTS_SCHEMA`, so that a new setting,
    or a default that changes, never reuses a result computed without it. The specs are checked
    together (:func:`~sfem_filters.cardiac.specs.check_specs`) before any job runs."""
    check_specs(model, estimator, loop)
    estimator = estimator.with_(max_iterations=estimator.iteration_limit(model.drive))
    return {"model": model.to_json(), "estimator": estimator.to_json(), "loop": loop.to_json()}


def dense_specs(config: dict) -> tuple:
    """``(ModelSpec, EstimatorSettings, LoopSettings)`` of a dense job's configuration
    (:func:`dense_config`)."""
    unknown = sorted(set(config) - {"model", "estimator", "loop"})
    if unknown:
        raise ValueError(f"config: expected the keys 'model', 'estimator' and 'loop', got also {unknown}")
    return (ModelSpec.from_json(config.get("model", {})), EstimatorSettings.from_json(config.get("estimator", {})),
            LoopSettings.from_json(config.get("loop", {})))


def _version() -> str:
    try:
        return metadata.version("sfem_filters")
    except metadata.PackageNotFoundError:  # running from a source tree that is not installed
        return "unknown"


def _file_digest(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass
class Job:
    """One job of a batch.

    Attributes
    ----------
    kind : str
        ``"compare"`` (one seed of :func:`~sfem_filters.benchmark.run_comparison`) or ``"dense"``
        (one file through :func:`~sfem_filters.cardiac.closing_the_loop`).
    name : str
        Unique within a batch; the stem of its result files (``seed0007``, a file's stem).
    config : dict
        The job's settings (JSON values: :func:`run_comparison`'s keywords, or the specs of
        :func:`dense_config`): they and the inputs' contents make the fingerprint.
    inputs : tuple of str
        Files the job reads (hashed by content into the fingerprint).
    outputs : dict
        Optional ``figures``, ``export``, ``checkpoint_dir`` directories (not fingerprinted).
    """

    kind: str
    name: str
    config: dict
    inputs: tuple = ()
    outputs: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"kind: expected one of {KINDS}, got {self.kind!r}")
        if not isinstance(self.name, str) or not self.name or os.sep in self.name or self.name.startswith("."):
            raise ValueError(f"name: expected a non-empty file stem without '{os.sep}', got {self.name!r}")
        unknown = set(self.outputs) - set(OUTPUTS)
        if unknown:
            raise ValueError(f"outputs: expected keys among {OUTPUTS}, got {sorted(unknown)}")
        try:
            json.dumps(self.config, sort_keys=True, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"config: expected JSON values ({exc})") from None
        for p in self.inputs:
            if not os.path.isfile(p):
                raise ValueError(f"inputs: no such file {p!r}")

    def fingerprint(self) -> str:
        """SHA-256 of the kind, the configuration, the inputs' contents, the package version and
        :data:`RESULTS_SCHEMA`."""
        payload = {"kind": self.kind, "config": self.config, "version": _version(), "schema": RESULTS_SCHEMA,
                   "inputs": [[os.path.basename(p), _file_digest(p)] for p in self.inputs]}
        return hashlib.sha256(json.dumps(payload, sort_keys=True).encode()).hexdigest()

    def describe(self, fingerprint: str) -> dict:
        """What the result file records of its job (no absolute paths, nothing machine-bound)."""
        return {"kind": self.kind, "name": self.name, "config": self.config,
                "inputs": [os.path.basename(p) for p in self.inputs], "fingerprint": fingerprint}


@dataclass
class JobOutcome:
    """What :func:`run_job` returns: the result (JSON values, timing removed), its timing (the
    ``seconds`` entries that were removed, by path), the wall time (s), warnings raised during
    the run and the files the job wrote."""

    result: dict
    timing: dict
    wall_seconds: float
    warnings: list
    written: list


def compare_jobs(seeds, *, refine: int = 1, noise_mm: float = 0.1, engine: str = "structured", max_loops: int = 50,
                 tol: float = 1e-3, figures=None, export=None, checkpoint_dir=None) -> list:
    """One job per seed of the synthetic comparison (arguments as :func:`run_comparison`;
    ``noise_mm`` in mm). ``figures`` and ``export`` get a ``seed<N>`` folder per job."""
    seeds = list(seeds)
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds: expected distinct seeds, got {seeds!r}")
    jobs = []
    for s in seeds:
        out = {k: os.path.join(v, f"seed{s}") for k, v in (("figures", figures), ("export", export)) if v}
        if checkpoint_dir:
            out["checkpoint_dir"] = checkpoint_dir
        jobs.append(Job("compare", f"seed{int(s):04d}", {"seed": int(s), "refine": int(refine),
                                                          "noise_mm": float(noise_mm), "engine": engine,
                                                          "max_loops": int(max_loops), "tol": float(tol)},
                        outputs=out))
    return jobs


def dense_jobs(paths, model: ModelSpec = ModelSpec(), estimator: EstimatorSettings = EstimatorSettings(),
               loop: LoopSettings = LoopSettings(), *, figures=None, export=None) -> list:
    """One job per sequence file (``"example"`` for the shipped slice), each run by
    :func:`~sfem_filters.cardiac.closing_the_loop` with the specs ``model``, ``estimator`` and ``loop``
    (its configuration :func:`dense_config`; the number of worker processes and the progress are
    not settings of the results). Names are the files' stems (made unique with ``-2``, ``-3`` ...
    when two files share one)."""
    paths = [example_path() if p == "example" else os.fspath(p) for p in paths]
    if not paths:
        raise ValueError("paths: expected at least one sequence file")
    cfg = dense_config(model, estimator, loop)
    jobs, seen = [], {}
    for p in paths:
        stem = os.path.splitext(os.path.basename(p))[0]
        seen[stem] = seen.get(stem, 0) + 1
        name = stem if seen[stem] == 1 else f"{stem}-{seen[stem]}"
        out = {k: os.path.join(v, name) for k, v in (("figures", figures), ("export", export)) if v}
        jobs.append(Job("dense", name, cfg, inputs=(p,), outputs=out))
    return jobs


def split_timing(payload: dict) -> tuple:
    """``(result, timing)``: a deep copy of ``payload`` without its ``seconds`` entries, and
    those entries by their key path joined with ``/``."""
    result = copy.deepcopy(payload)
    timing = {}

    def walk(node, path):
        if isinstance(node, dict):
            for k in list(node):
                if k in _TIMING_KEYS:
                    timing["/".join(path + [k])] = node.pop(k)
                else:
                    walk(node[k], path + [k])
        elif isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, path + [str(i)])

    walk(result, [])
    return result, timing


def merge_timing(result: dict, timing: dict) -> dict:
    """Inverse of :func:`split_timing` (a new dict)."""
    out = copy.deepcopy(result)
    for key, value in timing.items():
        *path, last = key.split("/")
        node = out
        for p in path:
            node = node[int(p)] if isinstance(node, list) else node[p]
        node[last] = value
    return out


def _outputs(job: Job, result, figures, export) -> list:
    """Write the job's optional figures and ParaView files of ``result``; their paths."""
    written = []
    if "figures" in job.outputs:
        written += figures(result, job.outputs["figures"])
    if "export" in job.outputs:
        written += export(result, job.outputs["export"])
    return written


def _run_compare(job: Job) -> tuple:
    comp = run_comparison(**job.config, progress=False, checkpoint_dir=job.outputs.get("checkpoint_dir"))
    figures = functools.partial(comparison_figures, ekf_tol=job.config.get("tol", 1e-3))
    return comp.as_json(), _outputs(job, comp, figures, export_comparison)


def _run_dense(job: Job) -> tuple:
    out = closing_the_loop(load_sequence(job.inputs[0]), *dense_specs(job.config), progress=False)
    return out.as_json(), _outputs(job, out, dense_figures, export_dense)


_RUNNERS = {"compare": _run_compare, "dense": _run_dense}


def run_job(job: Job) -> JobOutcome:
    """Run one job (in this process, with BLAS held to one thread) and return its outcome.

    The result goes through a JSON round trip, so it is exactly what the result file holds
    (non-finite numbers become ``None``: JSON has no NaN).
    Exceptions propagate: the batch runner records them as the job's error.
    """
    with blas_threads(1), warnings.catch_warnings(record=True) as caught:     # explicit: the runs inside keep it
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        payload, written = _RUNNERS[job.kind](job)
        wall = time.perf_counter() - t0
    result, timing = split_timing(json.loads(json.dumps(json_safe(payload), allow_nan=False)))
    messages = sorted({f"{w.category.__name__}: {w.message}" for w in caught})
    return JobOutcome(result, timing, wall, messages, [str(p) for p in written])


def table_rows(record: dict, timing: dict) -> list:
    """Rows of the combined CSV table for one stored result: a row per strategy (``compare``) or
    per round plus the thin-plate spline (``dense``); ``seconds`` is the one column that depends
    on the machine."""
    job, res = record["job"], record["result"]
    if job["kind"] == "compare":
        rows = []
        for s, m in res["strategies"].items():
            row = {"job": job["name"], "seed": res["seed"], "refine": res["refine"], "noise_mm": res["noise_mm"],
                   "strategy": s, "label": LABELS[s]}
            row.update({k: v for k, v in m.items() if not isinstance(v, (list, dict))})
            row["seconds"] = timing.get(f"strategies/{s}/seconds", "")
            rows.append(row)
        return rows
    rows = []
    backward = {}                             # backward steps so far in each round: 3-1, 3-2, ...
    for r in res["rounds"]:
        removed = r.get("removed")
        if removed:
            backward[r["round"]] = backward.get(r["round"], 0) + 1
        row = {"job": job["name"], "input": job["inputs"][0],
               "strategy": f"round {r['round']}" + (f"-{backward[r['round']]}" if removed else ""),
               "label": f"- {removed}" if removed else (r["added"] or "baseline"),
               "effects": "+".join(r["effects"]), "drive": r["drive"]}
        row.update({k: v for k, v in r.items() if not isinstance(v, (list, dict)) and k not in row
                    and k not in ("added", "removed", "round")})
        row.update({f"residual_spline_{k}": v for k, v in (r.get("residual_spline") or {}).items()})
        for what, d in (r.get("versus_spline") or {}).items():
            if isinstance(d, dict):       # the model's and the +spline's difference from the spline, with interval
                row.update({f"versus_spline_{what}_{k}": d[k] for k in ("difference", "low", "high")})
        rows.append(row)
    ref = res["spline_reference"]
    rows.append({"job": job["name"], "input": job["inputs"][0], "strategy": "spline", "label": "thin-plate spline",
                 **{k: v for k, v in ref.items() if not isinstance(v, (list, dict))}})
    return rows


def describe_record(record: dict) -> str:
    """One line per stored result of a ``dense`` job: held-out error of the baseline and of the
    last round beside the thin-plate spline's, and why the rounds stopped."""
    job, res = record["job"], record["result"]
    if job["kind"] != "dense":
        raise ValueError(f"record: expected a dense job's record, got kind {job['kind']!r}")
    rounds = res["rounds"]
    last = rounds[-1]
    unit, k = length_display(res.get("length_unit", "px"))

    def length(v):                      # null in the file: no held-out data to score
        return "n/a" if v is None else f"{v * k:.3f} {unit}"
    return (f"{job['name']}: held-out RMSE baseline {length(rounds[0]['heldout_rmse_px'])} -> "
            f"round {last['round']}{'-' if last.get('removed') else ''} {length(last['heldout_rmse_px'])} "
            f"(effects {'+'.join(last['effects']) or 'none'}, "
            f"drive {last['drive']}); spline {length(res['spline_reference']['heldout_rmse_px'])}; "
            f"stopped: {res['stop_reason']}")
