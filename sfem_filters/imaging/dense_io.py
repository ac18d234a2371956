"""DENSE images in: DENSE-Sim case folders and DENSE phase and magnitude DICOM series.

DENSE (displacement encoding with stimulated echoes) stores, for each encoding direction
``d_j`` (a unit vector in image axes, x = column, y = row), a phase ``phi_j = 2 pi ke d_j . u``
(rad), ``ke`` the encoding frequency (cycles per unit length). This module checks arrays into a
:class:`DenseCase` (:func:`make_dense_case`) and reads them from DENSE-Sim case folders
(Barbaroux et al., JCMR 2025; :func:`read_dense_sim`), from DICOM series given as one directory
per series (:func:`read_dense_dicom`), and from a DICOM folder as scanners export it, the series
told apart by their ``ImageComments`` (:func:`read_dense_dicom_folder`). Phase processing (noise,
unwrapping, phase to Lagrangian displacement) is in :mod:`sfem_filters.imaging.dense`, which
re-exports every name here.

Units: pixels (x = column, y = row) for images; pixel size in mm where a file or argument
gives it, m inside :class:`DenseCase`; ``ke`` in cycles/mm in arguments, cycles/m inside; times
in s (DICOM ``TriggerTime`` in ms).
"""
from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass

import numpy as np
import yaml

from .._validate import as_float_array, as_mask, integer, positive, user_stacklevel

__all__ = ["DenseCase", "make_dense_case", "read_dense_sim", "read_dense_dicom", "read_dense_dicom_folder",
           "dense_masks", "dense_series_kind", "DICOM_SUBFOLDERS", "PHASE_TOLERANCE", "DEFAULT_RESOLUTION_PX",
           "check_resolution_px", "dicom_resolution_px", "dense_sim_grid"]

PHASE_TOLERANCE = 1e-4
"""rad: how far beyond +-pi a stored phase may lie (float rounding of a wrapped phase)."""

DEFAULT_RESOLUTION_PX = 1.0
"""The acquired resolution (reconstructed pixels) assumed when nothing says otherwise: the image's own
pixel, i.e. no blur beyond the pixel grid (the DENSE route's observation is then a point interpolation)."""


def check_resolution_px(resolution_px, name: str = "resolution_px") -> float:
    """A checked acquired resolution: a finite number >= 1 of reconstructed pixels (a clear error otherwise).

    The acquired resolution is the width of the acquisition's own pixel (field of view over the
    acquired matrix) in pixels of the reconstructed image: 1 when the image is reconstructed at
    the acquired matrix, above 1 when it is interpolated (zero-filled) to a finer grid. Below 1
    would be a blur narrower than the image's own pixel, which no image has: an image resampled to
    a grid coarser than its data is read as 1 by the readers (:func:`dense_sim_grid`,
    :func:`dicom_resolution_px`), and a user's value below 1 is an error.
    """
    try:
        w = float(resolution_px)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected the acquired resolution in reconstructed pixels (a number >= 1), got "
                         f"{resolution_px!r}") from None
    if not np.isfinite(w) or w < 1.0:
        raise ValueError(f"{name}: expected the acquired resolution in reconstructed pixels, a finite number >= 1 "
                         f"(1: the image's own pixel, no blur beyond it), got {resolution_px!r}")
    return w


@dataclass(frozen=True, eq=False)
class DenseCase:
    """A validated DENSE slice through the cycle (images indexed row = y, column = x).

    Attributes
    ----------
    phases : (2, F, H, W) array
        Wrapped phase (rad, in [-pi, pi]) of each encoding at each frame.
    magnitude : (F, H, W) array
        Image magnitude (arbitrary units, >= 0).
    masks : (F + 1, H, W) bool array
        Myocardium masks: index 0 the reference (encoding time t = 0), index f + 1 frame f.
    pixel_size_m : float
        Pixel size (m, square pixels).
    ke_per_m : float
        Encoding frequency (cycles/m).
    frame_times_s : (F,) array
        Time of each frame after the encoding (s).
    directions : (2, 2) array
        Row j is the unit vector (x, y) in image axes of encoding j.
    truth_ecc, truth_err : (F, H, W) arrays or None
        Ground-truth Green-Lagrange strain of each reference pixel (fraction), NaN elsewhere.
    provenance : str
        Where the case came from.
    resolution_px : float
        Acquired resolution in reconstructed pixels (>= 1; :func:`check_resolution_px`): the field
        of view over the acquired matrix, from the file when it says (DENSE-Sim's
        ``(FOV / N_im_pre_spiral)`` over the images' pixel, :func:`dense_sim_grid`; a DICOM's Rows and Columns over its ``AcquisitionMatrix``), else
        :data:`DEFAULT_RESOLUTION_PX`. The DENSE route's observation operator takes its point
        spread function from it (:func:`sfem_filters.imaging.dense.psf_sigma_px`).
    """

    phases: np.ndarray
    magnitude: np.ndarray
    masks: np.ndarray
    pixel_size_m: float
    ke_per_m: float
    frame_times_s: np.ndarray
    directions: np.ndarray
    truth_ecc: np.ndarray | None = None
    truth_err: np.ndarray | None = None
    provenance: str = ""
    resolution_px: float = DEFAULT_RESOLUTION_PX

    @property
    def n_frames(self) -> int:
        """Number of frames F."""
        return self.phases.shape[1]

    @property
    def shape(self) -> tuple:
        """Image size (H, W) in pixels."""
        return self.phases.shape[2:]

    @property
    def pixel_size_mm(self) -> float:
        """Pixel size (mm)."""
        return self.pixel_size_m * 1e3

    @property
    def reference_mask(self) -> np.ndarray:
        """(H, W) bool: the reference myocardium (encoding time)."""
        return self.masks[0]

    @property
    def frame_masks(self) -> np.ndarray:
        """(F, H, W) bool: the myocardium of each frame."""
        return self.masks[1:]

    @property
    def has_truth(self) -> bool:
        """True when both ground-truth strains, ``truth_ecc`` and ``truth_err``, are present."""
        return self.truth_ecc is not None and self.truth_err is not None


