"""What the DENSE route's bands can and cannot see: their error model against the truth, and the tracks' share.

The route's 95% bands (:mod:`sfem_filters.cardiac.strain_bands`) add to the smoother's variance an
excess-error variance ``tau_t^2 = tau0^2 + k^2 m_t^2 + j^2 c_t^2`` (``c`` the curve's second difference
over the frames, its bend) whose three parameters are fitted by moments to
the curve's disagreement with the unsmoothed finite-difference strain of the same tracks. This claim
asks, on every given DENSE-Sim case, both SNRs and three seeds (the strain page's runs,
:mod:`validation.strain_dense_sim`: the spec's noise, :func:`sfem_filters.cardiac.dense_case_strain`
with :func:`sfem_filters.cardiac.image_settings`), three questions of the six segment curves:

1. **Is the form right?** The same three parameters fitted instead to the estimate's true error (the
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
3. **Is the truth registered to the images?** DENSE-Sim computes its ground truth on a finer grid
   and resamples it to the images' (its README: "about a quarter pixel of offset"). An offset ``s``
   of the truth's grid from the images' makes every method's curves disagree with it by
   ``s . grad(truth)``, an error the images cannot show and the bands, measured against the images,
   cannot see. :func:`truth_offset` fits ``s`` per case (:mod:`validation._truth_offset`) to the
   *noise-free* images' own tracks (the
   conventional finite-difference strain of the case without added noise: it does not involve our
   estimate), and the route's bands are scored again against the truth moved by the offset pooled
   over the cases (first order, ``truth + s . grad(truth)`` per pixel, then the segment means): a
   diagnostic of the benchmark's truth, not a method (the route never sees the truth or ``s``).

Reported per case and SNR, means over the seeds (strain in percentage points): the segment curves'
RMS error, the bands' RMS sd (total, and the smoother's own), the route's coverage (and, before and
after from one run, the coverage of the rule that subtracted the reference's whole noise variance from
the disagreement's square, not less the estimate's own share, ``curve_discrepancy`` without
``model_sd``; of the rule before the bend term, ``tau0`` and ``k`` alone fitted to the same
disagreement; and of the same bands with the six segments' pooled excess, the rule before the partial
pooling), the fitted
``tau0``, ``k`` and ``j`` of the route (RMS over its six segments, with the mean weight of the segments'
own fits against their pooled one, :func:`sfem_filters.cardiac.strain_route.curve_discrepancy`) and
of the truth, the coverage with the truth's parameters, and the
near-peak RMS errors of the estimate, of the reference and of their difference, and the coverage
against the re-registered truth, with each case's fitted offset. Quick tier: the
phantom's first 8 frames, SNR 30, seed 0.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from sfem_filters.cardiac import dense_case_strain, image_settings
from sfem_filters.cardiac.strain_bands import curve_curvature, discrepancy_variance
from sfem_filters.cardiac.strain_route import curve_discrepancy
from sfem_filters.imaging import (add_complex_noise, conventional_analysis, phase_to_displacement, read_dense_sim,
                                  reference_points, segment_curves, truth_at_points)
from sfem_filters.imaging.strain import Z95

from ._core import fmt, md_table
from ._truth_offset import DEPTH_PX, fit_offset, registered_truth
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
FIELDS = ("error_rms", "sd_rms", "sd_model_rms", "coverage_pct", "coverage_pct_pooled", "coverage_pct_two_term",
          "coverage_pct_whole_noise",
          "tau0", "k", "j", "own_weight", "tau0_truth", "k_truth", "j_truth",
          "coverage_pct_truth_fit", "near_peak_error_rms", "near_peak_reference_error_rms", "near_peak_difference_rms",
          "coverage_pct_registered")


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


def truth_offset(case) -> dict:
    """The truth's sub-pixel offset from the images of one noise-free case (module docstring, question 3).

    :func:`validation._truth_offset.fit_offset` of the conventional finite-difference strain of the
    case's own (noise-free) tracks against the truth, Ecc and Err together, each weighted by the
    precision of its own fit. Returns a dict: ``s_px`` (2,), the weighted normal equations ``XtX``
    (2, 2) and ``Xty`` (2,) (summed over cases for the pooled offset), and the per-component fits
    ``s_px_Ecc``, ``s_px_Err``.
    """
    conv = conventional_analysis(case, 0.0)
    out, XtX, Xty = {}, np.zeros((2, 2)), np.zeros(2)
    for q, e, t in zip(("Ecc", "Err"), (conv.strain.Ecc, conv.strain.Err), truth_at_points(case)):
        s, A, b = fit_offset(conv.tracks.points, case.reference_mask, e, t)
        out[f"s_px_{q}"] = s.tolist()
        XtX, Xty = XtX + A, Xty + b
    return {"s_px": np.linalg.solve(XtX, Xty).tolist(), "XtX": XtX.tolist(), "Xty": Xty.tolist(), **out}


def quantity_row(q, route, truth_curves, registered_curves=None) -> dict:
    """One quantity's metrics (module docstring) from the route's result and the true segment curves."""
    seg, glob = route.segment_curves, route.global_curves
    m, sd, sd_model = (np.asarray(seg[k], float) for k in (q, f"{q}_sd", f"{q}_sd_model"))      # (6, F)
    c = curve_curvature(m.T).T                                                       # each segment's bend
    t = np.asarray(truth_curves, float)
    e = m - t
    ok = np.isfinite(e) & np.isfinite(sd_model) & np.isfinite(c)
    tau0_2, k2, j2 = discrepancy_variance(-e[ok], m[ok], sd_model[ok] ** 2, c[ok])
    fitted = np.sqrt(sd_model ** 2 + tau0_2 + k2 * m ** 2 + j2 * c ** 2)
    disc = route.settings["discrepancy_sd"][q]
    seg_tau = np.asarray(disc["segments"], float)                                    # (6, 3): tau0, k, j per segment
    tau0, k, j = np.sqrt(np.mean(seg_tau ** 2, axis=0))
    p0, pk, pj = np.asarray(disc["segments_pooled"], float)
    pooled_sd = np.sqrt(sd_model ** 2 + p0 ** 2 + pk ** 2 * m ** 2 + pj ** 2 * c ** 2)
    # the rules before, from the same run and the same disagreement: the bend term left out; and the
    # reference's whole noise variance subtracted (not less the estimate's own share, model_sd)
    curves = np.vstack([np.asarray(glob[q], float)[None], m])                        # (7, F): global, segments
    diffs = np.vstack([np.asarray(glob[f"{q}_reference"], float)[None], np.asarray(seg[f"{q}_reference"], float)])
    own = np.vstack([np.asarray(glob[f"{q}_sd_model"], float)[None], sd_model])
    tau2 = curve_discrepancy((diffs - curves).T, curves.T, curvature=False, model_sd=own.T)
    two_term_sd = np.sqrt(sd_model ** 2 + tau2[1:, :1] + tau2[1:, 1:2] * m ** 2)
    tau_w = curve_discrepancy((diffs - curves).T, curves.T)
    whole_sd = np.sqrt(sd_model ** 2 + tau_w[1:, :1] + tau_w[1:, 1:2] * m ** 2 + tau_w[1:, 2:] * c ** 2)
    e_near = _near_peak_means(e, t, QUANTITIES[q])
    tr_near = _near_peak_means(np.asarray(seg[f"{q}_reference"], float) - t, t, QUANTITIES[q])

    def rms(a):
        return float(np.sqrt(np.nanmean(np.asarray(a, float) ** 2)))
    return {"error_rms": PCT * rms(e), "sd_rms": PCT * rms(sd), "sd_model_rms": PCT * rms(sd_model),
            "coverage_pct": _coverage(m, sd, t), "tau0": PCT * float(tau0), "k": float(k), "j": float(j),
            "own_weight": float(np.mean(disc["segment_weights"])), "coverage_pct_pooled": _coverage(m, pooled_sd, t),
            "coverage_pct_two_term": _coverage(m, two_term_sd, t),
            "coverage_pct_whole_noise": _coverage(m, whole_sd, t),
            "tau0_truth": PCT * float(np.sqrt(tau0_2)), "k_truth": float(np.sqrt(k2)), "j_truth": float(np.sqrt(j2)),
            "coverage_pct_truth_fit": _coverage(m, fitted, t), "near_peak_error_rms": PCT * rms(e_near),
            "near_peak_reference_error_rms": PCT * rms(tr_near),
            "near_peak_difference_rms": PCT * rms(e_near - tr_near),
            "coverage_pct_registered": (np.nan if registered_curves is None
                                        else _coverage(m, sd, np.asarray(registered_curves, float)))}


def run_case(folder, snr: float, seed: int, frames=None, s_px=None) -> list:
    """The route and the tracks' own strain on one case, SNR and seed: a row per quantity (``s_px``: the
    truth's offset to score the re-registered coverage against, :func:`truth_offset`)."""
    case = _truncated(read_dense_sim(folder), frames)
    t_ecc, t_err = truth_at_points(case)
    points = reference_points(case.reference_mask)
    noisy = add_complex_noise(case, snr, seed)
    tracks = phase_to_displacement(noisy)
    t0 = time.perf_counter()
    r = dense_case_strain(noisy, image_settings(noisy), tracks=tracks)
    seconds = time.perf_counter() - t0
    rows = []
    for q, truth in (("Ecc", t_ecc), ("Err", t_err)):
        reg = None if s_px is None else segment_curves(registered_truth(points, truth, case.shape, s_px), r.labels)
        row = quantity_row(q, r, segment_curves(truth, r.labels), reg)
        rows.append({"case": folder.name, "snr": snr, "seed": seed, "quantity": q, "seconds": seconds, **row})
    print(f"  {NAME}: {folder.name} SNR {snr:g} seed {seed}: {seconds:.0f} s", flush=True)
    return rows


