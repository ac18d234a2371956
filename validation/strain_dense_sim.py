"""Strain against a truth nobody here wrote: DENSE-Sim cases, our route beside the conventional analysis.

For every DENSE-Sim case folder in the data directory (``$SFEM_FILTERS_DATA/dense_sim/``; the
library's registry names the two public ones, other cases of the same layout are scored alike),
each SNR and noise seed: complex Gaussian noise exactly as the scoring spec pins it
(:func:`sfem_filters.imaging.add_complex_noise`), one phase-to-Lagrangian-displacement conversion
shared by every method (:func:`sfem_filters.imaging.phase_to_displacement`), then

* the conventional analysis, finite-difference Green-Lagrange strain without smoothing and with a
  Gaussian of sigma 1 px inside the mask (:func:`sfem_filters.imaging.conventional_analysis`);
* our DENSE route, :func:`sfem_filters.cardiac.dense_case_strain` with its default for images
  (:func:`sfem_filters.cardiac.image_settings`, what ``sfem-filters strain`` runs): a Gmsh mesh of
  the reference myocardium, every tracked pixel observed through the shape functions blurred by the
  acquisition's point spread (``resolution_px`` from the case's acquisition,
  :attr:`sfem_filters.imaging.DenseCase.resolution_px`, with the complex signal around the
  myocardium from the images, :func:`sfem_filters.imaging.dense.background_signal`), the case's
  myocardium masks of every frame fused in (``border_masks=True``: each border node's motion across
  the border, read where the phase data's own smoothed estimate puts the node,
  ``border_correspondence="phase"``, with the contours route's sd rule) with the phase data at their
  own maximum-likelihood level (``phase_noise_level="evidence"``), the process noise per frame
  interval from the data's own acceleration (``process_profile="data"``), the linear smoother,
  Green-Lagrange strain of the recovered gradient with delta-method sd, the maximum-likelihood noise
  scale and the excess-error term in the 95% bands;
* at the first seed of each case and SNR, the error budget (:data:`ABLATIONS`): the point spread,
  the masks and the process profile each left out in turn; the masks at their stated level, and
  both sources at theirs; the masks' border data from the contours route's landmarks instead
  (tracked by bending-energy matching); the route's earlier default (the phase alone at the pixel
  centres with one process level) and that with its process noise chosen by its evidence
  (``process_fraction=None``, type-II maximum likelihood); and the nodal least-squares fit of each
  frame alone (no dynamics, no bands);

each scored by :func:`sfem_filters.benchmark.score_strain` (pixel RMSE, global and segment peak
errors in percentage points; coverage of the true segment curves by the 95% bands, with their mean
width; beside it the coverage of the true pixels and of the true global curve by their bands). The issue's
goals for the DENSE route are printed beside, and :func:`check` reports which
are met; the claim's plausibility check only asks that every number is finite and the conventional
analysis behaves as the spec describes (smoothing lowers the pixel RMSE).
"""
from __future__ import annotations

import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import scipy.sparse as sp

from sfem_filters.benchmark import score_strain
from sfem_filters.cardiac import StrainRouteSettings, dense_case_strain, image_settings
from sfem_filters.cardiac.strain_route import build_dense_model, gradient_operators, reference_mesh
from sfem_filters.imaging import (add_complex_noise, conventional_analysis, phase_to_displacement, read_dense_sim,
                                  truth_at_points)
from sfem_filters.imaging.strain import green_strain, mask_centre, project_strain

from ._core import MIB, fmt, md_table, mib_to_gb, peak_rss_bytes

NAME = "strain_dense_sim"
NEEDS_DATA = True
TITLE = "Strain against DENSE-Sim's ground truth"
FULL_COST = "about 18-25 minutes on 2 cores (12 runs of our route, 28 of its ablations)"
#: The quick tier runs one ablation (the full tier, without an ``ablations`` key, runs them all).
TIERS = {"quick": {"cases": ["phantom_subject_1"], "snr": [30.0], "seeds": [0], "frames": 8, "route": True,
                   "ablations": ["ours, without the masks (phase alone)"]},
         "full": {"cases": None, "snr": [30.0, 8.0], "seeds": [0, 1, 2], "frames": None, "route": True}}