def make_dense_case(phases, magnitude, masks, pixel_size_mm, ke_cycles_per_mm, frame_times_s, directions=None,
                    truth_ecc=None, truth_err=None, provenance: str = "",
                    resolution_px: float = DEFAULT_RESOLUTION_PX) -> DenseCase:
    """Check arrays into a :class:`DenseCase`; errors name the argument and the expectation.

    Parameters
    ----------
    phases : (2, F, H, W) array
        Wrapped phase (rad) of the two encodings; values within +-pi (+ :data:`PHASE_TOLERANCE`).
    magnitude : (F, H, W) array
        Magnitude images (>= 0).
    masks : (F + 1, H, W) bool array
        Index 0 the reference myocardium, index f + 1 frame f; none may be empty.
    pixel_size_mm : float
        Pixel size (mm).
    ke_cycles_per_mm : float
        Encoding frequency (cycles/mm, > 0).
    frame_times_s : (F,) array
        Frame times after the encoding (s), increasing.
    directions : (2, 2) array, optional
        Encoding directions (rows, unit vectors (x, y) in image axes); default the identity
        (encoding 0 along x = columns, encoding 1 along y = rows).
    truth_ecc, truth_err : (F, H, W) arrays, optional
        Ground-truth strain (fraction), NaN outside the reference mask.
    provenance : str
    resolution_px : float
        Acquired resolution in reconstructed pixels (>= 1; default 1, no blur beyond the pixel).
    """
    resolution_px = check_resolution_px(resolution_px)
    if ke_cycles_per_mm is None:
        raise ValueError("ke_cycles_per_mm: expected the DENSE encoding frequency in cycles/mm, got None")
    ke = positive("ke_cycles_per_mm", ke_cycles_per_mm, "cycles/mm")
    px = positive("pixel_size_mm", pixel_size_mm, "mm")
    phases = as_float_array("phases", phases, shape=(2, None, None, None))
    bad = np.abs(phases) > np.pi + PHASE_TOLERANCE
    if bad.any():
        raise ValueError(f"phases: expected wrapped phases in [-pi, pi] rad, got {int(bad.sum())} values outside "
                         f"(largest |phase| {float(np.abs(phases).max()):.4g} rad); convert stored values to radians")
    F, H, W = phases.shape[1:]
    magnitude = as_float_array("magnitude", magnitude, shape=(F, H, W))
    if np.any(magnitude < 0):
        raise ValueError("magnitude: expected non-negative magnitudes, got negative values")
    masks = as_mask("masks", masks, ndim=3, shape=(F + 1, H, W))
    if not masks[0].any():
        raise ValueError("masks: expected the reference mask (index 0) to hold myocardium, got no tissue pixel")
    empty = np.flatnonzero(~masks[1:].any(axis=(1, 2)))
    if empty.size:
        raise ValueError(f"masks: expected myocardium in every frame's mask, got none in frame(s) {empty.tolist()}")
    times = as_float_array("frame_times_s", frame_times_s, shape=(F,))
    if F > 1 and np.any(np.diff(times) <= 0):
        raise ValueError("frame_times_s: expected increasing frame times (s)")
    d = np.eye(2) if directions is None else as_float_array("directions", directions, shape=(2, 2))
    if not np.allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-6) or abs(np.linalg.det(d)) < 1e-3:
        raise ValueError(f"directions: expected two independent unit vectors (x, y) as rows, got {d.tolist()}")
    truths = []
    for name, t in (("truth_ecc", truth_ecc), ("truth_err", truth_err)):
        truths.append(None if t is None else as_float_array(name, t, shape=(F, H, W), allow_nan=True))
    return DenseCase(phases=phases, magnitude=magnitude, masks=masks, pixel_size_m=px * 1e-3, ke_per_m=ke * 1e3,
                     frame_times_s=times, directions=d, truth_ecc=truths[0], truth_err=truths[1],
                     provenance=provenance, resolution_px=resolution_px)


def _load(folder: str, name: str, required: bool = True):
    p = os.path.join(folder, name)
    if not os.path.isfile(p):
        if required:
            raise FileNotFoundError(f"path: expected {name} in the DENSE-Sim case folder {folder!r}, not found")
        return None
    return np.load(p, allow_pickle=False)


