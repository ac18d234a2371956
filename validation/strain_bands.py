"""What the DENSE route's bands can and cannot see: their error model against the truth, and the tracks' share.

The route's 95% bands (:mod:`sfem_filters.cardiac.strain_bands`) add to the smoother's variance an
excess-error variance ``tau_t^2 = tau0^2 + k^2 m_t^2`` whose two parameters are fitted by moments to
the curve's disagreement with the unsmoothed finite-difference strain of the same tracks. This claim
asks, on every given DENSE-Sim case, both SNRs and three seeds (the strain page's runs,
:mod:`validation.strain_dense_sim`: the spec's noise, :func:`sfem_filters.cardiac.dense_case_strain`
with :func:`sfem_filters.cardiac.image_settings`), two questions of the six segment curves:

1. **Is the form right?** The same two parameters fitted instead to the estimate's true error (the
   same moment equations, :func:`sfem_filters.cardiac.strain_bands.discrepancy_variance`, with the
   truth in place of the tracks and the smoother's own variance in place of the tracks' noise):
   the coverage of the truth by bands of that form is what the form can do when its parameters
   are right. Not a method (it reads the truth); a yardstick for the one that does not.
2. **Can the tracks see the error?** Around each segment's true peak (the peak frame and
   :data:`HALF_WINDOW` frames each side), the mean error of the estimate's curve and that of the
   reference the route measured its excess error against (the curves' ``*_reference``: the tracks'
   unsmoothed finite-difference strain, with the acquisition's blur compensated as the route
   compensates it): when their difference (the disagreement itself) is much smaller than the
   estimate's error, that error is the reference's own too, and no moment of the disagreement can
   see it.

Reported per case and SNR, means over the seeds (strain in percentage points): the segment curves'
RMS error, the bands' RMS sd (total, and the smoother's own), the route's coverage (and the coverage of
the same bands with the six segments' pooled excess, the route's rule before the partial pooling:
before and after from one run), the fitted
``tau0`` and ``k`` of the route (RMS over its six segments, with the mean weight of the segments'
own fits against their pooled one, :func:`sfem_filters.cardiac.strain_route.curve_discrepancy`) and
of the truth, the coverage with the truth's parameters, and the
near-peak RMS errors of the estimate, of the reference and of their difference. Quick tier: the
phantom's first 8 frames, SNR 30, seed 0.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from sfem_filters.cardiac import dense_case_strain, image_settings
from sfem_filters.cardiac.strain_bands import discrepancy_variance
from sfem_filters.imaging import (add_complex_noise, phase_to_displacement, read_dense_sim, segment_curves,
                                  truth_at_points)
from sfem_filters.imaging.strain import Z95

from ._core import fmt, md_table
from .strain_dense_sim import _truncated, case_folders

NAME = "strain_bands"
NEEDS_DATA = True
TITLE = "What the DENSE route's bands can see: their error model against the truth"
FULL_COST = "about 15 minutes on 2 cores (12 runs of the route)"
TIERS = {"quick": {"cases": ["phantom_subject_1"], "snr": [30.0], "seeds": [0], "frames": 8, "figure": False},
         "full": {"cases": None, "snr": [30.0, 8.0], "seeds": [0, 1, 2], "frames": None, "figure": True}}
FIGURE = "strain_bands.png"
#: The issue's goal for the band coverage of the segment-frames (percent).
COVERAGE_GOAL = (85.0, 99.0)
TOLERANCES = {"*": (1e-6, 1e-9), "seconds": None}
#: Frames each side of a segment's true peak in the near-peak means.
HALF_WINDOW = 3
PCT = 100.0
QUANTITIES = {"Ecc": np.argmin, "Err": np.argmax}
FIELDS = ("error_rms", "sd_rms", "sd_model_rms", "coverage_pct", "coverage_pct_pooled", "tau0", "k", "own_weight",
          "tau0_truth", "k_truth",
          "coverage_pct_truth_fit", "near_peak_error_rms", "near_peak_reference_error_rms", "near_peak_difference_rms")


def _coverage(m, sd, truth) -> float:
    ok = np.isfinite(truth) & np.isfinite(m) & np.isfinite(sd)
    return float(PCT * np.mean(np.abs(truth - m)[ok] <= Z95 * sd[ok]))


def _near_peak_means(err, truth, peak) -> np.ndarray:
    """(S,) mean of ``err`` (S, F) over the frames within HALF_WINDOW of each segment's true peak."""
    out = np.full(len(err), np.nan)
    for g in range(len(err)):
        if np.all(np.isnan(truth[g])):
            continue
        fill = np.inf if peak is np.argmin else -np.inf
        p = int(peak(np.where(np.isfinite(truth[g]), truth[g], fill)))
        out[g] = np.nanmean(err[g, max(p - HALF_WINDOW, 0):p + HALF_WINDOW + 1])
    return out


