"""The wall's thickening seen three ways against DENSE-Sim's ground truth: masks, magnitude, phase.

Where the DENSE route's two sources (the phase and the myocardium masks) disagree, which one errs?
Their residuals cannot say (:doc:`strain_dense_sim`'s "what remains"), but the truth can. This
claim measures, for every given case and frame, the wall's mean thickening relative to frame 0
(the first frame; the reference itself has no image) along rays from the centre, seen:

* by the **truth**: along each ray from the reference mask's centre of mass, the mean over the
  reference wall of the radial stretch ``sqrt(1 + 2 Err)`` (the deformed thickness of a radial
  line over its reference thickness, shear neglected), the truth sampled at the nearest reference
  pixel of each point of the ray;
* by the **masks**: along the same angles from each frame's mask centre, the distance from the
  first to the last tissue sample of the frame's mask;
* by the **magnitude** (a third, independent view of the border: the image whose edges the masks
  should follow): along the same rays, the magnitude modelled as a cavity level, a tissue level and
  an outside level with steps at the endo- and epicardial radii, blurred by the acquisition's point
  spread (a Gaussian of the case's acquired resolution, :func:`sfem_filters.imaging.dense.psf_sigma_px`),
  fitted by least squares (the levels in closed form, the radii by Gauss-Newton);
* by the **phase**: the truth's construction applied to the noise-free conventional analysis's
  radial strain (:func:`sfem_filters.imaging.conventional_analysis`, no smoothing).

Each view's thickening is the mean over rays of its per-ray ratio to frame 0. Reported per case:
the truth's peak thickening, each view's error there (points of thickness ratio, and the global
radial strain that error alone would make, ``((1 + r_view)^2 - (1 + r_true)^2) / 2``), and the
RMS error over frames. The images are noise-free (the spec's noise touches only the phase; the
masks and the magnitude stay as given), so what differs here is each source's own construction.

**Where the truth sits.** The data's README says the truth was computed on a finer grid and
resampled to the image's, with about a quarter pixel of offset. If so, the noise-free tracks'
strain ``e`` at a reference pixel ``X`` matches the truth ``T`` at ``X + delta`` rather than at ``X``:
``e - T ~ grad T . delta``. :func:`truth_offset` fits ``delta`` (px, x and y) by least squares
(:mod:`validation._truth_offset`: each frame's constant removed, the pixels two or more inside the
mask, the frames from a quarter of the sequence on), for Ecc and Err, on the conventional analysis
without smoothing and with a
Gaussian of 1 px, and reports the segment curves' error (RMS over the six segments and the
frames, the spec's segments) against the truth as given and against the truth moved by ``delta``:
a smooth error the segment means keep (what the bands of the DENSE route must cover), not the
pixels' noise.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.special import ndtr

from sfem_filters.imaging import conventional_analysis, read_dense_sim, reference_points
from sfem_filters.imaging.dense import psf_sigma_px
from sfem_filters.imaging.strain import mask_centre, segment_labels

from ._core import fmt, md_table
from ._truth_offset import fit_offset, registered_truth
from .strain_dense_sim import _truncated, case_folders

NAME = "border_views"
NEEDS_DATA = True
TITLE = "The wall's thickening seen by the masks, the magnitude and the phase against DENSE-Sim's truth"
FULL_COST = "about 1 min"
TIERS = {"quick": {"cases": ["phantom_subject_1"], "frames": 8, "rays": 90, "figure": False},
         "full": {"cases": [], "frames": None, "rays": 180, "figure": True}}
TOLERANCES = {"*": (1e-6, 1e-9), "seconds": None}
FIGURE = "border_views.png"
VIEWS = ("masks", "magnitude", "phase")
#: Ray sampling step (px) for the masks, and for the magnitude's profiles and the fields along a ray.
STEP_PX = 0.05
PROFILE_STEP_PX = 0.25
#: How far beyond a mask's wall (px) a magnitude profile reaches on each side.
MARGIN_PX = 4.0


def _ray_points(centre, angles, radii):
    d = np.column_stack([np.cos(angles), np.sin(angles)])
    return centre[0] + radii * d[:, :1], centre[1] + radii * d[:, 1:]


def mask_wall(mask, centre, angles, step: float = STEP_PX) -> tuple:
    """Endo- and epicardial radii (px) along rays: the first and last sample inside ``mask`` (nearest pixel)."""
    r = np.arange(0.0, float(np.hypot(*mask.shape)), step)[None]
    x, y = _ray_points(centre, angles, r)
    inside = ndimage.map_coordinates(np.asarray(mask, float), [y, x], order=0, mode="constant") > 0.5
    if not inside.any(axis=1).all():
        raise ValueError("mask: expected tissue along every ray from its centre")
    first = np.argmax(inside, axis=1)
    last = inside.shape[1] - 1 - np.argmax(inside[:, ::-1], axis=1)
    return r[0, first], r[0, last]


def _levels_residual(design, profile):
    """Least-squares levels of each ray's design (n, k, 3) for its profile (n, k), and the residual."""
    gram = np.einsum("nki,nkj->nij", design, design) + 1e-12 * np.eye(3)
    beta = np.linalg.solve(gram, np.einsum("nki,nk->ni", design, profile)[..., None])[..., 0]
    return profile - np.einsum("nki,ni->nk", design, beta), beta


