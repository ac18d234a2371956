"""Strain from the myocardium masks alone (the contours route) against DENSE-Sim's ground truth.

:func:`sfem_filters.cardiac.contour_strain` on every given DENSE-Sim case (its masks and frame
times only: no phase, so no noise level applies) beside the thin-plate spline through the same
tracked contour landmarks, both scored as ``../shared/specs/strain-ground-truth.md`` pins
(:func:`sfem_filters.benchmark.score_strain`). The route's goal (issue 42): beat the spline through
the same points on pixel RMSE and on segmental peaks. A third row per case is the route without its
guided pass (``ContourRouteSettings(guided_passes=0)``: the landmarks' data alone, the route before
the pass was added), run in the same claim.
"""
from __future__ import annotations

from sfem_filters.cardiac import ContourRouteSettings

from ._contour_rows import METRICS, ROUTE, SPLINE, beats_spline, contour_rows
from ._core import fmt, md_table
from .strain_dense_sim import case_folders

NAME = "strain_contours"
NEEDS_DATA = True
TITLE = "Strain from the masks alone (contours route) against DENSE-Sim's ground truth"
FULL_COST = "about 3 min on 2 cores"
TIERS = {"quick": {"cases": ["phantom_subject_1"], "frames": 4},
         "full": {"cases": [], "frames": None}}
#: Label of the route's row without its guided pass (appended to the route's method name).
UNGUIDED = ", landmarks alone (no guided pass)"
#: The errors compared with and without the guided pass (absolute values).
COMPARED = ("pixel_rmse_Ecc", "pixel_rmse_Err", "global_peak_error_Ecc", "global_peak_error_Err",
            "segment_peak_error_Ecc_mean", "segment_peak_error_Err_mean")
TOLERANCES = {"*": (1e-6, 1e-9), "seconds": None, "cpu_seconds": None, "peak_rss_mb": None}


def compute(settings: dict, out_dir) -> dict:
    rows = []
    unguided = ContourRouteSettings(guided_passes=0)
    for folder in case_folders(settings["cases"]):
        route, spline = contour_rows(folder, frames=settings["frames"])
        alone = contour_rows(folder, frames=settings["frames"], settings=unguided, label=UNGUIDED)[0]
        rows += [route, alone, spline]
    return {"rows": rows, "beats_spline": beats_spline(rows), "guided_vs_landmarks": guided_vs_landmarks(rows)}


def guided_vs_landmarks(rows) -> dict:
    """Per case and metric of :data:`COMPARED`: is the route's error lower than without its guided pass?"""
    by = {(r["case"], r["method"]): r for r in rows}
    return {case: {k: abs(by[case, ROUTE][k]) < abs(by[case, ROUTE + UNGUIDED][k]) for k in COMPARED}
            for case in sorted({r["case"] for r in rows}) if (case, ROUTE + UNGUIDED) in by and (case, ROUTE) in by}


def markdown(results: dict) -> str:
    cols = ["case", "method", "RMSE Ecc", "RMSE Err", "global peak err Ecc", "global peak err Err",
            "segment peak err Ecc mean / max", "segment peak err Err mean / max", "band coverage Ecc / Err [%]",
            "band width Ecc / Err", "seconds"]
    body = [[r["case"], r["method"], fmt(r["pixel_rmse_Ecc"], ".2f"), fmt(r["pixel_rmse_Err"], ".2f"),
             fmt(r["global_peak_error_Ecc"], "+.2f"), fmt(r["global_peak_error_Err"], "+.2f"),
             f"{fmt(r['segment_peak_error_Ecc_mean'], '.2f')} / {fmt(r['segment_peak_error_Ecc_max'], '.2f')}",
             f"{fmt(r['segment_peak_error_Err_mean'], '.2f')} / {fmt(r['segment_peak_error_Err_max'], '.2f')}",
             f"{fmt(r['coverage_pct_Ecc'], '.1f')} / {fmt(r['coverage_pct_Err'], '.1f')}",
             f"{fmt(r['band_width_Ecc'], '.2f')} / {fmt(r['band_width_Err'], '.2f')}", fmt(r["seconds"], ".0f")]
            for r in results["rows"]]
    names = {"pixel_rmse_Ecc": "pixel RMSE Ecc", "pixel_rmse_Err": "pixel RMSE Err",
             "global_peak_error_Ecc": "global peak Ecc", "global_peak_error_Err": "global peak Err",
             "segment_peak_error_Ecc_mean": "segment peaks Ecc", "segment_peak_error_Err_mean": "segment peaks Err"}
    guided = "; ".join(f"{case}: " + ", ".join(f"{names[k]} {'yes' if v else 'no'}" for k, v in c.items())
                       for case, c in results.get("guided_vs_landmarks", {}).items())
    verdict = "; ".join(f"{case}: pixel RMSE {'yes' if v['pixel RMSE'] else 'no'}, segment peaks "
                        f"{'yes' if v['segment peaks'] else 'no'}" for case, v in results["beats_spline"].items())
    return (md_table(cols, body) + "\n\nStrain in percentage points (Green-Lagrange, radial and circumferential "
            "about the reference myocardium's centre of mass); peak errors signed (estimate - truth); band coverage: "
            "the fraction of (segment, frame) pairs whose true segment mean lies inside the 95% band, with the bands' "
            "mean width. The masks carry no phase, so no noise level applies; seconds: wall time of one run.\n\n"
            f"The contours route beats the spline through the same landmarks: {verdict}.\n\n"
            f"The row \"{ROUTE}{UNGUIDED}\" is the same route with its landmarks' data alone "
            "(`ContourRouteSettings(guided_passes=0)`), the route before its second pass guided by the first "
            "was added: the before and after of that change, from the same run. Lower error with the guided pass "
            "than without: " + guided + ".")


def check(results: dict, tier: str) -> list:
    """Every metric finite; the three rows present for every case."""
    problems = [f"{r['case']} {r['method']}: {k} {r[k]}" for r in results["rows"]
                for k in METRICS[:4] if r.get(k) is None or not abs(r[k]) < 1e3]
    methods = {(r["case"], r["method"]) for r in results["rows"]}
    problems += [f"{case}: {m} missing" for case in {r["case"] for r in results["rows"]}
                 for m in (ROUTE, SPLINE, ROUTE + UNGUIDED) if (case, m) not in methods]
    return problems
