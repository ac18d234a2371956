"""Stiff springs only along the contours: the rounds before and after.

The rounds' correction ``springs:x10`` (springs ten times stiffer) was offered to every spring
drive; on the isolated landmarks of the penalty drive, stiff springs pull tents in the wall that
the evidence can reward while the held-out error grows. Now it is offered only to springs spread
along the whole contour (``stiff_springs="contour"``, ``--stiff-springs contour``, the default);
``"any"`` is the rounds as before. Both, on the measured slice (the command ``sfem-filters dense
example`` with its default search, as a user runs it) and on the synthetic checks of the rounds
(:mod:`validation.rounds_synthetic`'s cases, the motion drawn on a polar mesh finer than any
estimator's, under the same search): the final model, whether it keeps stiffer springs, the
held-out error beside the thin-plate spline's.
"""
from __future__ import annotations

import time

from sfem_filters.cardiac import SEARCHES

from . import rounds_synthetic, search
from ._core import fmt, md_table

NAME = "springs"
TITLE = "Stiff springs only along the contours"
#: Needs the measured slice (``sfem_filters.datasets``: set SFEM_FILTERS_DATA).
NEEDS_DATA = True
FULL_COST = "about 15-25 min"
TIERS = {"quick": {"search": "coarse", "slice_args": ["--effects", "none", "--max-iterations", "1"],
                   "synthetic": {"cases": ["clean"], "seeds": [0], "frames": 4, "max_rounds": 1,
                                 "truth_element_px": 0.7},
                   "synthetic_max_iterations": 1},
         "full": {"search": "coarse", "slice_args": [],
                  "synthetic": {"cases": ["two", "akinetic", "clean"], "seeds": [0], "frames": 24, "max_rounds": 5,
                                "truth_element_px": 0.5},
                  "synthetic_max_iterations": None}}
TOLERANCES = {"*": (1e-6, 1e-9), "seconds": None, "peak_memory_gb": None}
OFFERS = ("any", "contour")


def compute(settings: dict, out_dir) -> dict:
    name = settings["search"]
    rows = []
    for offer in OFFERS:
        r = search.measured_slice_row(name, [*settings["slice_args"], "--stiff-springs", offer], out_dir)
        rows.append({**r, "stiff_springs": offer, "springs_kept": "springs x" in r["final"]})
    s = SEARCHES[name]
    limit = settings["synthetic_max_iterations"] or s.max_iterations("penalty")
    for offer in OFFERS:
        syn = {**settings["synthetic"], "max_iterations": limit,
               "loop": {**s.settings(), "workers": None, "stiff_springs": offer}}
        t0 = time.perf_counter()
        res = rounds_synthetic.compute(syn, out_dir)
        seconds = time.perf_counter() - t0
        for r in res["rows"]:
            rows.append({"search": name, "stiff_springs": offer, "case": r["case"], "truth": r["truth"],
                         "final": ", ".join(r["effects"]) or "none", "steps": r["steps"],
                         "springs_kept": _springs_kept(r["steps"]),
                         "heldout_rmse_px": r["heldout_rmse_px"], "spline_rmse_px": r["spline_rmse_px"],
                         "seconds": seconds / len(res["rows"])})
    return {"rows": rows}


def _springs_kept(steps) -> bool:
    """Whether the final model of a run of the rounds has stiffer springs: added and not taken out."""
    return sum((s == "+ springs:x10") - (s == "- springs:x10") for s in steps) > 0


def markdown(results: dict) -> str:
    cols = ["springs:x10 offered to", "case", "truth", "final model", "stiffer springs", "held-out [px]",
            "spline [px]", "seconds"]
    label = {"any": "any spring drive (before)", "contour": "contour springs only (now)"}
    body = [[label[r["stiff_springs"]], r["case"], r.get("truth", "unknown"), r["final"] or "none",
             "yes" if r["springs_kept"] else "no", fmt(r["heldout_rmse_px"], ".3f"), fmt(r["spline_rmse_px"], ".3f"),
             fmt(r["seconds"], ".0f")] for r in results["rows"]]
    return (md_table(cols, body) + "\n\nThe measured slice's rows: the command `sfem-filters dense example "
            "--stiff-springs S` with the default search, wall time from the command to the report. Synthetic rows: "
            "the rounds under the same search on sequences drawn from the library's generative model on a polar "
            "mesh finer than any estimator's, sampled at the pixels; seconds the mean per case. Held-out error on "
            "the points no fit saw, beside the thin-plate spline through the same observed points.")


def check(results: dict, tier: str) -> list:
    """Every held-out error finite and positive; both offers present for every case."""
    problems = [f"{r['stiff_springs']} {r['case']}: held-out {r['heldout_rmse_px']}" for r in results["rows"]
                if not (r["heldout_rmse_px"] is not None and r["heldout_rmse_px"] > 0)]
    cases = {}
    for r in results["rows"]:
        cases.setdefault(r["case"], set()).add(r["stiff_springs"])
    problems += [f"{c}: offers {sorted(o)}, expected {list(OFFERS)}" for c, o in cases.items() if o != set(OFFERS)]
    return problems
