"""What a strain report adds to the curves: peaks and time to peak, the ground truth's curves, a tidy CSV.

Works on the JSON that ``sfem-filters strain`` writes (the docs' how-to 'Strain from your DENSE
images' tables its keys), as a dict, so that a saved report can be re-read, tabulated and drawn
again without rerunning anything.
A report holds *method blocks*: the route's own (the top level, ``report["route"]`` names it,
``"dense"`` or ``"contours"``) and the optional ``conventional``, ``spline`` and ``truth`` blocks,
each with the same names:

* ``strain``: ``Ecc``, ``Err`` (and ``Ecr``, ``Ecc_sd``, ``Err_sd`` where the method has them), each
  (F, P), one column per reference pixel ``points[p]``;
* ``global``: ``Ecc``, ``Err`` (and ``_sd``, ``_lo``, ``_hi`` where the method has a 95% band), each (F,);
* ``segments``: ``start_deg`` and the same names, each (6, F): segment k spans
  ``start_deg + 60 k`` to ``start_deg + 60 (k + 1)`` degrees about the centre, from the image's +x
  axis towards +y.

Strains are Green-Lagrange, a fraction (dimensionless; ``100 x`` for percent), points in pixels
(x = column, y = row), times in s after the encoding (the reference configuration, t = 0).
``None`` in the JSON is a missing value (NaN here).

* :func:`peaks`: peak value and time to peak of each curve, the minimum for Ecc (shortening) and
  the maximum for Err (thickening), with the curve's 95% band at that frame where it has one;
* :func:`truth_block`: a ground truth (DENSE-Sim's ``GT_Ecc``, ``GT_Err``) as a method block, its
  curves the means over the same pixels and segments as the estimate's;
* :func:`spline_block`: the thin-plate spline through the route's observed points
  (:func:`sfem_filters.imaging.spline_strain.spline_strain`) as the ``spline`` block;
* :func:`with_peaks`: the report with a ``peaks`` entry in every method block;
* :func:`strain_csv`: the report as one tidy (long) CSV table, :data:`CSV_COLUMNS`.

>>> import numpy as np
>>> from sfem_filters.imaging.strain_report import peaks
>>> t = np.array([0.0, 0.1, 0.2, 0.3])
>>> p = peaks({"Ecc": [-0.01, -0.05, -0.12, -0.08], "Err": [0.02, 0.1, 0.3, 0.2]}, t)
>>> p["Ecc"]["value"], p["Ecc"]["time_s"], p["Err"]["frame"]
(-0.12, 0.2, 2)
"""
from __future__ import annotations

import csv
import gzip
import math

import numpy as np

from .._validate import as_float_array
from .strain import N_SEGMENTS, curve_peak, global_curve, segment_curves, segment_labels

__all__ = ["peaks", "truth_block", "spline_block", "with_peaks", "method_blocks", "strain_csv", "csv_row_count",
           "CSV_COLUMNS", "PEAK_KIND", "COMPONENTS", "BLOCKS", "Z95"]

#: Which extreme a curve's peak is: Ecc shortens (minimum), Err thickens (maximum).
PEAK_KIND = {"Ecc": "min", "Err": "max"}
#: Strain components a report may hold, in the CSV's order.
COMPONENTS = ("Ecc", "Err", "Ecr")
#: Optional method blocks beside the route's own, in the CSV's order.
BLOCKS = ("conventional", "spline", "truth")
#: Two-sided 95% normal quantile (a pixel's band in the CSV is ``value +- Z95 sd``).
Z95 = 1.959963984540054
#: Columns of :func:`strain_csv`, one row per (method, region, frame, component).
CSV_COLUMNS = ("method", "region", "index", "segment", "x_px", "y_px", "frame", "time_s", "component", "value",
               "sd", "lo", "hi")


def _js(a):
    """A float array as JSON lists, ``None`` for NaN."""
    a = np.asarray(a, float)
    return np.where(np.isfinite(a), a.astype(object), None).tolist()


