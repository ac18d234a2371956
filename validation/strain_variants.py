"""The same heart mirrored, transposed, sampled at half the frame rate or with broken masks: what the DENSE route
depends on.

The checks of issue 42 also run on DENSE-Sim cases we are not given, which may lie in another
orientation on the image grid, come at another frame rate or carry a frame's mask that is no ring.
This claim takes each given case,
adds the spec's noise once (SNR 30, seed 0, :func:`sfem_filters.imaging.add_complex_noise`), and
runs the DENSE route's default for images (:func:`sfem_filters.cardiac.dense_case_strain` with
:func:`sfem_filters.cardiac.image_settings`, what ``sfem-filters strain`` runs) on:

* the case **as given**;
* the noisy images **mirrored** left to right (``numpy.fliplr`` of every image, mask and truth; the
  x encoding changes sign) and **transposed** (rows and columns swapped; the two encodings swap):
  the same tissue, the same noise pixel for pixel, the same truth at the same tissue, so any
  difference is the route's own dependence on the orientation (Gmsh meshes the outline afresh; the
  masks' border data are read where the phase data's own estimate puts each border node, so they
  have no contour start);
* **every second frame** of the noisy case (half the frame rate, the frame times kept), scored
  beside the case as given scored on the same frames;
* the case as given with the masks of every :data:`CUT_EVERY`-th frame (frames 2, 8, 14, ...) cut
  through on one side (:func:`masks_cut`: a radial gap of 3 pixels that no mending bridges), the
  route's default, which leaves those frames' border data out and fuses the others' (row "masks of
  every 6th frame cut"), beside the same case on the phase alone, what the route fell back to
  before for any frame whose mask it could not read (row "..., the phase alone (the fallback
  before)");
* as given, mirrored and transposed again with the masks' border data from landmarks tracked by
  bending-energy matching (``border_correspondence="landmarks"``, the route's default before the
  phase placed the border), averaged over :data:`STARTS` contour start angles (``border_starts``,
  ``--border-starts``; rows "..., landmarks over 8 contour starts"), which removes the landmarks'
  dependence on where the contours start.

Each run is scored against its own truth with the strain page's metrics
(:func:`sfem_filters.benchmark.score_strain`; segments from 0 degrees in each variant's own image,
so the segment rows of a mirrored case cover other tissue than the unmirrored's: compare their
means, the global curve and the pixels, which cover the same tissue). Quick tier: the phantom, its
first 4 frames, as given, mirrored, with frame 2's mask cut and as given over the contour starts.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from sfem_filters.benchmark import score_strain
from sfem_filters.cardiac import dense_case_strain, image_settings
from sfem_filters.imaging import add_complex_noise, read_dense_sim, truth_at_points

from ._core import fmt, md_table
from .strain_dense_sim import METRICS, _truncated, case_folders

NAME = "strain_variants"
NEEDS_DATA = True
TITLE = "The same heart mirrored, transposed, at half the frame rate or with broken masks: the DENSE route's strain"
FULL_COST = "about 15 min"
#: Contour start angles of the averaged rows (:class:`sfem_filters.cardiac.StrainRouteSettings` ``border_starts``).
STARTS = 8
AVERAGED = f", landmarks over {STARTS} contour starts"
#: Every this-many-th frame's mask is cut (:func:`masks_cut`), from frame :data:`CUT_FIRST` on.
CUT_EVERY, CUT_FIRST = 6, 2
CUT = f"masks of every {CUT_EVERY}th frame cut"
CUT_ALONE = CUT + ", the phase alone (the fallback before)"
VARIANTS = ("as given", "mirrored", "transposed", "every 2nd frame", CUT, CUT_ALONE, "as given" + AVERAGED,
            "mirrored" + AVERAGED, "transposed" + AVERAGED)
TIERS = {"quick": {"cases": ["phantom_subject_1"], "frames": 4, "variants": ["as given", "mirrored", CUT,
                                                                             "as given" + AVERAGED],
                   "snr": 30.0, "seed": 0},
         "full": {"cases": [], "frames": None, "variants": list(VARIANTS), "snr": 30.0, "seed": 0}}
TOLERANCES = {"*": (1e-6, 1e-9), "seconds": None}


def _turned(case, image, phases):
    """``case`` with every image, mask and truth mapped by ``image`` and the encodings by ``phases``."""
    return replace(case, phases=phases(case.phases), magnitude=image(case.magnitude), masks=image(case.masks),
                   truth_ecc=None if case.truth_ecc is None else image(case.truth_ecc),
                   truth_err=None if case.truth_err is None else image(case.truth_err))


def mirrored(case):
    """Left to right (x -> W - 1 - x): the x displacement, so the x encoding's phase, changes sign."""
    def image(a):
        return np.ascontiguousarray(a[..., ::-1])

    def phases(p):
        px, py = image(p[0]), image(p[1])
        return np.stack([np.angle(np.exp(-1j * px)).astype(p.dtype), py])
    return _turned(case, image, phases)


