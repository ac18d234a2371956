"""The strain command's time and memory, up to the largest slice issue 42 names.

Issue 42 (item 3) asks that a DENSE-Sim slice of up to about 1300 reference pixels and 62 frames
runs end to end, images to report, in at most 3 minutes and 4 GB on a 2-core machine with the
default settings, with progress from its first second. The given cases are smaller (their sizes
are in the table), and the route's cost grows with the mesh (the filter's, about as the cube of
the nodes; its stored matrices as their square), so the cases alone do not show the budget at
the size it names. This claim runs the command exactly as a user types it:

``sfem-filters strain FOLDER --snr 30 --json OUT``

(default settings, default BLAS threads, progress on; ``--snr 30`` as the validation page adds
its noise) on

* each given case as it is, and
* the in-vivo case **resampled to a finer grid** until its reference myocardium has at least
  :data:`TARGET_PIXELS` pixels (:func:`write_resampled_case`): the same anatomy, motion,
  acquisition and truth, sampled at a smaller pixel, so the mesh and every array grow as a
  larger slice's would. The complex signal ``magnitude * exp(i phase)`` of each encoding is
  interpolated linearly (the wrapped phase itself cannot be), the masks by linear interpolation of
  their indicator at 1/2, the truth by linear interpolation normalised over its known pixels; the
  configuration keeps the field of view and gets the new matrix (``round(N_im * zoom)``: the zoom
  aligns the images' edges, so the pixel shrinks by the new matrix over the old; the target's
  matrix is the smallest that reaches it, :func:`matrix_for_pixels`) and the acquired resolution (``N_im / N_im_pre_spiral``) grows by as much. The folder is
  written to a temporary folder and removed after the run (it is made from the data directory's
  case, never committed).

Measured per run (first_run's measurement, :mod:`validation.first_run`): the wall time from the
command to the report, the time to the first line on stderr and to the run's own first progress
line, and the peak resident memory of the command's process (``ru_maxrss`` of a wrapper's only
child, so each run is measured alone); from its JSON, the reference pixels, frames, mesh nodes
and state dimension, the route's own seconds, and its scores against the case's truth (the
validation page's metrics, to show that the larger slice is still answered sensibly, not as a
goal). Quick tier: the resampling and the command on the in-vivo case shrunk to a coarser grid,
first 6 frames.

Timings depend on the machine and what else runs on it; the header's load average says which.
"""
from __future__ import annotations

import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml
from scipy import ndimage

from sfem_filters.benchmark import score_strain

from ._core import fmt, md_table
from .closing_loop import command
from .first_run import FIRST_LINE_S, _timed_run, first_progress, load_stretch, user_environment
from .strain_dense_sim import case_folders

NAME = "strain_budget"
TITLE = "The strain command's time and memory, up to a 1300-pixel slice"
NEEDS_DATA = True
FULL_COST = "about 3-4 min"
#: The reference myocardium the resampled slice must reach (issue 42, item 3: "up to about 1300").
TARGET_PIXELS = 1300
#: The issue's budget for one slice, images to report, default settings, on a 2-core machine.
BUDGET_S = 180.0
BUDGET_GB = 4.0
#: Each run: (case folder name, zoom: a factor, "target" to reach TARGET_PIXELS, or 1 as given; frames or None).
TIERS = {"quick": {"runs": [["invivo_subject_1", 0.6, 6]], "snr": 30.0},
         "full": {"runs": [["invivo_subject_1", 1.0, None], ["phantom_subject_1", 1.0, None],
                           ["invivo_subject_1", "target", None]], "snr": 30.0}}
#: Times and memory are the machine's; the rest (sizes, scores) is deterministic.
TOLERANCES = {"*": (1e-6, 1e-9), "wall_s": None, "first_output_s": None, "first_progress_s": None,
              "peak_rss_gb": None, "route_s": None, "matrix_search": None}
#: The files of a DENSE-Sim case folder and how each is resampled.
_COMPLEX = ("phase_x.npy", "phase_y.npy")
_MASKS = "LV_mask_time_lowres.npy"
_TRUTH = ("GT_Ecc.npy", "GT_Err.npy")

# Runs the command as its only child and writes that child's peak resident memory (kB) to argv[1].
_WRAPPER = ("import resource, subprocess, sys\n"
            "code = subprocess.call(sys.argv[2:])\n"
            "open(sys.argv[1], 'w').write(str(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss))\n"
            "sys.exit(code)\n")