#: Noise draws are seeded, our route is deterministic; timings are not compared.
TOLERANCES = {"*": (1e-6, 1e-9), "seconds": None, "cpu_seconds": None, "peak_rss_mb": None, "load": None}
#: The issue's goals for the DENSE route (percentage points; coverage in percent).
GOALS = {"global_peak_error_Ecc": 1.0, "global_peak_error_Err": 3.0, "segment_peak_error_Ecc_mean": 1.0,
         "segment_peak_error_Err_mean": 4.0, "coverage": (85.0, 99.0), "seconds": 180.0}
METRICS = ("pixel_rmse_Ecc", "pixel_rmse_Err", "global_peak_error_Ecc", "global_peak_error_Err",
           "segment_peak_error_Ecc_mean", "segment_peak_error_Ecc_max", "segment_peak_error_Err_mean",
           "segment_peak_error_Err_max", "coverage_pct_Ecc", "coverage_pct_Err", "band_width_Ecc", "band_width_Err",
           "coverage_pct_pixels_Ecc", "coverage_pct_pixels_Err", "band_width_pixels_Ecc", "band_width_pixels_Err",
           "coverage_pct_global_Ecc", "coverage_pct_global_Err", "band_width_global_Ecc", "band_width_global_Err",
           "coverage_pct_peak_Ecc", "coverage_pct_peak_Err", "coverage_pct_global_peak_Ecc",
           "coverage_pct_global_peak_Err")
#: The route's default, and its ablations (run at the first seed only).
OURS = "ours (DENSE route)"
#: Each ablation leaves one ingredient of the route's default for images (:func:`image_settings`: the acquisition's
#: point spread; the masks fused, their border placed by the phase data, the phase data and the masks each at their
#: evidence level; the process noise profile from the data) out, or changes it; the last two rows are the route's
#: earlier default (the phase alone at the pixel centres, one process level) and that with its process noise chosen
#: by the evidence.
ABLATIONS = {"ours, point observation (no PSF)": {"resolution_px": 1.0},
             "ours, without the masks (phase alone)": {"border_masks": False},
             "ours, masks at their stated level": {"mask_noise_level": "stated"},
             "ours, both sources at their stated levels": {"phase_noise_level": "stated", "mask_noise_level": "stated"},
             "ours, masks' border by landmark tracking (earlier default)": {"border_correspondence": "landmarks"},
             "ours, constant process noise": {"process_profile": "constant"},
             "ours, earlier default (phase alone, point observation, constant process noise)":
                 {"resolution_px": 1.0, "border_masks": False, "process_profile": "constant"},
             "ours, earlier default with process noise by the evidence":
                 {"resolution_px": 1.0, "border_masks": False, "process_profile": "constant",
                  "process_fraction": None}}
NODAL_FIT = "nodal fit per frame (no dynamics)"
#: ``strain_dense_sim_summary.md``: the page's first table alone, which the README shows.
EXTRA_MARKDOWN = {"summary": lambda results: summary_markdown(results)}


def data_root() -> Path:
    """``$SFEM_FILTERS_DATA/dense_sim`` (the cases' folder)."""
    env = os.environ.get("SFEM_FILTERS_DATA")
    if not env:
        raise FileNotFoundError("SFEM_FILTERS_DATA: expected the data directory holding dense_sim/<case>/ "
                                "(see sfem_filters.datasets), not set")
    return Path(env) / "dense_sim"


def case_folders(names) -> list:
    """The case folders to score: ``names``, or every folder with a ``config.yaml`` under the root."""
    root = data_root()
    folders = [root / n for n in names] if names else sorted(p.parent for p in root.glob("*/config.yaml"))
    missing = [str(f) for f in folders if not (f / "config.yaml").is_file()]
    if missing or not folders:
        raise FileNotFoundError(f"cases: expected DENSE-Sim case folders under {root}, missing {missing or 'all'}")
    return folders


def _truncated(case, frames):
    """The case's first ``frames`` frames (quick tier), or the case itself."""
    if not frames:
        return case
    from dataclasses import fields, replace
    kw = {}
    for f in fields(case):
        v = getattr(case, f.name)
        if isinstance(v, np.ndarray) and f.name == "phases":
            kw[f.name] = v[:, :frames]
        elif isinstance(v, np.ndarray) and f.name == "masks":
            kw[f.name] = v[:frames + 1]
        elif isinstance(v, np.ndarray) and f.name in ("magnitude", "truth_ecc", "truth_err", "frame_times_s"):
            kw[f.name] = v[:frames]
    return replace(case, **kw)


