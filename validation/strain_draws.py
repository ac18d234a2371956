"""The DENSE route on noise draws the strain page was not made with: how often each goal holds.

The main strain page (:mod:`validation.strain_dense_sim`) scores the route on the spec's three noise
draws (seeds 0, 1, 2) of each case and SNR. The checks of issue 42 also run on draws nobody here has
seen, and a goal met on three draws with a small margin may fail on a fourth. This claim runs the
same rows (:func:`validation.strain_dense_sim.run_case`: the conventional analysis without smoothing
and with sigma 1 px, and our route's default for images, no ablations) on six further draws, seeds 3
to 8, of both given cases at SNR 30 and 8, and counts, per case and SNR, the draws that meet every
goal and each goal's misses with the worst draw (:func:`validation.strain_dense_sim.draw_misses`, the
main page's rules). Nothing is chosen here: the route's settings are its defaults, fixed before these
draws were run.

The spec's band goal reads "95% bands covering the truth in 85-99% of segment-frames". The main page
judges the Ecc and Err bands each on its own (the stricter reading); the table also shows both pooled
over the segment-frames (each segment-frame has an Ecc and an Err band; :func:`pooled_coverage`), the
other reading the wording allows.

Quick tier: the phantom, its first 8 frames, SNR 30, seed 3.
"""
from __future__ import annotations

from ._core import fmt, md_table
from .strain_dense_sim import (GOAL_ORDER, GOALS, OURS, _better_conventional, case_folders, draw_misses,
                               nonfinite_metrics, run_case)

NAME = "strain_draws"
NEEDS_DATA = True
TITLE = "The DENSE route on noise draws the strain page was not made with"
FULL_COST = "about 35-45 min"
TIERS = {"quick": {"cases": ["phantom_subject_1"], "snr": [30.0], "seeds": [3], "frames": 8},
         "full": {"cases": None, "snr": [30.0, 8.0], "seeds": [3, 4, 5, 6, 7, 8], "frames": None}}
#: Noise draws are seeded, the route is deterministic; timings and memory are the machine's.
TOLERANCES = {"*": (1e-6, 1e-9), "seconds": None, "cpu_seconds": None, "peak_rss_mb": None}


def compute(settings: dict, out_dir) -> dict:
    rows = []
    for folder in case_folders(settings["cases"]):
        for snr in settings["snr"]:
            for seed in settings["seeds"]:
                rows.extend(run_case(folder, float(snr), int(seed), frames=settings["frames"]))
                print(f"  {NAME}: {folder.name}, SNR {snr:g}, seed {seed}: {rows[-1]['seconds']:.0f} s", flush=True)
    return {"rows": rows, "seeds": list(settings["seeds"]), "frames": settings["frames"]}


def pooled_coverage(r: dict) -> float:
    """Coverage (%) of the Ecc and Err segment-frames together: the mean of the two coverages.

    Each is over the segment-frames where the truth and that component's band are finite; the truth's
    are the same for both (the scoring's joint mask), and the route's bands are finite wherever its
    estimate is, so both count the same segment-frames and the mean is the pooled fraction
    (``coverage_pct`` of :func:`sfem_filters.benchmark.score_strain`, which the rows do not store).
    """
    return 0.5 * (r["coverage_pct_Ecc"] + r["coverage_pct_Err"])


def _span(values, spec: str) -> str:
    lo, hi = fmt(min(values), spec), fmt(max(values), spec)
    return lo if lo == hi else f"{lo} to {hi}"


def groups(results: dict) -> dict:
    """``{(case, snr): [our route's rows]}`` in the run's order."""
    out = {}
    for r in results["rows"]:
        if r["method"] == OURS:
            out.setdefault((r["case"], r["snr"]), []).append(r)
    return out


