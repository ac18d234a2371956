"""What ``sfem-filters strain`` reads from PATH: a DENSE-Sim case folder, a folder of DENSE DICOM files
or a sequence ``.npz`` of points on the pixel grid, each turned into Lagrangian tracks (pixels), the
reference mask, the pixel size and the frame times; an error names the command's argument."""
from __future__ import annotations

import argparse
import os
import re

import numpy as np

from ..cardiac import load_sequence
from ..cardiac.strain_route import StrainRouteSettings, image_settings, masks_can_be_fused, masks_move, \
    route_settings, temporal_noise_floor
from ..imaging import (add_complex_noise, phase_to_displacement, read_dense_dicom_folder, read_dense_sim,
                       tracks_on_pixel_grid)
from ..imaging.dense import check_resolution_px


_IMAGE_ONLY = (("ke", "--ke"), ("masks", "--masks"), ("directions", "--directions"), ("phase_range", "--phase-range"))
_DICOM_ARGUMENTS = {"ke_cycles_per_mm": "--ke", "masks": "--masks", "directions": "--directions",
                    "phase_range": "--phase-range"}
_CASE_NAMES = ("config.yaml", "phase_x.npy", "phase_y.npy", "magnitude.npy", "LV_mask_time_lowres.npy")
_CASE_FILES = ", ".join(_CASE_NAMES[:-1]) + " and " + _CASE_NAMES[-1]


def _strain_input(args, say) -> dict:
    """What ``strain`` reads from PATH: a DENSE-Sim case folder, a DENSE DICOM folder or a sequence ``.npz``.

    Returns a dict: ``case`` (the :class:`~sfem_filters.imaging.DenseCase`, ``None`` for a
    sequence), ``tracks`` (Lagrangian, pixels), ``reference_mask``, ``masks`` ((F + 1, H, W) for
    the contours route and ``--with-masks``, or ``None``; ``frame_masks_given``: whether they are
    each frame's own, not the reference repeated), ``pixel_size_m``, ``frame_times_s``,
    ``conventional`` (what the conventional analysis is) and ``input`` (the settings block that
    says what was read)."""
    path = args.path
    if os.path.isfile(path):
        return _sequence_input(args, say)
    if not os.path.isdir(path):
        raise ValueError(f"path: expected a DENSE-Sim case folder, a folder of DENSE DICOM files or a sequence .npz, "
                         f"got {path!r} (no such file or folder)")
    say(f"reading {path}")
    if os.path.isfile(os.path.join(path, "config.yaml")):
        given = [flag for name, flag in _IMAGE_ONLY if getattr(args, name) is not None]
        if given:
            raise ValueError(f"{given[0]}: is for DICOM folders; a DENSE-Sim case folder carries its own ke "
                             f"(config.yaml), masks and directions")
        case = read_dense_sim(path)
        info = {"kind": "DENSE-Sim case folder", "path": path}
        per_frame = True
    elif _has_dicom_file(path):
        case, info = _dicom_case(args, path)
        per_frame = info["masks_shape"] is not None and len(info["masks_shape"]) == 3
    else:
        present = [f for f in _CASE_NAMES if os.path.isfile(os.path.join(path, f))]
        hint = (f" (a DENSE-Sim case folder? it has {', '.join(present)} but not "
                f"{', '.join(f for f in _CASE_NAMES if f not in present)})" if present else
                " (none of a DENSE-Sim case's files and no DICOM file)")
        raise ValueError(f"path: expected a DENSE-Sim case folder with {_CASE_FILES}, a folder of DENSE DICOM files or "
                         f"a sequence .npz, got {path!r}{hint}")
    if args.snr is not None:
        say(f"adding complex noise at SNR {args.snr:g} (seed {args.seed})")
        case = add_complex_noise(case, args.snr, args.seed)
    say("phase to Lagrangian displacement")
    tracks = phase_to_displacement(case)
    return {"case": case, "tracks": tracks, "reference_mask": case.reference_mask, "masks": case.masks,
            "frame_masks_given": per_frame, "pixel_size_m": case.pixel_size_m, "frame_times_s": case.frame_times_s,
            "input": info,
            "conventional": "finite-difference Green-Lagrange strain on the reference pixel grid of the Lagrangian "
                            "tracks from the unwrapped phase (the same tracks the DENSE route observes)"}


#: ``--resolution-px`` word for the acquisition's own resolution (a DENSE-Sim config, a DICOM's AcquisitionMatrix).
ACQUISITION = "acquisition"