def _wall_design(r, a, b, sigma):
    inner, outer = ndtr((r - a[:, None]) / sigma), ndtr((r - b[:, None]) / sigma)
    return np.stack([1.0 - inner, inner - outer, outer], axis=-1)      # cavity, tissue, outside


def fit_blurred_wall(profile, r, a0, b0, sigma: float, iterations: int = 15) -> tuple:
    """Radii ``a < b`` (px) of a blurred wall fitted to profiles ``(n, k)`` sampled at radii ``r`` (k,).

    Model: ``c (1 - Phi((r - a)/s)) + m (Phi((r - a)/s) - Phi((r - b)/s)) + o Phi((r - b)/s)``,
    levels ``c, m, o`` by linear least squares for given radii (variable projection), the radii by
    Gauss-Newton steps (forward-difference Jacobian, steps clipped to 1 px) from ``a0, b0``.
    """
    a, b = np.asarray(a0, float).copy(), np.asarray(b0, float).copy()
    h = 1e-4
    for _ in range(iterations):
        e0, _ = _levels_residual(_wall_design(r, a, b, sigma), profile)
        ea, _ = _levels_residual(_wall_design(r, a + h, b, sigma), profile)
        eb, _ = _levels_residual(_wall_design(r, a, b + h, sigma), profile)
        J = np.stack([(ea - e0) / h, (eb - e0) / h], axis=-1)
        step = -np.linalg.solve(np.einsum("nki,nkj->nij", J, J) + 1e-9 * np.eye(2),
                                np.einsum("nki,nk->ni", J, e0)[..., None])[..., 0]
        step = np.clip(step, -1.0, 1.0)
        a, b = a + step[:, 0], np.maximum(b + step[:, 1], a + step[:, 0] + 0.5)
    return a, b


def magnitude_wall(image, centre, angles, sigma: float, start_radii) -> tuple:
    """Endo- and epicardial radii (px) along rays, the blurred-wall model fitted to the magnitude.

    ``start_radii``: the ``(a0, b0)`` the fit starts from and whose wall (plus :data:`MARGIN_PX`) the
    profiles span, the frame's mask's (:func:`mask_wall`).
    """
    a0, b0 = (np.asarray(r, float) for r in start_radii)
    offsets = np.arange(0.0, float(np.max(b0 - a0)) + 2 * MARGIN_PX + PROFILE_STEP_PX, PROFILE_STEP_PX)
    start = np.maximum(a0 - MARGIN_PX, 0.5)
    x, y = _ray_points(centre, angles, start[:, None] + offsets[None])
    profile = ndimage.map_coordinates(np.asarray(image, float), [y, x], order=3, mode="nearest")
    scale = float(np.median(profile)) or 1.0
    a, b = fit_blurred_wall(profile / scale, offsets, a0 - start, b0 - start, sigma)
    return a + start, b + start


def mean_along_rays(field, centre, angles, a, b, step: float = PROFILE_STEP_PX) -> np.ndarray:
    """Per ray, the mean of ``field`` (H, W; NaN outside the tissue) between radii ``a`` and ``b`` (nearest pixel)."""
    out = np.empty(len(angles))
    for i, (ai, bi) in enumerate(zip(a, b)):
        r = np.arange(ai, bi + 1e-9, step)
        x, y = _ray_points(centre, angles[i:i + 1], r[None])
        v = field[np.clip(np.rint(y[0]).astype(int), 0, field.shape[0] - 1),
                  np.clip(np.rint(x[0]).astype(int), 0, field.shape[1] - 1)]
        out[i] = np.nanmean(v) if np.isfinite(v).any() else np.nan
    return out


