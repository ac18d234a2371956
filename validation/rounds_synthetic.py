"""Closing the loop in rounds where the answer is known: synthetic annulus checks, the spline beside.

Synthetic annulus sequences drawn from the library's own generative model
(:func:`sfem_filters.cardiac.annulus_sequence`), run through
:func:`sfem_filters.cardiac.closing_the_loop` with its defaults (rounds, smoother, region map,
the evidence as criterion): ``scale``, pressure-driven passive tissue at 5, 30 and 100 kPa (the
pressure scaled with E), no effect: the estimated stiffness level with its 95% interval; ``two``,
undeclared ``active_polar`` and ``active_helical`` at once, at two balances of strength;
``akinetic``, ``active_segments`` with segment 2 not contracting; ``clean``, no undeclared
effect, seeds 0-3. Per case: the steps the rounds took, why they stopped, NIS / dof and the
held-out RMSE of the final model, and the thin-plate spline's held-out RMSE. The setting
``truth_element_px`` draws the motion on a polar mesh of that edge (pixels) instead of the
node-per-pixel mesh (:func:`sfem_filters.cardiac.annulus_sequence`).
"""
from __future__ import annotations

import functools
import warnings

import numpy as np

from sfem_filters import Material
from sfem_filters.cardiac import NOMINAL, closing_the_loop, prepare, specs_from
from sfem_filters.cardiac import annulus_sequence as _annulus_sequence

from ._core import fmt, md_table

NAME = "rounds_synthetic"
TITLE = "Closing the loop where the answer is known (synthetic annulus)"
FULL_COST = "about 35-60 min"
TIERS = {"quick": {"cases": ["clean"], "seeds": [0], "frames": 8, "max_iterations": 2, "max_rounds": 1},
         "full": {"cases": ["scale", "two", "akinetic", "clean"], "seeds": [0, 1, 2, 3], "frames": 24,
                  "max_iterations": 6, "max_rounds": 5}}
TOLERANCES = {"*": (1e-5, 1e-8)}


def _row(case, out, truth, **extra) -> dict:
    e = out.extended.metrics
    return {"case": case, "truth": truth, "effects": list(out.effects), "stop": out.stop_reason,
            "steps": [r.change for r in out.rounds[1:]], "nis_over_dof": e["nis_mean_over_dof"],
            "heldout_rmse_px": e["heldout_rmse_px"], "spline_rmse_px": out.reference["heldout_rmse_px"], **extra}


def compute(settings: dict, out_dir) -> dict:
    warnings.simplefilter("ignore", RuntimeWarning)
    frames, rows = settings["frames"], []
    # "loop": further settings by the specs' field names (for example the search's: mesh, warm_start,
    # screening), and "workers"
    kw = {"effects": "auto", "max_iterations": settings["max_iterations"], "max_rounds": settings["max_rounds"],
          **settings.get("loop", {})}
    workers = kw.pop("workers", 1)

    def closing(seq, **change):
        return closing_the_loop(seq, *specs_from(**{**kw, **change}), workers=workers)
    # "truth_element_px": draw the motion on a polar mesh that fine, sampled at the pixels (every
    # estimator's mesh then pays its discretisation error); None: on the node-per-pixel mesh
    fine = settings.get("truth_element_px")
    annulus_sequence = functools.partial(_annulus_sequence, truth_element_px=fine)
    if "scale" in settings["cases"]:
        mesh = prepare(annulus_sequence(None, n_frames=4), 8, **({} if fine is None else
                                                                 {"mesh": "polar", "element_px": fine})).mesh
        for E in (5.0, 30.0, 100.0):
            mat = Material.uniform(mesh.n_elements, E * 1e3, NOMINAL["nu"])
            seq = annulus_sequence(None, seed=0, drive="pressure", material=mat, peak_pressure=2e3 * E / 10,
                                   n_frames=frames)
            out = closing(seq, drive="pressure", max_iterations=max(80, kw["max_iterations"]))
            m = out.baseline.metrics
            rows.append(_row(f"pressure drive, E = {E:g} kPa", out, "none", level_kPa=m["E_level_kPa"],
                             level_kPa_95=list(m["E_level_kPa_95"]), true_level_kPa=E))
    if "two" in settings["cases"]:
        for label, amps in (("polar (0.15, -0.3) + helical 0.3", ((0.15, -0.3), (0.0, 0.3))),
                            ("polar (0.1, -0.2) + helical 0.6", ((0.1, -0.2), (0.0, 0.6)))):
            seq = annulus_sequence(["active_polar", "active_helical"], amplitude=amps, seed=0, n_frames=frames)
            rows.append(_row(label, closing(seq), "active_polar, active_helical"))
    if "akinetic" in settings["cases"]:
        amp = np.tile([0.15, -0.3], 6)
        amp[[4, 5]] = 0.0
        seq = annulus_sequence("active_segments", amplitude=tuple(amp), seed=0, n_frames=frames)
        rows.append(_row("active_segments, segment 2 akinetic", closing(seq), "active_segments"))
    if "clean" in settings["cases"]:
        for seed in settings["seeds"]:
            out = closing(annulus_sequence(None, seed=seed, n_frames=frames))
            rows.append(_row(f"no effect, seed {seed}", out, "none"))
    return {"rows": rows}


def markdown(results: dict) -> str:
    cols = ["case", "truth", "final effects", "steps", "stop", "NIS / dof", "held-out [px]", "spline [px]",
            "stiffness level [kPa] (95%)"]
    body = [[r["case"], r["truth"], ", ".join(r["effects"]) or "none", "; ".join(r["steps"]) or "-", r["stop"],
             fmt(r["nis_over_dof"], ".3f"), fmt(r["heldout_rmse_px"], ".3f"), fmt(r["spline_rmse_px"], ".3f"),
             (f"{r['level_kPa']:.2f} ({r['level_kPa_95'][0]:.2f}-{r['level_kPa_95'][1]:.2f})"
              if "level_kPa" in r else "")] for r in results["rows"]]
    return md_table(cols, body) + "\n\nSteps: what each round added, removed or corrected after the baseline."


def check(results: dict, tier: str) -> list:
    """Figures finite and positive; in the full tier, no effect added to clean data in at least 3 of
    4 seeds and every stiffness level's 95% interval holding the true level."""
    problems = [f"{r['case']}: {k} {r[k]}" for r in results["rows"] for k in ("nis_over_dof", "heldout_rmse_px")
                if not (r[k] is not None and r[k] > 0)]
    if tier == "full":
        clean = [r for r in results["rows"] if r["case"].startswith("no effect")]
        if sum(not r["effects"] for r in clean) < len(clean) - 1:
            problems.append("effects added to clean data in more than one seed")
        for r in results["rows"]:
            if "level_kPa_95" in r and not r["level_kPa_95"][0] <= r["true_level_kPa"] <= r["level_kPa_95"][1]:
                problems.append(f"{r['case']}: level interval {r['level_kPa_95']} misses {r['true_level_kPa']}")
    return problems
