"""``sfem-filters observe``: images or masks -> a confidence-weighted observation sequence (shape
tracking of the borders, Eqs. 35-37; phase-contrast velocities with their coherence, Eqs. 38-39)."""
from __future__ import annotations

import os
import sys
from dataclasses import replace

import numpy as np

from ..cardiac.frontend import observe
from ..cardiac.sequence import save_sequence
from ..imaging.readers import make_image_series, read_images
from ..imaging.tracking import TrackingOptions
from ..plotting.frontend import observe_figures
from ._common import _positive_float, _positive_int


def add_parser(sub) -> None:
    """The ``observe`` subcommand and its options, on the subparsers ``sub``."""
    o = sub.add_parser("observe", help="images or masks -> confidence-weighted observation sequence",
                       description="Shape-track the myocardial borders of a mask (or segmented image) sequence "
                                   "(Eqs. 35-37), sample phase-contrast velocities at mid-wall with their local "
                                   "phase coherence (Eqs. 38-39), and write a sequence file with confidences.")
    o.add_argument("path", help="images: a DICOM directory, .nii/.nii.gz, .npz (keys magnitude, velocity, masks, "
                                "pixel_spacing, frame_interval, venc) or .npy; or a sequence .npz with frame_masks")
    o.add_argument("--out", required=True, metavar="PATH", help="sequence .npz to write")
    o.add_argument("--pixel-spacing", type=_positive_float, help="pixel size in m (overrides the file)")
    o.add_argument("--frame-interval", type=_positive_float, help="time between frames in s (overrides the file)")
    o.add_argument("--venc", type=_positive_float, help="velocity encoding in m/s (overrides the file)")
    o.add_argument("--window", type=_positive_int, default=2, help="search window, contour points (default 2)")
    o.add_argument("--figures", metavar="DIR", help="write the figures (PNG) into DIR")
    o.add_argument("-q", "--quiet", action="store_true",
                   help="for scripts: no progress output (observe shows no bars; accepted as by every verb); "
                        "the results, errors and warnings are still printed")


def cmd_observe(args) -> int:
    path = args.path
    series = None
    if path.endswith(".npz") and os.path.isfile(path):
        try:
            with np.load(path, allow_pickle=False) as f:
                keys = set(f.files)
                if "frame_masks" in keys and not keys & {"masks", "magnitude"}:
                    series = make_image_series(masks=f["frame_masks"], provenance=path,
                                               pixel_spacing=f["pixel_spacing"] if "pixel_spacing" in keys else None,
                                               frame_interval=f["frame_interval"] if "frame_interval" in keys else None)
        except (OSError, EOFError) as exc:
            raise ValueError(f"{path}: not a readable .npz file ({exc})") from None
    if series is None:
        series = read_images(path)
    over = {k: v for k, v in (("pixel_spacing", args.pixel_spacing), ("frame_interval", args.frame_interval),
                              ("venc", args.venc)) if v is not None}
    if over:
        series = replace(series, **over)
    seq, tracks, vel, masks = observe(series, TrackingOptions(window=args.window))
    written = save_sequence(seq, args.out)
    c = tracks.step_confidence[1:]
    print(f"frames {seq.n_frames}; border points {len(tracks.points)} (endo {int((tracks.contour == 0).sum())}, "
          f"epi {int((tracks.contour == 1).sum())}); match confidence c median {np.median(c):.2f} "
          f"(5-95%: {np.percentile(c, 5):.2f}-{np.percentile(c, 95):.2f}); tracking sd at the last frame "
          f"median {np.median(tracks.sigma[-1]):.2f} px")
    if vel is not None:
        print(f"velocity points {len(vel.points)}; LPC median {np.median(vel.lpc):.2f} "
              f"(5-95%: {np.percentile(vel.lpc, 5):.2f}-{np.percentile(vel.lpc, 95):.2f})")
    print(f"wrote {written}", file=sys.stderr)
    if args.figures:
        for p in observe_figures({"tracks": tracks, "masks": masks, "velocity": vel}, args.figures):
            print(f"wrote {p}", file=sys.stderr)
    return 0