def _square_fov_mm(value, name: str) -> float:
    """A square field of view (mm) from a config entry: ``[fx, fy, (fz)]`` with ``fx == fy``, or one number."""
    try:
        fov = np.atleast_1d(np.asarray(value, float)).ravel()
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a field of view in mm, [x, y, z] or one number, got {value!r}") from None
    fov = fov[:2] if fov.size >= 2 else np.repeat(fov, 2)
    if fov.size != 2 or not np.isclose(fov[0], fov[1]):
        raise ValueError(f"{name}: expected a square field of view (mm), got {np.asarray(value).tolist()}")
    return positive(name, fov[0], "mm")


def _output_grids(sim: dict) -> list:
    """``[(size, fov_mm), ...]`` of a DENSE-Sim config's ``output_dim`` (``sizes``, ``FOVs``); [] without one."""
    out = sim.get("output_dim")
    if out is None:
        return []
    if not isinstance(out, dict):
        raise ValueError(f"config.yaml output_dim: expected a mapping with sizes and FOVs, got {out!r}")
    sizes, fovs = out.get("sizes", []), out.get("FOVs", [])
    if not isinstance(sizes, (list, tuple)) or not isinstance(fovs, (list, tuple)):
        raise ValueError(f"config.yaml output_dim: expected lists of sizes and FOVs, got sizes {sizes!r}, FOVs {fovs!r}")
    if len(sizes) != len(fovs):
        raise ValueError(f"config.yaml output_dim: expected one FOV per size, got {len(sizes)} sizes and "
                         f"{len(fovs)} FOVs")
    return [(integer(f"config.yaml output_dim sizes[{i}]", n, 1),
             _square_fov_mm(f, f"config.yaml output_dim FOVs[{i}]")) for i, (n, f) in enumerate(zip(sizes, fovs))]


def dense_sim_grid(sim: dict, image_shape) -> tuple:
    """Pixel size and acquired resolution of a DENSE-Sim case's images, from its ``sim_params``.

    The simulation runs over ``FOV`` (mm) on an ``N_im`` grid, the spins' signal gridded on an
    ``N_im_pre_spiral`` matrix over that field of view (:func:`read_dense_sim`: the acquired pixel is
    ``FOV / N_im_pre_spiral`` mm). Its ``output_dim`` (``sizes``, ``FOVs``) lists the grids a case may
    be written on (DENSE-Sim's config: 128 over 224 mm or 90 over 200 mm). When the images come on
    ``N_im`` pixels the pixel is ``FOV / N_im``; when they come on another of the ``output_dim`` sizes
    the pixel is that size's ``FOV / size`` and the acquired pixel stays ``FOV / N_im_pre_spiral``
    (the output grid resamples the simulated images; it acquires nothing new), so the acquired
    resolution is ``(FOV / N_im_pre_spiral) / pixel``, ``N_im / N_im_pre_spiral`` on the ``N_im``
    grid. Images smaller than ``N_im`` on a side and on no ``output_dim`` grid are read as a crop of
    the ``N_im`` grid (pixel ``FOV / N_im``), with a warning that says so: a case resampled to a grid
    its config does not name would need that grid in ``output_dim``. Images larger than ``N_im`` on
    a grid the config does not name are an error: their pixel size, and so every displacement in
    pixels, would be a guess.

    Parameters
    ----------
    sim : dict
        ``config.yaml``'s ``sim_params``: ``FOV`` (mm, ``[x, y, z]`` or one number), ``N_im``, optional
        ``N_im_pre_spiral`` and ``output_dim``.
    image_shape : tuple of int
        (rows, columns) of the case's images.

    Returns
    -------
    pixel_size_mm : float
        The images' pixel (mm).
    resolution_px : float
        The acquired resolution in the images' pixels, at least :data:`DEFAULT_RESOLUTION_PX` (1):
        that, with a warning, when the config gives no ``N_im_pre_spiral`` or when the acquired pixel
        is finer than the images' (images resampled to a coarser grid than their data, as a DICOM's
        :func:`dicom_resolution_px` also reads it: the images' own pixel is then their blur).

    Raises
    ------
    ValueError
        A missing key, a field of view that is not square, images larger than ``N_im`` on a grid the
        config does not name, an ``output_dim`` that is not one FOV per size. (An ``output_dim`` that
        gives the ``N_im`` grid another field of view than ``FOV``, and images read as a crop, are
        warnings: ``FOV / N_im`` is taken, as DENSE-Sim's README states it; so are a missing
        ``N_im_pre_spiral`` and an acquired pixel finer than the images', read as resolution 1.)

    >>> sim = {"FOV": [224, 224, 8], "N_im": 128, "N_im_pre_spiral": 60,
    ...        "output_dim": {"sizes": [128, 90], "FOVs": [[224, 224, 8], [200, 200, 8]]}}
    >>> dense_sim_grid(sim, (128, 128))
    (1.75, 2.1333333333333333)
    >>> [round(v, 4) for v in dense_sim_grid(sim, (90, 90))]
    [2.2222, 1.68]
    """
    for key in ("FOV", "N_im"):
        if key not in sim:
            raise ValueError(f"config.yaml: expected the key sim_params.{key}, not found")
    shape = tuple(int(v) for v in image_shape)
    if len(shape) != 2 or min(shape) < 1:
        raise ValueError(f"image_shape: expected the images' (rows, columns), got {shape}")
    n_img = shape[0] if shape[0] == shape[1] else None
    fov_sim = _square_fov_mm(sim["FOV"], "config.yaml FOV")
    n_im = integer("config.yaml N_im", sim["N_im"], 1)
    grids = _output_grids(sim)
    if n_img == n_im:
        for n, f in grids:
            if n == n_im and not np.isclose(f, fov_sim):
                warnings.warn(f"config.yaml output_dim gives the N_im grid ({n_im} pixels) a field of view of {f:g} mm, "
                              f"but FOV is {fov_sim:g} mm: the pixel is taken as FOV / N_im = {fov_sim / n_im:g} mm, "
                              "as DENSE-Sim's README states it; check the case's config", UserWarning,
                              stacklevel=user_stacklevel())
        fov_out, label = fov_sim, "config.yaml N_im / N_im_pre_spiral"
    elif not any(n == n_img for n, _ in grids):
        if max(shape) > n_im:
            raise ValueError(f"config.yaml N_im: the images are {shape[0]} x {shape[1]} pixels, but N_im is {n_im} and "
                             f"output_dim lists sizes {[n for n, _ in grids]}; expected the images' size in one of "
                             "them (or a crop of the N_im grid), so that the pixel size is known")
        warnings.warn(f"config.yaml N_im: the images are {shape[0]} x {shape[1]} pixels, but N_im is {n_im} and no "
                      f"output_dim grid has that size: read as a crop of the N_im grid, pixel FOV / N_im = "
                      f"{fov_sim / n_im:g} mm; if they were resampled to another grid, give it in config.yaml "
                      "output_dim (sizes, FOVs)", UserWarning, stacklevel=user_stacklevel())
        fov_out, label, n_img = fov_sim, "config.yaml N_im / N_im_pre_spiral", n_im
    else:
        match = [f for n, f in grids if n == n_img]
        if not np.allclose(match, match[0]):
            raise ValueError(f"config.yaml output_dim: lists the size {n_img} with fields of view {match} mm; "
                             "expected one")
        fov_out, label = match[0], f"config.yaml (FOV / N_im_pre_spiral) / the {n_img}-pixel grid's pixel"
    px_mm = fov_out / n_img
    if sim.get("N_im_pre_spiral") is None:
        warnings.warn("config.yaml: no sim_params.N_im_pre_spiral, so the acquired resolution is not known: taken as "
                      f"{DEFAULT_RESOLUTION_PX:g} pixel (no blur beyond the images' own pixel); give it with "
                      "--resolution-px (StrainRouteSettings.resolution_px) if you know it", UserWarning,
                      stacklevel=user_stacklevel())
        return px_mm, DEFAULT_RESOLUTION_PX
    n_acq = integer("config.yaml N_im_pre_spiral", sim["N_im_pre_spiral"], 1)
    ratio = (fov_sim / n_acq) / px_mm
    if np.isfinite(ratio) and ratio < DEFAULT_RESOLUTION_PX:
        warnings.warn(f"{label}: the acquired pixel ({fov_sim / n_acq:g} mm) is finer than the images' pixel "
                      f"({px_mm:g} mm), so the images were resampled to a coarser grid than their data: the images' "
                      f"own pixel is their resolution ({DEFAULT_RESOLUTION_PX:g} pixel)", UserWarning,
                      stacklevel=user_stacklevel())
        return px_mm, DEFAULT_RESOLUTION_PX
    return px_mm, check_resolution_px(ratio, label)


