"""Closing the loop on the measured DENSE slice: ``sfem-filters dense example``.

Runs the command line itself (the console script ``sfem-filters``, ``--json``, one worker so the
machine's other core stays free; the report is the same whatever the number of workers) and
renders its JSON: the rounds (each adds the best significant candidate effect or correction
while the evidence rises), the baseline against the final model, and the thin-plate spline
through the same observed points, the yardstick the physics has to beat. Full tier: the
command's defaults (8 landmarks per contour, rounds of ``--effects auto``, the iterated
smoother); quick tier: one declared effect, one loop of the paper's cyclic filter.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from ._core import fmt, md_table

NAME = "closing_loop"
TITLE = "Closing the loop on the measured DENSE slice"
#: Needs the measured slice (``sfem_filters.datasets``: set SFEM_FILTERS_DATA).
NEEDS_DATA = True
FULL_COST = "about 5-10 min"
TIERS = {"quick": {"args": ["--effects", "active_polar", "--estimator", "cyclic", "--max-loops", "1",
                            "--workers", "1"]},
         "full": {"args": ["--landmarks", "8", "--workers", "1"]}}
#: The command's JSON is deterministic (same to the last printed digit); seconds are not compared.
TOLERANCES = {"*": (1e-6, 1e-9), "seconds": None}
METRICS = (("held-out RMSE [px]", "heldout_rmse_px", ".3f"), ("radial [px]", "heldout_rmse_radial_px", ".3f"),
           ("circumferential [px]", "heldout_rmse_circumferential_px", ".3f"),
           ("worst frame [px]", "heldout_rmse_worst_frame_px", ".3f"),
           ("innovation RMS [px]", "innovation_rms_px", ".3f"),
           ("mean NIS / dof (1 = consistent)", "nis_mean_over_dof", ".3f"),
           ("frames outside the 95% NIS band", "nis_fraction_outside_95", ".3f"),
           ("innovation lag-1 autocorrelation", "innovation_lag1_autocorrelation", ".3f"),
           ("log p(y) [nats]", "log_evidence", ".1f"))


def command() -> list:
    """The console script next to this Python, else on the PATH."""
    here = Path(sys.executable).with_name("sfem-filters")
    exe = str(here) if here.exists() else shutil.which("sfem-filters")
    if exe is None:
        raise RuntimeError("sfem-filters: the console script is not installed (pip install -e .)")
    return [exe]


def compute(settings: dict, out_dir) -> dict:
    path = Path(out_dir) / "closing_loop.command.json"
    args = ["dense", "example", *settings["args"], "--no-progress", "--json", str(path)]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1")}
    proc = subprocess.run(command() + args, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"sfem-filters {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    with open(path) as f:
        report = json.load(f)
    path.unlink()
    keep = [k for _, k, _ in METRICS] + ["iterations", "loops", "converged", "estimator", "seconds"]
    runs = {name: {k: report[name].get(k) for k in keep} for name in ("baseline", "extended") if report.get(name)}
    if report.get("extended"):
        runs["extended"]["effects"] = report["extended"].get("effects")
    rounds = [{"round": r["round"], "effects": r["effects"], "added": r.get("added"), "removed": r.get("removed"),
               "corrections": {k: r.get(k) for k in ("drive", "process_scale", "spring_scale", "drive_trend",
                                                     "effect_rates")},
               "log_evidence": r.get("log_evidence"), "heldout_rmse_px": r.get("heldout_rmse_px"),
               "nis_over_dof": r.get("nis_mean_over_dof"), "lag1": r.get("innovation_lag1_autocorrelation"),
               "cv_rmse_px": (r.get("cross_validation") or {}).get("rmse_px"),
               "plus_spline_px": (r.get("residual_spline") or {}).get("heldout_rmse_px")}
              for r in report.get("rounds", [])]
    spline = report["spline_reference"]
    return {"command": "sfem-filters " + " ".join(a for a in args if a not in ("--json", str(path))),
            "config": {k: report["config"].get(k) for k in ("landmarks", "observe", "drive", "parameterisation",
                                                             "estimator", "n_observed", "n_heldout", "max_rounds")},
            "noise_floor_px": report["noise_floor_px"], "stop_reason": report.get("stop_reason"),
            "runs": runs, "rounds": rounds,
            "spline": {k: spline.get(k) for k in ("heldout_rmse_px", "heldout_rmse_radial_px",
                                                  "heldout_rmse_circumferential_px")}}


def _model(r) -> str:
    c = r["corrections"]
    extra = [f"{k} {v}" for k, v in c.items() if k in ("process_scale", "spring_scale") and v not in (None, 1.0)]
    extra += [k.replace("_", " ") for k in ("drive_trend", "effect_rates") if c.get(k)]
    extra += [f"drive {c['drive']}"] if c.get("drive") not in (None, "penalty") else []
    return " + ".join(r["effects"] or ["none"]) + (f" ({', '.join(extra)})" if extra else "")


def markdown(results: dict) -> str:
    runs, spline = results["runs"], results["spline"]
    names = [n for n in ("baseline", "extended") if n in runs]
    heads = ["", *("baseline" if n == "baseline" else "final: " + " + ".join(runs[n].get("effects") or ["none"])
                   for n in names), "thin-plate spline"]
    body = [[label, *(fmt(runs[n].get(key), spec) for n in names), fmt(spline.get(key), spec)]
            for label, key, spec in METRICS]
    # "loops": Gauss-Newton iterations of the smoother or loops of the cyclic filter (a count; the
    # smoother's "iterations" is its per-iteration record)
    body.append(["iterations or loops", *(str(runs[n].get("loops")) + ("" if runs[n].get("converged") else "*")
                                          for n in names), ""])
    text = [f"`{results['command']}`: {results['config']['n_observed']} points observed, "
            f"{results['config']['n_heldout']} held out; noise floor {results['noise_floor_px']:.3f} px; "
            f"stop: {results['stop_reason']}.", "", md_table(heads, body),
            "", "`*`: stopped at its limit before the material met the stop rule."]
    if results["rounds"]:
        cols = ["round", "model", "added", "log p(y)", "NIS / dof", "lag-1", "CV [px]", "held-out [px]",
                "+ spline [px]"]
        rows = [[r["round"], _model(r), r["added"] or (f"removed {r['removed']}" if r["removed"] else "-"),
                 fmt(r["log_evidence"], ".1f"), fmt(r["nis_over_dof"], ".3f"), fmt(r["lag1"], ".3f"),
                 fmt(r["cv_rmse_px"], ".3f"), fmt(r["heldout_rmse_px"], ".3f"), fmt(r["plus_spline_px"], ".3f")]
                for r in results["rounds"]]
        text += ["", md_table(cols, rows), "", "CV: cross-validation over the observed points; + spline: the "
                 "model plus a thin-plate spline of its residual at the observed points."]
    return "\n".join(text)


def check(results: dict, tier: str) -> list:
    """Held-out errors finite and positive; the final model predicts the held-out points better
    than the baseline; the noise floor between 0.01 and 0.5 px."""
    problems = []
    runs = results["runs"]
    for name, r in runs.items():
        if not (r.get("heldout_rmse_px") or 0) > 0:
            problems.append(f"{name}: held-out RMSE {r.get('heldout_rmse_px')}")
    if "extended" in runs and not runs["extended"]["heldout_rmse_px"] < runs["baseline"]["heldout_rmse_px"]:
        problems.append("the final model does not beat the baseline on the held-out points")
    if not 0.01 < results["noise_floor_px"] < 0.5:
        problems.append(f"noise floor {results['noise_floor_px']} px")
    return problems
