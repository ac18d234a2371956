"""The first run a newcomer makes on measured data: ``sfem-filters dense example``, as it comes.

Runs the console script exactly as a user types it (default settings, default workers and BLAS
threads, progress on) and measures what the user meets: the wall time from the command to the
report, the time to the first line on stderr (the console script says it has started before the
library loads) and to the run's own first progress line, the peak memory of the largest process
(the command or one of its workers), and the model it ends with, against the thin-plate spline
through the same points. Full tier: the bare default command. Quick tier: one baseline fit of the
paper's cyclic filter (what the test suite can afford), to check the measurement itself.

Timings depend on the machine and what else runs on it; the header's load average says which.
"""
from __future__ import annotations

import json
import os
import subprocess
import threading
import time
from pathlib import Path

from sfem_filters.cli.starting import STARTING

from ._core import fmt, md_table, peak_rss_bytes
from .closing_loop import _model, command

NAME = "first_run"
TITLE = "The first run on measured data: time, progress, memory"
#: Needs the measured slice (``sfem_filters.datasets``: set SFEM_FILTERS_DATA).
NEEDS_DATA = True
FULL_COST = "about 3-5 min"
#: The budget the default command must meet on a 2-core machine (seconds, wall).
BUDGET_S = 180.0
TIERS = {"quick": {"args": ["--effects", "none", "--estimator", "cyclic", "--max-loops", "1", "--workers", "1"]},
         "full": {"args": []}}
#: The command's JSON is deterministic; times and memory are not compared.
TOLERANCES = {"*": (1e-6, 1e-9), "wall_s": None, "first_output_s": None, "first_progress_s": None,
              "peak_rss_gb": None}
#: The goal for the first line on stderr (seconds from the command).
FIRST_LINE_S = 1.0


def _timed_run(argv: list, env: dict) -> dict:
    """Run ``argv``; wall time, stderr's lines each with the time it was complete (seconds from the
    start; a progress bar's ``\r`` ends a line too), return code."""
    chunks = []
    start = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)

    def read():
        while True:
            chunk = proc.stderr.read1(4096)
            if not chunk:
                return
            chunks.append((time.perf_counter() - start, chunk))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    code = proc.wait()
    wall = time.perf_counter() - start
    reader.join(timeout=10)
    return {"wall_s": wall, "lines": _timed_lines(chunks), "returncode": code,
            "stderr": b"".join(c for _, c in chunks).decode(errors="replace")}


def user_environment() -> dict:
    """The user's environment as it is: this process's, less the BLAS thread settings the suite may
    have set (none is forced on the command)."""
    return {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                             "MKL_NUM_THREADS")}


def first_progress(lines) -> tuple:
    """``(seconds, line)`` of the run's own first progress: the first timed line after the console
    script's "starting" line (:data:`~sfem_filters.cli.starting.STARTING`), or ``(None, None)``."""
    return next(((t, ln) for t, ln in lines if not STARTING.match(ln)), (None, None))


def _timed_lines(chunks) -> list:
    """``(seconds, line)`` of every non-empty line in the timed ``chunks`` of a stream."""
    out, pending = [], b""
    for t, chunk in chunks:
        parts = (pending + chunk).replace(b"\r", b"\n").split(b"\n")
        pending = parts.pop()
        out.extend((t, p.decode(errors="replace").strip()) for p in parts if p.strip())
    if pending.strip():
        out.append((chunks[-1][0], pending.decode(errors="replace").strip()))
    return out