def _peak_rss_mb() -> float:
    """This process's peak resident memory in MiB (2**20 bytes): what ``peak_rss_mb`` stores."""
    return peak_rss_bytes() / MIB


def _row(base, method, score, seconds, cpu, extra=None) -> dict:
    d = score.to_dict()
    return {**base, "method": method, **{k: d.get(k) for k in METRICS}, **(extra or {}),
            "seconds": seconds, "cpu_seconds": cpu, "peak_rss_mb": _peak_rss_mb()}


def run_case(folder: Path, snr: float, seed: int, frames=None, route: bool = True,
             ablations=False) -> list:
    """Every method on one case, SNR and seed: a list of rows (metrics in percentage points).

    ``ablations``: False for none, True for all of :data:`ABLATIONS`, or a list of their names."""
    if ablations is not False and ablations is not True:
        unknown = [a for a in ablations if a not in ABLATIONS]
        if unknown:
            raise ValueError(f"ablations: expected names from {list(ABLATIONS)}, got {unknown}")
    case = _truncated(read_dense_sim(folder), frames)
    t_ecc, t_err = truth_at_points(case)
    t0, c0 = time.perf_counter(), time.process_time()
    noisy = add_complex_noise(case, snr, seed)
    tracks = phase_to_displacement(noisy)
    t_tracks, c_tracks = time.perf_counter() - t0, time.process_time() - c0
    base = {"case": folder.name, "snr": snr, "seed": seed, "n_points": int(len(tracks.points)),
            "n_frames": int(t_ecc.shape[0]), "untracked": int(tracks.n_untracked)}
    rows = []
    for sigma in (0.0, 1.0):
        t1, c1 = time.perf_counter(), time.process_time()
        a = conventional_analysis(noisy, sigma=sigma, tracks=tracks)
        sc = score_strain(a.strain.Ecc, a.strain.Err, t_ecc, t_err, a.strain.points, a.strain.centre)
        rows.append(_row(base, f"conventional, sigma {sigma:g} px", sc, t_tracks + time.perf_counter() - t1,
                         c_tracks + time.process_time() - c1))
    if not route:
        return rows
    chosen = ABLATIONS if ablations is True else {a: ABLATIONS[a] for a in ablations} if ablations else {}
    variants = {OURS: {}, **chosen}
    for method, kw in variants.items():
        t1, c1 = time.perf_counter(), time.process_time()
        r = dense_case_strain(noisy, image_settings(noisy, **kw), tracks=tracks)
        sc = score_strain(r.Ecc, r.Err, t_ecc, t_err, r.points, r.centre, start_deg=r.start_deg,
                          ecc_band=r.band("Ecc"), err_band=r.band("Err"),
                          pixel_bands={q: r.band(q, "pixels") for q in ("Ecc", "Err")},
                          global_bands={q: r.band(q, "global") for q in ("Ecc", "Err")})
        rows.append(_row(base, method, sc, t_tracks + time.perf_counter() - t1, c_tracks + time.process_time() - c1,
                         {"noise_scale_ml": r.settings.get("noise_scale_ml"),
                          "phase_noise_scale": r.settings.get("phase_noise_scale"),
                          "process_fraction": r.settings.get("process_fraction"),
                          "resolution_px": r.settings.get("resolution_px")}))
    if ablations:
        t1, c1 = time.perf_counter(), time.process_time()
        ecc, err, pts, centre = nodal_fit_strain(tracks, noisy.reference_mask, noisy.pixel_size_m)
        sc = score_strain(ecc, err, t_ecc, t_err, pts, centre)
        rows.append(_row(base, NODAL_FIT, sc, t_tracks + time.perf_counter() - t1, c_tracks + time.process_time() - c1))
    return rows


