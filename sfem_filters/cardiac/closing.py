"""Closing the loop on measured data: residual diagnosis, missing effects, before and after.

Step 5 of the paper's section 3.2 workflow, on top of :mod:`sfem_filters.cardiac.measured`:
the baseline model's innovations are scored against a catalogue of candidate missing effects
(:mod:`sfem_filters.cardiac.effects`, a score test per candidate), the chosen effects are added
and the model is run again; :func:`closing_the_loop` returns both runs, the ranking and what
the data themselves say about the wall as a :class:`LoopResult`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..filtering import diagnostics
from .effects import CATALOGUE, build_effects
from .measured import (NOMINAL, Run, Setup, equivalent_eigenstrain, measured_wall_kinematics, prepare, run)
from .sequence import Sequence

__all__ = ["LoopResult", "closing_the_loop", "candidate_loads", "format_report"]


def candidate_loads(setup: Setup, names=None) -> list:
    """(name, load matrix) of every catalogue effect, for scoring."""
    names = sorted(CATALOGUE) if names is None else names
    effs = build_effects(names, setup.mesh, setup.geometry, scale=NOMINAL["E"])
    return [(e.name, e.loads) for e in effs]


@dataclass(eq=False)
class LoopResult:
    """Outcome of :func:`closing_the_loop`.

    Attributes
    ----------
    setup : Setup
        Mesh, geometry and the observed / held-out split.
    baseline, extended : Run
        The run without effects and the run with :attr:`effects` (the same run when none).
    effects : list of str
        The effects added.
    ranking : list of dict
        Score test of every candidate on the baseline innovations, best first.
    measured : dict
        What the data say about the wall (:func:`sfem_filters.cardiac.measured.measured_wall_kinematics`).
    config : dict
        The settings of the workflow.
    """

    setup: Setup
    baseline: Run
    extended: Run
    effects: list
    ranking: list
    measured: dict
    config: dict

    def as_json(self) -> dict:
        """The report as plain JSON-able values (the ``--json`` file of ``sfem-filters dense``)."""
        setup = self.setup
        return {
            "noise_floor_px": setup.noise_px,
            "measured": self.measured,
            "nominal": {k: NOMINAL[k] for k in setup.nominal},
            "config": dict(self.config),
            "baseline": self.baseline.metrics,
            "extended": {"effects": list(self.effects), **self.extended.metrics},
            "ranking": [{"effect": r["effect"], "score": r["score"], "lm": r["lm"], "df": r["df"],
                         "explained": r["explained"]} for r in self.ranking],
        }


def closing_the_loop(seq: Sequence, effects="auto", drive: str = "penalty", landmarks: int = 8,
                     observe: str = "boundary", holdout_seed: int = 0, parameterisation: str = "region",
                     max_loops: int = 5, progress: bool = False) -> LoopResult:
    """Baseline run, residual diagnostics, effect ranking, extended run: the whole loop.

    Parameters
    ----------
    effects : "auto", "none" or a sequence of effect names
        ``auto`` adds the effect the score test ranks first.
    drive, parameterisation : str
        See :func:`sfem_filters.cardiac.measured.build_model`.
    landmarks, observe, holdout_seed :
        See :func:`sfem_filters.cardiac.measured.prepare`.
    max_loops : int
        Cyclic loop limit of each run.
    """
    setup = prepare(seq, landmarks, observe, holdout_seed)
    base = run(setup, (), drive, parameterisation, max_loops, progress=progress, name="baseline")
    ranking = diagnostics.rank_effects(base.model, base.result.history, candidate_loads(setup))
    if isinstance(effects, str):
        if effects == "auto":
            chosen = [ranking[0]["effect"]]
        elif effects == "none":
            chosen = []
        else:
            chosen = [e.strip() for e in effects.split(",") if e.strip()]
    else:
        chosen = list(effects)
    ext = run(setup, chosen, drive, parameterisation, max_loops, progress=progress, name="extended") \
        if chosen else base
    config = {"drive": drive, "landmarks": landmarks, "observe": observe, "holdout_seed": holdout_seed,
              "parameterisation": parameterisation, "max_loops": max_loops, "n_points": int(seq.n_points),
              "n_frames": int(seq.n_frames), "n_observed": int(len(setup.observed)),
              "n_heldout": int(len(setup.heldout)), "mesh_nodes": int(setup.mesh.n_nodes),
              "mesh_elements": int(setup.mesh.n_elements)}
    return LoopResult(setup=setup, baseline=base, extended=ext, effects=chosen, ranking=ranking,
                      measured=measured_wall_kinematics(setup), config=config)


def format_report(result: "LoopResult") -> str:
    """Text summary of :func:`closing_the_loop`."""
    report = result.as_json()
    b, e = report["baseline"], report["extended"]
    cfg = report["config"]
    lines = [f"{cfg['n_points']} points, {cfg['n_frames']} frames; mesh {cfg['mesh_nodes']} nodes, "
             f"{cfg['mesh_elements']} triangles; {cfg['n_observed']} observed, {cfg['n_heldout']} held out "
             f"({cfg['landmarks']} landmarks per contour, observe {cfg['observe']}, drive {cfg['drive']}, "
             f"material {cfg['parameterisation']})",
             f"noise floor {report['noise_floor_px']:.3f} px" + (
                 f"; nominal (not in the file): {report['nominal']}" if report["nominal"] else ""),
             "data: wall area x{w:.3f} and wall thickness {t0:.2f} -> {tp:.2f} px at frame {f} (peak area); mean strain "
             "there E_rr {er:+.3f}, E_cc {ec:+.3f} (w.r.t. frame 0); frame 0 displacement RMS {r0:.2f} px, last-to-first "
             "{rl:.2f} px".format(w=report["measured"]["wall_area_ratio_peak"], t0=report["measured"]["wall_thickness_px_frame0"],
                                  tp=report["measured"]["wall_thickness_px_peak"], f=report["measured"]["peak_frame"],
                                  er=report["measured"]["mean_radial_strain_peak"],
                                  ec=report["measured"]["mean_circumferential_strain_peak"],
                                  r0=report["measured"]["frame0_displacement_rms_px"],
                                  rl=report["measured"]["last_to_first_rms_px"]),
             "", "ranking of candidate effects (score test on the baseline innovations; -log10 p, higher = stronger):"]
    for r in report["ranking"]:
        lines.append(f"  {r['effect']:<24} {r['score']:9.1f}   LM = {r['lm']:9.1f} on {r['df']:3d} dof, "
                     f"explains {100 * r['explained']:5.1f}% of the NIS")
    lines += ["", f"{'':<34}{'baseline':>12}{'extended':>18}", f"{'effects':<34}{'none':>12}{','.join(e['effects']) or 'none':>18}"]
    for key, label in (("heldout_rmse_px", "held-out RMSE [px]"), ("heldout_rmse_radial_px", "  radial [px]"),
                       ("heldout_rmse_circumferential_px", "  circumferential [px]"),
                       ("heldout_rmse_worst_frame_px", "  worst frame [px]"),
                       ("innovation_rms_px", "innovation RMS [px]"), ("nis_mean_over_dof", "mean NIS / dof (1 = consistent)"),
                       ("nis_fraction_outside_95", "frames outside 95% NIS band"),
                       ("innovation_lag1_autocorrelation", "innovation lag-1 autocorrelation"),
                       ("nis_z", "NIS z (|z| > 3: inconsistent)"), ("lag1_z", "whiteness z (|z| > 3: correlated)")):
        lines.append(f"{label:<34}{b[key]:>12.3f}{e[key]:>18.3f}")
    lines.append(f"{'loops (* material not converged)':<34}"
                 + "".join(f"{str(r['loops']) + ('' if r['converged'] else '*'):>{w}}" for r, w in ((b, 12), (e, 18))))
    if b.get("material_drift_sd") is not None and e.get("material_drift_sd") is not None:
        lines.append(f"{'last loop material step / sd':<34}{b['material_drift_sd']:>12.3f}{e['material_drift_sd']:>18.3f}")
    if "active_polar[0]" in e.get("effect_state_names", []):
        offset = e["effect_state_names"].index("active_polar[0]")
        st = np.array(e["effect_states"])[:, offset:offset + 2]
        peak = int(np.argmax(np.abs(st[:, 1])))
        eps = equivalent_eigenstrain(st[peak])
        lines.append(f"active_polar at frame {peak}: a_c = {st[peak, 0]:.3f}, a_r = {st[peak, 1]:.3f} (x E0), "
                     f"equivalent eigenstrain eps_cc = {eps[0]:+.3f}, eps_rr = {eps[1]:+.3f}")
    return "\n".join(lines)