def compute(settings: dict, out_dir) -> dict:
    path = Path(out_dir) / "first_run.command.json"
    args = ["dense", "example", *settings["args"], "--json", str(path)]
    env = user_environment()
    before = peak_rss_bytes("children")
    run = _timed_run(command() + args, env)
    peak = peak_rss_bytes("children")
    if run["returncode"] != 0:
        raise RuntimeError(f"sfem-filters {' '.join(args)} failed ({run['returncode']}):\n{run['stderr'][-2000:]}")
    with open(path) as f:
        report = json.load(f)
    path.unlink()
    final = report.get("extended") or report["baseline"]
    lines = run["lines"]
    # the run's own progress: the first line after the console script's "starting" line
    progress = first_progress(lines)
    return {"command": "sfem-filters " + " ".join(a for a in args if a not in ("--json", str(path))),
            "wall_s": run["wall_s"], "first_output_s": lines[0][0] if lines else None,
            "first_output_line": lines[0][1] if lines else None,
            "first_progress_s": progress[0], "first_progress_line": progress[1],
            # ru_maxrss of the children is the largest single process; a run before this one in the
            # same process could only raise it, so say when one did. Decimal GB (1e9 bytes).
            "peak_rss_gb": peak / 1e9, "peak_rss_may_include_earlier_child": bool(before),
            "budget_s": BUDGET_S, "stop_reason": report.get("stop_reason"),
            "final_effects": final.get("effects") or [], "final_model": _final_label(report),
            "baseline_heldout_px": report["baseline"]["heldout_rmse_px"],
            "final_heldout_px": final["heldout_rmse_px"], "final_converged": final.get("converged"),
            "spline_heldout_px": report["spline_reference"]["heldout_rmse_px"],
            "rounds": len(report.get("rounds", []))}


def _final_label(report: dict) -> str:
    """The final model as the closing_loop claim names it: effects, then the corrections."""
    rounds = report.get("rounds") or []
    if not rounds:
        return " + ".join(report["baseline"].get("effects") or ["none"])
    last = rounds[-1]
    return _model({"effects": last.get("effects") or [],
                   "corrections": {k: last.get(k) for k in ("drive", "process_scale", "spring_scale", "drive_trend",
                                                            "effect_rates")}})


def markdown(results: dict) -> str:
    within = results["wall_s"] <= results["budget_s"]
    heads = ["command", "wall time [s]", "first line [s]", "first progress [s]", "peak memory [GB]", "final model",
             "held-out: baseline [px]", "held-out: final [px]", "held-out: spline [px]"]
    row = [f"`{results['command']}`", fmt(results["wall_s"], ".0f"), fmt(results["first_output_s"], ".2f"),
           fmt(results["first_progress_s"], ".2f"),
           fmt(results["peak_rss_gb"], ".2f"), results["final_model"] + ("" if results["final_converged"] else " *"),
           fmt(results["baseline_heldout_px"], ".3f"), fmt(results["final_heldout_px"], ".3f"),
           fmt(results["spline_heldout_px"], ".3f")]
    text = [md_table(heads, [row]), "",
            f"Wall time from the command to the report, with the default workers and BLAS threads; first line: the "
            f"first text on stderr (`{results['first_output_line']}`), goal {FIRST_LINE_S:.0f} s; first progress: "
            f"the run's own first progress line, after the library has loaded "
            f"(`{results['first_progress_line']}`); peak memory: the largest "
            f"single process (the command or a worker). Budget {results['budget_s']:.0f} s: "
            f"{'met' if within else 'not met'} on the machine and load of the header. Stop: "
            f"{results['stop_reason']}."]
    if not results["final_converged"]:
        text.append("`*`: the final fit stopped at its iteration limit before the material met the stop rule.")
    return "\n".join(text)


def load_stretch() -> float:
    """How much slower than idle this machine runs now: the 1-minute load average per core, at least 1."""
    return max(1.0, os.getloadavg()[0] / max(os.cpu_count() or 1, 1))


def check(results: dict, tier: str) -> list:
    """A first line within :data:`FIRST_LINE_S`, the run's own progress within 5 s, a finite wall
    time, a final held-out error below the baseline's when rounds ran. The two limits are an idle
    machine's; on a loaded one they stretch by the load per core (:func:`load_stretch`: the test
    suite runs the quick tier beside its other workers), so the check says whether the command is
    prompt, not how busy the machine was."""
    problems = []
    stretch = load_stretch()
    if results["first_output_s"] is None or not results["first_output_s"] < FIRST_LINE_S * stretch:
        problems.append(f"first line after {results['first_output_s']} s (limit {FIRST_LINE_S * stretch:.1f} s)")
    if results["first_progress_s"] is None or not results["first_progress_s"] < 5.0 * stretch:
        problems.append(f"first progress after {results['first_progress_s']} s (limit {5.0 * stretch:.1f} s)")
    if not results["wall_s"] > 0:
        problems.append(f"wall time {results['wall_s']}")
    if results["rounds"] and not results["final_heldout_px"] <= results["baseline_heldout_px"]:
        problems.append("the final model does not beat the baseline on the held-out points")
    return problems