def _zoom_mask(mask, zoom: float) -> np.ndarray:
    """A boolean mask (..., H, W) on the grid ``zoom`` times finer: its indicator interpolated linearly, at 1/2."""
    m = np.asarray(mask, float)
    factors = (1.0,) * (m.ndim - 2) + (zoom, zoom)
    return ndimage.zoom(m, factors, order=1, grid_mode=True, mode="grid-constant") >= 0.5


def resampled_pixels(reference_mask, zoom: float) -> int:
    """Reference myocardium pixels of ``reference_mask`` (H, W) on the grid ``zoom`` times finer."""
    return int(_zoom_mask(reference_mask, zoom).sum())


def matrix_for_pixels(reference_mask, target: int, max_size: int | None = None) -> tuple:
    """The smallest square matrix whose resampled reference mask has ``>= target`` pixels.

    Every matrix size ``n`` from the mask's own upwards is tried in turn: the grid-mode zoom
    ``n / N`` (``N`` the mask's size) makes exactly an ``n x n`` image, so these are all the
    resamplings there are, and the first that reaches the target is the smallest (the count need
    not grow monotonically with ``n``, so no bisection). Returns ``(n, zoom, pixels, tried)``,
    ``tried`` the ``[n, pixels]`` pairs evaluated.

    Parameters
    ----------
    reference_mask : (N, N) array_like of bool
        The reference myocardium.
    target : int
        Reference pixels to reach (> 0).
    max_size : int, optional
        Largest matrix to try (default ``4 N``).
    """
    mask = np.asarray(reference_mask, bool)
    if mask.ndim != 2 or mask.shape[0] != mask.shape[1]:
        raise ValueError(f"reference_mask: expected a square (N, N) mask, got shape {mask.shape}")
    if not mask.any():
        raise ValueError("reference_mask: expected some myocardium, got an empty mask")
    if not int(target) > 0:
        raise ValueError(f"target: expected a positive number of pixels, got {target!r}")
    size = mask.shape[0]
    tried = []
    for n in range(size, int(max_size or 4 * size) + 1):
        pixels = resampled_pixels(mask, n / size)
        tried.append([n, pixels])
        if pixels >= target:
            return n, n / size, pixels, tried
    raise RuntimeError(f"matrix_for_pixels: no matrix up to {max_size or 4 * size} reaches {target} pixels")


def fourier_operator(n_old: int, n_new: int) -> np.ndarray:
    """The (n_new, n_old) matrix that samples a band-limited image's interpolant on another grid.

    Both grids span the same field of view with their edges aligned (grid mode, as the linear
    zoom): new pixel ``j``'s centre lies at ``(j + 1/2) n_old / n_new - 1/2`` old pixels from the
    old pixel 0's centre. Row ``j`` is the periodic Dirichlet kernel there over the frequencies
    both grids hold, ``|k| <= min(n_old, n_new) / 2`` cycles per field of view (the Nyquist term of
    an even size at half weight on each side, so ``n_new = n_old`` gives the identity). Every
    frequency ``|k| < min(n_old, n_new) / 2`` is sampled exactly; above it the image's content is
    cut (a Nyquist line of an even smaller grid comes out at half its amplitude). For an image whose
    content lies below that limit, this is what a reconstruction straight onto the new matrix
    gives, with no blur of its own; what lies above it is lost, as on a coarser acquisition. Apply
    as ``R @ image @ R.T``.
    """
    n_old, n_new = int(n_old), int(n_new)
    x = (np.arange(n_new) + 0.5) * n_old / n_new - 0.5
    d = x[:, None] - np.arange(n_old)[None, :]
    half = min(n_old, n_new) / 2.0
    k = np.arange(1, int(np.ceil(half)))
    kernel = 1.0 + 2.0 * np.cos(2.0 * np.pi * k[:, None, None] * d[None] / n_old).sum(axis=0)
    if float(half).is_integer():                   # an even size: its Nyquist frequency, +-half at half weight each
        kernel += np.cos(2.0 * np.pi * half * d / n_old)
    return kernel / n_old


def _resampled(a, zoom: float, method: str) -> np.ndarray:
    """Images (frames, N, N) on the new grid: linear interpolation or the band-limited interpolant."""
    if method == "linear":
        return ndimage.zoom(a, (1.0, zoom, zoom), order=1, grid_mode=True, mode="grid-constant")
    n = a.shape[-1]
    R = fourier_operator(n, round(n * zoom))
    return np.einsum("ij,fjk,lk->fil", R, a, R, optimize=True)