def nodal_fit_strain(tracks, reference_mask, pixel_size_m, settings=None) -> tuple:
    """The error budget's middle term: each frame's weighted least-squares nodal fit alone (no dynamics).

    The route's mesh and data weights (:func:`sfem_filters.cardiac.strain_route.build_dense_model`) with
    ``StrainRouteSettings()`` by default, i.e. the phase data alone observed at the pixel centres (what each
    frame's pixels say, without the images' point spread or masks), the fit ``U_t = J_t^-1 D^T W_t y_t`` of every frame on its own, and the strain of
    the route's gradient (``settings.strain``). Returns ``(Ecc, Err, points, centre)``.
    """
    cfg = StrainRouteSettings() if settings is None else settings
    if cfg.process_fraction is None:          # no dynamics here: the process noise plays no part
        cfg = replace(cfg, process_fraction=0.1)
    s = pixel_size_m
    mesh = reference_mesh(reference_mask, s, cfg.mesh, cfg.element_px)
    model, y, _, Xin = build_dense_model(mesh, tracks, s, cfg)
    U = y if y.shape[1] == mesh.n_dofs else np.zeros((y.shape[0], mesh.n_dofs))
    if y.shape[1] != mesh.n_dofs:
        U[:, model.dofmap.free] = y
    ops, weights = gradient_operators(mesh, Xin, cfg.strain)
    F, P = y.shape[0], len(tracks.points)
    grad = np.stack([(sp.csr_matrix(weights @ op) @ U.T).T for op in ops], axis=-1).reshape(F, P, 2, 2)
    centre = mask_centre(reference_mask) if cfg.centre is None else np.asarray(cfg.centre, float)
    ecc, err, _ = project_strain(green_strain(grad), tracks.points, centre)
    return ecc, err, tracks.points, centre


def compute(settings: dict, out_dir) -> dict:
    rows = []
    for folder in case_folders(settings["cases"]):
        for snr in settings["snr"]:
            for seed in settings["seeds"]:
                print(f"{folder.name} SNR {snr:g} seed {seed}", flush=True)
                rows.extend(run_case(folder, snr, seed, settings.get("frames"), settings.get("route", True),
                                     ablations=(settings.get("ablations", True)
                                                if seed == settings["seeds"][0] else False)))
    return {"rows": rows, "goals": {k: list(v) if isinstance(v, tuple) else v for k, v in GOALS.items()},
            "units": "strain metrics in percentage points; coverage in percent of segment-frames"}


def _mean_rows(rows) -> list:
    """Per case, SNR and method: the mean over seeds of every metric."""
    groups = {}
    for r in rows:
        groups.setdefault((r["case"], r["snr"], r["method"]), []).append(r)
    out = []
    for (case, snr, method), rs in groups.items():
        mean = {k: float(np.mean([r[k] for r in rs])) if all(r.get(k) is not None for r in rs) else None
                for k in (*METRICS, "seconds", "process_fraction", "resolution_px")}
        peak = [r["peak_rss_mb"] for r in rs if r.get("peak_rss_mb") is not None]
        out.append({"case": case, "snr": snr, "method": method, "seeds": len(rs), **mean,
                    "peak_rss_mb": max(peak) if peak else None})
    return out


def _pair(r, a, b, spec=".2f") -> str:
    return f"{fmt(r[a], spec)} / {fmt(r[b], spec)}" if r.get(a) is not None and r.get(b) is not None else ""


def summary_markdown(results: dict) -> str:
    """The page's first table: our route's default on each case and SNR, beside the better conventional variant,
    with the goals met and missed (the full tables follow it)."""
    means = _mean_rows(results["rows"])
    better = _better_conventional(results["rows"])            # per seed, as goals_met compares
    conv = {}
    for (case, snr, _seed, m), v in better.items():
        conv.setdefault((case, snr, m), []).append(v)
    conv = {k: float(np.mean(v)) for k, v in conv.items()}
    cols = ["case", "SNR", "RMSE Ecc / Err (conventional)", "global peak error Ecc / Err",
            "segment peak error Ecc / Err", "coverage Ecc / Err [%]", "at the peaks [%]", "s"]
    body = []
    for r in means:
        if r["method"] != OURS:
            continue
        c = [conv.get((r["case"], r["snr"], m)) for m in ("pixel_rmse_Ecc", "pixel_rmse_Err")]
        body.append([r["case"], fmt(r["snr"], "g"),
                     f"{_pair(r, 'pixel_rmse_Ecc', 'pixel_rmse_Err')} ({fmt(c[0], '.2f')} / {fmt(c[1], '.2f')})",
                     _pair(r, "global_peak_error_Ecc", "global_peak_error_Err", "+.2f"),
                     _pair(r, "segment_peak_error_Ecc_mean", "segment_peak_error_Err_mean"),
                     _pair(r, "coverage_pct_Ecc", "coverage_pct_Err", ".1f"),
                     _pair(r, "coverage_pct_peak_Ecc", "coverage_pct_peak_Err", ".1f"), fmt(r["seconds"], ".0f")])
    notes = ["Our route's default for images (what `sfem-filters strain CASE_DIR` runs), means over the noise seeds; "
             "strain in percentage points, peak errors signed (estimate - truth). RMSE: over every reference pixel "
             "and frame, in brackets the better conventional variant's (the better of the two at each seed, as the "
             "goal compares them); segment peak error: the mean over the six "
             "segments of its absolute value; coverage: of the true segment curves by our 95% bands, over every "
             "segment-frame and at the frame of each segment's true peak; s: seconds a run. "
             "Goals, every case and SNR at once: "
             "pixel RMSE below the better conventional variant; |global peak error| at most 1.0 (Ecc) and 3.0 (Err); "
             "mean segment peak error at most 1.0 (Ecc) and 4.0 (Err); band coverage of the segment-frames 85-99%; "
             "at most 180 s a run. No goal is set for the coverage at the peaks (where a peak is read): it is "
             "reported beside."]
    met = goals_met(results)
    if met:
        notes.append("Goals met: " + "; ".join(f"{k} {'yes' if v else 'no'}" for k, v in met.items()) + ".")
        misses = goals_missed(results)
        notes.append("Where a goal is missed (each case and SNR; the worst seed): "
                     + ("; ".join(misses) if misses else "nowhere") + ".")
    return md_table(cols, body) + "\n\n" + "\n\n".join(notes)


