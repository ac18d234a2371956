"""The batch runner: same bytes from any scheduler, resume after a kill, failures isolated,
fingerprints, the combined table, and Table 1 over many draws (Wilson intervals)."""
from __future__ import annotations

import csv
import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time

import dask
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sfem_filters.batch import Job, ResultStore, compare_jobs, dense_jobs, describe_record, merge_timing, run_batch, \
    run_job, split_timing
from sfem_filters.batch import dense_specs
from sfem_filters.batch import jobs as jobs_module
from sfem_filters.batch.runner import _client
from sfem_filters.benchmark import format_summary, format_table, summarise, wilson_interval
from sfem_filters.benchmark.comparison import ROWS
from sfem_filters.cardiac.specs import EstimatorSettings, LoopSettings, ModelSpec
from sfem_filters.cli import main

# A cheap comparison job: few loops (the numbers are not the point here, their bytes are).
CHEAP = dict(max_loops=3)


# --- Wilson interval -------------------------------------------------------------------------

def test_wilson_interval_matches_newcombe_1998():
    # Newcombe (1998), Stat. Med. 17:857, Table I: 81/263 -> 0.2553-0.3662; 15/148 -> 0.0624-0.1605;
    # 0/20 -> 0-0.1611; 1/29 -> 0.0061-0.1718 (method 3, Wilson score without continuity correction)
    for (k, n), (lo, hi) in {(81, 263): (0.2553, 0.3662), (15, 148): (0.0624, 0.1605), (0, 20): (0.0, 0.1611),
                             (1, 29): (0.0061, 0.1718)}.items():
        got = wilson_interval(k, n)
        assert got == pytest.approx((lo, hi), abs=1e-4)


@given(n=st.integers(1, 500), frac=st.floats(0, 1), level=st.floats(0.5, 0.999))
def test_wilson_interval_properties(n, frac, level):
    k = int(round(frac * n))
    lo, hi = wilson_interval(k, n, level)
    assert 0.0 <= lo <= k / n <= hi <= 1.0
    lo2, hi2 = wilson_interval(n - k, n, level)          # symmetric under k -> n - k
    assert (lo2, hi2) == pytest.approx((1 - hi, 1 - lo), abs=1e-12)
    lo3, hi3 = wilson_interval(k, n, min(0.9995, level + 0.0004))   # wider at a higher level
    assert lo3 <= lo + 1e-12 and hi3 >= hi - 1e-12


def test_wilson_interval_coverage_near_nominal():
    # coverage of the 95% interval over binomial draws, computed exactly from the pmf
    from scipy.stats import binom
    for n, p in ((100, 0.95), (100, 0.05), (100, 0.5)):
        cover = sum(binom.pmf(k, n, p) for k in range(n + 1) if wilson_interval(k, n)[0] <= p <= wilson_interval(k, n)[1])
        assert 0.92 < cover < 0.99


@pytest.mark.parametrize("args, match", [((5, 0), "n"), ((-1, 10), "successes"), ((11, 10), "successes"),
                                         ((1, 10, 1.5), "level")])
def test_wilson_interval_bad_input(args, match):
    with pytest.raises(ValueError, match=match):
        wilson_interval(*args)


# --- timing split, jobs, fingerprints --------------------------------------------------------

json_values = st.recursive(
    st.none() | st.integers() | st.floats(allow_nan=False, allow_infinity=False),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.sampled_from(["a", "b", "seconds", "c"]), inner,
                                                                max_size=3),
    max_leaves=10)


@settings(max_examples=100, suppress_health_check=[HealthCheck.too_slow])
@given(payload=st.dictionaries(st.sampled_from(["x", "seconds", "strategies"]), json_values, max_size=3))
def test_split_timing_round_trip(payload):
    result, timing = split_timing(payload)

    def keys(node):
        if isinstance(node, dict):
            for k, v in node.items():
                yield k
                yield from keys(v)
        elif isinstance(node, list):
            for v in node:
                yield from keys(v)

    assert "seconds" not in set(keys(result))
    assert merge_timing(result, timing) == payload


def test_job_validation_names_the_argument(tmp_path):
    with pytest.raises(ValueError, match="kind"):
        Job("table", "a", {})
    with pytest.raises(ValueError, match="name"):
        Job("compare", "a/b", {})
    with pytest.raises(ValueError, match="outputs"):
        Job("compare", "a", {}, outputs={"pictures": "x"})
    with pytest.raises(ValueError, match="config"):
        Job("compare", "a", {"x": object()})
    with pytest.raises(ValueError, match="inputs"):
        Job("dense", "a", {}, inputs=(str(tmp_path / "missing.npz"),))
    with pytest.raises(ValueError, match="seeds"):
        compare_jobs([1, 1])
    with pytest.raises(ValueError, match="jobs"):
        run_batch([], tmp_path)
    with pytest.raises(ValueError, match="names must be unique"):
        run_batch(compare_jobs([0]) + compare_jobs([0]), tmp_path, scheduler="serial")
    with pytest.raises(ValueError, match="workers"):
        run_batch(compare_jobs([0]), tmp_path, scheduler="serial", workers=2)
    with pytest.raises(ValueError, match="scheduler"):
        run_batch(compare_jobs([0]), tmp_path, scheduler="cluster")


