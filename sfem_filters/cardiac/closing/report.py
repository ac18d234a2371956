"""The text report of :func:`~sfem_filters.cardiac.closing.rounds.closing_the_loop` (and its lengths
in the sequence's units)."""
from __future__ import annotations

import re

import numpy as np

from ..measured import equivalent_eigenstrain
from ..specs import ModelSpec
from .records import LoopResult

__all__ = ["format_report", "length_display", "not_converged_note"]


def _variant(js: dict) -> ModelSpec:
    """The model of a round's JSON (:meth:`~sfem_filters.cardiac.specs.ModelSpec.as_json`; the set-up's
    fields at their defaults)."""
    return ModelSpec(tuple(js["effects"]), drive=js["drive"], drive_trend=js["drive_trend"],
                     effect_rates=js["effect_rates"], process_scale=js["process_scale"],
                     spring_scale=js["spring_scale"], material=js.get("material"))


def _round_label(r: dict) -> str:
    """A round's label in the report: its number, with ``-`` for a backward step."""
    return f"{r['round']}-" if r.get("removed") else str(r["round"])


_VERSUS_LENGTHS = ("difference", "low", "high", "se", "rmse_a", "rmse_b")


def _lengths_scaled(value, factor: float, length: bool = False, versus: bool = False):
    """The report with every length multiplied by ``factor``: the values (and lists of values)
    of keys with ``_px`` in their name, and the ``difference``, ``low`` and ``high`` of a
    ``versus_spline`` entry (``difference``, ``low``, ``high``, ``se``, ``rmse_a``, ``rmse_b``)."""
    if isinstance(value, dict):
        return {k: _lengths_scaled(v, factor, length or "_px" in k or (versus and k in _VERSUS_LENGTHS),
                                   versus or k.startswith("versus_spline"))
                for k, v in value.items()}
    if isinstance(value, list):
        return [_lengths_scaled(v, factor, length, versus) for v in value]
    if length and isinstance(value, (int, float)) and not isinstance(value, bool):
        return value * factor
    return value


def length_display(units: str) -> tuple:
    """``(label, factor)`` to show lengths of a sequence with ``units`` ("px" or "m"): pixels as
    they are, metres in millimetres (``value * factor`` in ``label``)."""
    if units not in ("px", "m"):
        raise ValueError(f"units: expected 'px' or 'm', got {units!r}")
    return ("mm", 1e3) if units == "m" else ("px", 1.0)


def _number(value, width: int) -> str:
    """A report's figure to 3 decimals, or '-' where it is undefined (None or not finite)."""
    return f"{'-':>{width}}" if value is None or not np.isfinite(value) else f"{value:>{width}.3f}"


def not_converged_note(report: dict) -> str:
    """What a report's reader must know when its baseline or final fit stopped short of the stop
    rule (empty when both converged): which, and what to rerun with. ``report``:
    :meth:`LoopResult.as_json`."""
    cfg = report["config"]
    which = [key for key in ("baseline", "extended") if not report[key]["converged"]]
    if not which:
        return ""
    smoother = cfg["estimator"] == "smoother"
    limit = cfg.get("max_iterations") if smoother else cfg.get("max_loops")
    names = " and the ".join("final model" if k == "extended" else k for k in which)
    option = "--max-iterations" if smoother else "--max-loops"
    stuck = [k for k in which if report[k].get("stop_reason") == "damping"]
    why = (f"stopped at the limit of {limit} {'iterations' if smoother else 'loops'}" if not stuck else
           "stopped where no damping of the step lowered the MAP cost" if len(stuck) == len(which) else
           "stopped at the iteration limit or where no damping lowered the MAP cost")
    return (f"the {names} {why} before the material met the stop rule: the material, its sds, intervals and prior "
            f"check are where the fit stopped, not the posterior's" + (f"; rerun with a larger {option}" if not stuck
                                                                        else ""))


def format_report(result: "LoopResult") -> str:
    """Text summary of :func:`closing_the_loop`.

    Lengths are in pixels; a sequence in metres (``units = "m"``) is reported in millimetres
    (:func:`length_display`).
    """
    report = result.as_json()
    label, factor = length_display(report["length_unit"])
    if factor != 1.0:
        report = _lengths_scaled(report, factor)
        return re.sub(r"\bpx\b", label, _format_report(report))
    return _format_report(report)