def markdown(results: dict) -> str:
    means = _mean_rows(results["rows"])
    cols = ["case", "SNR", "method", "seeds", "RMSE Ecc", "RMSE Err", "global peak err Ecc", "global peak err Err",
            "segment peak err Ecc mean / max", "segment peak err Err mean / max", "seconds", "peak memory [GB]"]
    body = []
    for r in means:
        body.append([r["case"], fmt(r["snr"], "g"), r["method"], r["seeds"], fmt(r["pixel_rmse_Ecc"], ".2f"),
                     fmt(r["pixel_rmse_Err"], ".2f"), fmt(r["global_peak_error_Ecc"], "+.2f"),
                     fmt(r["global_peak_error_Err"], "+.2f"),
                     f"{fmt(r['segment_peak_error_Ecc_mean'], '.2f')} / {fmt(r['segment_peak_error_Ecc_max'], '.2f')}",
                     f"{fmt(r['segment_peak_error_Err_mean'], '.2f')} / {fmt(r['segment_peak_error_Err_max'], '.2f')}",
                     fmt(r["seconds"], ".0f"),
                     fmt(mib_to_gb(r["peak_rss_mb"]), ".2f") if r.get("peak_rss_mb") is not None else ""])
    bcols = ["case", "SNR", "method", "band coverage Ecc / Err [%]", "at each segment's peak frame [%]",
             "band width Ecc / Err", "pixel band coverage Ecc / Err [%] (width)", "global band coverage Ecc / Err [%]",
             "global band holds the peak Ecc / Err [%]", "process fraction", "resolution [px]"]
    bbody = []
    for r in means:
        if r["coverage_pct_Ecc"] is None:
            continue
        bbody.append([r["case"], fmt(r["snr"], "g"), r["method"], _pair(r, "coverage_pct_Ecc", "coverage_pct_Err", ".1f"),
                      _pair(r, "coverage_pct_peak_Ecc", "coverage_pct_peak_Err", ".1f"),
                      _pair(r, "band_width_Ecc", "band_width_Err"),
                      f"{_pair(r, 'coverage_pct_pixels_Ecc', 'coverage_pct_pixels_Err', '.1f')} "
                      f"({_pair(r, 'band_width_pixels_Ecc', 'band_width_pixels_Err', '.1f')})",
                      _pair(r, "coverage_pct_global_Ecc", "coverage_pct_global_Err", ".1f"),
                      _pair(r, "coverage_pct_global_peak_Ecc", "coverage_pct_global_peak_Err", ".0f"),
                      fmt(r["process_fraction"], ".2f") if r.get("process_fraction") is not None else "",
                      fmt(r["resolution_px"], ".2f") if r.get("resolution_px") is not None else ""])
    notes = ["Accuracy: strain in percentage points (Green-Lagrange, radial and circumferential about the reference "
             "myocardium's centre of mass), means over the noise seeds; peak errors are signed (estimate - truth). "
             "Our route's default (main row, every "
             "seed) is its default for images (sfem_filters.cardiac.image_settings, the command line's default): "
             "each datum observed through the acquisition's point spread (a Gaussian of FWHM the acquired pixel, "
             "from the case's config) over the tissue with the complex signal the images show around the "
             "myocardium mixed in at the borders; the case's myocardium masks of every frame fused in (each border "
             "node's motion across the mask's border, read where the phase data's own estimate puts the node, with "
             "the contours route's sd rule), the phase data and the masks each at their own maximum-likelihood "
             "level; the process noise per frame interval following the data's own acceleration "
             "(never below 0.1 of the noise floor). The ablations, at the first seed only, each leave one of these "
             "out or change it (the point observation at the pixel centre; the phase alone; the masks at their "
             "stated sd; both sources at their stated sd; the masks' border data from landmarks tracked by "
             "bending-energy matching; one process level for every interval), then the route's earlier default "
             "(the phase alone at the pixel centres, one process level) and that with its process noise chosen by "
             "its evidence (type-II maximum likelihood), and each frame's nodal least-squares fit alone. "
             "Seconds: wall time of one run, phase conversion included, on the machine of the header (mean over "
             "the seeds). Peak memory: the claim process's peak resident memory at the end of the run (the most "
             "over the seeds; every run shares one process, so this bounds each run's own from above).",
             "Bands (our route and its ablations): the fraction of (segment, frame) pairs whose true segment mean "
             "lies inside our 95% band (the spec's coverage), and of the six segments at the frame of each one's "
             "true peak; the bands' mean width; the same for the pixels (with the pixel bands' mean width) and for "
             "the global curve's frames, and whether the global band holds the true global curve at its peak frame "
             "(the percentage of seeds). Process fraction: the route's process noise per frame over the noise floor "
             "(mean over the seeds). Resolution: the acquired resolution (reconstructed pixels) the observation "
             "operator used (1: point observation)."]
    return (summary_markdown(results) + "\n\n**Accuracy of every method**\n\n" + md_table(cols, body)
            + "\n\n**Bands of our route**\n\n" + md_table(bcols, bbody) + "\n\n" + "\n\n".join(notes))