def compute(settings: dict, out_dir) -> dict:
    folders = case_folders(settings["cases"])
    offsets = {f.name: truth_offset(_truncated(read_dense_sim(f), settings.get("frames"))) for f in folders}
    s_pooled = np.linalg.solve(sum(np.asarray(o["XtX"]) for o in offsets.values()),
                               sum(np.asarray(o["Xty"]) for o in offsets.values())).tolist()
    print(f"  {NAME}: the truth's offset from the images, pooled over the cases: "
          f"({s_pooled[0]:+.3f}, {s_pooled[1]:+.3f}) px", flush=True)
    rows = [row for folder in folders for snr in settings["snr"]
            for seed in settings["seeds"] for row in run_case(folder, snr, seed, settings.get("frames"), s_pooled)]
    out = {"rows": rows, "half_window_frames": HALF_WINDOW, "offset_depth_px": DEPTH_PX,
           "truth_offset_px": {name: {k: o[k] for k in ("s_px", "s_px_Ecc", "s_px_Err")}
                               for name, o in offsets.items()},
           "truth_offset_pooled_px": s_pooled,
           "units": "strain in percentage points, k and j dimensionless, coverage in percent of segment-frames"}
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
        rules = (("coverage_pct", "route", "C0", -0.28),
                 ("coverage_pct_whole_noise", "the reference's whole noise (before)", "C3", -0.14),
                 ("coverage_pct_two_term", "two terms (before the bend)", "C1", 0.0),
                 ("coverage_pct_truth_fit", "form fitted to the truth", "C2", 0.14),
                 ("coverage_pct_registered", "route, truth re-registered", "C4", 0.28))
        for k, (key, name, colour, dx) in enumerate(rules):
            vals = [[r[key] for r in rows if (r["case"], r["snr"]) == g and r["quantity"] == q] for g in groups]
            mean = np.array([np.mean(v) for v in vals])
            # clipped at 0: seeds that agree (all at 100%, say) leave a mean a rounding error off their min
            lo = np.maximum(mean - np.array([min(v) for v in vals]), 0.0)
            hi = np.maximum(np.array([max(v) for v in vals]) - mean, 0.0)
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
    cols = ["case, SNR", "strain", "RMS error", "band sd: total / smoother's",
            "coverage [%] (the reference's whole noise; two terms; segments pooled)", "tau0 / k / j: route (segments' own share)",
            "tau0 / k / j: fitted to the truth", "coverage with those [%]",
            "near the peak: error of ours / of the reference / of the difference",
            "coverage against the re-registered truth [%]"]
    body = [[f"{r['case']}, {r['snr']:g}", r["quantity"], fmt(r["error_rms"], ".2f"),
             f"{fmt(r['sd_rms'], '.2f')} / {fmt(r['sd_model_rms'], '.2f')}",
             f"{fmt(r['coverage_pct'], '.1f')} ({fmt(r['coverage_pct_whole_noise'], '.1f')}; "
             f"{fmt(r['coverage_pct_two_term'], '.1f')}; "
             f"{fmt(r['coverage_pct_pooled'], '.1f')})",
             f"{fmt(r['tau0'], '.2f')} / {fmt(r['k'], '.3f')} / {fmt(r['j'], '.2f')} ({fmt(r['own_weight'], '.2f')})",
             f"{fmt(r['tau0_truth'], '.2f')} / {fmt(r['k_truth'], '.3f')} / {fmt(r['j_truth'], '.2f')}",
             fmt(r["coverage_pct_truth_fit"], ".1f"),
             f"{fmt(r['near_peak_error_rms'], '.2f')} / {fmt(r['near_peak_reference_error_rms'], '.2f')} / "
             f"{fmt(r['near_peak_difference_rms'], '.2f')}", fmt(r["coverage_pct_registered"], ".1f")]
            for r in mean_rows(results["rows"])]
    return (md_table(cols, body) + "\n\nSegment curves (six per run), means over "
            f"{max(len({r['seed'] for r in results['rows']}), 1)} seed(s); strain in percentage points. RMS error: of the "
            "curves against the truth over segment-frames. Band sd: the total (what the bands use) and the smoother's "
            "own. Coverage: of the true segment curves by the route's 95% bands; in brackets, from the same run and "
            "the same disagreement, by the bands of the rule before the estimate's own share of the noise (the "
            "reference's whole noise variance subtracted from the disagreement's square, not less the smoother's own "
            "variance), by those of the rule before the bend term (tau0 and k alone) and by the "
            "route's bands with the six segments' pooled excess (the rule before the partial pooling). tau0 / k / j: "
            "the excess-error parameters the route fitted to its disagreement with the tracks (tau_t^2 = tau0^2 + "
            "k^2 m_t^2 + j^2 c_t^2, c the curve's second difference over the frames; RMS over the six segments; in "
            "brackets the mean weight of each segment's own fit against the six segments' pooled one), and the same "
            "parameters fitted to the true error (pooled over the segments); coverage with those: of the truth by "
            "bands of the route's form "
            "with the truth's parameters (a yardstick, it reads the truth). Near the peak: the RMS over segments of "
            f"the mean error within {results['half_window_frames']} frames of each segment's true peak, of our curve, "
            "of the reference the route measured its excess error against (the tracks' unsmoothed finite-difference "
            "curve, the blur compensated), and of their difference: a difference much smaller than our error is an "
            "error the reference shares, which no moment of the disagreement can see. Coverage against the "
            "re-registered truth: of the truth moved by the offset below by the same bands (a diagnostic of the "
            "truth; the route never sees it).\n\n" + offsets_text(results))


