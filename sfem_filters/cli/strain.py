"""``sfem-filters strain``: DENSE images (or tracked pixels) -> Green-Lagrange strain of every reference
pixel with its sd and 95% bands, beside the conventional analysis and the thin-plate spline. What
PATH is and how it is read: :mod:`sfem_filters.cli.strain_input`."""
from __future__ import annotations

import importlib.util
import sys
import time

import numpy as np

from ..cardiac import dense_case_strain, dense_strain
from ..cardiac.dense_model import PROCESS_PROFILES
from ..cardiac.strain_route import BORDER_CORRESPONDENCES, PHASE_NOISE_LEVELS
from ..fem.polygon_mesh import GMSH_REQUIREMENT
from ..cardiac.contours_route import ContourRouteSettings, contour_spline_strain, contour_strain
from ..imaging import conventional_from_displacement, mask_centre, truth_at_points
from ..imaging.spline_strain import spline_strain
from ..imaging.strain_report import spline_block, strain_csv, truth_block, with_peaks
from ..plotting.strain import strain_figures
from ._common import _angle_deg, _finite_float, _int_at_least, _message, _non_negative_float, _non_negative_int, \
    _positive_float, _progress, _progress_options, _write_json
from .strain_input import ACQUISITION, _dense_settings, _resolution_px, _strain_input