def write_resampled_case(src, dst, zoom: float, frames: int | None = None, method: str = "linear") -> dict:
    """Write the DENSE-Sim case folder ``src`` resampled ``zoom`` times finer (first ``frames`` frames) to ``dst``.

    The module docstring says how each file is resampled. ``zoom`` 1 with all frames reproduces the
    case (to float32 round-off of the complex interpolation's phase). Returns the new matrix size
    and the reference pixels.

    Parameters
    ----------
    src, dst : path-like
        The case folder, and the folder to write (created).
    zoom : float
        Grid refinement (> 0; > 1 gives more pixels): the pixel shrinks by it.
    frames : int, optional
        Keep the first ``frames`` frames (and the reference mask, and the frame times they need).
    method : {"linear", "fourier"}
        How the complex signal is resampled: linear interpolation (the default; it adds a blur of
        about a pixel of the given grid), or the band-limited interpolant of each image
        (:func:`fourier_operator`: no blur of its own; content above the coarser grid's limit is
        cut). The masks and the truth are interpolated linearly either way.

    The case must lie on its config's ``N_im`` grid (not another of ``output_dim``'s); the new
    config keeps ``FOV``, gets the new ``N_im`` and drops ``output_dim``.
    """
    src, dst = Path(src), Path(dst)
    if not zoom > 0:
        raise ValueError(f"zoom: expected a positive grid refinement, got {zoom!r}")
    if method not in ("linear", "fourier"):
        raise ValueError(f"method: expected 'linear' or 'fourier', got {method!r}")
    with open(src / "config.yaml") as fh:
        cfg = yaml.safe_load(fh)
    sim = cfg["sim_params"]
    keep = slice(None) if frames is None else slice(0, int(frames))
    mag = np.load(src / "magnitude.npy")[keep].astype(float)
    if mag.shape[-1] != int(sim["N_im"]):
        raise ValueError(f"src: expected a case on its config's N_im grid ({sim['N_im']} pixels over FOV), got images "
                         f"of {mag.shape[-1]} pixels (another of output_dim's grids); the resampling keeps FOV and "
                         "rewrites N_im")
    dst.mkdir(parents=True, exist_ok=True)
    factors = (1.0, zoom, zoom)
    new_mag = None
    for name in _COMPLEX:
        signal = mag * np.exp(1j * np.load(src / name)[keep].astype(float))
        re, im = _resampled(signal.real, zoom, method), _resampled(signal.imag, zoom, method)
        np.save(dst / name, np.angle(re + 1j * im).astype(np.float32))
        if new_mag is None:
            new_mag = np.hypot(re, im)
    np.save(dst / "magnitude.npy", new_mag.astype(np.float32))
    masks = np.load(src / _MASKS)
    masks = masks if frames is None else masks[:int(frames) + 1]
    new_masks = _zoom_mask(masks, zoom)
    np.save(dst / _MASKS, new_masks)
    for name in _TRUTH:
        if not (src / name).is_file():
            continue
        g = np.load(src / name)[keep].astype(float)
        known = np.isfinite(g)
        v = ndimage.zoom(np.where(known, g, 0.0), factors, order=1, grid_mode=True, mode="grid-constant")
        w = ndimage.zoom(known.astype(float), factors, order=1, grid_mode=True, mode="grid-constant")
        out = np.where(w > 1e-6, v / np.maximum(w, 1e-6), np.nan)
        out[:, ~new_masks[0]] = np.nan
        np.save(dst / name, out.astype(np.float32))
    n_new = int(new_masks.shape[-1])
    if new_mag.shape[-1] != n_new:
        raise RuntimeError(f"zoom {zoom}: the images came on {new_mag.shape[-1]} pixels, the masks on {n_new}")
    sim["N_im"] = n_new                     # the field of view stays: grid-mode zoom keeps the images' edges
    sim.pop("output_dim", None)             # the new grid is N_im over FOV, not one of the simulator's outputs
    if frames is not None:
        sim["tt"] = list(sim["tt"])[:int(frames) + 1]
        sim["Nt"] = int(frames)
    with open(dst / "config.yaml", "w") as fh:
        yaml.safe_dump(cfg, fh)
    for extra in ("LICENSE", "README.md"):
        if (src.parent / extra).is_file():
            shutil.copy(src.parent / extra, dst / extra)
    return {"n_im": n_new, "reference_pixels": int(new_masks[0].sum())}