def offsets_text(results: dict) -> str:
    """The fitted offsets of the truth from the images, and what re-registering it does to the coverage."""
    parts = [f"{name}: ({o['s_px'][0]:+.2f}, {o['s_px'][1]:+.2f}) px (from Ecc alone ({o['s_px_Ecc'][0]:+.2f}, "
             f"{o['s_px_Ecc'][1]:+.2f}), from Err alone ({o['s_px_Err'][0]:+.2f}, {o['s_px_Err'][1]:+.2f}))"
             for name, o in results["truth_offset_px"].items()]
    sp = results["truth_offset_pooled_px"]
    text = ("The truth's offset from the images (x, y), fitted to each noise-free case's own tracks "
            "(their unsmoothed finite-difference strain against the truth, pixels at least "
            f"{results['offset_depth_px']} px inside the reference mask, frames from a quarter of the sequence on): "
            + "; ".join(parts) + f"; pooled over the cases ({sp[0]:+.2f}, {sp[1]:+.2f}) px.")
    means = mean_rows(results["rows"])
    moves = []
    for case in dict.fromkeys(r["case"] for r in means):
        for q in QUANTITIES:
            rs = [r for r in means if r["case"] == case and r["quantity"] == q]
            before = ", ".join(f"{r['coverage_pct']:.1f}" for r in rs)
            after = ", ".join(f"{r['coverage_pct_registered']:.1f}" for r in rs)
            snrs = "/".join(f"{r['snr']:g}" for r in rs)
            moves.append(f"{case} {q} (SNR {snrs}) {before} -> {after}%")
    return text + (" Coverage of the route's bands against the truth as given -> against the truth moved by the "
                   "pooled offset: " + "; ".join(moves) + ".")


def check(results: dict, tier: str) -> list:
    """Every field finite; coverages within 0-100; the offsets finite."""
    problems = [f"truth offset {v}: not finite" for v in [results.get("truth_offset_pooled_px")]
                if v is None or not np.all(np.isfinite(v))]
    problems += [f"{r['case']} SNR {r['snr']:g} seed {r['seed']} {r['quantity']}: {k} is {r.get(k)}"
                for r in results["rows"] for k in FIELDS if r.get(k) is None or not np.isfinite(r[k])]
    problems += [f"{r['case']} {r['quantity']}: {k} = {r[k]} outside 0-100" for r in results["rows"]
                 for k in ("coverage_pct", "coverage_pct_pooled", "coverage_pct_two_term", "coverage_pct_whole_noise",
                           "coverage_pct_truth_fit",
                           "coverage_pct_registered")
                 if not 0.0 <= r[k] <= 100.0]
    return problems + ([] if results["rows"] else ["no rows"])