def transposed(case):
    """Rows and columns swapped (x <-> y): the two encodings swap."""
    def image(a):
        return np.ascontiguousarray(np.swapaxes(a, -1, -2))

    def phases(p):
        return np.stack([image(p[1]), image(p[0])])
    return _turned(case, image, phases)


def every_other_frame(case):
    """Frames 0, 2, 4, ... (half the frame rate), with their times and masks (the reference kept)."""
    keep = np.arange(0, len(case.frame_times_s), 2)
    pick = (lambda a: None if a is None else a[keep])
    return replace(case, phases=case.phases[:, keep], magnitude=pick(case.magnitude),
                   masks=case.masks[np.r_[0, keep + 1]], frame_times_s=case.frame_times_s[keep],
                   truth_ecc=pick(case.truth_ecc), truth_err=pick(case.truth_err))


def masks_cut(case, every: int = CUT_EVERY, first: int = CUT_FIRST, width_px: float = 3.0):
    """``case`` with the masks of frames ``first``, ``first + every``, ... cut through the wall on the +x side.

    The gap is the rows within ``width_px / 2`` of the reference mask's centre row, right of its
    centre column: a cut of 3 pixels, wider than the two that
    :func:`sfem_filters.imaging.repair_myocardium_mask` bridges, so those masks have no cavity. The
    reference mask, the phases, the magnitude and the truth are unchanged.
    """
    rows, cols = np.nonzero(case.reference_mask)
    yy, xx = np.mgrid[0:case.shape[0], 0:case.shape[1]]
    gap = (np.abs(yy - rows.mean()) <= width_px / 2) & (xx > cols.mean())
    masks = case.masks.copy()
    frames = np.arange(first, case.n_frames, every)
    masks[frames + 1] &= ~gap
    return replace(case, masks=masks)


def _score(r, truth, frames=None):
    f = slice(None) if frames is None else frames
    seg = {q: tuple(b[:, f] for b in r.band(q)) for q in ("Ecc", "Err")}
    return score_strain(r.Ecc[f], r.Err[f], truth[0][f], truth[1][f], r.points, r.centre, start_deg=r.start_deg,
                        ecc_band=seg["Ecc"], err_band=seg["Err"],
                        pixel_bands={q: tuple(b[f] for b in r.band(q, "pixels")) for q in ("Ecc", "Err")},
                        global_bands={q: tuple(b[f] for b in r.band(q, "global")) for q in ("Ecc", "Err")}).to_dict()


def _row(case, variant, r, truth, seconds, frames=None) -> dict:
    d = _score(r, truth, frames)
    n = len(r.frame_times_s) if frames is None else len(np.arange(len(r.frame_times_s))[frames])
    return {"case": case, "variant": variant, "frames": int(n), "seconds": seconds, **{k: d.get(k) for k in METRICS}}


def case_rows(folder, settings) -> list:
    """Every variant of one case (module docstring), each a row of metrics (percentage points)."""
    noisy = _truncated(add_complex_noise(read_dense_sim(folder), settings["snr"], settings["seed"]),
                       settings["frames"])
    rows, base = [], None
    make = {"as given": lambda c: c, "mirrored": mirrored, "transposed": transposed,
            "every 2nd frame": every_other_frame, CUT: masks_cut, CUT_ALONE: masks_cut}
    for variant in settings["variants"]:
        turn = variant.removesuffix(AVERAGED)
        case = make[turn](noisy)
        extra = ({"border_starts": STARTS, "border_correspondence": "landmarks"} if turn != variant
                 else {"border_masks": False} if variant == CUT_ALONE else {})
        t0 = time.perf_counter()
        r = dense_case_strain(case, image_settings(case, **extra))
        seconds = time.perf_counter() - t0
        truth = truth_at_points(case)
        if variant == "as given":
            base = (r, truth)
        if variant == "every 2nd frame" and base is not None:
            rows.append(_row(folder.name, "as given, scored on every 2nd frame", *base, None, slice(None, None, 2)))
        rows.append(_row(folder.name, variant, r, truth, seconds))
        print(f"  {NAME}: {folder.name}, {variant}: {seconds:.0f} s", flush=True)
    return rows