def read_dense_sim(path) -> DenseCase:
    """Read a DENSE-Sim case folder exactly as the simulator publishes it.

    Files: ``phase_x.npy``, ``phase_y.npy`` (F, H, W) wrapped phase (rad) of the x (column) and
    y (row) encodings; ``magnitude.npy``; ``LV_mask_time_lowres.npy`` (F + 1, H, W), index 0 the
    reference; optional ``GT_Ecc.npy``, ``GT_Err.npy``; ``config.yaml`` (``sim_params``: ``FOV``
    in mm, first two entries; ``N_im``; ``ke`` in cycles/mm; ``tt`` in ms, frame f at
    ``tt[f + 1]``; optional ``N_im_pre_spiral`` and ``output_dim``). Pixel size = FOV / N_im, or, for
    images on another of ``output_dim``'s grids, that grid's FOV over its size (:func:`dense_sim_grid`).

    Acquired resolution (:attr:`DenseCase.resolution_px`) = the acquired pixel ``FOV /
    N_im_pre_spiral`` over the images' pixel (``N_im / N_im_pre_spiral`` on the ``N_im`` grid) when the
    config gives ``N_im_pre_spiral``, else 1. Why that ratio: the simulator grids the spins' signal
    on an ``N_im_pre_spiral`` matrix over the field of view and rescales its spiral trajectory to
    span +-``N_im_pre_spiral / 2`` cycles per field of view (``generate_sampling`` in DENSE-Sim's
    ``run_DENSE_sim.py``), then reconstructs on the ``N_im`` grid: the data hold no spatial
    frequency above that of an ``N_im_pre_spiral`` matrix, so the acquired pixel is
    ``FOV / N_im_pre_spiral``, ``N_im / N_im_pre_spiral`` reconstructed pixels wide.

    Parameters
    ----------
    path : str or path-like
        The case folder.
    """
    folder = os.fspath(path)
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"path: expected a DENSE-Sim case folder, got {folder!r} (not a directory)")
    cfg_path = os.path.join(folder, "config.yaml")
    if not os.path.isfile(cfg_path):
        raise FileNotFoundError(f"path: expected config.yaml in the DENSE-Sim case folder {folder!r}, not found")
    with open(cfg_path) as fh:
        cfg = yaml.safe_load(fh)
    sim = cfg.get("sim_params", cfg) if isinstance(cfg, dict) else None
    if not isinstance(sim, dict):
        raise ValueError(f"config.yaml: expected a mapping with sim_params, got {type(cfg).__name__}")
    for key in ("FOV", "N_im", "ke", "tt"):
        if key not in sim:
            raise ValueError(f"config.yaml: expected the key sim_params.{key}, not found in {cfg_path!r}")
    if sim["ke"] is None:
        raise ValueError("config.yaml ke: expected the encoding frequency in cycles/mm, got None")
    px, py = _load(folder, "phase_x.npy"), _load(folder, "phase_y.npy")
    if px.shape != py.shape:
        raise ValueError(f"phase_y.npy: expected the shape of phase_x.npy {px.shape}, got {py.shape}")
    if px.ndim != 3:
        raise ValueError(f"phase_x.npy: expected (frames, rows, columns) phases, got shape {px.shape}")
    F = px.shape[0]
    px_mm, res = dense_sim_grid(sim, px.shape[1:])
    tt = np.asarray(sim["tt"], float)
    if tt.size < F + 1:
        raise ValueError(f"config.yaml tt: expected at least F + 1 = {F + 1} times (ms), got {tt.size}")
    return make_dense_case(phases=np.stack([px, py]), magnitude=_load(folder, "magnitude.npy"),
                           masks=_load(folder, "LV_mask_time_lowres.npy"), pixel_size_mm=px_mm,
                           ke_cycles_per_mm=sim["ke"], frame_times_s=tt[1:F + 1] * 1e-3,
                           truth_ecc=_load(folder, "GT_Ecc.npy", False), truth_err=_load(folder, "GT_Err.npy", False),
                           provenance=f"DENSE-Sim case {folder}", resolution_px=res)