def _num(x) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def peaks(curves: dict, times) -> dict:
    """Peak value and time to peak of each Ecc and Err curve in ``curves``.

    Parameters
    ----------
    curves : dict
        ``Ecc`` and/or ``Err``, each (F,) (a global curve) or (K, F) (K segment curves), a fraction;
        optionally ``Ecc_lo``, ``Ecc_hi``, ``Err_lo``, ``Err_hi`` of the same shape (a 95% band).
        Other entries (``start_deg``, ``*_sd``) are ignored. ``None`` or NaN: a missing frame.
    times : (F,) array
        Frame times (s after the encoding).

    Returns
    -------
    dict
        Per component present, ``{"value", "time_s", "frame", "lo", "hi"}``: the minimum (Ecc) or
        maximum (Err) over frames, the time and frame index where it is (the first such frame),
        and the curve's band at that frame (``None`` when the curve has no band). This band is
        the curve's pointwise 95% band at the peak frame, not an interval of the peak value or of
        its time. Scalars for a (F,) curve, lists of K for (K, F); ``None`` and frame -1 for a
        curve with no finite value.
    """
    t = as_float_array("times", times, shape=(None,))
    out = {}
    for q, kind in PEAK_KIND.items():
        if q not in curves:
            continue
        c = as_float_array(f"curves[{q!r}]", curves[q], allow_nan=True)
        if c.ndim not in (1, 2) or c.shape[-1] != len(t):
            raise ValueError(f"curves[{q!r}]: expected shape ({len(t)},) or (K, {len(t)}) to match times, "
                             f"got shape {c.shape}")
        band = [as_float_array(f"curves[{q + s!r}]", curves[q + s], shape=c.shape, allow_nan=True)
                if q + s in curves else None for s in ("_lo", "_hi")]
        rows = []
        for k, row in enumerate(np.atleast_2d(c)):
            value, i = curve_peak(row, kind)
            at = [None if b is None or i < 0 else _num(np.atleast_2d(b)[k, i]) for b in band]
            rows.append({"value": _num(value), "time_s": float(t[i]) if i >= 0 else None, "frame": int(i),
                         "lo": at[0], "hi": at[1]})
        out[q] = rows[0] if c.ndim == 1 else {key: [r[key] for r in rows] for key in rows[0]}
    return out


def truth_block(truth_ecc, truth_err, points, centre, start_deg: float = 0.0,
                source: str = "ground truth") -> dict:
    """A ground truth (F, P) of Ecc and Err at ``points`` as a method block (see the module docstring).

    Its global and segment curves are means over the pixels with a finite truth, per frame, the
    segments from ``centre`` (x, y pixels) and ``start_deg`` as the estimate's
    (:func:`sfem_filters.imaging.strain.segment_labels`), so truth and estimate are compared on
    the same pixels. ``source`` says where the truth comes from (kept in the block).
    """
    X = as_float_array("points", points, shape=(None, 2))
    ecc = as_float_array("truth_ecc", truth_ecc, shape=(None, len(X)), allow_nan=True)
    err = as_float_array("truth_err", truth_err, shape=ecc.shape, allow_nan=True)
    labels = segment_labels(X, centre, start_deg)
    return {"source": str(source), "strain": {"Ecc": _js(ecc), "Err": _js(err)},
            "global": {"Ecc": _js(global_curve(ecc)), "Err": _js(global_curve(err))},
            "segments": {"start_deg": float(start_deg), "Ecc": _js(segment_curves(ecc, labels)),
                         "Err": _js(segment_curves(err, labels))}}


def spline_block(spline, through: str) -> dict:
    """A :class:`sfem_filters.imaging.spline_strain.SplineStrain` as the report's ``spline`` block (the
    names of ``conventional``, with the spline's delta-method ``*_sd``, ``*_lo``, ``*_hi`` where its data
    had an sd); ``through`` says which observed points it interpolates, ``settings`` how."""
    d = spline.to_dict()
    return {"through": str(through), "settings": d["settings"], "seconds": d["seconds"], "strain": d["strain"],
            "global": d["global"], "segments": d["segments"]}


def method_blocks(report: dict) -> list:
    """``(method name, block)`` of every method in a report: the route's own first (named by
    ``report["route"]``), then :data:`BLOCKS` that are present."""
    if not isinstance(report, dict) or "global" not in report or "frame_times_s" not in report:
        raise ValueError("report: expected the strain report dict (keys frame_times_s, global, segments, ...), got "
                         + (f"keys {sorted(report)}" if isinstance(report, dict) else type(report).__name__))
    out = [(str(report.get("route", "estimate")), report)]
    out += [(name, report[name]) for name in BLOCKS if isinstance(report.get(name), dict)]
    return out


def with_peaks(report: dict) -> dict:
    """``report`` with ``peaks`` in every method block, ``{"global": peaks(global), "segments":
    peaks(segments)}`` (:func:`peaks`; segment lists indexed by k); a new dict, the input unchanged."""
    method_blocks(report)
    t = report["frame_times_s"]

    def add(block):
        p = {"global": peaks(block["global"], t)}
        if "segments" in block:
            p["segments"] = peaks(block["segments"], t)
        return {**block, "peaks": p}
    out = add(report)                              # shallow copies: the arrays are shared, not copied
    for name in BLOCKS:
        if isinstance(report.get(name), dict):
            out[name] = add(report[name])
    return out