def quantity_row(q, route, truth_curves) -> dict:
    """One quantity's metrics (module docstring) from the route's result and the true segment curves."""
    seg = route.segment_curves
    m, sd, sd_model = (np.asarray(seg[k], float) for k in (q, f"{q}_sd", f"{q}_sd_model"))      # (6, F)
    t = np.asarray(truth_curves, float)
    e = m - t
    ok = np.isfinite(e) & np.isfinite(sd_model)
    tau0_2, k2 = discrepancy_variance(-e[ok], m[ok], sd_model[ok] ** 2)
    fitted = np.sqrt(sd_model ** 2 + tau0_2 + k2 * m ** 2)
    disc = route.settings["discrepancy_sd"][q]
    seg_tau = np.asarray(disc["segments"], float)                                    # (6, 2): tau0, k per segment
    tau0, k = np.sqrt(np.mean(seg_tau ** 2, axis=0))
    p0, pk = np.asarray(disc["segments_pooled"], float)
    pooled_sd = np.sqrt(sd_model ** 2 + p0 ** 2 + pk ** 2 * m ** 2)
    e_near = _near_peak_means(e, t, QUANTITIES[q])
    tr_near = _near_peak_means(np.asarray(seg[f"{q}_reference"], float) - t, t, QUANTITIES[q])

    def rms(a):
        return float(np.sqrt(np.nanmean(np.asarray(a, float) ** 2)))
    return {"error_rms": PCT * rms(e), "sd_rms": PCT * rms(sd), "sd_model_rms": PCT * rms(sd_model),
            "coverage_pct": _coverage(m, sd, t), "tau0": PCT * float(tau0), "k": float(k),
            "own_weight": float(np.mean(disc["segment_weights"])), "coverage_pct_pooled": _coverage(m, pooled_sd, t),
            "tau0_truth": PCT * float(np.sqrt(tau0_2)), "k_truth": float(np.sqrt(k2)),
            "coverage_pct_truth_fit": _coverage(m, fitted, t), "near_peak_error_rms": PCT * rms(e_near),
            "near_peak_reference_error_rms": PCT * rms(tr_near),
            "near_peak_difference_rms": PCT * rms(e_near - tr_near)}


def run_case(folder, snr: float, seed: int, frames=None) -> list:
    """The route and the tracks' own strain on one case, SNR and seed: a row per quantity."""
    case = _truncated(read_dense_sim(folder), frames)
    t_ecc, t_err = truth_at_points(case)
    noisy = add_complex_noise(case, snr, seed)
    tracks = phase_to_displacement(noisy)
    t0 = time.perf_counter()
    r = dense_case_strain(noisy, image_settings(noisy), tracks=tracks)
    seconds = time.perf_counter() - t0
    rows = []
    for q, truth in (("Ecc", t_ecc), ("Err", t_err)):
        row = quantity_row(q, r, segment_curves(truth, r.labels))
        rows.append({"case": folder.name, "snr": snr, "seed": seed, "quantity": q, "seconds": seconds, **row})
    print(f"  {NAME}: {folder.name} SNR {snr:g} seed {seed}: {seconds:.0f} s", flush=True)
    return rows


def compute(settings: dict, out_dir) -> dict:
    rows = [row for folder in case_folders(settings["cases"]) for snr in settings["snr"]
            for seed in settings["seeds"] for row in run_case(folder, snr, seed, settings.get("frames"))]
    out = {"rows": rows, "half_window_frames": HALF_WINDOW,
           "units": "strain in percentage points, k dimensionless, coverage in percent of segment-frames"}
    if settings.get("figure"):
        out["figure"] = figure(rows, out_dir / FIGURE)
    return out


