"""Closing the loop: the coarse search (the ``dense`` command's default) and the fast one.

For each search of :data:`sfem_filters.cardiac.closing.SEARCHES` (``--search coarse|fast``): the
command ``sfem-filters dense example --search S`` on the measured slice, as a user runs it (its
default workers, one per core), with its wall time from the command to the report and the peak
memory of the command and its worker processes; and the synthetic checks of the rounds
(:mod:`validation.rounds_synthetic`'s cases, drawn from the library's generative model, where the
answer is known, drawn on the node-per-pixel mesh and on a finer polar mesh) under the same
search. Per run: the final model, the held-out error beside the
thin-plate spline's, the number of rounds' fits and the wall time.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from sfem_filters.cardiac import SEARCHES

from . import rounds_synthetic
from ._core import fmt, md_table

NAME = "search"
TITLE = "Closing the loop: the coarse and fast searches"
#: Needs the measured slice (``sfem_filters.datasets``: set SFEM_FILTERS_DATA).
NEEDS_DATA = True
FULL_COST = "about 40-60 min"
#: ``truths``: the meshes the synthetic motion is drawn on: ``None`` the node-per-pixel mesh (the
#: rounds' checks as frozen so far: an estimator on that mesh shares the generator's discretisation),
#: a number a polar mesh of that edge (pixels), finer than any estimator's, sampled at the pixels.
TIERS = {"quick": {"searches": ["fast"], "slice_args": ["--effects", "none", "--max-iterations", "1"],
                   "synthetic": {"cases": ["clean"], "seeds": [0], "frames": 4, "max_rounds": 1},
                   "truths": [0.7], "synthetic_max_iterations": 1},
         "full": {"searches": ["coarse", "fast"], "slice_args": [],
                  "synthetic": {"cases": ["two", "akinetic", "clean"], "seeds": [0], "frames": 24, "max_rounds": 5},
                  "truths": [None, 0.5], "synthetic_max_iterations": None}}
TOLERANCES = {"*": (1e-6, 1e-9), "seconds": None, "peak_memory_gb": None}

#: Runs the command line in this interpreter and prints the peak resident memory (GB) of the
#: process and of its largest worker (Linux: ru_maxrss in KiB; decimal GB, 1e9 bytes) after the command's own output.
_RUNNER = ("import resource, sys\n"
           "from sfem_filters.cli import main\n"
           "rc = main(sys.argv[1:])\n"
           "peak = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,\n"
           "           resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss) * 1024 / 1e9\n"
           "print(f'PEAK_GB {peak:.3f}', file=sys.stderr)\n"
           "sys.exit(rc)\n")


def measured_slice_row(search: str, args: list, out_dir) -> dict:
    """The command ``sfem-filters dense example --search <search> <args>`` as a user runs it: its final
    model, held-out error beside the spline's, fits, wall time and peak memory (one table row)."""
    path = Path(out_dir) / f"search_{search}.command.json"
    cmd = ["dense", "example", "--search", search, *args, "--no-progress", "--json", str(path)]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS", "1")}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", _RUNNER, *cmd], capture_output=True, text=True, env=env)
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"sfem-filters {' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    peak = [float(line.split()[1]) for line in proc.stderr.splitlines() if line.startswith("PEAK_GB")]
    with open(path) as f:
        report = json.load(f)
    path.unlink()
    ext, cfg = report["extended"], report["config"]
    fits = sum(len(r.get("tried", [])) + len(r.get("backward", [])) for r in report["rounds"]) + 1
    return {"search": search, "case": "measured slice (sfem-filters dense example)",
            "command": "sfem-filters " + " ".join(cmd[:-2]),
            "final": ", ".join(cfg["final"]["effects"]) + "".join(
                f" [{k}]" for k in _terms(cfg["final"])), "fits": fits,
            "heldout_rmse_px": ext["heldout_rmse_px"], "spline_rmse_px": report["spline_reference"]["heldout_rmse_px"],
            "baseline_converged": bool(report["baseline"]["converged"]),
            "mesh_nodes": cfg["mesh_nodes"], "seconds": seconds, "peak_memory_gb": peak[-1] if peak else None}