def _resolution_px(text: str):
    """argparse type of ``--resolution-px``: ``acquisition`` or a number >= 1 (reconstructed pixels)."""
    if text.strip().lower() == ACQUISITION:
        return ACQUISITION
    try:
        return check_resolution_px(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected the acquired resolution in reconstructed pixels, a finite number "
                                         f">= 1 (1: no blur beyond the pixel), or '{ACQUISITION}' for the images' own "
                                         f"acquisition, got {text!r}") from None


def _dense_settings(args, src: dict) -> StrainRouteSettings:
    """The DENSE route's settings from the command line and what PATH carries.

    Images (a DENSE-Sim case, a DICOM folder): :func:`sfem_filters.cardiac.image_settings`, the
    acquisition's point spread and the masks fused when they move from frame to frame, each
    option given overriding it. A sequence file: no acquisition (point observation unless
    ``--resolution-px`` gives a number), its masks fused when it carries each frame's. Raises
    ValueError naming the option that cannot apply."""
    case, masks = src["case"], src["masks"]
    value = getattr(args, "resolution_px", None)
    if value == ACQUISITION and case is None:
        raise ValueError(f"--resolution-px {ACQUISITION}: a sequence file carries no acquisition; give the "
                         f"acquired resolution in reconstructed pixels (a number >= 1)")
    fuse = getattr(args, "masks_fusion", None)          # True (--with-masks), False (--no-masks), None (auto)
    moving = masks is not None and src.get("frame_masks_given", False) and masks_move(masks)
    if fuse and not moving:
        if masks is None:
            got = "none (the sequence file has no reference_mask and frame_masks)"
        elif not src.get("frame_masks_given", False):
            got = "one mask for every frame (--masks (H, W)); give --masks (F, H, W) or (F + 1, H, W)"
        else:
            got = "masks that do not move (every frame's is the reference's): their borders carry no motion"
        raise ValueError(f"--with-masks: expected the myocardium mask of every frame, moving with the wall, got {got}")
    level = getattr(args, "phase_noise_level", None)
    starts = getattr(args, "border_starts", None)
    starts = None if starts == 1 else starts                 # the default: nothing to average, fused or not
    correspondence = getattr(args, "border_correspondence", None)
    tracked = correspondence == "landmarks" or (correspondence is None and starts is not None)
    fuse = (moving and masks_can_be_fused(masks, every_frame=tracked)) if fuse is None else fuse
    why = ("(--no-masks)" if getattr(args, "masks_fusion", None) is False
           else "(the masks it needs cannot be made rings; the warning above names them)" if moving
           else "(no mask of every frame that moves)")
    mask_level = getattr(args, "mask_noise_level", None)
    for flag, given_value, what in (("--phase-noise-level", level, "weighs the phase data against the masks"),
                                    ("--mask-noise-level", mask_level, "weighs the masks against the phase data"),
                                    ("--border-starts", starts, "averages the masks' border data"),
                                    ("--border-correspondence", correspondence, "places the masks' border data")):
        if given_value is not None and not fuse:
            raise ValueError(f"{flag}: {what}, which this run does not fuse {why}")
    if starts is not None and correspondence == "phase":
        raise ValueError(f"--border-starts: averages landmarks tracked from several contour starts; with "
                         f"--border-correspondence phase there are none (give --border-correspondence landmarks, "
                         f"or leave --border-starts out), got --border-starts {starts}")
    if starts is not None and correspondence is None:
        correspondence = "landmarks"                          # the starts are the landmarks' own
    overrides = {"start_deg": args.segment_start, "border_masks": bool(fuse)}
    given = {"phase_noise_level": level, "mask_noise_level": mask_level, "process_profile": args.process_profile,
             "border_starts": starts,
             "border_correspondence": correspondence,
             "resolution_px": None if value in (None, ACQUISITION) else float(value)}
    overrides.update({k: v for k, v in given.items() if v is not None})
    return image_settings(case, **overrides) if case is not None else route_settings(**overrides)


def _has_dicom_file(folder: str) -> bool:
    """Whether a file under ``folder`` carries the DICOM preamble (``DICM`` at byte 128)."""
    for root, _, files in os.walk(folder):
        for name in files:
            try:
                with open(os.path.join(root, name), "rb") as fh:
                    fh.seek(128)
                    if fh.read(4) == b"DICM":
                        return True
            except OSError:
                continue
    return False


