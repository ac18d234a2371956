"""A small synthetic strain report with the names of ``sfem-filters strain``'s JSON (issue 42), for the
report, CSV and figure tests: pixels on a ring, a shortening and thickening cycle, every method block."""
from __future__ import annotations

import json

import numpy as np

from sfem_filters.imaging.strain import global_curve, segment_curves, segment_labels
from sfem_filters.imaging.strain_report import Z95


def _js(a):
    a = np.asarray(a, float)
    return np.where(np.isfinite(a), a.astype(object), None).tolist()


def synthetic_report(n_frames: int = 8, n_pixels: int = 60, seed: int = 0, empty_segment: int | None = None,
                     material: bool = False, start_deg: float = 30.0) -> dict:
    """A report dict as the verb writes it (JSON-ready: lists, ``None`` for NaN).

    ``empty_segment``: no pixel in that segment (its curves are all missing). ``material``: add a
    ``material`` block with a relative stiffness per segment and its sd.
    """
    rng = np.random.default_rng(seed)
    centre = np.array([32.0, 30.0])
    ang = np.sort(rng.uniform(0, 2 * np.pi, n_pixels))
    if empty_segment is not None:
        lo = np.radians(start_deg + 60 * empty_segment)
        ang = ang[np.mod(ang - lo, 2 * np.pi) >= np.radians(60)]
    r = rng.uniform(8, 12, len(ang))
    pts = np.round(centre + np.column_stack([r * np.cos(ang), r * np.sin(ang)]))
    t = 0.0225 + 0.015 * np.arange(n_frames)
    shape = np.sin(np.pi * (np.arange(n_frames) + 1) / (n_frames + 1))[:, None]        # a peak mid-cycle
    labels = segment_labels(pts, centre, start_deg)

    def field(a_cc, a_rr, noise):
        ecc = -a_cc * shape * (1 + 0.2 * np.cos(ang))[None] + noise * rng.standard_normal((n_frames, len(ang)))
        err = a_rr * shape * (1 + 0.3 * np.sin(ang))[None] + noise * rng.standard_normal((n_frames, len(ang)))
        ecr = 0.01 * shape * np.cos(2 * ang)[None]
        return ecc, err, ecr

    def curves(ecc, err, sd=None):
        g = {"Ecc": global_curve(ecc), "Err": global_curve(err)}
        s = {"Ecc": segment_curves(ecc, labels), "Err": segment_curves(err, labels)}
        if sd is not None:
            for d in (g, s):
                for q in ("Ecc", "Err"):
                    d[q + "_sd"] = np.where(np.isfinite(d[q]), sd, np.nan)
                    d[q + "_lo"], d[q + "_hi"] = d[q] - Z95 * d[q + "_sd"], d[q] + Z95 * d[q + "_sd"]
        return ({k: _js(v) for k, v in g.items()},
                {"start_deg": start_deg, **{k: _js(v) for k, v in s.items()}})

    ecc, err, ecr = field(0.15, 0.4, 0.01)
    g, s = curves(ecc, err, sd=0.004)
    report = {"route": "dense", "points": _js(pts), "frame_times_s": _js(t), "centre": _js(centre),
              "strain": {"Ecc": _js(ecc), "Err": _js(err), "Ecr": _js(ecr),
                         "Ecc_sd": _js(np.full_like(ecc, 0.01)), "Err_sd": _js(np.full_like(err, 0.02))},
              "global": g, "segments": s, "seconds": 1.0,
              "settings": {"material": "fixed: E of compliant_modulus unless given, nu nominal"}}
    for name, (a_cc, a_rr, noise) in {"conventional": (0.16, 0.3, 0.03), "spline": (0.14, 0.25, 0.0),
                                      "truth": (0.15, 0.45, 0.0)}.items():
        c, e, x = field(a_cc, a_rr, noise)
        g, s = curves(c, e, sd=0.006 if name == "spline" else None)             # the spline has a band too
        block = {"strain": {"Ecc": _js(c), "Err": _js(e)}, "global": g, "segments": s}
        if name == "spline":
            block["strain"]["Ecc_sd"] = _js(np.full_like(c, 0.02))
        if name == "conventional":
            block["strain"]["Ecr"] = _js(x)
            block["smoothing_sigma_px"] = 1.0
        if name == "truth":
            block["source"] = "synthetic truth"
        report[name] = block
    if material:
        report["material"] = {"segments": {"relative_stiffness": [1.0, 1.2, 0.8, 1.5, 1.0, 0.9],
                                           "relative_stiffness_sd": [0.1, 0.2, 0.1, 0.3, 0.15, 0.1]}}
    return json.loads(json.dumps(report))                      # exactly what a saved JSON reads back as