def figure(rows, path) -> str:
    """Per quantity, for each case and SNR: the coverage of the route's bands (seeds' range as a bar), of the
    pooled rule's and of the truth-fitted form's, against the goal; and the near-peak errors."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    means = mean_rows(rows)
    groups = list(dict.fromkeys((r["case"], r["snr"]) for r in means))
    labels = [f"{c.split('_')[0]}\nSNR {snr:g}" for c, snr in groups]
    x = np.arange(len(groups))
    fig, axes = plt.subplots(2, 2, figsize=(10.5, 6.6), constrained_layout=True)
    for col, q in enumerate(QUANTITIES):
        ax = axes[0, col]
        ax.axhspan(*COVERAGE_GOAL, color="0.88", label="goal 85-99%")
        rules = (("coverage_pct", "route (partially pooled)", "C0", -0.22),
                 ("coverage_pct_pooled", "segments pooled (before)", "C1", 0.0),
                 ("coverage_pct_truth_fit", "form fitted to the truth", "C2", 0.22))
        for k, (key, name, colour, dx) in enumerate(rules):
            vals = [[r[key] for r in rows if (r["case"], r["snr"]) == g and r["quantity"] == q] for g in groups]
            mean = np.array([np.mean(v) for v in vals])
            lo, hi = mean - np.array([min(v) for v in vals]), np.array([max(v) for v in vals]) - mean
            ax.errorbar(x + dx, mean, yerr=[lo, hi], fmt="o", color=colour, capsize=3, label=name)
        ax.set_xticks(x, labels)
        ax.set_ylabel("segment-frames inside the 95% band [%]")
        ax.set_title(f"{q}: band coverage (mean, seeds' range)")
        ax.grid(alpha=0.3, axis="y")
        ax = axes[1, col]
        for k, (key, name, colour) in enumerate((("near_peak_error_rms", "our error", "C0"),
                                                 ("near_peak_reference_error_rms", "the reference's error", "C3"),
                                                 ("near_peak_difference_rms", "their difference", "0.5"))):
            vals = [next(r[key] for r in means if (r["case"], r["snr"]) == g and r["quantity"] == q) for g in groups]
            ax.bar(x + (k - 1) * 0.26, vals, width=0.26, color=colour, label=name)
        ax.set_xticks(x, labels)
        ax.set_ylabel("RMS over segments [percentage points]")
        ax.set_title(f"{q}: error near each segment's true peak (+-{HALF_WINDOW} frames)")
        ax.set_ylim(0, 1.3 * ax.get_ylim()[1])
        ax.grid(alpha=0.3, axis="y")
    axes[0, 0].legend(fontsize=8, loc="lower left")
    axes[1, 0].legend(fontsize=8, loc="upper center", ncol=3)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path).name


def mean_rows(rows) -> list:
    """Per case, SNR and quantity: the mean over seeds of every field."""
    groups = {}
    for r in rows:
        groups.setdefault((r["case"], r["snr"], r["quantity"]), []).append(r)
    return [{"case": c, "snr": s, "quantity": q, "seeds": len(rs), **{k: float(np.mean([r[k] for r in rs]))
                                                                     for k in FIELDS}}
            for (c, s, q), rs in groups.items()]


def markdown(results: dict) -> str:
    cols = ["case, SNR", "strain", "RMS error", "band sd: total / smoother's", "coverage [%] (segments pooled)",
            "tau0 / k: route (segments' own share)", "tau0 / k: fitted to the truth", "coverage with those [%]",
            "near the peak: error of ours / of the reference / of the difference"]
    body = [[f"{r['case']}, {r['snr']:g}", r["quantity"], fmt(r["error_rms"], ".2f"),
             f"{fmt(r['sd_rms'], '.2f')} / {fmt(r['sd_model_rms'], '.2f')}",
             f"{fmt(r['coverage_pct'], '.1f')} ({fmt(r['coverage_pct_pooled'], '.1f')})",
             f"{fmt(r['tau0'], '.2f')} / {fmt(r['k'], '.3f')} ({fmt(r['own_weight'], '.2f')})", f"{fmt(r['tau0_truth'], '.2f')} / {fmt(r['k_truth'], '.3f')}",
             fmt(r["coverage_pct_truth_fit"], ".1f"),
             f"{fmt(r['near_peak_error_rms'], '.2f')} / {fmt(r['near_peak_reference_error_rms'], '.2f')} / "
             f"{fmt(r['near_peak_difference_rms'], '.2f')}"] for r in mean_rows(results["rows"])]
    return (md_table(cols, body) + "\n\nSegment curves (six per run), means over "
            f"{max(len({r['seed'] for r in results['rows']}), 1)} seed(s); strain in percentage points. RMS error: of the "
            "curves against the truth over segment-frames. Band sd: the total (what the bands use) and the smoother's "
            "own. Coverage: of the true segment curves by the route's 95% bands; in brackets by the same bands with "
            "the six segments' pooled excess (the route's rule before the partial pooling), from the same run. tau0 / k: the excess-error parameters the route fitted to its disagreement with the tracks (RMS over "
            "the six segments; in brackets the mean weight of each segment's own fit against the six segments' pooled "
            "one), and the same parameters fitted to the true error (pooled over the segments); coverage with those: of the truth by bands of the route's form "
            "with the truth's parameters (a yardstick, it reads the truth). Near the peak: the RMS over segments of "
            f"the mean error within {results['half_window_frames']} frames of each segment's true peak, of our curve, "
            "of the reference the route measured its excess error against (the tracks' unsmoothed finite-difference "
            "curve, the blur compensated), and of their difference: a difference much smaller than our error is an "
            "error the reference shares, which no moment of the disagreement can see.")


def check(results: dict, tier: str) -> list:
    """Every field finite; coverages within 0-100."""
    problems = [f"{r['case']} SNR {r['snr']:g} seed {r['seed']} {r['quantity']}: {k} is {r.get(k)}"
                for r in results["rows"] for k in FIELDS if r.get(k) is None or not np.isfinite(r[k])]
    problems += [f"{r['case']} {r['quantity']}: {k} = {r[k]} outside 0-100" for r in results["rows"]
                 for k in ("coverage_pct", "coverage_pct_pooled", "coverage_pct_truth_fit") if not 0.0 <= r[k] <= 100.0]
    return problems + ([] if results["rows"] else ["no rows"])