DICOM_SUBFOLDERS = ("phase_x", "phase_y", "magnitude")
"""Sub-folders of a DICOM folder whose files carry no DENSE ``ImageComments``: the phase series of
the x (encoding 0) and y (encoding 1) encodings and the magnitude series."""

# DENSEanalysis's reading of the ImageComments of Siemens DENSE exports (parseImageCommentsDENSE):
# 'DENSE x-enc pha - Scale:1.00 EncFreq:0.10 ... Phs:0/47 ...', 'DENSE overall mag - ... Phs:46/47 ...';
# case-insensitive wildcards tried in this order
_KINDS = (("mag.overall", "dense.*overall.*mag"), ("mag.x", "dense.*x.*mag"), ("mag.y", "dense.*y.*mag"),
          ("mag.z", "dense.*z.*mag"), ("pha.x", "dense.*x.*pha"), ("pha.y", "dense.*y.*pha"),
          ("pha.z", "dense.*z.*pha"))
_ENC_FREQ = re.compile(r"encfreq:\s*([-+]?[0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)", re.IGNORECASE)


def dense_series_kind(image_comments) -> str | None:
    """Which DENSE series a DICOM file belongs to, from its ``ImageComments``.

    As DENSEanalysis reads Siemens DENSE exports: a comment starting with ``DENSE`` is
    ``"mag.overall"``, ``"mag.x"``, ``"mag.y"``, ``"mag.z"``, ``"pha.x"``, ``"pha.y"`` or
    ``"pha.z"`` by the case-insensitive patterns ``DENSE*overall*mag``, ``DENSE*x*mag``, ...,
    ``DENSE*z*pha`` (tried in that order), else ``"unknown"``; any other comment ``None``.

    >>> dense_series_kind("DENSE x-enc pha - Scale:1.000000 EncFreq:0.10 Rep:0/1 Slc:0/1 Par:0/1 Phs:0/47")
    'pha.x'
    >>> dense_series_kind("DENSE overall mag - Rep:0/1 Slc:0/1 Par:0/1 Phs:46/47"), dense_series_kind("cine")
    ('mag.overall', None)
    """
    s = str(image_comments if image_comments is not None else "").strip().lower()
    if not s.startswith("dense"):
        return None
    for kind, pattern in _KINDS:
        if re.match(pattern, s):
            return kind
    return "unknown"


def _read_dicom_file(path):
    """``(dataset, image)`` with the modality rescale applied, or ``None`` if not a DICOM image."""
    import pydicom                                          # the optional [dicom] extra
    from pydicom.pixels import apply_modality_lut
    try:
        ds = pydicom.dcmread(path)
        img = apply_modality_lut(ds.pixel_array, ds).astype(float)
    except Exception:                          # not a DICOM image (DICOMDIR, notes): skip
        return None
    return ds, img