def add_parser(sub) -> None:
    """The ``strain`` subcommand and its options, on the subparsers ``sub``."""
    s = sub.add_parser("strain", help="DENSE images (or tracked pixels) -> Green-Lagrange strain of every reference "
                                      "pixel, with sd and 95%% bands, beside the conventional analysis",
                       description="Phase to Lagrangian displacement of every reference myocardial pixel, the "
                                   "finite-element smoother on a mesh chosen apart from the pixels, Green-Lagrange "
                                   "strain (radial and circumferential about the reference myocardium's centre of "
                                   "mass) with its sd, global and six-segment curves with 95% bands; the "
                                   "conventional analysis (finite differences) and the thin-plate spline through "
                                   "the same observed points in the same run. JSON keys: points, frame_times_s, "
                                   "strain, global, segments, conventional, spline, truth (when the case has one), "
                                   "peaks, seconds, route, settings "
                                   "(the docs' validation page 'Strain against DENSE-Sim's ground truth' scores it). "
                                   "PATH is a DENSE-Sim case folder, a folder of DENSE DICOM files (give --ke and "
                                   "--masks) or a sequence .npz of points on the pixel grid (the how-to page "
                                   "'Formats and readers' has the layouts).")
    s.add_argument("path", help="a DENSE-Sim case folder (phase_x.npy, phase_y.npy, magnitude.npy, "
                                "LV_mask_time_lowres.npy, config.yaml); or a folder of DENSE DICOM files, one file "
                                "per frame, its series told apart by ImageComments as scanners export them ('DENSE "
                                "x-enc pha ...', 'DENSE y-enc pha ...', 'DENSE overall mag ...'), else in the "
                                "sub-folders phase_x, phase_y and magnitude (needs --ke and --masks); or a sequence "
                                ".npz whose points are reference pixel centres (pixel_spacing and frame_interval or "
                                "frame_times_s required; its tracks are the data, the conventional analysis is their "
                                "finite differences)")
    s.add_argument("--json", required=True, metavar="OUT", help="write the strain report (JSON) to OUT")
    s.add_argument("--route", choices=("dense", "contours"), default="dense",
                   help="dense (default): from the DENSE phase; contours: from the masks alone (tracked "
                        "endo- and epicardial borders, the interior from the physics; no phase)")
    s.add_argument("--segment-start", type=_angle_deg, default=0.0, metavar="DEG",
                   help="start of segment 0: degrees about the centre from the image's +x axis towards +y, "
                        "taken modulo 360 (default 0; the anterior RV insertion when you know it)")
    s.add_argument("--conventional-sigma", type=_non_negative_float, default=1.0, metavar="PX",
                   help="Gaussian smoothing (pixels, inside the mask) of the conventional analysis beside ours "
                        "(default 1; 0 none)")
    s.add_argument("--ke", type=_positive_float, metavar="CYCLES_PER_MM",
                   help="DICOM folders (required there): the DENSE encoding frequency in cycles/mm (e.g. 0.1)")
    s.add_argument("--masks", metavar="FILE.npy",
                   help="DICOM folders (required there): the myocardium mask(s), boolean or 0/1, rows = y, columns = "
                        "x: (H, W) the reference (also used as every frame's mask; a warning says so), (F, H, W) "
                        "each frame's (the reference taken as frame 0's) or (F + 1, H, W) the reference then each "
                        "frame's")
    s.add_argument("--directions", type=_finite_float, nargs=4, metavar=("X0", "Y0", "X1", "Y1"),
                   help="DICOM folders: the unit vectors (x = column, y = row) of the x-enc and y-enc encodings "
                        "(default 1 0 0 1: along the columns and the rows)")
    s.add_argument("--phase-range", type=_finite_float, nargs=2, metavar=("LO", "HI"),
                   help="DICOM folders: the rescaled phase values (after RescaleSlope and RescaleIntercept) that map "
                        "to -pi and +pi, e.g. -4096 4094 for 12-bit phase with slope 2 and intercept -4096 "
                        "(default: the rescaled values are radians)")
    s.add_argument("--snr", type=_positive_float, metavar="SNR",
                   help="add complex Gaussian noise first (SNR = mean myocardial magnitude / noise sd), as the "
                        "validation does; default none (images only: a sequence has no images)")
    s.add_argument("--seed", type=_non_negative_int, default=0, help="seed of --snr's noise (default 0)")
    s.add_argument("--resolution-px", type=_resolution_px, metavar=f"W|{ACQUISITION}",
                   help="dense route: the images' acquired resolution, in reconstructed pixels (the acquisition's "
                        "pixel, field of view over acquired matrix, over the image's pixel; >= 1); the observation "
                        "operator models each datum as the point-spread-weighted mean of the displacement over "
                        "the tissue around its pixel, with the signal the images show around the myocardium mixed in "
                        "at the borders (a Gaussian of FWHM W). "
                        f"Default for images '{ACQUISITION}': from the images (DENSE-Sim config: the acquired "
                        "pixel FOV / N_im_pre_spiral over the images' pixel; a DICOM's Rows and Columns over its "
                        "AcquisitionMatrix; at least 1, the images' own pixel, and 1 with a warning when they say "
                        "nothing); for a sequence file 1. 1: point observation at the pixel centres (the docs' "
                        "validation page reports both)")
    fusion = s.add_mutually_exclusive_group()
    fusion.add_argument("--with-masks", dest="masks_fusion", action="store_const", const=True, default=None,
                        help="dense route: observe the myocardium masks of every frame beside the phase (Shi & Liu's "
                             "fusion of shape tracking with phase data in one model): each border node's motion "
                             "across the endo- or epicardial border, where --border-correspondence places it, with "
                             "the contours route's sd (the mask's quantisation or the data's own temporal noise "
                             "floor). The default whenever PATH carries a mask of every "
                             "frame that moves (DENSE-Sim folders; a DICOM folder's --masks (F, H, W) or "
                             "(F + 1, H, W); a sequence file's reference_mask and frame_masks); this option makes "
                             "it an error when it does not")
    fusion.add_argument("--no-masks", dest="masks_fusion", action="store_const", const=False,
                        help="dense route: the phase alone, even when PATH carries every frame's mask")
    s.add_argument("--phase-noise-level", choices=PHASE_NOISE_LEVELS, default=None,
                   help="with the masks fused: the level at which the phase data join them. evidence (default): the "
                        "phase data's sd times their own maximum-likelihood noise level from a filter pass without "
                        "the masks (the pass that places the border, or one pass more); stated: the phase "
                        "data's sd as the route states it (their sd scaled to their temporal noise floor)")
    s.add_argument("--mask-noise-level", choices=PHASE_NOISE_LEVELS, default=None,
                   help="with the masks fused: the level of the masks' data beside the phase data's. evidence "
                        "(default): their stated sd (a binary border's quantisation) times the factor of largest "
                        "evidence of the fused model (three to five filter passes), so that masks drawn well or "
                        "badly are weighed by the noise they show; stated: their stated sd")
    s.add_argument("--process-profile", choices=PROCESS_PROFILES, default=None,
                   help="dense route: the process noise over the cycle. data (default): each frame interval's level "
                        "from the data's own acceleration (the tracks projected on smooth fields, less the noise's "
                        "share), never below the constant level, so a short systole is not flattened; constant: "
                        "one level, 0.1 of the data's temporal noise floor per frame (the docs' validation page "
                        "reports both)")
    s.add_argument("--border-correspondence", choices=BORDER_CORRESPONDENCES, default=None,
                   help="dense route with the masks fused: how each border node's place along the masks' border is "
                        "found. phase (default): where the phase data's own smoothed motion puts it (one filter "
                        "and smoother pass of the phase alone), the datum the mask border's offset across itself "
                        "there; landmarks: landmarks tracked through the masks by bending-energy matching (the "
                        "contours route's data; along a smooth border they slide)")
    s.add_argument("--border-starts", type=_int_at_least(1, " contour start angles"), default=None, metavar="N",
                   help="dense route with the masks' landmarks (implies --border-correspondence landmarks): average "
                        "their border data over N contour start angles spread evenly about the cavity, so that "
                        "they do not depend on where the contours start, i.e. on how the heart lies on the image "
                        "grid (default 1; 8 makes them nearly independent of it; N - 1 more border trackings). For "
                        "comparison: the default's border data have no contour start, and the landmarks' slides "
                        "weigh more at the masks' evidence level (the docs' strain variants page)")
    s.add_argument("--csv", metavar="PATH",
                   help="also write the report as one tidy CSV table (one row per method, region = pixel, global "
                        "or segment, frame and component; PATH ending .gz is compressed); see the how-to page "
                        "'Command-line recipes'")
    s.add_argument("--figures", metavar="DIR",
                   help="write the figures (PNG) into DIR: segment and global curves with 95%% bands against "
                        "the conventional analysis, the spline (and the ground truth when the case has one), "
                        "rings of peak strain and time to peak")
    _progress_options(s, "a line per step of the route")