def test_fingerprint_covers_configuration_and_input_contents_not_outputs(tmp_path, monkeypatch):
    a = compare_jobs([0])[0]
    assert a.fingerprint() == compare_jobs([0], figures=str(tmp_path))[0].fingerprint()
    assert a.fingerprint() != compare_jobs([0], refine=2)[0].fingerprint()
    assert a.fingerprint() != compare_jobs([1])[0].fingerprint()
    f = tmp_path / "s.npz"
    f.write_bytes(b"one")
    j1 = dense_jobs([str(f)], ModelSpec(landmarks=8))[0]
    fp1 = j1.fingerprint()
    f.write_bytes(b"two")
    assert j1.fingerprint() != fp1
    fp_now = j1.fingerprint()
    assert dense_jobs([str(f)], ModelSpec(landmarks=16))[0].fingerprint() != fp_now
    assert [j.name for j in dense_jobs([str(f), str(f)])] == ["s", "s-2"]
    monkeypatch.setattr(jobs_module, "RESULTS_SCHEMA", jobs_module.RESULTS_SCHEMA + 1)
    assert j1.fingerprint() != fp_now                   # a result computed otherwise is not reused


#: A value other than the default of every field of the three specs (a new field must be added here)
OTHER_VALUES = {
    "model": {"effects": ("active_polar",), "drive": "contour", "drive_trend": True, "effect_rates": True,
              "process_scale": 2.0, "spring_scale": 10.0, "material": "basis", "parameterisation": "basis",
              "landmarks": 6, "observe": "boundary+midwall", "holdout_seed": 1, "mesh": "polar", "element_px": 3.0,
              "angle_origin_deg": -30.0},
    "estimator": {"estimator": "cyclic", "max_iterations": 7, "max_loops": 2, "laplace": "exact",
                  "measurement_noise": "estimate"},
    "loop": {"effects": "none", "candidates": ("active_polar",), "max_rounds": 2, "alpha": 0.05, "min_evidence": 1.0,
             "max_tries": 2, "selection": "first", "corrections": False, "stiff_springs": "any", "criterion": "cv",
             "folds": 3, "min_cv_gain": 0.1, "prune": False, "warm_start": True, "screen_iterations": 2},
}
SPECS = {"model": ModelSpec, "estimator": EstimatorSettings, "loop": LoopSettings}


def test_a_dense_job_carries_every_setting_of_the_specs_defaults_included(tmp_path):
    """No key only when it differs from a default: passing a default explicitly is the same job, every
    field of the three specs is in the configuration and changes the fingerprint (so a new setting
    or a changed default changes it), and settings that are not specs are an error."""
    f = tmp_path / "s.npz"
    f.write_bytes(b"one")
    implicit = dense_jobs([str(f)])[0]
    explicit = dense_jobs([str(f)], ModelSpec(mesh="delaunay"), EstimatorSettings(laplace="gauss-newton",
                                                                                   max_iterations=20),
                          LoopSettings(stiff_springs="contour", warm_start=False, candidates=None))[0]
    assert implicit.config == explicit.config and implicit.fingerprint() == explicit.fingerprint()
    assert set(implicit.config) == set(SPECS)
    for key, cls in SPECS.items():
        assert set(implicit.config[key]) == {f.name for f in dataclasses.fields(cls)} == set(OTHER_VALUES[key])
        for name, value in OTHER_VALUES[key].items():
            spec = cls(**{name: value})
            assert getattr(spec, name) != getattr(cls(), name), name
            assert cls.to_json(spec)[name] != implicit.config[key][name], name
    # the job runs what it records: its specs, from its configuration
    assert dense_specs(implicit.config) == (ModelSpec(), EstimatorSettings(max_iterations=20), LoopSettings())
    assert dense_jobs([str(f)], loop=LoopSettings(stiff_springs="any"))[0].fingerprint() != implicit.fingerprint()
    # the drive's default iteration limit, resolved
    assert dense_jobs([str(f)], ModelSpec(drive="pressure"))[0].config["estimator"]["max_iterations"] == 80
    with pytest.raises(TypeError, match="model: expected sfem_filters.cardiac.ModelSpec"):
        dense_jobs([str(f)], {"mesh": "polar"})
    with pytest.raises(ValueError, match="laplace: 'exact' needs a material map"):
        dense_jobs([str(f)], ModelSpec(parameterisation="none"), EstimatorSettings(laplace="exact"))
    with pytest.raises(ValueError, match="config"):
        dense_specs({**implicit.config, "workers": 2})