def _measured_run(argv: list, env: dict, rss_path: Path) -> dict:
    """``argv`` through the wrapper: first_run's timed run, plus the command's own peak memory (GB)."""
    run = _timed_run([sys.executable, "-c", _WRAPPER, str(rss_path)] + argv, env)
    run["peak_rss_gb"] = float(rss_path.read_text()) * 1024 / 1e9 if rss_path.is_file() else None   # kB (KiB) to GB
    return run


def _scores(report: dict) -> dict:
    """The validation page's metrics of the command's JSON against the case's truth."""
    seg, truth = report["segments"], report["truth"]["strain"]
    sc = score_strain(np.asarray(report["strain"]["Ecc"], float), np.asarray(report["strain"]["Err"], float),
                      np.asarray(truth["Ecc"], float), np.asarray(truth["Err"], float),
                      np.asarray(report["points"], float), np.asarray(report["centre"], float),
                      start_deg=float(seg["start_deg"]),
                      ecc_band=(np.asarray(seg["Ecc_lo"], float), np.asarray(seg["Ecc_hi"], float)),
                      err_band=(np.asarray(seg["Err_lo"], float), np.asarray(seg["Err_hi"], float)))
    d = sc.to_dict()
    keys = ("pixel_rmse_Ecc", "pixel_rmse_Err", "global_peak_error_Ecc", "global_peak_error_Err",
            "coverage_pct_Ecc", "coverage_pct_Err")
    return {k: d[k] for k in keys}


def run_one(case: str, zoom, frames, snr: float) -> dict:
    """One run of the command (module docstring) on ``case`` at ``zoom`` (or the target), first ``frames``."""
    folder = case_folders([case])[0]
    search = None
    if zoom == "target":
        _, zoom, _, search = matrix_for_pixels(np.load(folder / _MASKS)[0], TARGET_PIXELS)
    zoom = float(zoom)
    resampled = zoom != 1.0 or frames is not None
    size = int(np.load(folder / _MASKS, mmap_mode="r").shape[-1])
    label = case if not resampled else (f"{case} resampled to {round(size * zoom)} x {round(size * zoom)}"
                                        + (f", first {frames} frames" if frames is not None else ""))
    env = user_environment()
    with tempfile.TemporaryDirectory(prefix=f"{NAME}-") as tmp:
        tmp = Path(tmp)
        if resampled:
            write_resampled_case(folder, tmp / case, zoom, frames)
            folder = tmp / case
        out = tmp / "report.json"
        args = ["strain", str(folder), "--snr", f"{snr:g}", "--json", str(out)]
        run = _measured_run(command() + args, env, tmp / "rss")
        if run["returncode"] != 0:
            raise RuntimeError(f"sfem-filters {' '.join(args)} failed ({run['returncode']}):\n{run['stderr'][-2000:]}")
        with open(out) as fh:
            report = json.load(fh)
    lines = run["lines"]
    progress = first_progress(lines)
    s = report["settings"]
    return {"case": label, "zoom": zoom, "matrix_search": search,
            "command": f"sfem-filters strain <{label}> --snr {snr:g}",
            "reference_pixels": len(report["points"]), "frames": len(report["frame_times_s"]),
            "n_nodes": int(s["n_nodes"]), "dim_state": int(s["dim_state"]),
            "wall_s": run["wall_s"], "route_s": float(report["seconds"]),
            "first_output_s": lines[0][0] if lines else None, "first_progress_s": progress[0],
            "first_progress_line": None if progress[1] is None else progress[1].replace(str(folder), f"<{label}>"),
            "peak_rss_gb": run["peak_rss_gb"],
            **_scores(report)}


def compute(settings: dict, out_dir) -> dict:
    rows = []
    for case, zoom, frames in settings["runs"]:
        print(f"  {NAME}: {case}, zoom {zoom}, frames {frames or 'all'}", flush=True)
        rows.append(run_one(case, zoom, frames, settings["snr"]))
    return {"rows": rows, "snr": settings["snr"], "budget_s": BUDGET_S, "budget_gb": BUDGET_GB, "target_pixels": TARGET_PIXELS}


def _within(r: dict, budget_s: float, budget_gb: float) -> bool:
    return r["wall_s"] <= budget_s and r["peak_rss_gb"] is not None and r["peak_rss_gb"] <= budget_gb