def _stretch_image(err, mask):
    img = np.full(mask.shape, np.nan)
    rows, cols = np.nonzero(mask)
    img[rows, cols] = np.sqrt(np.maximum(1.0 + 2.0 * np.asarray(err, float), 0.0))
    return img


def case_views(folder, frames=None, rays: int = 180) -> dict:
    """Each view's mean thickening relative to frame 0, per frame, for one case (module docstring)."""
    case = _truncated(read_dense_sim(folder), frames)
    angles = np.linspace(0.0, 2 * np.pi, int(rays), endpoint=False)
    ref = case.reference_mask
    c0 = mask_centre(ref)
    a_ref, b_ref = mask_wall(ref, c0, angles)
    conventional = {sigma: conventional_analysis(case, sigma=sigma) for sigma in (0.0, 1.0)}
    conv = conventional[0.0]
    sigma = psf_sigma_px(case.resolution_px)
    per_ray = {v: [] for v in ("truth",) + VIEWS}
    for f in range(case.n_frames):
        per_ray["truth"].append(mean_along_rays(_stretch_image(case.truth_err[f][ref], ref), c0, angles, a_ref, b_ref))
        per_ray["phase"].append(mean_along_rays(_stretch_image(conv.strain.Err[f], ref), c0, angles, a_ref, b_ref))
        m = case.frame_masks[f]
        cf = mask_centre(m)
        a, b = mask_wall(m, cf, angles)
        per_ray["masks"].append(b - a)
        a, b = magnitude_wall(case.magnitude[f], cf, angles, sigma, (a, b))
        per_ray["magnitude"].append(b - a)
    curves = {}
    for v, arr in per_ray.items():
        arr = np.asarray(arr)
        curves[v] = (np.nanmean(arr / arr[0], axis=1) - 1.0).tolist()      # thickening relative to frame 0
    return {"case": folder.name, "frame_times_s": case.frame_times_s.tolist(), "thickening": curves,
            "psf_sigma_px": float(sigma), "rays": int(rays),
            "truth_offset": truth_offset(case, conventional, folder.name)}


def truth_offset(case, conventional: dict, name: str) -> list:
    """The offset ``delta`` (px) that best maps the truth onto each conventional strain, and what it does to the segments.

    ``conventional``: ``{sigma: ConventionalStrain}`` of ``case`` (noise-free). Module docstring,
    "where the truth sits"; the fit and the moved truth are :mod:`validation._truth_offset`'s.
    """
    points = reference_points(case.reference_mask)
    labels = segment_labels(points, mask_centre(case.reference_mask))
    out = []
    for sigma, conv in conventional.items():
        for q in ("Ecc", "Err"):
            truth_img = case.truth_ecc if q == "Ecc" else case.truth_err
            truth = truth_img[:, points[:, 1].astype(int), points[:, 0].astype(int)]
            est = np.asarray(getattr(conv.strain, q), float)
            delta = fit_offset(points, case.reference_mask, est, truth)[0]
            moved = registered_truth(points, truth, case.reference_mask.shape, delta)

            def seg_rms(ref):
                err = [np.nanmean((est - ref)[:, labels == k], axis=1) for k in range(6)]
                return float(np.sqrt(np.nanmean(np.square(err))))
            out.append({"case": name, "strain": q, "sigma_px": float(sigma), "delta_x_px": float(delta[0]),
                        "delta_y_px": float(delta[1]), "segment_rms_error": seg_rms(truth),
                        "segment_rms_error_truth_moved": seg_rms(moved)})
    return out


def summary(views: dict) -> list:
    """Per view: its thickening and error at the truth's peak frame, the radial strain that error makes, its RMS error."""
    truth = np.asarray(views["thickening"]["truth"])
    k = int(np.nanargmax(truth))
    rows = []
    for v in VIEWS:
        est = np.asarray(views["thickening"][v])
        err = est - truth
        rows.append({"case": views["case"], "view": v, "peak_frame": k, "truth_at_peak": float(truth[k]),
                     "view_at_peak": float(est[k]), "error_at_peak": float(err[k]),
                     "radial_strain_error_at_peak": float(((1 + est[k]) ** 2 - (1 + truth[k]) ** 2) / 2),
                     "rms_error": float(np.sqrt(np.nanmean(err ** 2)))})
    return rows


def compute(settings: dict, out_dir) -> dict:
    cases = [case_views(folder, settings["frames"], settings["rays"]) for folder in case_folders(settings["cases"])]
    out = {"cases": cases, "rows": [r for c in cases for r in summary(c)],
           "offset_rows": [r for c in cases for r in c["truth_offset"]]}
    if settings["figure"]:
        out["figure"] = figure(cases, out_dir / FIGURE)
    return out