def test_every_setting_changes_a_dense_jobs_fingerprint(tmp_path):
    f = tmp_path / "s.npz"
    f.write_bytes(b"one")
    base = dense_jobs([str(f)])[0].fingerprint()
    seen = {base}
    for key, cls in SPECS.items():
        for name, value in OTHER_VALUES[key].items():
            if (key, name) in (("model", "effects"), ("model", "material")):
                continue                    # the loop starts from a model without them (check_specs)
            fp = dense_jobs([str(f)], **{key: cls(**{name: value})})[0].fingerprint()
            assert fp not in seen, (key, name)
            seen.add(fp)


# --- running batches ---------------------------------------------------------------------------

def _bytes(directory, jobs):
    return {j.name: open(os.path.join(directory, f"{j.name}.json"), "rb").read() for j in jobs}


def test_local_cluster_gives_the_serial_bytes_and_failures_are_isolated(tmp_path):
    bad = tmp_path / "broken.npz"
    bad.write_bytes(b"not a zip file")
    jobs = compare_jobs([0, 1], **CHEAP) + dense_jobs([str(bad)])
    serial = run_batch(jobs, tmp_path / "serial", scheduler="serial", progress=False)
    environ = dict(os.environ)
    local = run_batch(jobs, tmp_path / "local", scheduler="local", workers=2, progress=False)
    assert dict(os.environ) == environ     # Dask's worker settings (OPENBLAS_NUM_THREADS=1 ...) do not leak
    for rep in (serial, local):
        assert sorted(rep.ran) == ["seed0000", "seed0001"]
        assert list(rep.failed) == ["broken"] and "not a readable .npz" in rep.failed["broken"]
        err = json.loads((tmp_path / rep.directory / "broken.error.json").read_text())
        assert "Traceback" in err["traceback"] and err["fingerprint"] == jobs[2].fingerprint()
    assert _bytes(tmp_path / "serial", jobs[:2]) == _bytes(tmp_path / "local", jobs[:2])
    # the stored result is exactly the run's result, and the same run in this process gives it again
    rec = json.loads(_bytes(tmp_path / "local", jobs[:1])["seed0000"])
    assert rec["job"]["fingerprint"] == jobs[0].fingerprint()
    assert rec["result"] == run_job(jobs[0]).result
    # a rerun skips what exists and retries only the failure
    again = run_batch(jobs, tmp_path / "local", scheduler="serial", progress=False)
    assert sorted(again.skipped) == ["seed0000", "seed0001"] and again.ran == [] and list(again.failed) == ["broken"]


def test_local_cluster_workers_keep_glibc_trimming_profiler_off_one_task_each():
    """The settings that made the batch fast (benchmarks/batch.py; README): no aggressive heap
    trimming in the workers, no statistical profiler, one task per free worker thread."""
    environ = dict(os.environ)
    client, cluster = _client("local", 1)
    try:
        env = client.run(lambda: (os.environ.get("MALLOC_TRIM_THRESHOLD_"), os.environ.get("OPENBLAS_NUM_THREADS")))
        assert list(env.values()) == [(None, "1")]
        assert list(client.run(lambda: dask.config.get("distributed.worker.profile.enabled")).values()) == [False]
        assert cluster.scheduler.WORKER_SATURATION == 1.0
    finally:
        client.close()
        cluster.close()
        os.environ.clear()
        os.environ.update(environ)


