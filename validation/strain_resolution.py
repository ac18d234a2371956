"""The same hearts on coarser matrices: the DENSE route where a pixel is 2.2-2.5 mm.

DENSE-Sim writes its images on a 128 x 128 matrix over 224 mm (1.75 mm pixels; both given cases)
or, by its configuration's ``output_dim``, on 90 x 90 over 200 mm (2.22 mm pixels). The hidden
test cases of issue 42 may come on the coarser grid, where the wall spans a pixel or two fewer.
This claim takes each given case and resamples it onto coarser matrices over the same field of
view (:func:`validation.strain_budget.write_resampled_case` with ``method="fourier"``: each
image's band-limited interpolant sampled on the new grid, which adds no blur of its own; the little
content the images hold above the coarser grid's limit, such as the sharp edge of the simulator's
zeroed background, is cut; the masks' indicators and the truth are interpolated linearly;
``config.yaml``'s ``N_im`` changes, so the acquired resolution ``N_im / N_im_pre_spiral`` stays the
same in mm). Linear interpolation of the images would add a blur of its own, which the file does
not state and the route would not model. The table shows the acquired resolution the file states
beside the one the magnitude's edge spread measures
(:func:`sfem_filters.imaging.dense.edge_spread_resolution`) on each grid:

* **101 x 101**: 2.22 mm pixels, DENSE-Sim's other output pixel;
* **90 x 90**: 2.49 mm pixels, coarser still;
* and the case **as given** (128 x 128) in the same run, as the baseline.

On each it adds the spec's noise (SNR 30 and 8, seeds 0, 1, 2; :func:`sfem_filters.imaging.add_complex_noise`)
and runs exactly the rows of the main strain page (:func:`validation.strain_dense_sim.run_case`):
the conventional analysis without smoothing and with sigma 1 px, and our route's default for images
(what ``sfem-filters strain`` runs), each scored against the case's own truth with the page's
metrics and set against the page's goals.

What resampling cannot give: a case simulated natively on the coarser grid has its own phase
texture and its own truth resampled once from the simulator's finer grid; here the truth was
resampled twice (the simulator's, then linear interpolation). The comparison with the conventional
analysis, scored against the same truth, is the like-for-like one. The table shows means over the
seeds; the goals are judged at every seed, as on the main strain page. Quick tier: the phantom, its
first 6 frames, at 90 x 90, SNR 30, seed 0.
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from sfem_filters.imaging import read_dense_sim
from sfem_filters.imaging.dense import edge_spread_resolution

from ._core import fmt, md_table
from .strain_budget import write_resampled_case
from .strain_dense_sim import GOALS, OURS, _better_conventional, case_folders, goals_missed, nonfinite_metrics, run_case

NAME = "strain_resolution"
NEEDS_DATA = True
TITLE = "The same hearts on coarser matrices: the DENSE route where a pixel is 2.2-2.5 mm"
FULL_COST = "about 15-20 min"
TIERS = {"quick": {"cases": ["phantom_subject_1"], "matrices": [90], "snr": [30.0], "seeds": [0], "frames": 6},
         "full": {"cases": None, "matrices": [128, 101, 90], "snr": [30.0, 8.0], "seeds": [0, 1, 2], "frames": None}}
#: Noise draws are seeded, the route is deterministic; timings and memory are the machine's.
TOLERANCES = {"*": (1e-6, 1e-9), "seconds": None, "cpu_seconds": None, "peak_rss_mb": None}
#: How the images are resampled (:func:`validation.strain_budget.write_resampled_case` ``method``).
RESAMPLING = "fourier"
_RESAMPLED = {"fourier": "the images resampled by their band-limited interpolant",
              "linear": "the images resampled by linear interpolation"}


def _native_size(folder: Path) -> int:
    return int(np.load(folder / "LV_mask_time_lowres.npy", mmap_mode="r").shape[-1])


def case_rows(folder: Path, matrices, snrs, seeds, frames) -> list:
    """Every matrix, SNR and seed of one case: the strain page's rows, each with its ``matrix`` and pixel size."""
    size = _native_size(folder)
    rows = []
    with tempfile.TemporaryDirectory(prefix=f"{NAME}-") as tmp:
        for n in matrices:
            n = int(n)
            if n == size:
                where = folder
            else:
                where = Path(tmp) / f"{folder.name}_{n}"
                info = write_resampled_case(folder, where, n / size, method=RESAMPLING)
                if info["n_im"] != n:
                    raise RuntimeError(f"{folder.name}: resampling to {n} x {n} gave {info['n_im']} x {info['n_im']}")
            case = read_dense_sim(where)
            seen = {"resolution_px_file": float(case.resolution_px),
                    "resolution_px_edges": float(edge_spread_resolution(case)["resolution_px"])}
            for snr in snrs:
                for seed in seeds:
                    for r in run_case(where, float(snr), int(seed), frames=frames):
                        rows.append({**r, "case": f"{folder.name}, {n} x {n}", "subject": folder.name, "matrix": n,
                                     "pixel_mm": float(case.pixel_size_mm), **seen})
                    print(f"  {NAME}: {folder.name} at {n} x {n}, SNR {snr:g}, seed {seed}: {rows[-1]['seconds']:.0f} s",
                          flush=True)
    return rows