def _better_conventional(rows) -> dict:
    """``{(case, snr, seed, metric): the lower pixel RMSE of the two conventional variants}``."""
    conv = {}
    for r in rows:
        if r["method"].startswith("conventional"):
            key = (r["case"], r["snr"], r["seed"])
            for m in ("pixel_rmse_Ecc", "pixel_rmse_Err"):
                conv[key + (m,)] = min(conv.get(key + (m,), np.inf), r[m])
    return conv


def goals_met(results: dict) -> dict:
    """Each goal of the DENSE route: met on every case, SNR and seed (True) or not."""
    rows = results["rows"]
    ours = [r for r in rows if r["method"] == OURS]
    if not ours:
        return {}
    conv = _better_conventional(rows)
    lo, hi = GOALS["coverage"]
    return {
        "pixel RMSE below the better conventional": all(
            r[m] < conv[(r["case"], r["snr"], r["seed"], m)] for r in ours
            for m in ("pixel_rmse_Ecc", "pixel_rmse_Err")),
        "global peaks": all(abs(r["global_peak_error_Ecc"]) <= GOALS["global_peak_error_Ecc"]
                            and abs(r["global_peak_error_Err"]) <= GOALS["global_peak_error_Err"] for r in ours),
        "segment peaks": all(r["segment_peak_error_Ecc_mean"] <= GOALS["segment_peak_error_Ecc_mean"]
                             and r["segment_peak_error_Err_mean"] <= GOALS["segment_peak_error_Err_mean"]
                             for r in ours),
        "band coverage": all(lo <= r[c] <= hi for r in ours for c in ("coverage_pct_Ecc", "coverage_pct_Err")),
        "time": all(r["seconds"] <= GOALS["seconds"] for r in ours),
    }