def _stack_frames(frames, name: str):
    """(F, H, W) images, (F,) trigger times (ms) and the first dataset of one series' files."""
    items = [(float(getattr(ds, "TriggerTime", np.nan)), int(getattr(ds, "InstanceNumber", 0) or 0), ds, img)
             for ds, img in frames]
    items.sort(key=lambda f: (np.nan_to_num(f[0], nan=np.inf), f[1]))
    shapes = {f[3].shape for f in items}
    if len(shapes) != 1:
        raise ValueError(f"{name}: expected frames of one size, got sizes {sorted(shapes)}")
    times = np.array([f[0] for f in items])
    known = times[np.isfinite(times)]
    if known.size and np.unique(known).size < known.size:
        raise ValueError(f"{name}: expected one file per frame (one slice, one repetition), got {known.size} files "
                         f"at {np.unique(known).size} distinct TriggerTime values")
    return np.stack([f[3] for f in items]), times, items[0][2]


def _read_dicom_frames(directory, name: str):
    directory = os.fspath(directory)
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"{name}: expected a directory of DICOM files, got {directory!r}")
    frames = [r for r in (_read_dicom_file(os.path.join(directory, e)) for e in sorted(os.listdir(directory))
                          if os.path.isfile(os.path.join(directory, e))) if r is not None]
    if not frames:
        raise FileNotFoundError(f"{name}: expected DICOM image files in {directory!r}, found none")
    return _stack_frames(frames, name)


def dense_masks(masks, n_frames: int) -> np.ndarray:
    """The (F + 1, H, W) masks of a :class:`DenseCase` (reference first) from what a user has.

    Parameters
    ----------
    masks : (H, W), (F, H, W) or (F + 1, H, W) bool array
        (F + 1, H, W): the reference myocardium (encoding time) then each frame's, as DENSE-Sim
        stores them; (F, H, W): each frame's, the reference taken as frame 0's (the first frame
        is some 20 ms after the encoding, the wall barely moved); (H, W): the reference, used as
        every frame's mask too (a warning says so: the wall moves out of it through systole, and
        the phase is unwrapped inside each frame's mask).
    n_frames : int
        F, the number of image frames.
    """
    F = integer("n_frames", n_frames, 1)
    m = np.asarray(masks)
    if m.ndim == 2:
        m = as_mask("masks", m, 2, nonempty=True)
        warnings.warn("masks: one (H, W) mask given; it is used as the reference and as every frame's myocardium. "
                      "Give (F, H, W) masks of each frame where the wall moves by more than a pixel", UserWarning,
                      stacklevel=2)
        return np.repeat(m[None], F + 1, axis=0)
    if m.ndim != 3 or m.shape[0] not in (F, F + 1):
        raise ValueError(f"masks: expected (H, W) the reference, (F, H, W) each frame's or (F + 1, H, W) the reference "
                         f"then each frame's myocardium, with F = {F} frames, got shape {m.shape}")
    m = as_mask("masks", m, 3)
    return m if m.shape[0] == F + 1 else np.concatenate([m[:1], m])


def _case_from_series(phase_series, names, magnitude, masks, ke_cycles_per_mm, directions, phase_range,
                      provenance: str) -> DenseCase:
    """A :class:`DenseCase` from two phase series and a magnitude series (each ``_stack_frames``'s answer)."""
    mag, times, ds0 = magnitude
    if phase_range is not None:
        lo, hi = (float(v) for v in phase_range)
        if not hi > lo:
            raise ValueError(f"phase_range: expected lo < hi, got {phase_range!r}")
    phases = []
    for name, (img, t, _) in zip(names, phase_series):
        if img.shape != mag.shape:
            raise ValueError(f"{name}: expected the magnitude's shape {mag.shape} (frames, rows, columns), "
                             f"got {img.shape}")
        both = np.isfinite(t) & np.isfinite(times)
        if both.any() and not np.allclose(t[both], times[both], atol=0.5):
            raise ValueError(f"{name}: expected the magnitude's TriggerTime of each frame (ms), got times "
                             f"differing by up to {float(np.max(np.abs(t[both] - times[both]))):.3g} ms")
        if phase_range is not None:
            if img.min() < lo - 1e-9 * abs(hi - lo) or img.max() > hi + 1e-9 * abs(hi - lo):
                raise ValueError(f"{name}: expected rescaled values within phase_range {lo:g} to {hi:g} (mapped to "
                                 f"-pi to pi), got values from {float(img.min()):.6g} to {float(img.max()):.6g}")
            img = -np.pi + 2 * np.pi * (img - lo) / (hi - lo)
        elif np.abs(img).max() > np.pi + PHASE_TOLERANCE:
            raise ValueError(f"{name}: expected phases in radians within +-pi, got values up to "
                             f"{float(np.abs(img).max()):.4g}; give phase_range, the rescaled values of -pi and pi, "
                             "e.g. (-4096, 4094)")
        phases.append(img)
    m = np.asarray(masks)
    if m.ndim == 3 and m.shape[1:] != mag.shape[1:]:
        raise ValueError(f"masks: expected masks of the images' size {mag.shape[1]} x {mag.shape[2]} (rows x columns), "
                         f"got {m.shape[1]} x {m.shape[2]}")
    if not hasattr(ds0, "PixelSpacing"):
        raise ValueError("magnitude: expected PixelSpacing (mm) in the DICOM files, not found")
    ps = [float(v) for v in ds0.PixelSpacing]
    if not np.isclose(ps[0], ps[1], rtol=1e-3):
        raise ValueError(f"PixelSpacing: expected square pixels, got {ps} mm")
    if not np.all(np.isfinite(times)):
        raise ValueError("magnitude: expected TriggerTime (ms) in every DICOM file, not found")
    return make_dense_case(phases=np.stack(phases), magnitude=mag, masks=masks, pixel_size_mm=ps[0],
                           ke_cycles_per_mm=ke_cycles_per_mm, frame_times_s=times * 1e-3, directions=directions,
                           provenance=provenance, resolution_px=dicom_resolution_px(ds0))