def compute(settings: dict, out_dir) -> dict:
    rows = [r for folder in case_folders(settings["cases"])
            for r in case_rows(folder, settings["matrices"], settings["snr"], settings["seeds"], settings["frames"])]
    return {"rows": rows, "seeds": list(settings["seeds"]), "frames": settings["frames"], "resampling": RESAMPLING}


def _ours(results: dict) -> list:
    return [r for r in results["rows"] if r["method"] == OURS]


def _mean(values) -> float:
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else float("nan")


def markdown(results: dict) -> str:
    rows = results["rows"]
    seeds = results.get("seeds", [results.get("seed")])
    conv = _better_conventional(rows)
    raw = {(r["case"], r["snr"], r["seed"]): r for r in rows if r["method"] == "conventional, sigma 0 px"}
    groups = {}
    for r in _ours(results):
        groups.setdefault((r["case"], r["snr"]), []).append(r)
    cols = ["case", "matrix (pixel; myocardium)", "resolution [px]: file / edges", "SNR", "RMSE Ecc / Err (conventional)",
            "global peak error Ecc / Err", "segment peak error Ecc / Err", "coverage Ecc / Err [%]",
            "global peak error Err, conventional unsmoothed"]
    body = []
    for (case, snr), rs in groups.items():
        r0 = rs[0]
        m = {k: _mean(r[k] for r in rs) for k in ("pixel_rmse_Ecc", "pixel_rmse_Err", "global_peak_error_Ecc",
                                                  "global_peak_error_Err", "segment_peak_error_Ecc_mean",
                                                  "segment_peak_error_Err_mean", "coverage_pct_Ecc", "coverage_pct_Err")}
        c = {q: _mean(conv[(case, snr, r["seed"], q)] for r in rs) for q in ("pixel_rmse_Ecc", "pixel_rmse_Err")}
        unsmoothed = _mean(raw[(case, snr, r["seed"])]["global_peak_error_Err"] for r in rs)
        body.append([r0["subject"].replace("_", " "), f"{r0['matrix']} ({r0['pixel_mm']:.2f} mm; {r0['n_points']} pixels)",
                     f"{fmt(r0.get('resolution_px_file'), '.2f')} / {fmt(r0.get('resolution_px_edges'), '.2f')}",
                     f"{snr:g}",
                     f"{fmt(m['pixel_rmse_Ecc'], '.2f')} / {fmt(m['pixel_rmse_Err'], '.2f')} "
                     f"({fmt(c['pixel_rmse_Ecc'], '.2f')} / {fmt(c['pixel_rmse_Err'], '.2f')})",
                     f"{fmt(m['global_peak_error_Ecc'], '+.2f')} / {fmt(m['global_peak_error_Err'], '+.2f')}",
                     f"{fmt(m['segment_peak_error_Ecc_mean'], '.2f')} / {fmt(m['segment_peak_error_Err_mean'], '.2f')}",
                     f"{fmt(m['coverage_pct_Ecc'], '.1f')} / {fmt(m['coverage_pct_Err'], '.1f')}",
                     fmt(unsmoothed, "+.2f")])
    lo, hi = GOALS["coverage"]
    draws = (f"one noise draw (seed {seeds[0]})" if len(seeds) == 1
             else f"means over {len(seeds)} noise draws (seeds {', '.join(str(s) for s in seeds)})")
    text = (md_table(cols, body)
            + f"\n\nOur route's default for images on each case as given and resampled to coarser matrices over the "
            f"same field of view ({_RESAMPLED.get(results.get('resampling', 'linear'))}; matrix: its side; resolution: the "
            "acquired resolution in pixels, as the file states it and as the magnitude's edge spread measures it; "
            f"myocardium: the reference myocardium's pixels); {draws} per case, matrix and SNR. Strain in "
            "percentage points (Green-Lagrange); RMSE over every reference pixel and frame, in brackets the better "
            "of the two conventional variants at each draw (no smoothing, sigma 1 px); peak errors signed "
            "(estimate - truth); segment peak error: the mean over the six segments of its absolute value; coverage: "
            "of the true segment curves by our 95% bands; the unsmoothed conventional analysis's global peak error of "
            "Err beside ours, from the same tracks (each run's seconds are in the JSON). The goals of the main strain page, at every "
            "draw: pixel RMSE below the better conventional; |global peak error| at most "
            f"{GOALS['global_peak_error_Ecc']:g} (Ecc) and {GOALS['global_peak_error_Err']:g} (Err); mean segment "
            f"peak error at most {GOALS['segment_peak_error_Ecc_mean']:g} (Ecc) and "
            f"{GOALS['segment_peak_error_Err_mean']:g} (Err); coverage {lo:g}-{hi:g}%.")
    missed = goals_missed({"rows": rows})
    text += ("\n\nWhere a goal is missed (each case, matrix and SNR; the worst draw): " + "; ".join(missed) + "."
             if missed else "\n\nEvery goal is met on every case, matrix, SNR and draw.")
    return text


def check(results: dict, tier: str) -> list:
    """Plausibility, not the goals: every metric of every row finite, and every case has its route's row
    at every matrix and SNR of the run."""
    problems = nonfinite_metrics(results["rows"])
    runs = {(r["case"], r["snr"]) for r in results["rows"]}
    ours = {(r["case"], r["snr"]) for r in _ours(results)}
    problems += [f"{c} SNR {s:g}: no row of our route" for c, s in sorted(runs - ours)]
    return problems + ([] if results["rows"] else ["no rows"])