def markdown(results: dict) -> str:
    heads = ["case", "reference pixels x frames", "mesh nodes (states)", "wall time [s]", "route [s]",
             "first line [s]", "first progress [s]", "peak memory [GB]", "within budget",
             "RMSE Ecc / Err", "global peak error Ecc / Err", "coverage Ecc / Err [%]"]
    body = [[r["case"], f"{r['reference_pixels']} x {r['frames']}", f"{r['n_nodes']} ({r['dim_state']})",
             fmt(r["wall_s"], ".0f"), fmt(r["route_s"], ".0f"), fmt(r["first_output_s"], ".2f"),
             fmt(r["first_progress_s"], ".2f"), fmt(r["peak_rss_gb"], ".2f"),
             "yes" if _within(r, results["budget_s"], results["budget_gb"]) else "**no**",
             f"{fmt(r['pixel_rmse_Ecc'], '.2f')} / {fmt(r['pixel_rmse_Err'], '.2f')}",
             f"{fmt(r['global_peak_error_Ecc'], '+.2f')} / {fmt(r['global_peak_error_Err'], '+.2f')}",
             f"{fmt(r['coverage_pct_Ecc'], '.1f')} / {fmt(r['coverage_pct_Err'], '.1f')}"] for r in results["rows"]]
    return (md_table(heads, body) + "\n\n"
            f"Each row is one run of `sfem-filters strain FOLDER --snr {results['snr']:g} --json OUT` with the default settings, BLAS "
            "threads and progress. Wall time: from the command to the report (the DENSE route, the conventional "
            "analysis and the thin-plate spline, the JSON); route: the route's own seconds from its JSON; first "
            "line and first progress: seconds to the first text on stderr and to the run's own first progress "
            f"line (`{results['rows'][0]['first_progress_line'] if results['rows'] else ''}`); peak memory: the "
            f"command's process alone. Budget {results['budget_s']:.0f} s and {results['budget_gb']:.0f} GB "
            "(a slice of up to about 1300 pixels and 62 frames), on the machine and load of the header. Scores against each case's truth, in "
            "percentage points (the strain page's metrics; not goals here). A resampled case is the given one on "
            "another matrix over the same field of view" + (
                f"; the finer one is the smallest matrix whose reference myocardium has at least "
                f"{results['target_pixels']} pixels." if any(r.get("matrix_search") for r in results["rows"])
                else " (the quick tier: a coarser matrix and the first frames)."))


def check(results: dict, tier: str) -> list:
    """Every run measured (times, memory, sizes, finite scores), its first line within
    :data:`~validation.first_run.FIRST_LINE_S` and its own progress within 5 s; in the full tier, a
    run at the target size and every run within the budget. The time limits are an idle machine's
    and stretch by the load per core (:func:`~validation.first_run.load_stretch`), as first_run's
    do; memory does not stretch."""
    problems = []
    stretch = load_stretch()
    for r in results["rows"]:
        for k in ("wall_s", "route_s", "first_output_s", "first_progress_s", "peak_rss_gb", "pixel_rmse_Ecc",
                  "pixel_rmse_Err", "global_peak_error_Ecc", "global_peak_error_Err"):
            if r[k] is None or not np.isfinite(r[k]):
                problems.append(f"{r['case']}: {k} is {r[k]}")
        if not r["reference_pixels"] > 0 or not r["frames"] > 0:
            problems.append(f"{r['case']}: {r['reference_pixels']} pixels x {r['frames']} frames")
        if r["first_output_s"] is not None and not r["first_output_s"] < FIRST_LINE_S * stretch:
            problems.append(f"{r['case']}: first line after {r['first_output_s']:.2f} s")
        if r["first_progress_s"] is not None and not r["first_progress_s"] < 5.0 * stretch:
            problems.append(f"{r['case']}: first progress after {r['first_progress_s']:.2f} s")
        if tier == "full" and r["peak_rss_gb"] is not None and r["wall_s"] is not None and not _within(
                r, results["budget_s"] * stretch, results["budget_gb"]):
            problems.append(f"{r['case']}: {r['wall_s']:.0f} s and {r['peak_rss_gb']:.2f} GB, outside the budget")
    if tier == "full" and not any(r["reference_pixels"] >= results["target_pixels"] for r in results["rows"]):
        problems.append(f"no run reaches {results['target_pixels']} reference pixels")
    return problems
