"""Readers for the images users have: numpy / npz always, DICOM and NIfTI as optional extras.

Every reader returns an :class:`ImageSeries`: one short-axis slice through the cycle, with the
pixel spacing (m) and the frame interval (s) when the file records them. Install the extras
with ``pip install "sfem-filters[dicom]"`` (pydicom) or ``"sfem-filters[nifti]"`` (nibabel).

npz / npy layout (keys, all optional but one of ``magnitude`` / ``masks``):

============== ================ ==========================================================
magnitude      (F, H, W)        intensity images
velocity       (F, H, W, 2)     phase-contrast velocity (vx, vy), m/s
masks          (F, H, W) bool   myocardium mask of each frame
pixel_spacing  ()               m per pixel
frame_interval ()               s between frames
venc           ()               velocity encoding, m/s
============== ================ ==========================================================

A bare ``.npy`` holds magnitude images (F, H, W).
"""
from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass

import numpy as np

from .._validate import as_float_array, as_mask, positive


@dataclass(frozen=True, eq=False)
class ImageSeries:
    """A validated image sequence of one slice (row = y, column = x)."""

    magnitude: np.ndarray | None = None      # (F, H, W)
    velocity: np.ndarray | None = None       # (F, H, W, 2) m/s
    masks: np.ndarray | None = None          # (F, H, W) bool
    pixel_spacing: float | None = None       # m
    frame_interval: float | None = None      # s
    venc: float | None = None                # m/s
    provenance: str = ""

    @property
    def n_frames(self) -> int:
        """Number of frames F (of ``masks``, else of ``magnitude``)."""
        return len(self.masks if self.masks is not None else self.magnitude)

    @property
    def shape(self) -> tuple:
        """Image size (H, W) in pixels."""
        return (self.masks if self.masks is not None else self.magnitude).shape[1:3]


def make_image_series(magnitude=None, velocity=None, masks=None, pixel_spacing=None, frame_interval=None,
                      venc=None, provenance: str = "") -> ImageSeries:
    """Check arrays into an :class:`ImageSeries` (errors name the argument and the expectation)."""
    if magnitude is None and masks is None:
        raise ValueError("magnitude, masks: expected intensity images or myocardium masks, got neither")
    shape = None
    if magnitude is not None:
        magnitude = as_float_array("magnitude", magnitude, shape=(None, None, None))
        shape = magnitude.shape
    if masks is not None:
        m = as_mask("masks", masks, 3)
        if shape is not None and m.shape != shape:
            raise ValueError(f"masks: expected the shape of magnitude {shape}, got {m.shape}")
        masks, shape = m, m.shape
    if shape[0] < 2:
        raise ValueError(f"images: expected at least 2 frames, got {shape[0]}")
    if velocity is not None:
        velocity = as_float_array("velocity", velocity, shape=(shape[0], shape[1], shape[2], 2))
        if venc is None:
            raise ValueError("venc: velocity images need their velocity encoding (m/s), got none")
    out = {}
    for name, v, unit in (("pixel_spacing", pixel_spacing, "m"), ("frame_interval", frame_interval, "s"),
                          ("venc", venc, "m/s")):
        if v is not None:
            out[name] = positive(name, float(np.asarray(v)), unit)
    return ImageSeries(magnitude=magnitude, velocity=velocity, masks=masks, provenance=str(provenance), **out)