def _require_gmsh() -> None:
    """Fail before any costly step when Gmsh, which both routes mesh the reference myocardium with, is not
    installed: an ImportError naming the install."""
    if importlib.util.find_spec("gmsh") is None:
        raise ImportError(f"strain: meshes the reference myocardium with Gmsh, an optional dependency "
                          f"(GPL-2.0-or-later) that is not installed: pip install '{GMSH_REQUIREMENT}' (from a clone of "
                          "the repository: pip install -e '.[mesh]')")


def cmd_strain(args) -> int:
    say = (lambda m: _message("strain", "progress", m)) if _progress(args) else (lambda m: None)
    t0 = time.perf_counter()
    _require_gmsh()
    src = _strain_input(args, say)
    case, tracks = src["case"], src["tracks"]
    if args.route == "contours":       # the masks alone (no phase): tracked borders, interior from the physics
        for name, flag in (("resolution_px", "--resolution-px"), ("masks_fusion", "--with-masks/--no-masks"),
                           ("phase_noise_level", "--phase-noise-level"), ("mask_noise_level", "--mask-noise-level"),
                           ("process_profile", "--process-profile")):
            if getattr(args, name, None) is not None:
                raise ValueError(f"{flag}: is for the dense route; the contours route observes the masks' tracked "
                                 f"borders alone and chooses its process noise by its evidence")
        if getattr(args, "border_starts", None) is not None:
            raise ValueError("--border-starts: is for the dense route with the masks fused; the contours route tracks "
                             "its landmarks from one contour start")
        if getattr(args, "border_correspondence", None) is not None:
            raise ValueError("--border-correspondence: is for the dense route with the masks fused; the contours "
                             "route has no phase data to place the border by and tracks landmarks")
        if src["masks"] is None:
            raise ValueError("--route contours: expected the myocardium masks of the reference and of every frame; the "
                             "sequence file has no reference_mask and frame_masks (use --route dense)")
        if args.snr:
            _message("strain", "note", "--snr: the noise goes into the phase, which only the conventional analysis "
                     "beside the contours route reads; the route itself reads the masks, which carry no phase")
        ours = contour_strain(src["masks"], src["pixel_size_m"], src["frame_times_s"],
                              ContourRouteSettings(start_deg=args.segment_start), progress=say)
        _message("strain", "note", "the contours route's 95% bands hold how well the masks' borders are known "
                 "given an elastic interior, not the interior model's own error; on DENSE-Sim's ground truth its "
                 "radial bands are too narrow and its radial peaks low (docs: validation/strain_contours)")
    else:
        settings = _dense_settings(args, src)
        say("dense route: "
            + (f"observed through a point spread of {settings.resolution_px:.2f} px"
               if settings.resolution_px > 1 else "observed at the pixel centres")
            + (f", each frame's mask fused with the phase (border placed by the {settings.border_correspondence}; "
               f"phase level: {settings.phase_noise_level}, masks' level: {settings.mask_noise_level})"
               if settings.border_masks else ", the phase alone")
            + (", process noise from the data's motion" if settings.process_profile == "data"
               else ", one process level"))
        if case is not None:
            ours = dense_case_strain(case, settings, tracks=tracks, progress=say)
        else:
            ours = dense_strain(tracks, src["reference_mask"], src["pixel_size_m"], settings, progress=say,
                                masks=src["masks"] if settings.border_masks else None)
    centre = ours.centre if ours.centre is not None else mask_centre(src["reference_mask"])
    conv = conventional_from_displacement(tracks, centre, sigma=args.conventional_sigma, start_deg=args.segment_start)
    out = ours.to_dict()
    if args.route == "contours":
        say("thin-plate spline through the same tracked contour landmarks")
        out["spline"] = spline_block(contour_spline_strain(ours), "the tracked contour landmarks (the points the "
                                     "contours route observes, their full tracked displacement), each component "
                                     "with the larger of the landmark's normal and tangential sd")

    def js(a):
        a = np.asarray(a, float)
        return np.where(np.isfinite(a), a.astype(object), None).tolist()
    out["conventional"] = {
        "what": src["conventional"],
        "smoothing_sigma_px": args.conventional_sigma,
        "strain": {k: js(getattr(conv.strain, k)) for k in ("Ecc", "Err", "Ecr")},
        "global": {"Ecc": js(conv.global_Ecc), "Err": js(conv.global_Err)},
        "segments": {"start_deg": conv.start_deg, "Ecc": js(conv.segments_Ecc), "Err": js(conv.segments_Err)}}
    out["settings"] = {**out["settings"], "input": src["input"], "noise_snr": args.snr,
                       "noise_seed": args.seed if args.snr else None,
                       "untracked_point_frames": int(tracks.n_untracked)}
    if "spline" not in out:
        out["spline"] = _dense_spline(tracks, ours.centre, args.segment_start, say)
    out["seconds"] = time.perf_counter() - t0
    out = _strain_extras(case, out, say)
    g = ours.global_curves
    peak_cc, peak_rr = int(np.nanargmin(g["Ecc"])), int(np.nanargmax(g["Err"]))
    truth = ""
    if "truth" in out:
        tg = out["truth"]["global"]
        truth = (f"; the case's ground truth: Ecc {100 * np.nanmin(np.asarray(tg['Ecc'], float)):.2f}%, "
                 f"Err {100 * np.nanmax(np.asarray(tg['Err'], float)):.2f}%")
    ms = 1e3 * np.asarray(ours.frame_times_s, float)
    print(f"{len(ours.points)} reference pixels x {len(ours.frame_times_s)} frames; global peak Ecc "
          f"{100 * g['Ecc'][peak_cc]:.2f}% at {ms[peak_cc]:.0f} ms (95% band of the curve at that frame, "
          "not of the peak: "
          f"{100 * g['Ecc_lo'][peak_cc]:.2f} to {100 * g['Ecc_hi'][peak_cc]:.2f}%), Err {100 * g['Err'][peak_rr]:.2f}% "
          f"at {ms[peak_rr]:.0f} ms ({100 * g['Err_lo'][peak_rr]:.2f} to {100 * g['Err_hi'][peak_rr]:.2f}%); "
          f"conventional (sigma {args.conventional_sigma:g} px): Ecc {100 * np.nanmin(conv.global_Ecc):.2f}%, "
          f"Err {100 * np.nanmax(conv.global_Err):.2f}%{truth}; {out['seconds']:.0f} s from reading the input "
          "to the report (the last progress line gives the total, files included)")
    _write_json(args.json, out)
    if args.csv:
        say(f"writing the CSV table {args.csv}")
        print(f"wrote {strain_csv(out, args.csv)}", file=sys.stderr)
    if args.figures:
        say(f"drawing the figures into {args.figures}")
        for p in strain_figures(out, args.figures):
            print(f"wrote {p}", file=sys.stderr)
        if "material" not in out:
            say("no stiffness figure: the route holds the material fixed (its settings say so), so there is no "
                "stiffness per segment with an sd to draw")
    say(f"finished in {time.perf_counter() - t0:.0f} s, from reading the input to the last file written")
    return 0