def _dicom_case(args, path: str) -> tuple:
    """The :class:`~sfem_filters.imaging.DenseCase` of a DENSE DICOM folder; errors name the CLI arguments."""
    if args.ke is None:
        raise ValueError("--ke: expected the DENSE encoding frequency in cycles/mm for a DICOM folder (DICOM has no "
                         "standard tag for it), e.g. --ke 0.1")
    if args.masks is None:
        raise ValueError("--masks: expected a .npy file of the myocardium mask(s) for a DICOM folder (DICOM carries "
                         "none): (H, W) the reference, (F, H, W) each frame's or (F + 1, H, W) the reference then "
                         "each frame's")
    if not os.path.isfile(args.masks):
        raise ValueError(f"--masks: expected a .npy file of myocardium masks, got {args.masks!r} (no such file)")
    try:
        masks = np.load(args.masks, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"--masks: expected a .npy file of boolean (or 0/1) masks, could not read {args.masks!r} "
                         f"({exc})") from None
    if not isinstance(masks, np.ndarray):
        masks.close()
        raise ValueError(f"--masks: expected a .npy file (one array), got an .npz archive {args.masks!r}")
    directions = None if args.directions is None else np.reshape(args.directions, (2, 2))
    try:
        case = read_dense_dicom_folder(path, masks, args.ke, directions=directions, phase_range=args.phase_range)
    except ValueError as exc:       # the library names its parameters; say the command's arguments
        text = re.sub(r"^(masks|directions):", lambda m: _DICOM_ARGUMENTS[m.group(1)] + ":", str(exc))
        raise ValueError(re.sub(r"\b(ke_cycles_per_mm|phase_range)\b", lambda m: _DICOM_ARGUMENTS[m.group(1)],
                                text)) from None
    info = {"kind": "DENSE DICOM folder", "path": path, "provenance": case.provenance, "ke_cycles_per_mm": args.ke,
            "masks": args.masks, "masks_shape": list(np.shape(masks)), "directions": case.directions.tolist(),
            "phase_range": None if args.phase_range is None else list(args.phase_range)}
    return case, info


def _sequence_input(args, say) -> dict:
    """A sequence ``.npz`` as the strain routes take it: its points on the pixel grid, its tracks the data."""
    given = [flag for name, flag in _IMAGE_ONLY + (("snr", "--snr"),) if getattr(args, name) is not None]
    if given:
        raise ValueError(f"{given[0]}: is for DENSE images (a DENSE-Sim case or a DICOM folder); {args.path!r} is a "
                         f"sequence file, whose tracks are the data")
    say(f"reading the sequence {args.path}")
    seq = load_sequence(args.path)
    if seq.units != "px":
        raise ValueError(f"{args.path}: units: expected 'px' (points as reference pixel centres, as the strain routes "
                         f"need), got {seq.units!r}")
    if seq.pixel_spacing is None:
        raise ValueError(f"{args.path}: missing pixel_spacing (m): the strain routes need the pixel size; save the "
                         f"sequence with pixel_spacing")
    F = seq.n_frames
    if "frame_times_s" in seq.extra:
        times = np.asarray(seq.extra["frame_times_s"], float)
        if times.shape != (F,):
            raise ValueError(f"{args.path}: frame_times_s: expected {F} frame times (s), got shape {times.shape}")
        time_source = "frame_times_s"
    elif seq.frame_interval is not None:
        times = np.arange(F) * seq.frame_interval
        time_source = "frame_interval: frame f at f * frame_interval"
    else:
        raise ValueError(f"{args.path}: missing frame_interval (s) (or frame_times_s, (F,) s): the strain routes need "
                         f"the frame times")
    if seq.sigma is not None:
        sd, sd_source = seq.sigma, "sigma (both components)"
    else:
        sd = temporal_noise_floor(seq.displacement)
        sd_source = f"no sigma in the file: the tracks' temporal noise floor, {sd:.4g} px, for every datum"
    try:
        tracks, mask = tracks_on_pixel_grid(seq.points, seq.displacement, times, sd, seq.confidence,
                                            seq.reference_mask)
    except ValueError as exc:
        raise ValueError(f"{args.path}: {exc}") from None
    masks = None
    if seq.reference_mask is not None and seq.frame_masks is not None:
        masks = np.concatenate([mask[None], seq.frame_masks])
    info = {"kind": "sequence file", "path": args.path, "provenance": seq.provenance, "frame_times": time_source,
            "sd": sd_source, "reference_mask": "reference_mask" if seq.reference_mask is not None else
            "the points' pixels", "points_reordered": bool(not np.array_equal(tracks.points, seq.points))}
    return {"case": None, "tracks": tracks, "reference_mask": mask, "masks": masks,
            "frame_masks_given": masks is not None, "pixel_size_m": seq.pixel_spacing, "frame_times_s": times,
            "input": info,
            "conventional": "finite-difference Green-Lagrange strain of the sequence's tracks on the reference pixel "
                            "grid (no images: the tracks are the data)"}