def read_npz(path) -> ImageSeries:
    """Read an ``.npz`` (keys in the module docstring) or an ``.npy`` of magnitude images."""
    path = os.fspath(path)
    try:
        if path.endswith(".npy"):
            return make_image_series(magnitude=np.load(path, allow_pickle=False), provenance=path)
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
        raise ValueError(f"{path}: not a readable numpy image file ({exc})") from None
    known = {"magnitude", "velocity", "masks", "pixel_spacing", "frame_interval", "venc"}
    if not known & set(data):
        raise ValueError(f"{path}: expected some of the keys {sorted(known)}, found {sorted(data)}")
    try:
        return make_image_series(provenance=path, **{k: data[k] for k in known if k in data})
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def read_dicom_series(directory) -> ImageSeries:
    """Read a cine DICOM series (one slice, one file per frame) from a directory.

    Frames are ordered by TriggerTime (then InstanceNumber). The pixel spacing comes from
    PixelSpacing (mm, converted to m; rows and columns must agree), the frame interval from the
    median step of TriggerTime (ms, converted to s) when there is one.
    """
    try:
        import pydicom
    except ImportError:
        raise ImportError("reading DICOM needs pydicom: pip install 'sfem-filters[dicom]'") from None
    directory = os.fspath(directory)
    if not os.path.isdir(directory):
        raise ValueError(f"directory: expected a directory of DICOM files, got {directory!r}")
    frames = []
    for name in sorted(os.listdir(directory)):
        p = os.path.join(directory, name)
        if not os.path.isfile(p):
            continue
        try:
            ds = pydicom.dcmread(p)
            img = ds.pixel_array
        except Exception:                      # not a DICOM image: skip (e.g. DICOMDIR, notes)
            continue
        frames.append((float(getattr(ds, "TriggerTime", np.nan)), int(getattr(ds, "InstanceNumber", 0)), ds, img))
    if len(frames) < 2:
        raise ValueError(f"directory: expected at least 2 DICOM image frames in {directory!r}, found {len(frames)}")
    frames.sort(key=lambda f: (np.nan_to_num(f[0], nan=np.inf), f[1]))
    shapes = {f[3].shape for f in frames}
    if len(shapes) != 1:
        raise ValueError(f"directory: expected frames of one size, got sizes {sorted(shapes)}")
    images = np.stack([f[3] for f in frames]).astype(float)
    ds0 = frames[0][2]
    spacing = None
    if hasattr(ds0, "PixelSpacing"):
        ps = [float(v) for v in ds0.PixelSpacing]
        if not np.isclose(ps[0], ps[1], rtol=1e-3):
            raise ValueError(f"PixelSpacing: expected square pixels, got {ps} mm")
        spacing = ps[0] * 1e-3
    times = np.array([f[0] for f in frames])
    interval = None
    if np.all(np.isfinite(times)) and len(times) > 1:
        steps = np.diff(times)
        if np.all(steps > 0):
            interval = float(np.median(steps)) * 1e-3
    return make_image_series(magnitude=images, pixel_spacing=spacing, frame_interval=interval,
                             provenance=f"DICOM series {directory}")


def read_nifti(path) -> ImageSeries:
    """Read a NIfTI cine slice: a 3D (X, Y, T) or 4D (X, Y, 1, T) image.

    Spatial and time units follow the header's ``xyzt_units`` (mm and ms/s/us are converted to
    m and s); nibabel's first axis is the image column (x), the second the row (y).
    """
    try:
        import nibabel as nib
    except ImportError:
        raise ImportError("reading NIfTI needs nibabel: pip install 'sfem-filters[nifti]'") from None
    path = os.fspath(path)
    try:
        img = nib.load(path)
        data = np.asarray(img.dataobj, dtype=float)
    except Exception as exc:
        raise ValueError(f"{path}: not a readable NIfTI image ({type(exc).__name__}: {exc})") from None
    if data.ndim == 4 and data.shape[2] == 1:
        data = data[:, :, 0, :]
    if data.ndim != 3:
        raise ValueError(f"{path}: expected one slice through time, (X, Y, T) or (X, Y, 1, T), got shape {data.shape}")
    hdr = img.header
    space_unit, time_unit = hdr.get_xyzt_units()
    zooms = hdr.get_zooms()
    to_m = {"mm": 1e-3, "meter": 1.0, "micron": 1e-6}.get(space_unit)
    to_s = {"sec": 1.0, "msec": 1e-3, "usec": 1e-6}.get(time_unit)
    spacing = None
    if to_m is not None and zooms[0] > 0:
        if not np.isclose(zooms[0], zooms[1], rtol=1e-3):
            raise ValueError(f"{path}: expected square pixels, got pixdim {zooms[:2]}")
        spacing = float(zooms[0]) * to_m
    interval = None
    t_zoom = zooms[3] if len(zooms) > 3 else None
    if to_s is not None and t_zoom:
        interval = float(t_zoom) * to_s
    images = np.transpose(data, (2, 1, 0))              # (T, rows = y, columns = x)
    return make_image_series(magnitude=images, pixel_spacing=spacing, frame_interval=interval,
                             provenance=f"NIfTI {path}")


def read_images(path) -> ImageSeries:
    """Read an image series by its kind: a directory (DICOM), ``.nii`` / ``.nii.gz``, ``.npz`` / ``.npy``."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise ValueError(f"path: no such file or directory {path!r}")
    if os.path.isdir(path):
        return read_dicom_series(path)
    if path.endswith((".nii", ".nii.gz")):
        return read_nifti(path)
    if path.endswith((".npz", ".npy")):
        return read_npz(path)
    raise ValueError(f"path: expected a DICOM directory, .nii(.gz), .npz or .npy, got {path!r}")