def figure(cases, path) -> str:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(cases), figsize=(5.2 * len(cases), 3.8), constrained_layout=True, squeeze=False)
    style = {"truth": ("k", "-", "truth (radial stretch)"), "masks": ("C0", "-", "masks"),
             "magnitude": ("C2", "--", "magnitude (blurred-wall fit)"), "phase": ("C3", ":", "phase (conventional)")}
    for ax, c in zip(axes[0], cases):
        t = 1e3 * np.asarray(c["frame_times_s"])
        for v, (col, ls, label) in style.items():
            ax.plot(t, 100 * np.asarray(c["thickening"][v]), color=col, ls=ls, lw=1.6, label=label)
        ax.set_title(c["case"])
        ax.set_xlabel("time after encoding [ms]")
        ax.set_ylabel("wall thickening from frame 0 [%]")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path.name


def markdown(results: dict) -> str:
    cols = ["case", "view", "truth's peak thickening [%]", "view there [%]", "error there [points]",
            "radial strain that error makes [points]", "RMS error over frames [points]"]
    body = [[r["case"], r["view"], fmt(100 * r["truth_at_peak"], ".1f"), fmt(100 * r["view_at_peak"], ".1f"),
             fmt(100 * r["error_at_peak"], "+.1f"), fmt(100 * r["radial_strain_error_at_peak"], "+.1f"),
             fmt(100 * r["rms_error"], ".1f")] for r in results["rows"]]
    return (md_table(cols, body) + "\n\nThickening: the wall's mean thickness along rays from the centre relative to "
            "the first frame, in percent (the truth's: the mean radial stretch along the same rays). Noise-free images; "
            "the radial strain an error makes is ((1 + view)^2 - (1 + truth)^2) / 2 at the truth's peak frame.\n\n"
            + "; ".join(_verdict(results["rows"], case) for case in dict.fromkeys(r["case"] for r in results["rows"]))
            + ".\n\n" + _offset_table(results["offset_rows"]))


def _offset_table(rows) -> str:
    cols = ["case", "strain", "conventional smoothing [px]", "offset delta x / y [px]",
            "segment curves' RMS error, truth as given [points]", "truth moved by delta [points]"]
    body = [[r["case"], r["strain"], fmt(r["sigma_px"], ".0f"),
             f"{fmt(r['delta_x_px'], '+.2f')} / {fmt(r['delta_y_px'], '+.2f')}",
             fmt(100 * r["segment_rms_error"], ".2f"), fmt(100 * r["segment_rms_error_truth_moved"], ".2f")]
            for r in rows]
    return (md_table(cols, body) + "\n\nWhere the truth sits: the offset delta that best maps the truth onto the "
            "noise-free conventional strain (e - T ~ c_t + grad T . delta, least squares over the pixels two or more "
            "inside the mask and the frames from a quarter of the sequence on, each frame's constant c_t removed), and the "
            "six segment curves' error (RMS over segments and frames) against the truth as given and moved by delta.")


def _verdict(rows, case: str) -> str:
    """Which view of ``case`` has the smallest RMS error, and which see less thickening than the truth at its peak."""
    mine = [r for r in rows if r["case"] == case]
    best = min(mine, key=lambda r: r["rms_error"])["view"]
    under = [r["view"] for r in mine if r["error_at_peak"] < 0]
    return (f"{case}: smallest RMS error over frames by the {best}; below the truth at its peak: "
            f"{', '.join(under) if under else 'none'}")


def check(results: dict, tier: str) -> list:
    """Every number finite; all three views for every case; the truth's thickening positive at its peak."""
    problems = [f"{r['case']} {r['view']}: {k} {r[k]}" for r in results["rows"]
                for k in ("view_at_peak", "error_at_peak", "rms_error") if not np.isfinite(r[k])]
    problems += [f"{c['case']}: the truth's peak thickening is {max(c['thickening']['truth'])}"
                 for c in results["cases"] if not max(c["thickening"]["truth"]) > 0]
    problems += [f"{r['case']} {r['strain']} sigma {r['sigma_px']}: offset not finite" for r in results["offset_rows"]
                 if not (np.isfinite(r["delta_x_px"]) and np.isfinite(r["delta_y_px"]))]
    seen = {(r["case"], r["view"]) for r in results["rows"]}
    problems += [f"{c['case']}: view {v} missing" for c in results["cases"] for v in VIEWS if (c["case"], v) not in seen]
    return problems
