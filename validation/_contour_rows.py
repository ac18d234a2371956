"""Rows of the contours route for the ``strain_dense_sim`` claim: strain from the masks alone, and its yardstick.

:func:`contour_rows` runs :func:`sfem_filters.cardiac.contour_strain` on one DENSE-Sim case folder
(its myocardium masks and frame times only: no phase, so the complex noise the claim adds to the
phase does not reach this route) and the thin-plate spline through the same tracked contour
landmarks (:func:`sfem_filters.cardiac.contour_spline_strain`), each scored against the case's
ground truth by :func:`sfem_filters.benchmark.score_strain` exactly as the claim scores its other
methods. The rows have the claim's keys (``case``, ``snr``, ``seed``, ``n_points``, ``n_frames``,
``untracked``, ``method``, the metrics, ``seconds``, ``cpu_seconds``, ``peak_rss_mb``); ``snr`` and
``seed`` only label the run the rows sit in (the numbers do not depend on them).

Method names do not start with ``"ours"``, so the claim's goals of the DENSE route
(``goals_met``, which selects ``method.startswith("ours")``) do not include them; the contours
route's own goal (issue 42) is to beat the spline through the same points on pixel RMSE and on
segmental peaks: :func:`beats_spline`.
"""
from __future__ import annotations

import time
from pathlib import Path

from sfem_filters.benchmark import score_strain
from sfem_filters.cardiac import ContourRouteSettings, contour_spline_strain, contour_strain
from sfem_filters.imaging import read_dense_sim, truth_at_points

from ._core import MIB, peak_rss_bytes

#: Method names of the rows.
ROUTE = "contours route (masks only, no phase)"
SPLINE = "spline through the contour landmarks"
#: The claim's metric keys (``validation.strain_dense_sim.METRICS``).
METRICS = ("pixel_rmse_Ecc", "pixel_rmse_Err", "global_peak_error_Ecc", "global_peak_error_Err",
           "segment_peak_error_Ecc_mean", "segment_peak_error_Ecc_max", "segment_peak_error_Err_mean",
           "segment_peak_error_Err_max", "coverage_pct_Ecc", "coverage_pct_Err", "band_width_Ecc", "band_width_Err")


def _peak_rss_mb() -> float:
    """This process's peak resident memory in MiB (2**20 bytes): what ``peak_rss_mb`` stores."""
    return peak_rss_bytes() / MIB


def contour_rows(case_dir, snr: float | None = None, seed: int | None = None, frames: int | None = None,
                 settings: ContourRouteSettings | None = None, label: str = "") -> list:
    """The contours route and its spline on one case: two rows (strain metrics in percentage points).

    Parameters
    ----------
    case_dir : path
        A DENSE-Sim case folder (``config.yaml``, ``LV_mask_time_lowres.npy``, ``GT_Ecc.npy``, ...).
    snr, seed : optional
        Labels of the claim's run the rows belong to (the masks carry no noise).
    frames : int, optional
        Only the first ``frames`` frames (the claim's quick tier).
    settings : ContourRouteSettings, optional
        The route's settings (default: its defaults); ``label`` is appended to both method names.
    """
    folder = Path(case_dir)
    case = read_dense_sim(folder)
    t_ecc, t_err = truth_at_points(case)
    masks, times = case.masks, case.frame_times_s
    if frames:
        masks, times, t_ecc, t_err = masks[:frames + 1], times[:frames], t_ecc[:frames], t_err[:frames]
    base = {"case": folder.name, "snr": snr, "seed": seed, "n_points": int(t_ecc.shape[1]),
            "n_frames": int(t_ecc.shape[0]), "untracked": 0}
    t0, c0 = time.perf_counter(), time.process_time()
    r = contour_strain(masks, case.pixel_size_m, times, settings or ContourRouteSettings())
    t_route, c_route = time.perf_counter() - t0, time.process_time() - c0
    t1, c1 = time.perf_counter(), time.process_time()
    s = contour_spline_strain(r)
    t_spline, c_spline = time.perf_counter() - t1, time.process_time() - c1
    rows = []
    for method, est, sec, cpu in ((ROUTE + label, r, t_route, c_route), (SPLINE + label, s, t_spline, c_spline)):
        sc = score_strain(est.Ecc, est.Err, t_ecc, t_err, est.points, est.centre, start_deg=est.start_deg,
                          ecc_band=est.band("Ecc"), err_band=est.band("Err")).to_dict()
        rows.append({**base, "method": method, **{k: sc.get(k) for k in METRICS}, "seconds": sec,
                     "cpu_seconds": cpu, "peak_rss_mb": _peak_rss_mb()})
    return rows


def beats_spline(rows) -> dict:
    """Per case: does the contours route beat the spline on pixel RMSE (Ecc and Err) and on mean
    segment peak error (Ecc and Err)? ``{case: {"pixel RMSE": bool, "segment peaks": bool}}``."""
    by = {}
    for r in rows:
        by.setdefault(r["case"], {})[r["method"]] = r
    out = {}
    for case, m in by.items():
        if ROUTE in m and SPLINE in m:
            a, b = m[ROUTE], m[SPLINE]
            out[case] = {"pixel RMSE": all(a[k] < b[k] for k in ("pixel_rmse_Ecc", "pixel_rmse_Err")),
                         "segment peaks": all(a[k] < b[k] for k in ("segment_peak_error_Ecc_mean",
                                                                    "segment_peak_error_Err_mean"))}
    return out
