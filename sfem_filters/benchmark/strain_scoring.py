"""Strain against a ground truth, scored as ``shared/specs/strain-ground-truth.md`` pins it.

Estimates and truth are Green-Lagrange strains (fraction) of the reference pixels, (F, P)
arrays of circumferential (Ecc) and radial (Err) strain; every reported strain figure is in
percentage points (100 x the fraction). Only the (frame, pixel) pairs where both the estimate
and the truth are finite enter any metric, and the curves of estimate and truth are means over
the same pixels:

* pixel RMSE of Ecc and Err over those pairs;
* global curve (mean over pixels per frame); its peak is the minimum (Ecc) or maximum (Err),
  each at its own frame; peak error = estimate's peak - truth's peak (signed);
* six segments, ``k = floor(((angle - start) mod 360) / 60)``, ``angle = atan2(y - cy,
  x - cx)`` in degrees; segment peak error as for the global curve, reported as the mean and
  the maximum of its absolute value over the segments;
* coverage: the percentage of (segment, frame) pairs whose true segment mean lies in the
  estimate's 95% band (when bands are given), with the band's mean width; likewise, when
  given, of the (frame, pixel) pairs by the pixel bands and of the frames by the global
  curve's band (the spec's coverage is the segments'; these two are reported beside);
* coverage at the peak: the percentage of the six segments whose true mean, at the frame of the
  true segment curve's own peak, lies in the band there (the frames users read a peak at; an
  average over every frame can hide bands that miss exactly there), and likewise whether the
  global band holds the true global curve at its peak frame (100 or 0).

>>> import numpy as np
>>> from sfem_filters.benchmark.strain_scoring import score_strain
>>> pts = np.array([[3.0, 0.0], [0.0, 3.0], [-3.0, 0.0], [0.0, -3.0]]) + 5
>>> truth = np.tile([[-0.10], [-0.20]], (1, 4))                 # 2 frames, 4 pixels
>>> s = score_strain(truth + 0.01, -truth, truth, -truth, pts, centre=[5, 5])
>>> round(s.pixel_rmse_Ecc, 9), round(s.global_peak_error_Ecc, 9), s.pixel_rmse_Err
(1.0, 1.0, 0.0)
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .._validate import as_float_array
from ..imaging.strain import N_SEGMENTS, curve_peak, global_curve, segment_curves, segment_labels

__all__ = ["StrainScore", "score_strain"]

PCT = 100.0


@dataclass(frozen=True)
class StrainScore:
    """The spec's metrics of one strain estimate (strain in percentage points, coverage in percent).

    ``global_peak_error_*`` are signed (estimate - truth); ``segment_peak_error_*_mean`` and
    ``_max`` are of absolute errors. ``coverage_pct_*`` and ``band_width_*`` are ``None``
    when no bands were given; ``coverage_pct`` pools the Ecc and Err segment-frames.
    ``n_valid`` / ``n_total``: (frame, pixel) pairs scored / given. ``*_pixels_*`` and
    ``*_global_*``: coverage and mean width of the pixel and global-curve bands (``None`` when
    not given). ``coverage_pct_peak_*``: of the six segments at each one's true peak frame;
    ``coverage_pct_global_peak_*``: of the global curve at its true peak frame (100 or 0).
    """

    pixel_rmse_Ecc: float
    pixel_rmse_Err: float
    global_peak_Ecc: float
    global_peak_Ecc_truth: float
    global_peak_error_Ecc: float
    global_peak_Err: float
    global_peak_Err_truth: float
    global_peak_error_Err: float
    segment_peak_error_Ecc_mean: float
    segment_peak_error_Ecc_max: float
    segment_peak_error_Err_mean: float
    segment_peak_error_Err_max: float
    coverage_pct_Ecc: float | None
    coverage_pct_Err: float | None
    coverage_pct: float | None
    band_width_Ecc: float | None
    band_width_Err: float | None
    n_valid: int
    n_total: int
    coverage_pct_pixels_Ecc: float | None = None
    coverage_pct_pixels_Err: float | None = None
    band_width_pixels_Ecc: float | None = None
    band_width_pixels_Err: float | None = None
    coverage_pct_global_Ecc: float | None = None
    coverage_pct_global_Err: float | None = None
    band_width_global_Ecc: float | None = None
    band_width_global_Err: float | None = None
    coverage_pct_peak_Ecc: float | None = None
    coverage_pct_peak_Err: float | None = None
    coverage_pct_global_peak_Ecc: float | None = None
    coverage_pct_global_peak_Err: float | None = None

    def to_dict(self) -> dict:
        """The metrics as plain floats, ints and ``None`` (JSON-ready)."""
        return asdict(self)


def _peak_error(est_curve, true_curve, kind: str) -> tuple:
    pe, _ = curve_peak(est_curve, kind)
    pt, _ = curve_peak(true_curve, kind)
    return pe, pt, pe - pt


def _coverage(band, true_seg, name: str):
    lo = as_float_array(f"{name}[0]", band[0], shape=true_seg.shape, allow_nan=True)
    hi = as_float_array(f"{name}[1]", band[1], shape=true_seg.shape, allow_nan=True)
    if np.any(hi < lo):
        raise ValueError(f"{name}: expected lower bounds <= upper bounds (lo, hi), got lo > hi somewhere")
    ok = np.isfinite(lo) & np.isfinite(hi) & np.isfinite(true_seg)
    if not ok.any():
        raise ValueError(f"{name}: expected finite bands where the truth is known, got none")
    inside = (true_seg >= lo) & (true_seg <= hi)
    return int(inside[ok].sum()), int(ok.sum()), float(np.mean((hi - lo)[ok])) * PCT


def _covered_at_peak(band, true_curves, kind: str) -> float:
    """Percentage of the curves (rows of ``true_curves``, (k, F)) whose true value at its own peak frame lies in
    the band ``(lo, hi)`` ((k, F) each) there; curves without a finite peak or band are left out."""
    hits = []
    for k in range(true_curves.shape[0]):
        _, t = curve_peak(true_curves[k], kind)
        if t < 0:
            continue                                         # no finite truth on this curve
        lo, hi, v = band[0][k][t], band[1][k][t], true_curves[k][t]
        if np.isfinite(lo) and np.isfinite(hi):
            hits.append(lo <= v <= hi)
    return PCT * float(np.mean(hits)) if hits else float("nan")


def score_strain(ecc, err, truth_ecc, truth_err, points, centre, start_deg: float = 0.0, ecc_band=None,
                 err_band=None, pixel_bands=None, global_bands=None) -> StrainScore:
    """Score an estimate of Ecc and Err against the truth (spec ``strain-ground-truth.md``).

    Parameters
    ----------
    ecc, err : (F, P) arrays
        Estimated Green-Lagrange strain (fraction), NaN where missing.
    truth_ecc, truth_err : (F, P) arrays
        True strain at the same points and frames (fraction), NaN where unknown.
    points : (P, 2) array
        Reference pixel centres (pixels, x = column, y = row).
    centre : (2,) array
        Centre (x, y) in pixels of the segments.
    start_deg : float
        Start of segment 0 (degrees, from +x towards +y).
    ecc_band, err_band : pair of (6, F) arrays, optional
        Lower and upper 95% bounds of the estimate's segment curves (fraction).
    pixel_bands : dict, optional
        ``{"Ecc": (lo, hi), "Err": (lo, hi)}``, each bound (F, P): 95% bands of the pixels.
    global_bands : dict, optional
        ``{"Ecc": (lo, hi), "Err": (lo, hi)}``, each bound (F,): 95% bands of the global curves.

    Returns
    -------
    StrainScore
    """
    X = as_float_array("points", points, shape=(None, 2))
    P = len(X)
    arrs = {}
    for name, v in (("ecc", ecc), ("err", err), ("truth_ecc", truth_ecc), ("truth_err", truth_err)):
        arrs[name] = as_float_array(name, v, shape=(None, P), allow_nan=True)
    F = arrs["ecc"].shape[0]
    for name, v in arrs.items():
        if v.shape != (F, P):
            raise ValueError(f"{name}: expected shape ({F}, {P}) like ecc, got {v.shape}")
    valid = np.isfinite(arrs["ecc"]) & np.isfinite(arrs["err"]) & np.isfinite(arrs["truth_ecc"]) \
        & np.isfinite(arrs["truth_err"])
    if not valid.any():
        raise ValueError("ecc, err, truth_ecc, truth_err: expected some (frame, pixel) pair where all are finite, "
                         "got none")
    e = {k: np.where(valid, v, np.nan) for k, v in arrs.items()}
    labels = segment_labels(X, centre, start_deg)
    out = {}
    cov_in, cov_n = 0, 0
    for q, kind, band in (("Ecc", "min", ecc_band), ("Err", "max", err_band)):
        est, tru = e[q.lower()], e["truth_" + q.lower()]
        out[f"pixel_rmse_{q}"] = float(np.sqrt(np.mean((est - tru)[valid] ** 2))) * PCT
        pe, pt, d = _peak_error(global_curve(est), global_curve(tru), kind)
        out[f"global_peak_{q}"], out[f"global_peak_{q}_truth"], out[f"global_peak_error_{q}"] = \
            pe * PCT, pt * PCT, d * PCT
        seg_est, seg_true = segment_curves(est, labels), segment_curves(tru, labels)
        errs = np.array([_peak_error(seg_est[k], seg_true[k], kind)[2] for k in range(N_SEGMENTS)])
        errs = np.abs(errs[np.isfinite(errs)])
        out[f"segment_peak_error_{q}_mean"] = float(errs.mean()) * PCT if errs.size else float("nan")
        out[f"segment_peak_error_{q}_max"] = float(errs.max()) * PCT if errs.size else float("nan")
        if band is None:
            out[f"coverage_pct_{q}"], out[f"band_width_{q}"] = None, None
        else:
            if len(band) != 2:
                raise ValueError(f"{q.lower()}_band: expected a pair (lo, hi) of (6, F) arrays, got {len(band)} items")
            k_in, k_n, width = _coverage(band, seg_true, f"{q.lower()}_band")
            out[f"coverage_pct_{q}"], out[f"band_width_{q}"] = PCT * k_in / k_n, width
            out[f"coverage_pct_peak_{q}"] = _covered_at_peak(
                (np.asarray(band[0], float), np.asarray(band[1], float)), seg_true, kind)
            cov_in, cov_n = cov_in + k_in, cov_n + k_n
        for name, bands, tru in (("pixels", pixel_bands, e["truth_" + q.lower()]),
                                 ("global", global_bands, global_curve(e["truth_" + q.lower()]))):
            if bands is None:
                continue
            if not isinstance(bands, dict) or q not in bands or len(bands[q]) != 2:
                raise ValueError(f"{name[:-1] if name == 'pixels' else name}_bands: expected a dict with 'Ecc' "
                                 f"and 'Err', each a pair (lo, hi), got {type(bands).__name__}")
            k_in, k_n, width = _coverage(bands[q], tru, f"{'pixel' if name == 'pixels' else name}_bands[{q!r}]")
            out[f"coverage_pct_{name}_{q}"], out[f"band_width_{name}_{q}"] = PCT * k_in / k_n, width
            if name == "global":
                out[f"coverage_pct_global_peak_{q}"] = _covered_at_peak(
                    (np.asarray(bands[q][0], float)[None], np.asarray(bands[q][1], float)[None]), tru[None], kind)
    both = ecc_band is not None and err_band is not None
    out["coverage_pct"] = PCT * cov_in / cov_n if both else None
    return StrainScore(**out, n_valid=int(valid.sum()), n_total=int(valid.size))