def compute(settings: dict, out_dir) -> dict:
    unknown = [v for v in settings["variants"] if v not in VARIANTS]
    if unknown:
        raise ValueError(f"variants: expected names from {VARIANTS}, got {unknown}")
    return {"rows": [r for folder in case_folders(settings["cases"]) for r in case_rows(folder, settings)],
            "snr": settings["snr"], "seed": settings["seed"]}


def markdown(results: dict) -> str:
    cols = ["case", "variant", "frames", "RMSE Ecc / Err", "global peak err Ecc / Err",
            "segment peak err Ecc mean / max", "segment peak err Err mean / max", "band coverage Ecc / Err [%]",
            "seconds"]
    body = [[r["case"], r["variant"], r["frames"], f"{fmt(r['pixel_rmse_Ecc'], '.2f')} / {fmt(r['pixel_rmse_Err'], '.2f')}",
             f"{fmt(r['global_peak_error_Ecc'], '+.2f')} / {fmt(r['global_peak_error_Err'], '+.2f')}",
             f"{fmt(r['segment_peak_error_Ecc_mean'], '.2f')} / {fmt(r['segment_peak_error_Ecc_max'], '.2f')}",
             f"{fmt(r['segment_peak_error_Err_mean'], '.2f')} / {fmt(r['segment_peak_error_Err_max'], '.2f')}",
             f"{fmt(r['coverage_pct_Ecc'], '.1f')} / {fmt(r['coverage_pct_Err'], '.1f')}",
             fmt(r["seconds"], ".0f") if r["seconds"] is not None else ""] for r in results["rows"]]
    spread = []
    for case in dict.fromkeys(r["case"] for r in results["rows"]):
        for suffix in ("", AVERAGED):
            names = [v + suffix for v in ("as given", "mirrored", "transposed")]
            same = [r for r in results["rows"] if r["case"] == case and r["variant"] in names]
            g = [r["global_peak_error_Err"] for r in same if r["global_peak_error_Err"] is not None]
            if len(same) > 1 and g:
                label = f" with the masks' landmarks over {STARTS} contour starts" if suffix else ""
                spread.append(f"{case}{label}: "
                              f"global peak error of Err from {min(g):+.2f} to {max(g):+.2f} over "
                              f"{', '.join(r['variant'].removesuffix(suffix) for r in same)}")
    cut = []
    for case in dict.fromkeys(r["case"] for r in results["rows"]):
        pair = {r["variant"]: r for r in results["rows"] if r["case"] == case and r["variant"] in (CUT, CUT_ALONE)}
        if len(pair) == 2:
            a, b = pair[CUT], pair[CUT_ALONE]
            cut.append(f"{case}: pixel RMSE of Err {fmt(a['pixel_rmse_Err'], '.2f')} against "
                       f"{fmt(b['pixel_rmse_Err'], '.2f')}, global peak error of Err "
                       f"{fmt(a['global_peak_error_Err'], '+.2f')} against {fmt(b['global_peak_error_Err'], '+.2f')}, "
                       f"band coverage of Err {fmt(a['coverage_pct_Err'], '.1f')}% against "
                       f"{fmt(b['coverage_pct_Err'], '.1f')}%")
    return (md_table(cols, body) + f"\n\nOne noise draw (SNR {results['snr']:g}, seed {results['seed']}) added to each "
            "case as given; every variant transforms those noisy images, so the rows of a case see the same noise. "
            "Strain in percentage points (Green-Lagrange), peak errors signed (estimate - truth), band coverage of the "
            "segment curves by their 95% bands; segments from 0 degrees in each variant's own image. Seconds: the "
            "route's wall time."
            + ("\n\nThe same tissue in another orientation (" + "; ".join(spread) + ")." if spread else "")
            + (f"\n\nWith the masks of every {CUT_EVERY}th frame cut, the route leaving only those frames' border "
               "data out against the phase alone, its fallback before (" + "; ".join(cut) + ")." if cut else ""))


def check(results: dict, tier: str) -> list:
    """Every metric finite; every case has the row as given."""
    problems = [f"{r['case']} {r['variant']}: {k} is {r.get(k)}" for r in results["rows"] for k in METRICS
                if r.get(k) is None or not np.isfinite(r[k])]
    cases = {r["case"] for r in results["rows"]}
    problems += [f"{c}: no row as given" for c in cases if not any(r["case"] == c and r["variant"] == "as given"
                                                                   for r in results["rows"])]
    return problems + ([] if results["rows"] else ["no rows"])