def markdown(results: dict) -> str:
    rows = results["rows"]
    conv = _better_conventional(rows)
    seeds = results.get("seeds", [])
    lo, hi = GOALS["coverage"]
    cols = ["case", "SNR", "draws meeting every goal", "RMSE Ecc / Err minus the better conventional, worst",
            "global peak error Ecc / Err, worst", "segment peak error Ecc / Err, worst", "coverage Ecc [%]",
            "coverage Err [%]", "coverage pooled [%]", "s a run, worst"]
    body, missed = [], []
    for (case, snr), rs in groups(results).items():
        misses = [draw_misses(r, conv) for r in rs]
        over = {m: max(r[m] - conv[(case, snr, r["seed"], m)] for r in rs) for m in ("pixel_rmse_Ecc", "pixel_rmse_Err")}
        worst = {m: max((r[m] for r in rs), key=abs) for m in ("global_peak_error_Ecc", "global_peak_error_Err")}
        seg = {m: max(r[m] for r in rs) for m in ("segment_peak_error_Ecc_mean", "segment_peak_error_Err_mean")}
        body.append([case.replace("_", " "), f"{snr:g}", f"{sum(not m for m in misses)} of {len(rs)}",
                     f"{fmt(over['pixel_rmse_Ecc'], '+.2f')} / {fmt(over['pixel_rmse_Err'], '+.2f')}",
                     f"{fmt(worst['global_peak_error_Ecc'], '+.2f')} / {fmt(worst['global_peak_error_Err'], '+.2f')}",
                     f"{fmt(seg['segment_peak_error_Ecc_mean'], '.2f')} / {fmt(seg['segment_peak_error_Err_mean'], '.2f')}",
                     _span([r["coverage_pct_Ecc"] for r in rs], ".1f"), _span([r["coverage_pct_Err"] for r in rs], ".1f"),
                     _span([pooled_coverage(r) for r in rs], ".1f"), fmt(max(r["seconds"] for r in rs), ".0f")])
        counts = [f"{g} in {sum(g in m for m in misses)} of {len(rs)} (worst: "
                  f"{max((m[g] for m in misses if g in m), key=lambda v: v[0])[1]})"
                  for g in GOAL_ORDER if any(g in m for m in misses)]
        pooled_out = [r for r in rs if not lo <= pooled_coverage(r) <= hi]
        if pooled_out:
            counts.append(f"pooled coverage outside {lo:g}-{hi:g}% in {len(pooled_out)} of {len(rs)}")
        if counts:
            missed.append(f"{case} SNR {snr:g}: " + "; ".join(counts))
    draws = (f"seed {seeds[0]}" if len(seeds) == 1 else f"seeds {seeds[0]} to {seeds[-1]}" if seeds else "the draws")
    text = (md_table(cols, body)
            + f"\n\nOur route's default for images (what `sfem-filters strain CASE_DIR` runs) on noise draws the strain "
            f"page was not made with ({draws}; that page's are seeds 0, 1, 2), each scored against the case's truth "
            "with the strain page's metrics and goals. Strain in percentage points; each cell is the worst draw "
            "(the largest excess of the pixel RMSE over the better of the two conventional variants at that draw, "
            "negative when ours is lower at every draw; the peak error furthest from zero; the largest mean segment "
            "peak error; the longest run's seconds, phase to strain, on this machine) or the range over the draws "
            "(each run's seconds and peak memory are in the JSON). Goals at every draw: pixel RMSE below the better "
            f"conventional; |global peak error| at most {GOALS['global_peak_error_Ecc']:g} (Ecc) and "
            f"{GOALS['global_peak_error_Err']:g} (Err); mean segment peak error at most "
            f"{GOALS['segment_peak_error_Ecc_mean']:g} (Ecc) and {GOALS['segment_peak_error_Err_mean']:g} (Err); band "
            f"coverage of the segment-frames {lo:g}-{hi:g}%, Ecc and Err each (the strain page's reading); pooled: "
            "both together, the other reading of the spec's wording, shown beside.")
    text += ("\n\nGoals missed, in how many draws (the worst draw's value): " + "; ".join(missed) + "."
             if missed else "\n\nEvery goal is met at every draw, on both readings of the band goal.")
    return text


def check(results: dict, tier: str) -> list:
    """Plausibility, not the goals: every metric of every row finite, our route's row at every case, SNR and seed."""
    problems = nonfinite_metrics(results["rows"])
    runs = {(r["case"], r["snr"], r["seed"]) for r in results["rows"]}
    ours = {(r["case"], r["snr"], r["seed"]) for r in results["rows"] if r["method"] == OURS}
    problems += [f"{c} SNR {s:g} seed {d}: no row of our route" for c, s, d in sorted(runs - ours)]
    return problems + ([] if results["rows"] else ["no rows"])