def dicom_resolution_px(ds) -> float:
    """Acquired resolution (reconstructed pixels) of a DICOM image: its Rows and Columns over its AcquisitionMatrix.

    ``AcquisitionMatrix`` (0018,1310) holds (frequency rows, frequency columns, phase rows, phase
    columns), two of them zero; the acquired samples along the image's rows and columns are the
    non-zero entries. The resolution is the larger of ``Columns / n_columns`` and ``Rows / n_rows``
    (a zero-filled reconstruction gives above 1), at least 1. Without the tag, or with an
    unusable one, :data:`DEFAULT_RESOLUTION_PX` (1: no blur beyond the pixel), with a warning.
    """
    am = getattr(ds, "AcquisitionMatrix", None)
    rows, cols = getattr(ds, "Rows", None), getattr(ds, "Columns", None)
    try:
        f_r, f_c, p_r, p_c = (int(v) for v in am)
        n_rows, n_cols = max(f_r, p_r), max(f_c, p_c)
        ratio = (float("nan") if n_rows <= 0 and n_cols <= 0 else       # no acquired size stated
                 max(float(rows) / n_rows if n_rows > 0 else 1.0, float(cols) / n_cols if n_cols > 0 else 1.0))
    except (TypeError, ValueError):
        ratio = float("nan")
    if not np.isfinite(ratio):
        warnings.warn(f"DICOM AcquisitionMatrix: expected four integers, the acquired rows and columns among them "
                      f"(and Rows, Columns), to give the acquired "
                      f"resolution, got {am!r}: taken as {DEFAULT_RESOLUTION_PX:g} pixel (no blur beyond the images' "
                      "own pixel); give it with --resolution-px (StrainRouteSettings.resolution_px) if you know it",
                      UserWarning, stacklevel=user_stacklevel())
        return DEFAULT_RESOLUTION_PX
    return max(DEFAULT_RESOLUTION_PX, ratio)


def read_dense_dicom(phase_dirs, magnitude_dir, masks, ke_cycles_per_mm, directions=((1.0, 0.0), (0.0, 1.0)),
                     phase_range=None) -> DenseCase:
    """Read DENSE phase and magnitude DICOM series (one slice, one file per frame, one directory per series).

    Frames are ordered by TriggerTime (ms; then InstanceNumber) and their times taken from it;
    the pixel size from PixelSpacing (mm). Stored values pass through the modality rescale
    (RescaleSlope, RescaleIntercept). The phase series' trigger times must match the
    magnitude's (within 0.5 ms).

    Parameters
    ----------
    phase_dirs : sequence of two directories
        The phase series of the two encodings.
    magnitude_dir : directory
        The magnitude series.
    masks : (F + 1, H, W) bool array
        Myocardium masks, index 0 the reference (DICOM carries none); :func:`dense_masks` makes
        them from a reference or per-frame masks.
    ke_cycles_per_mm : float
        Encoding frequency (cycles/mm).
    directions : (2, 2) array
        Row j: the unit vector (x = column, y = row) along which encoding j encodes.
    phase_range : (lo, hi), optional
        Rescaled values that map linearly to (-pi, pi); ``None``: the values are radians.
    """
    if ke_cycles_per_mm is None:
        raise ValueError("ke_cycles_per_mm: expected the DENSE encoding frequency in cycles/mm, got None")
    if len(phase_dirs) != 2:
        raise ValueError(f"phase_dirs: expected two phase series (one per encoding), got {len(phase_dirs)}")
    names = [f"phase_dirs[{j}]" for j in range(2)]
    series = [_read_dicom_frames(d, n) for d, n in zip(phase_dirs, names)]
    magnitude = _read_dicom_frames(magnitude_dir, "magnitude_dir")
    return _case_from_series(series, names, magnitude, masks, ke_cycles_per_mm, directions, phase_range,
                             f"DENSE DICOM {list(map(os.fspath, phase_dirs))}, {os.fspath(magnitude_dir)}")