def _drawn_on(fine) -> str:
    return "pixel nodes" if fine is None else f"{fine:g}-px polar mesh"


def _terms(final: dict) -> list:
    out = []
    if final.get("drive") not in (None, "penalty"):
        out.append(f"drive {final['drive']}")
    if final.get("drive_trend"):
        out.append("drive trend")
    if final.get("effect_rates"):
        out.append("effect trends")
    if final.get("spring_scale", 1.0) != 1.0:
        out.append(f"springs x{final['spring_scale']:g}")
    if final.get("process_scale", 1.0) != 1.0:
        out.append(f"process noise x{final['process_scale']:g}")
    if final.get("material"):
        out.append(f"material {final['material']}")
    return out


def compute(settings: dict, out_dir) -> dict:
    # the measured slice first, every search (its timings the ones users meet), then the checks
    rows = [measured_slice_row(name, settings["slice_args"], out_dir) for name in settings["searches"]]
    for name in settings["searches"]:
        search = SEARCHES[name]
        limit = settings["synthetic_max_iterations"] or search.max_iterations("penalty")
        for fine in settings.get("truths", [None]):
            syn = {**settings["synthetic"], "max_iterations": limit, "truth_element_px": fine,
                   "loop": {**search.settings(), "workers": None}}
            t0 = time.perf_counter()
            res = rounds_synthetic.compute(syn, out_dir)
            seconds = time.perf_counter() - t0
            for r in res["rows"]:
                rows.append({"search": name, "case": r["case"], "drawn_on": _drawn_on(fine), "truth": r["truth"],
                             "final": ", ".join(r["effects"]) or "none", "steps": r["steps"],
                             "heldout_rmse_px": r["heldout_rmse_px"], "spline_rmse_px": r["spline_rmse_px"],
                             "seconds": seconds / len(res["rows"])})
    return {"rows": rows}


def markdown(results: dict) -> str:
    cols = ["search", "case", "motion drawn on", "truth", "final model", "held-out [px]", "spline [px]", "fits",
            "seconds", "peak memory [GB]"]
    body = [[r["search"], r["case"], r.get("drawn_on", "(measured)"), r.get("truth", "unknown"), r["final"] or "none",
             fmt(r["heldout_rmse_px"], ".3f"), fmt(r["spline_rmse_px"], ".3f"), str(r.get("fits", "")),
             fmt(r["seconds"], ".0f"), fmt(r["peak_memory_gb"], ".2f") if r.get("peak_memory_gb") else ""]
            for r in results["rows"]]
    return (md_table(cols, body) + "\n\nThe measured slice's rows: the command `sfem-filters dense example "
            "--search S` with its default workers (one per core), wall time from the command to the report, "
            "peak resident memory of the command or its largest worker. Synthetic rows: the rounds on "
            "sequences drawn from the library's own generative model (the synthetic checks' page), seconds the "
            "mean per case; held-out error on the points no fit saw, beside the thin-plate spline through the same "
            "observed points. Motion drawn on the pixel nodes: the generator's mesh is the fast and full "
            "searches' own (node per pixel), so they pay no discretisation error and every other mesh does; on "
            "a fine polar mesh (finer than any estimator's, sampled at the pixels), every search pays its own.")


def check(results: dict, tier: str) -> list:
    """Every held-out error finite and positive; in the full tier, every search's rows present."""
    problems = [f"{r['search']} {r['case']}: held-out {r['heldout_rmse_px']}" for r in results["rows"]
                if not (r["heldout_rmse_px"] is not None and r["heldout_rmse_px"] > 0)]
    searches = {r["search"] for r in results["rows"]}
    problems += [f"no rows of the {s} search" for s in TIERS[tier]["searches"] if s not in searches]
    return problems