def draw_misses(r: dict, conv: dict) -> dict:
    """The goals one draw of our route (row ``r``) misses: ``{goal: (badness, text)}``, in the goals' order.

    ``conv``: :func:`_better_conventional` of the run. ``badness`` orders the misses of one goal over draws
    (the largest is the worst): the excess over the conventional RMSE, ``|peak error|``, the segment peak
    error, the coverage's distance from the goal band's middle, the seconds. A metric that is not a
    number (NaN) misses its goal (badness infinite): a draw without a figure has not met it.
    """
    lo, hi = GOALS["coverage"]
    out = {}
    for m in ("pixel_rmse_Ecc", "pixel_rmse_Err"):
        over = _number(r[m]) - conv[(r["case"], r["snr"], r["seed"], m)]
        if not over < 0:
            out[f"RMSE {m[-3:]}"] = (_bad(over), f"RMSE {m[-3:]} {over:+.2f} above the better conventional")
    for m in ("global_peak_error_Ecc", "global_peak_error_Err"):
        if not abs(_number(r[m])) <= GOALS[m]:
            out[f"global peak {m[-3:]}"] = (_bad(abs(_number(r[m]))), f"global peak {m[-3:]} {_number(r[m]):+.2f}")
    for m in ("segment_peak_error_Ecc_mean", "segment_peak_error_Err_mean"):
        if not _number(r[m]) <= GOALS[m]:
            out[f"segment peak {m.split('_')[3]}"] = (_bad(r[m]), f"segment peak {m.split('_')[3]} {_number(r[m]):.2f}")
    for m in ("coverage_pct_Ecc", "coverage_pct_Err"):
        if not lo <= _number(r[m]) <= hi:
            out[f"coverage {m[-3:]}"] = (_bad(abs(_number(r[m]) - (lo + hi) / 2)), f"coverage {m[-3:]} {_number(r[m]):.1f}%")
    if not _number(r["seconds"]) <= GOALS["seconds"]:
        out["time"] = (_bad(r["seconds"]), f"time {_number(r['seconds']):.0f} s")
    return out


def _number(v) -> float:
    """A metric as a float, NaN for None."""
    return float("nan") if v is None else float(v)


def _bad(v) -> float:
    """Badness for :func:`draw_misses`: infinite for NaN, so a draw without a figure is the worst."""
    v = _number(v)
    return v if np.isfinite(v) else float("inf")


#: The order :func:`goals_missed` names the goals in.
GOAL_ORDER = ("RMSE Ecc", "RMSE Err", "global peak Ecc", "global peak Err", "segment peak Ecc", "segment peak Err",
              "coverage Ecc", "coverage Err", "time")


def goals_missed(results: dict) -> list:
    """For each case and SNR, the goals our route's default misses on some seed, with the worst value (text)."""
    rows = results["rows"]
    conv = _better_conventional(rows)
    by = {}
    for r in rows:
        if r["method"] == OURS:
            by.setdefault((r["case"], r["snr"]), []).append(draw_misses(r, conv))
    out = []
    for (case, snr), draws in by.items():
        miss = [max((d[g] for d in draws if g in d), key=lambda v: v[0])[1] for g in GOAL_ORDER
                if any(g in d for d in draws)]
        if miss:
            out.append(f"{case} SNR {snr:g}: " + ", ".join(miss))
    return out


#: The metrics every row must hold as finite numbers (:func:`nonfinite_metrics`).
FINITE = ("pixel_rmse_Ecc", "pixel_rmse_Err", "global_peak_error_Ecc", "global_peak_error_Err",
          "segment_peak_error_Ecc_mean", "segment_peak_error_Err_mean")


def nonfinite_metrics(rows) -> list:
    """One problem (text) per row and metric of :data:`FINITE` that is missing or not finite."""
    return [f"{r['case']} SNR {r['snr']:g} seed {r['seed']} {r['method']}: {k} not finite"
            for r in rows for k in FINITE if r.get(k) is None or not np.isfinite(r[k])]


def check(results: dict, tier: str) -> list:
    """Plausibility, not the goals: every metric finite, and for each case, SNR and seed the
    conventional analysis smoothed at sigma 1 px has a lower pixel RMSE of Ecc than unsmoothed (the
    trade-off the spec describes)."""
    problems = nonfinite_metrics(results["rows"])
    by = {}
    for r in results["rows"]:
        by.setdefault((r["case"], r["snr"], r["seed"]), {})[r["method"]] = r
    for key, methods in by.items():
        raw, smooth = methods.get("conventional, sigma 0 px"), methods.get("conventional, sigma 1 px")
        if raw and smooth and not smooth["pixel_rmse_Ecc"] < raw["pixel_rmse_Ecc"]:
            problems.append(f"{key}: smoothing did not lower the conventional pixel RMSE of Ecc")
    return problems