def test_table_has_a_row_per_job_and_strategy_with_the_stored_values(tmp_path):
    jobs = compare_jobs([0, 1], **CHEAP)
    rep = run_batch(jobs, tmp_path, scheduler="serial", progress=False)
    with open(rep.table, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [(r["job"], r["strategy"]) for r in rows] == [(j.name, s) for j in jobs for s in ROWS]
    assert list(rows[0])[-1] == "seconds"
    for r in rows:
        m = rep.records[r["job"]]["result"]["strategies"][r["strategy"]]
        assert float(r["ks_D"]) == m["ks_D"] and float(r["rmse_eyy"]) == m["rmse_eyy"]
        assert float(r["seconds"]) == rep.timings[r["job"]][f"strategies/{r['strategy']}/seconds"] > 0
    # the printed table from the stored results is the table of the runs themselves
    results = [merge_timing(rep.records[j.name]["result"], rep.timings[j.name]) for j in jobs]
    assert format_table(results).splitlines()[2].split()[:3] == ["0", "KF,", "uniform"]


def test_other_configuration_reruns_and_keeps_the_old_result(tmp_path):
    a = compare_jobs([0], max_loops=1)
    run_batch(a, tmp_path, scheduler="serial", progress=False)
    old = (tmp_path / "seed0000.json").read_bytes()
    b = compare_jobs([0], max_loops=2)
    rep = run_batch(b, tmp_path, scheduler="serial", progress=False)
    assert rep.ran == ["seed0000"]
    kept = tmp_path / f"seed0000.{a[0].fingerprint()[:12]}.json"
    assert kept.read_bytes() == old
    assert ResultStore(tmp_path).load(b[0])["job"]["config"]["max_loops"] == 2


@pytest.mark.needs_data("subject_a")
def test_dense_job_record_and_rows(tmp_path):
    jobs = dense_jobs(["example"], ModelSpec(parameterisation="none"),
                      EstimatorSettings(estimator="cyclic", max_loops=1), LoopSettings(effects="none"))
    rep = run_batch(jobs, tmp_path, scheduler="serial", progress=False)
    assert rep.ran == ["subject_a"], rep.failed
    rec = rep.records["subject_a"]
    assert rec["job"]["inputs"] == ["subject_a.npz"]
    line = describe_record(rec)
    assert line.startswith("subject_a: held-out RMSE baseline") and "spline" in line
    with open(rep.table, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["strategy"] for r in rows] == ["round 0", "spline"]
    assert float(rows[0]["heldout_rmse_px"]) == rec["result"]["rounds"][0]["heldout_rmse_px"]
    assert float(rows[1]["heldout_rmse_px"]) == rec["result"]["spline_reference"]["heldout_rmse_px"]


def _results(folder):
    """Names of the jobs whose result file exists (not their run or error records)."""
    return sorted(p.name[:-len(".json")] for p in folder.glob("seed*.json") if re.fullmatch(r"seed\d+\.json", p.name))


def test_sigkill_of_the_client_then_rerun_finishes_only_the_rest(tmp_path):
    out = tmp_path / "batch"
    cmd = [sys.executable, "-m", "sfem_filters.cli", "compare", "--seed", "0-5", "--max-loops", "3",
           "--scheduler", "local", "--workers", "2", "--batch-dir", str(out), "--no-progress"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.time() + 120
        while time.time() < deadline and not _results(out):
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # orphaned worker processes, if any
        except ProcessLookupError:
            pass
    done = _results(out)  # a job is done once its result file is written (the commit point)
    assert 1 <= len(done) < 6, "the kill must land mid-batch"
    stamps = {n: (out / f"{n}.json").stat().st_mtime_ns for n in done}
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert f"{6 - len(done)} run, {len(done)} skipped (result exists), 0 failed" in res.stderr
    assert {n: (out / f"{n}.json").stat().st_mtime_ns for n in done} == stamps
    assert len(list(out.glob("seed*.run.json"))) == 6
    assert sorted(int(ln.split()[0]) for ln in res.stdout.splitlines() if ln[5:].startswith(" joint EKF")) == list(range(6))


# --- Table 1 over many draws ---------------------------------------------------------------------

def _fake(seed, D, H):
    m = {"ks_D": D, "ks_p_asymptotic": 1 - D, "ks_H": H, "rmse_displacement_mm": D, "seconds": 1.0}
    return {"seed": seed, "n_nodes": 35, "strategies": {"uniform_kf": m, "joint_ekf": {**m, "ks_H": 0, "loops": 3}}}


def test_summarise_counts_rejections_and_quartiles():
    rng = np.random.default_rng(1)
    D = rng.uniform(0, 1, 40)
    H = (D > 0.3).astype(int)
    s = summarise([_fake(i, float(d), int(h)) for i, (d, h) in enumerate(zip(D, H))])
    u = s["strategies"]["uniform_kf"]
    assert u["rejections"] == H.sum() and u["interval"] == wilson_interval(int(H.sum()), 40)
    assert u["quartiles"]["ks_D"] == pytest.approx(tuple(np.percentile(D, [25, 50, 75])))
    assert "loops" in s["strategies"]["joint_ekf"]["quartiles"] and "loops" not in u["quartiles"]
    text = format_summary(s)
    assert f"rejected  {H.sum()}/40" in text and "Wilson" in text
    with pytest.raises(ValueError, match="results"):
        summarise([])


def test_cli_batch_errors_exit_2(capsys, tmp_path):
    assert main(["compare", "--seed", "0", "--scheduler", "serial", "--workers", "2"]) == 2
    assert "--workers" in capsys.readouterr().err
    assert main(["compare", "--seed", "0", "--scheduler", "nowhere", "--batch-dir", str(tmp_path)]) == 2
    assert "scheduler" in capsys.readouterr().err