def _dense_spline(tracks, centre, start_deg: float, say) -> dict:
    """The yardstick of the DENSE route: the thin-plate spline through the same observed points (every
    tracked reference pixel, with the sd of the pixels behind each: the tracks share pixels, so on the curves'
    scale their errors are those of independent data at that sd, not at the smaller sd of each interpolated
    datum alone), its strain at the reference pixels, as the ``spline`` block."""
    say("thin-plate spline through the same observed points (the tracked reference pixels)")
    s = spline_strain(tracks.points, tracks.displacement, tracks.points, sd_px=tracks.pixel_sd, centre=centre,
                      start_deg=start_deg, frame_times_s=tracks.frame_times_s)
    return spline_block(s, "the tracked reference pixels (every datum the dense route observes), with their sd")


def _strain_extras(case, out: dict, say) -> dict:
    """The strain report with the case's ground truth as a ``truth`` block (when it has one) and the
    peaks and times to peak of every method's curves (``peaks`` in each block)."""
    if case is not None and case.has_truth and out.get("centre") is not None:
        say("ground truth of the case at the reference pixels")
        te, tr = truth_at_points(case)
        out["truth"] = truth_block(te, tr, out["points"], out["centre"], out["segments"]["start_deg"],
                                   source="DENSE-Sim GT_Ecc, GT_Err")
    return with_peaks(out)