def read_dense_dicom_folder(path, masks, ke_cycles_per_mm, directions=None, phase_range=None) -> DenseCase:
    """Read one DENSE slice from a folder of DICOM files as a scanner exports it.

    Layout: every DICOM image file under ``path`` (sub-folders included, other files skipped)
    is sorted into its series by ``ImageComments`` (:func:`dense_series_kind`, as Siemens DENSE
    exports write them and DENSEanalysis reads them): the phase series ``DENSE x-enc pha ...``
    (encoding 0) and ``DENSE y-enc pha ...`` (encoding 1), and the magnitude ``DENSE overall
    mag ...`` (else the mean of the ``x-enc`` and ``y-enc`` magnitudes); ``z`` series and other
    files are ignored. Files without a DENSE ``ImageComments``: the series are the sub-folders
    ``phase_x``, ``phase_y`` and ``magnitude`` (:data:`DICOM_SUBFOLDERS`). In each series one
    file per frame, ordered by ``TriggerTime`` (ms, the frame times) then ``InstanceNumber``;
    stored values through the modality rescale (RescaleSlope, RescaleIntercept); the pixel size
    from ``PixelSpacing`` (mm). A ``EncFreq`` in the phase files' comments that differs from
    ``ke_cycles_per_mm`` gives a warning (the argument is used).

    Parameters
    ----------
    path : str or path-like
        The folder.
    masks : (H, W), (F, H, W) or (F + 1, H, W) bool array
        Myocardium masks (DICOM carries none); see :func:`dense_masks`.
    ke_cycles_per_mm : float
        Encoding frequency (cycles/mm); required.
    directions : (2, 2) array, optional
        Row j the unit vector (x = column, y = row) of encoding j; default the identity.
    phase_range : (lo, hi), optional
        Rescaled phase values that map linearly to -pi and pi (12-bit Siemens phase with
        RescaleSlope 2 and RescaleIntercept -4096: ``(-4096, 4094)``); ``None``: the rescaled
        values are radians.
    """
    if ke_cycles_per_mm is None:
        raise ValueError("ke_cycles_per_mm: expected the DENSE encoding frequency in cycles/mm (DICOM has no standard "
                         "tag for it), got None")
    ke = positive("ke_cycles_per_mm", ke_cycles_per_mm, "cycles/mm")
    folder = os.fspath(path)
    if not os.path.isdir(folder):
        raise FileNotFoundError(f"path: expected a folder of DENSE DICOM files, got {folder!r} (not a directory)")
    groups, n_files = {}, 0
    for root, dirs, files in os.walk(folder):
        dirs.sort()
        for entry in sorted(files):
            r = _read_dicom_file(os.path.join(root, entry))
            if r is None:
                continue
            n_files += 1
            kind = dense_series_kind(getattr(r[0], "ImageComments", None))
            if kind is not None:
                groups.setdefault(kind, []).append(r)
    if groups:
        mags = [k for k in ("mag.overall", "mag.x", "mag.y") if k in groups]
        missing = [k for k in ("pha.x", "pha.y") if k not in groups] + ([] if mags else ["mag.overall"])
        if missing:
            raise ValueError(f"path: expected the DENSE series pha.x, pha.y and a magnitude (ImageComments 'DENSE "
                             f"x-enc pha ...', 'DENSE y-enc pha ...', 'DENSE overall mag ...'), found {sorted(groups)} "
                             f"in {folder!r}; missing {missing}")
        names = [f"path (DENSE {e}-enc pha series)" for e in "xy"]
        series = [_stack_frames(groups[k], n) for k, n in zip(("pha.x", "pha.y"), names)]
        if "mag.overall" in groups:
            magnitude = _stack_frames(groups["mag.overall"], "path (DENSE overall mag series)")
        else:
            stacks = [_stack_frames(groups[k], f"path (DENSE {k[-1]}-enc mag series)") for k in mags]
            if len({s[0].shape for s in stacks}) != 1:
                raise ValueError(f"path: expected the x-enc and y-enc magnitude series of one shape, got "
                                 f"{[s[0].shape for s in stacks]}")
            magnitude = (np.mean([s[0] for s in stacks], axis=0), stacks[0][1], stacks[0][2])
        freqs = {float(m.group(1)) for ds, _ in groups["pha.x"] + groups["pha.y"]
                 for m in [_ENC_FREQ.search(str(getattr(ds, "ImageComments", "")))] if m}
        odd = sorted(f for f in freqs if not np.isclose(f, ke, rtol=1e-3))
        if odd:
            warnings.warn(f"ke_cycles_per_mm: {ke:g} cycles/mm given, but the phase files' ImageComments say EncFreq "
                          f"{', '.join(f'{f:g}' for f in odd)}; the given value is used", UserWarning, stacklevel=2)
        provenance = f"DENSE DICOM folder {folder} (series by ImageComments)"
    else:
        subs = [os.path.join(folder, s) for s in DICOM_SUBFOLDERS]
        if not all(os.path.isdir(s) for s in subs):
            raise FileNotFoundError(
                f"path: expected DENSE DICOM files told apart by ImageComments ('DENSE x-enc pha ...', 'DENSE y-enc "
                f"pha ...', 'DENSE overall mag ...') or the sub-folders {', '.join(DICOM_SUBFOLDERS)} in {folder!r}; "
                f"found {n_files} DICOM image file(s) without a DENSE ImageComments and the sub-folders "
                f"{[s for s in DICOM_SUBFOLDERS if os.path.isdir(os.path.join(folder, s))]}")
        names = [f"path ({s})" for s in DICOM_SUBFOLDERS[:2]]
        series = [_read_dicom_frames(s, n) for s, n in zip(subs[:2], names)]
        magnitude = _read_dicom_frames(subs[2], "path (magnitude)")
        provenance = f"DENSE DICOM folder {folder} (sub-folders {', '.join(DICOM_SUBFOLDERS)})"
    return _case_from_series(series, names, magnitude, dense_masks(masks, magnitude[0].shape[0]), ke,
                             np.eye(2) if directions is None else directions, phase_range, provenance)