def _format_report(report: dict) -> str:
    b, e = report["baseline"], report["extended"]
    cfg = report["config"]
    lines = [f"{cfg['n_points']} points, {cfg['n_frames']} frames; mesh {cfg['mesh_nodes']} nodes, "
             f"{cfg['mesh_elements']} triangles ({cfg.get('mesh', 'delaunay')}"
             + (f", edges ~{cfg['element_px']:g} px" if cfg.get("element_px") else "")
             + f"); {cfg['n_observed']} observed, {cfg['n_heldout']} held out "
             f"({cfg['landmarks']} landmarks per contour"
             + (f" from {cfg['angle_origin_deg']:g} deg" if cfg.get("angle_origin_deg", 0.0) else "")
             + f", observe {cfg['observe']}, drive {cfg['drive']}, "
             f"material {cfg['parameterisation']}, estimator {cfg['estimator']}"
             + (", fits warm-started" if cfg.get("warm_start") else "")
             + (f", screened with {cfg['screen_iterations']} iterations" if cfg.get("screen_iterations") else "")
             + ")",
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
    crit = ("log p(y) rises" if cfg.get("criterion", "evidence") == "evidence"
            else f"the {cfg['folds']}-fold cross-validation error over the observed points falls")
    lines += ["", f"rounds (each adds the best significant candidate while {crit}"
              + ("; a row numbered k- is a backward step after round k, taking out the term whose removal "
                 "improves it most" if cfg.get("prune") else "") + f"; CV: {cfg.get('folds')}-fold "
              "cross-validation over the observed points, material at the fit's estimate; held-out points "
              "untouched until here):",
              f"  {'round':<6}{'model':<44}{'score':>8}{'need':>7}{'dlogp(y)':>10}{'NIS/dof':>9}{'lag-1':>7}"
              f"{'CV':>7}{'held-out':>9}{'radial':>8}{'circ.':>8}{'+spline':>9}"]
    previous = None
    for r in report["rounds"]:
        tried = {t["effect"]: t for t in r["tried"]}
        t = tried.get(r["added"], {})
        score = (f"{t['score']:.1f}" + ("t" if t.get("test") == "time courses" else "")
                 if t.get("score") is not None else "-")
        need = f"{r['threshold']:.1f}" if r["threshold"] is not None else "-"
        gain = (f"{t['evidence_gain']:+.1f}" if "evidence_gain" in t else
                f"{r['log_evidence'] - previous['log_evidence']:+.1f}" if r.get("removed") else "-")
        label = _variant(r).label(cfg["drive"])
        cv = f"{r['cross_validation']['rmse_px']:.3f}" if r.get("cross_validation") else "-"
        previous = r
        lines.append(f"  {_round_label(r):<6}{label:<44}{score:>8}{need:>7}{gain:>10}"
                     f"{r['nis_mean_over_dof']:>9.3f}{r['innovation_lag1_autocorrelation']:>7.3f}{cv:>7}"
                     f"{r['heldout_rmse_px']:>9.3f}{r['heldout_rmse_radial_px']:>8.3f}"
                     f"{r['heldout_rmse_circumferential_px']:>8.3f}{r['residual_spline']['heldout_rmse_px']:>9.3f}")
    ref = report["spline_reference"]
    cv = f"{ref['cross_validation']['rmse_px']:.3f}" if ref.get("cross_validation") else "-"
    lines.append(f"  {'-':<6}{'thin-plate spline, no physics':<44}{'':>8}{'':>7}{'':>10}{'':>9}{'':>7}{cv:>7}"
                 f"{ref['heldout_rmse_px']:>9.3f}{ref['heldout_rmse_radial_px']:>8.3f}"
                 f"{ref['heldout_rmse_circumferential_px']:>8.3f}")
    lines.append("  (+spline: held-out RMSE of the model plus a thin-plate spline of its residual at the observed "
                 "points; below the spline's only where the physics adds what interpolation misses)")
    vs = [(_round_label(r), r.get("versus_spline")) for r in report["rounds"] if r.get("versus_spline")]
    if vs:
        first = vs[0][1]
        lines.append(f"  held-out RMSE minus the spline's [px], {100 * first['model']['level']:.0f}% interval (jackknife over "
                     f"{first['sectors']} angular sectors of the held-out points; negative: better than the spline):")
        for k, v in vs:
            m, p = v["model"], v["model_plus_spline"]
            lines.append(f"    round {k}: model {m['difference']:+.3f} ({m['low']:+.3f} to {m['high']:+.3f}), "
                         f"+spline {p['difference']:+.3f} ({p['low']:+.3f} to {p['high']:+.3f})")
    if any(t.get("test") == "time courses" for r in report["rounds"] for t in r["tried"]):
        lines.append("  (t: score of the test with amplitudes tied to the current effects' time courses)")
    for r in report["rounds"]:
        if r.get("backward"):
            steps = ", ".join(f"{b['removed']} {b['evidence_gain']:+.1f}"
                              + (f" (CV {b['cv_rmse_px']:.3f})" if "cv_rmse_px" in b else "")
                              + (" (taken out)" if b["accepted"] else "") for b in r["backward"])
            lines.append(f"  backward steps from round {_round_label(r)} "
                         f"(term taken out: gain in log p(y), nats"
                         + ("; CV over the observed points, px" if any("cv_rmse_px" in b for b in r["backward"]) else "")
                         + f"): {steps}")
    att = report["last_attempt"]
    rejected = [f"{t['effect']} ({t['evidence_gain']:+.1f} nats" + (f", CV {t['cv_rmse_px']:.3f} px)" if "cv_rmse_px" in t
                                                                  else ")")
                for t in att["tried"] if not t["accepted"]]
    lines.append(f"  stopped: {report['stop_reason']}" + (
        f" (needed score > {att['threshold']:.1f}; best left "
        f"{att['ranking'][0]['effect']} {att['ranking'][0]['score']:.1f})" if att["ranking"] else "")
        + (f"; fitted and rejected: {', '.join(rejected)}" if rejected else ""))
    final = report["rounds"][-1]
    lines += ["", "final model: " + _variant(final).label(cfg["drive"]),
              f"{'':<34}{'baseline':>12}{'final':>18}"]
    for key, label in (("heldout_rmse_px", "held-out RMSE [px]"), ("heldout_rmse_radial_px", "  radial [px]"),
                       ("heldout_rmse_circumferential_px", "  circumferential [px]"),
                       ("heldout_rmse_worst_frame_px", "  worst frame [px]"),
                       ("innovation_rms_px", "innovation RMS [px]"), ("nis_mean_over_dof", "mean NIS / dof (1 = consistent)"),
                       ("nis_fraction_outside_95", "frames outside 95% NIS band"),
                       ("innovation_lag1_autocorrelation", "innovation lag-1 autocorrelation"),
                       ("nis_z", "NIS z (|z| > 3: inconsistent)"), ("lag1_z", "whiteness z (|z| > 3: correlated)"),
                       ("shear_strain_rms_peak_model", "2 E_rc at peak, RMS (model)"),
                       ("shear_strain_error_rms_peak", "  error vs measured, RMS"),
                       ("shear_strain_correlation_peak", "  correlation with measured")):
        lines.append(f"{label:<34}{_number(b[key], 12)}{_number(e[key], 18)}")
        if key == "heldout_rmse_circumferential_px":
            lines.append(f"{'  model + spline of its residual':<34}{b['residual_spline']['heldout_rmse_px']:>12.3f}"
                         f"{e['residual_spline']['heldout_rmse_px']:>18.3f}")
    lines.append(f"{'2 E_rc at peak, RMS (measured)':<34}{report['measured']['shear_strain_rms_peak']:>12.3f}")
    for key, col in (("baseline", b), ("extended", e)):
        if col.get("absolute_stiffness"):
            lo, hi = col["E_level_kPa_95"]
            lines.append(f"stiffness level ({key}): {col['E_level_kPa']:.2f} kPa (95%: {lo:.2f}-{hi:.2f} kPa), "
                         "set by the measured pressure" + ("" if col["converged"] else
                                                            "; NOT CONVERGED (*): not the posterior's interval"))
    if b.get("measurement_noise_scale") is not None and e.get("measurement_noise_scale") is not None:
        lines.append(f"{'measurement noise sd / floor (ML)':<34}{np.sqrt(b['measurement_noise_scale']):>12.3f}"
                     f"{np.sqrt(e['measurement_noise_scale']):>18.3f}")
    smoother = cfg["estimator"] == "smoother"
    label = "iterations (* not converged)" if smoother else "loops (* material not converged)"
    lines.append(f"{label:<34}"
                 + "".join(f"{str(r['loops']) + ('' if r['converged'] else '*'):>{w}}" for r, w in ((b, 12), (e, 18))))
    note = not_converged_note(report)
    if note:
        lines.append(f"  * {note}")
    if b.get("material_drift_sd") is not None and e.get("material_drift_sd") is not None:
        label = "last material step / sd" if smoother else "last loop material step / sd"
        lines.append(f"{label:<34}{b['material_drift_sd']:>12.3f}{e['material_drift_sd']:>18.3f}")
    if b.get("E_sd_log_median") is not None and e.get("E_sd_log_median") is not None:
        lines.append(f"{'posterior sd of log E (median)':<34}{b['E_sd_log_median']:>12.3f}{e['E_sd_log_median']:>18.3f}")
        lines.append(f"{'posterior sd of nu (median)':<34}{b['nu_sd_median']:>12.3f}{e['nu_sd_median']:>18.3f}")
    if cfg.get("laplace") == "exact" and e.get("material_covariance") is not None:
        x = e.get("exact_laplace") or {}
        lines.append("final material covariance: " + ("the exact Laplace (inverse exact Hessian of the MAP cost)"
                                                      if e["material_covariance"] == "exact" else
                                                      "Gauss-Newton (the exact Hessian is not positive definite)"))
        if x:
            lo, hi = x["relative_eigenvalues"]
            line = f"  exact Hessian / Gauss-Newton: eigenvalues {lo:.3f} to {hi:.3f} ({x['gradient_passes']} gradient passes)"
            if x["E_sd_log_ratio"] is not None:
                line += ("; sd exact / Gauss-Newton: log E {:.2f}-{:.2f}, nu {:.2f}-{:.2f}"
                         .format(*x["E_sd_log_ratio"], *x["nu_sd_ratio"]))
            lines.append(line)
    if b.get("prior_conflict") and e.get("prior_conflict"):
        lines.append(f"{'material vs its prior, -log10 p':<34}{max(0.0, -b['prior_conflict']['log10_p']):>12.1f}"
                     f"{max(0.0, -e['prior_conflict']['log10_p']):>18.1f}")
        for key, pc in (("baseline", b["prior_conflict"]), ("final", e["prior_conflict"])):
            if pc["flagged"]:
                items = "; ".join(f"{f['quantity']} in {f['where']} "
                                  + (f"(E x {f['estimate']:.3g}" if f["quantity"] == "log E" else f"(nu {f['estimate']:.3f}")
                                  + f", z {f['z']:+.1f})" for f in pc["flagged"][:3])
                lines.append(f"  prior-data conflict, {key} ({pc['n_flagged']} beyond |z| {pc['threshold']:.1f}): {items}")
    if b.get("strain_sd_median") is not None and e.get("strain_sd_median") is not None:
        for k, name in enumerate(("E_rr", "E_cc", "2 E_rc")):
            lines.append(f"{'strain sd ' + name + ' (median)':<34}{b['strain_sd_median'][k]:>12.4f}"
                         f"{e['strain_sd_median'][k]:>18.4f}")
    if "active_polar[0]" in e.get("effect_state_names", []):
        offset = e["effect_state_names"].index("active_polar[0]")
        st = np.array(e["effect_states"])[:, offset:offset + 2]
        peak = int(np.argmax(np.abs(st[:, 1])))
        eps = equivalent_eigenstrain(st[peak])
        lines.append(f"active_polar at frame {peak}: a_c = {st[peak, 0]:.3f}, a_r = {st[peak, 1]:.3f} (x E0), "
                     f"equivalent eigenstrain eps_cc = {eps[0]:+.3f}, eps_rr = {eps[1]:+.3f}")
    return "\n".join(lines)