def _labels(report: dict):
    """Segment of each reference pixel from the report's centre and start, or None without a centre."""
    if report.get("centre") is None:
        return None
    return segment_labels(report["points"], report["centre"], report.get("segments", {}).get("start_deg", 0.0))


def _cell(v) -> str:
    """A CSV cell: repr of a float (round-trips exactly), empty for a missing value."""
    if v is None:
        return ""
    v = float(v)
    return "" if not math.isfinite(v) else repr(v)


def _rows(method: str, block: dict, report: dict, labels):
    t = report["frame_times_s"]
    F = len(t)
    pts = report["points"]
    strain = block.get("strain", {})
    for q in COMPONENTS:
        if q not in strain:
            continue
        v = np.asarray(strain[q], float)
        sd = np.asarray(strain[q + "_sd"], float) if q + "_sd" in strain else None
        for f in range(F):
            for p in range(v.shape[1]):
                s = None if sd is None else sd[f, p]
                val = v[f, p]
                band = ("", "") if s is None or not np.isfinite(s) else (_cell(val - Z95 * s), _cell(val + Z95 * s))
                yield (method, "pixel", p, "" if labels is None else int(labels[p]), _cell(pts[p][0]),
                       _cell(pts[p][1]), f, _cell(t[f]), q, _cell(val), _cell(s), *band)
    for region, d in (("global", block.get("global", {})), ("segment", block.get("segments", {}))):
        for q in COMPONENTS:
            if q not in d:
                continue
            v = np.atleast_2d(np.asarray(d[q], float))
            extra = [np.atleast_2d(np.asarray(d[q + s], float)) if q + s in d else None for s in ("_sd", "_lo", "_hi")]
            for k in range(v.shape[0]):
                for f in range(F):
                    idx = "" if region == "global" else k
                    yield (method, region, idx, idx, "", "", f, _cell(t[f]), q, _cell(v[k, f]),
                           *("" if e is None else _cell(e[k, f]) for e in extra))


def csv_row_count(report: dict) -> int:
    """Rows (without the header) :func:`strain_csv` writes: per method block, frames x (pixels x
    pixel components + global components + 6 x segment components)."""
    F = len(report["frame_times_s"])
    n = 0
    for _, block in method_blocks(report):
        n += sum(F * np.shape(block.get("strain", {})[q])[1] for q in COMPONENTS if q in block.get("strain", {}))
        n += sum(F for q in COMPONENTS if q in block.get("global", {}))
        n += sum(F * N_SEGMENTS for q in COMPONENTS if q in block.get("segments", {}))
    return n


def strain_csv(report: dict, path) -> str:
    """Write a strain report as one tidy (long) CSV table; returns the path written.

    One row per (method, region, frame, component) the report holds, columns :data:`CSV_COLUMNS`:

    * ``method``: the route (``dense`` or ``contours``), ``conventional``, ``spline`` or ``truth``;
    * ``region``: ``pixel`` (``index`` = p, the row of ``points``; ``x_px``, ``y_px`` its reference
      position in pixels, x = column, y = row), ``global`` (``index`` empty) or ``segment``
      (``index`` = k); ``segment`` is the segment of the pixel or the segment itself (empty for
      global, and for pixels when the report has no ``centre``);
    * ``frame`` (0-based), ``time_s`` (s after the encoding), ``component`` (``Ecc``, ``Err``, ``Ecr``);
    * ``value``: Green-Lagrange strain, a fraction (dimensionless), exactly the JSON's number;
      ``sd`` its standard deviation and ``lo``, ``hi`` its 95% band where the method has them
      (for a pixel ``value -+ 1.96 sd``; for a curve the JSON's ``_lo``, ``_hi``); an empty cell is a
      missing value (pandas reads NaN, R reads NA).

    Pixel rows make up nearly all of the table (a DENSE-Sim slice: ~1000 pixels x 62 frames x 3
    components per method); filter on ``region`` for the curves. A ``path`` ending in ``.gz`` is
    written gzip-compressed (pandas and R read it directly).
    """
    blocks = method_blocks(report)
    labels = _labels(report)
    path = str(path)
    opener = gzip.open if path.endswith(".gz") else open
    with opener(path, "wt", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_COLUMNS)
        for name, block in blocks:
            w.writerows(_rows(name, block, report, labels))
    return path
