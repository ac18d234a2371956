"""DENSE images in: readers, complex noise, and phase to Lagrangian displacement.

DENSE (displacement encoding with stimulated echoes) stores, for each encoding direction
``d_j`` (a unit vector in image axes, x = column, y = row), a phase ``phi_j = 2 pi ke d_j . u``
(rad), ``ke`` the encoding frequency (cycles per unit length) and ``u`` the displacement of the
tissue now at the pixel from its position at the encoding time (an Eulerian field). This module
reads DENSE-Sim case folders (Barbaroux et al., JCMR 2025) and DICOM phase and magnitude
series into a :class:`DenseCase`, adds complex Gaussian noise exactly as
``shared/specs/strain-ground-truth.md`` pins it (:func:`add_complex_noise`), and turns the
phase into Lagrangian displacements of every reference myocardial pixel
(:func:`phase_to_displacement`): spatial unwrapping inside each frame's mask, the 2 pi offset of
each connected piece carried from frame to frame, the Eulerian field extended two pixels beyond
the mask (local plane fits), the inversion ``x = X + u_t(x)`` by fixed-point iteration, and each datum's noise sd
(from the local magnitude SNR) and confidence (from the phase's local quality; section 2.6 of
Shi & Liu 2003, the confidence-weighted data of Eqs. 38-39).

Units: displacements and points in pixels (x = column, y = row); pixel size in m and mm; ``ke``
in cycles/m inside (cycles/mm where a file or argument says so); times in s.

>>> import numpy as np
>>> from sfem_filters.imaging.dense import make_dense_case, phase_to_displacement
>>> yy, xx = np.mgrid[0:24, 0:24]
>>> ring = (np.hypot(xx - 11.5, yy - 11.5) >= 4) & (np.hypot(xx - 11.5, yy - 11.5) <= 9)
>>> u = 0.5                                                    # a rigid shift of 0.5 px in x
>>> phi = np.stack([np.full((3, 24, 24), 2 * np.pi * 0.1 * 1.75 * u), np.zeros((3, 24, 24))])
>>> case = make_dense_case(phases=phi, magnitude=np.ones((3, 24, 24)), masks=np.stack([ring] * 4),
...                        pixel_size_mm=1.75, ke_cycles_per_mm=0.1, frame_times_s=[0.02, 0.04, 0.06])
>>> d = phase_to_displacement(case)
>>> d.displacement.shape, round(float(d.displacement[..., 0].mean()), 6), d.n_untracked
((3, 204, 2), 0.5, 0)
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import yaml
from scipy import ndimage
from skimage.restoration import unwrap_phase

from .._validate import as_float_array, as_mask, integer, positive

__all__ = ["DenseCase", "make_dense_case", "read_dense_sim", "read_dense_dicom", "add_complex_noise",
           "LagrangianDisplacement", "unwrap_frames", "carry_offsets", "eulerian_displacement", "extend_field",
           "invert_eulerian", "estimate_noise_sd", "phase_quality", "phase_to_displacement", "reference_points",
           "truth_at_points", "PHASE_TOLERANCE"]

PHASE_TOLERANCE = 1e-4
"""rad: how far beyond +-pi a stored phase may lie (float rounding of a wrapped phase)."""

_CHI2_1_MEDIAN = 0.45493642311957283     # median of a chi-square variable with one degree of freedom


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

    @property
    def n_frames(self) -> int:
        return self.phases.shape[1]

    @property
    def shape(self) -> tuple:
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
        return self.truth_ecc is not None and self.truth_err is not None


def make_dense_case(phases, magnitude, masks, pixel_size_mm, ke_cycles_per_mm, frame_times_s, directions=None,
                    truth_ecc=None, truth_err=None, provenance: str = "") -> DenseCase:
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
    """
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
                     provenance=provenance)


def _load(folder: str, name: str, required: bool = True):
    p = os.path.join(folder, name)
    if not os.path.isfile(p):
        if required:
            raise FileNotFoundError(f"path: expected {name} in the DENSE-Sim case folder {folder!r}, not found")
        return None
    return np.load(p, allow_pickle=False)


def read_dense_sim(path) -> DenseCase:
    """Read a DENSE-Sim case folder exactly as the simulator publishes it.

    Files: ``phase_x.npy``, ``phase_y.npy`` (F, H, W) wrapped phase (rad) of the x (column) and
    y (row) encodings; ``magnitude.npy``; ``LV_mask_time_lowres.npy`` (F + 1, H, W), index 0 the
    reference; optional ``GT_Ecc.npy``, ``GT_Err.npy``; ``config.yaml`` (``sim_params``: ``FOV``
    in mm, first two entries; ``N_im``; ``ke`` in cycles/mm; ``tt`` in ms, frame f at
    ``tt[f + 1]``). Pixel size = FOV / N_im.

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
    fov = np.asarray(sim["FOV"], float)[:2]
    n_im = integer("config.yaml N_im", sim["N_im"], 1)
    if not np.isclose(fov[0], fov[1]):
        raise ValueError(f"config.yaml FOV: expected a square field of view (mm), got {fov.tolist()}")
    px_mm = positive("config.yaml FOV", fov[0], "mm") / n_im
    if sim["ke"] is None:
        raise ValueError("config.yaml ke: expected the encoding frequency in cycles/mm, got None")
    px, py = _load(folder, "phase_x.npy"), _load(folder, "phase_y.npy")
    if px.shape != py.shape:
        raise ValueError(f"phase_y.npy: expected the shape of phase_x.npy {px.shape}, got {py.shape}")
    F = px.shape[0]
    tt = np.asarray(sim["tt"], float)
    if tt.size < F + 1:
        raise ValueError(f"config.yaml tt: expected at least F + 1 = {F + 1} times (ms), got {tt.size}")
    return make_dense_case(phases=np.stack([px, py]), magnitude=_load(folder, "magnitude.npy"),
                           masks=_load(folder, "LV_mask_time_lowres.npy"), pixel_size_mm=px_mm,
                           ke_cycles_per_mm=sim["ke"], frame_times_s=tt[1:F + 1] * 1e-3,
                           truth_ecc=_load(folder, "GT_Ecc.npy", False), truth_err=_load(folder, "GT_Err.npy", False),
                           provenance=f"DENSE-Sim case {folder}")


def _read_dicom_frames(directory: str, name: str):
    import pydicom                                          # the optional [dicom] extra
    from pydicom.pixels import apply_modality_lut
    directory = os.fspath(directory)
    if not os.path.isdir(directory):
        raise FileNotFoundError(f"{name}: expected a directory of DICOM files, got {directory!r}")
    frames = []
    for entry in sorted(os.listdir(directory)):
        p = os.path.join(directory, entry)
        if not os.path.isfile(p):
            continue
        try:
            ds = pydicom.dcmread(p)
            img = apply_modality_lut(ds.pixel_array, ds).astype(float)
        except Exception:                          # not a DICOM image (DICOMDIR, notes): skip
            continue
        frames.append((float(getattr(ds, "TriggerTime", np.nan)), int(getattr(ds, "InstanceNumber", 0)), ds, img))
    if not frames:
        raise FileNotFoundError(f"{name}: expected DICOM image files in {directory!r}, found none")
    frames.sort(key=lambda f: (np.nan_to_num(f[0], nan=np.inf), f[1]))
    shapes = {f[3].shape for f in frames}
    if len(shapes) != 1:
        raise ValueError(f"{name}: expected frames of one size, got sizes {sorted(shapes)}")
    return np.stack([f[3] for f in frames]), np.array([f[0] for f in frames]), frames[0][2]


def read_dense_dicom(phase_dirs, magnitude_dir, masks, ke_cycles_per_mm, directions=((1.0, 0.0), (0.0, 1.0)),
                     phase_range=None) -> DenseCase:
    """Read DENSE phase and magnitude DICOM series (one slice, one file per frame).

    Frames are ordered by TriggerTime (ms; then InstanceNumber) and their times taken from it;
    the pixel size from PixelSpacing (mm). Stored values pass through the modality rescale
    (RescaleSlope, RescaleIntercept).

    Parameters
    ----------
    phase_dirs : sequence of two directories
        The phase series of the two encodings.
    magnitude_dir : directory
        The magnitude series.
    masks : (F + 1, H, W) bool array
        Myocardium masks, index 0 the reference (DICOM carries none).
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
    series = [_read_dicom_frames(d, f"phase_dirs[{j}]") for j, d in enumerate(phase_dirs)]
    mag, times, ds0 = _read_dicom_frames(magnitude_dir, "magnitude_dir")
    phases = []
    for j, (img, _, _) in enumerate(series):
        if img.shape != mag.shape:
            raise ValueError(f"phase_dirs[{j}]: expected the magnitude's shape {mag.shape}, got {img.shape}")
        if phase_range is not None:
            lo, hi = (float(v) for v in phase_range)
            if not hi > lo:
                raise ValueError(f"phase_range: expected lo < hi, got {phase_range!r}")
            img = -np.pi + 2 * np.pi * (img - lo) / (hi - lo)
        elif np.abs(img).max() > np.pi + PHASE_TOLERANCE:
            raise ValueError(f"phase_dirs[{j}]: expected phases in radians within +-pi, got values up to "
                             f"{float(np.abs(img).max()):.4g}; give phase_range, e.g. (-4096, 4096)")
        phases.append(img)
    if not hasattr(ds0, "PixelSpacing"):
        raise ValueError("magnitude_dir: expected PixelSpacing (mm) in the DICOM files, not found")
    ps = [float(v) for v in ds0.PixelSpacing]
    if not np.isclose(ps[0], ps[1], rtol=1e-3):
        raise ValueError(f"PixelSpacing: expected square pixels, got {ps} mm")
    if not np.all(np.isfinite(times)):
        raise ValueError("magnitude_dir: expected TriggerTime (ms) in every DICOM file, not found")
    return make_dense_case(phases=np.stack(phases), magnitude=mag, masks=masks, pixel_size_mm=ps[0],
                           ke_cycles_per_mm=ke_cycles_per_mm, frame_times_s=times * 1e-3, directions=directions,
                           provenance=f"DENSE DICOM {list(map(os.fspath, phase_dirs))}, {os.fspath(magnitude_dir)}")


# ------------------------------------------------------------------------------------------- noise
def add_complex_noise(case: DenseCase, snr: float, seed: int) -> DenseCase:
    """The case with complex Gaussian noise on each encoding, as the strain spec pins it.

    ``sd = mean(mag[M]) / snr`` with ``M`` the frames' masks (``masks[1:]``); with
    ``rng = numpy.random.default_rng(seed)``, for each encoding in order (x, then y):
    ``z = mag exp(i phase) + sd (rng.standard_normal(shape) + 1j rng.standard_normal(shape))``,
    noisy phase ``angle(z)`` as float32. Magnitude, masks and everything else unchanged.

    Parameters
    ----------
    snr : float
        Mean myocardial magnitude over the noise sd of each real component (> 0).
    seed : int
        Seed of numpy's default generator.
    """
    positive("snr", snr)
    integer("seed", seed, 0)
    mag = case.magnitude
    sd = float(np.mean(mag[case.frame_masks])) / snr
    rng = np.random.default_rng(seed)
    noisy = []
    for phase in case.phases:
        z = mag * np.exp(1j * phase) + sd * (rng.standard_normal(phase.shape) + 1j * rng.standard_normal(phase.shape))
        noisy.append(np.angle(z).astype(np.float32))
    return DenseCase(phases=np.stack(noisy).astype(float), magnitude=case.magnitude, masks=case.masks,
                     pixel_size_m=case.pixel_size_m, ke_per_m=case.ke_per_m, frame_times_s=case.frame_times_s,
                     directions=case.directions, truth_ecc=case.truth_ecc, truth_err=case.truth_err,
                     provenance=f"{case.provenance} + complex noise SNR {snr:g} seed {seed}")


# ------------------------------------------------------------------------------- phase unwrapping
def unwrap_frames(phase, masks) -> np.ndarray:
    """Unwrap each frame's phase inside its mask, the 2 pi offset of each piece carried in time.

    Spatial unwrapping: :func:`skimage.restoration.unwrap_phase` (Herraez et al. 2002) on the
    frame's phase masked outside its myocardium (seeded, so deterministic). Temporal offset:
    each 4-connected piece of the frame's mask gets the multiple ``k`` of 2 pi that brings its
    mean closest to the previous frame's unwrapped values at the same pixels (``k = round(mean(
    prev - cur) / 2 pi)`` over the pixels in both masks); frame 0, and a piece that overlaps
    nothing of the previous frame, are referred to zero displacement (the reference t = 0).

    Parameters
    ----------
    phase : (F, H, W) array
        Wrapped phase (rad) of one encoding.
    masks : (F, H, W) bool array
        The frames' myocardium masks.

    Returns
    -------
    (F, H, W) array
        Unwrapped phase (rad), NaN outside each frame's mask.
    """
    phase = np.asarray(phase, float)
    masks = np.asarray(masks, bool)
    out = np.full(phase.shape, np.nan)
    prev = None
    for f in range(phase.shape[0]):
        m = masks[f]
        cur = np.asarray(unwrap_phase(np.ma.array(phase[f], mask=~m), rng=0).filled(np.nan))
        out[f] = carry_offsets(cur, m, prev)
        prev = out[f]
    return out


def carry_offsets(unwrapped, mask, previous=None) -> np.ndarray:
    """Shift each 4-connected piece of a spatially unwrapped frame by the 2 pi multiple that fits in time.

    ``k = round(mean(previous - unwrapped) / 2 pi)`` over the piece's pixels where ``previous``
    is finite; against zero (``k = round(-mean(unwrapped) / 2 pi)``) where there is no previous
    frame or no overlap. So the answer does not depend on the arbitrary offset the spatial
    unwrapper gives each piece.

    Parameters
    ----------
    unwrapped : (H, W) array
        Phase (rad) unwrapped within each piece of ``mask``.
    mask : (H, W) bool array
    previous : (H, W) array, optional
        The previous frame's answer (rad), NaN outside its mask.

    Returns
    -------
    (H, W) array
        The shifted phase (rad), NaN outside ``mask``.
    """
    m = np.asarray(mask, bool)
    cur = np.array(unwrapped, float)
    labels, n = ndimage.label(m)
    for piece in range(1, n + 1):
        sel = labels == piece
        ref = None if previous is None else previous[sel]
        if ref is not None and np.isfinite(ref).any():
            delta = np.nanmean(ref - cur[sel])
        else:
            delta = -np.mean(cur[sel])
        cur[sel] += 2 * np.pi * np.round(delta / (2 * np.pi))
    cur[~m] = np.nan
    return cur


def eulerian_displacement(case: DenseCase) -> np.ndarray:
    """The Eulerian displacement field of each frame inside its mask (pixels).

    ``phi_j = 2 pi ke d_j . u`` for both encodings, so ``u = D^-1 phi / (2 pi ke)`` (m) divided
    by the pixel size (m), with the phases unwrapped by :func:`unwrap_frames`.

    Returns
    -------
    (F, H, W, 2) array
        ``(u_x, u_y)`` in pixels (x = column, y = row), NaN outside each frame's mask.
    """
    unwrapped = np.stack([unwrap_frames(p, case.frame_masks) for p in case.phases], axis=-1)
    u_m = unwrapped @ np.linalg.inv(case.directions).T / (2 * np.pi * case.ke_per_m)
    return u_m / case.pixel_size_m


def extend_field(field, valid, rings: int = 2) -> np.ndarray:
    """Extend a field defined on ``valid`` pixels by ``rings`` rings of pixels around it.

    Each new pixel ``p`` takes the value at ``p`` of the least-squares plane ``a + b dx + c dy``
    through the known pixels in the square window of half-width ``rings + 1`` around it (exact
    for an affine field; averaging over the window keeps noise and partial-volume values at the
    border from being amplified, as a two-point extrapolation would); where the window holds
    fewer than three non-collinear known pixels, the mean of the known ones. So a tracked point
    up to ``rings`` pixels outside the frame's mask can still be interpolated bilinearly.

    Parameters
    ----------
    field : (H, W, C) array
        Values (any unit); entries outside ``valid`` are ignored.
    valid : (H, W) bool array
        Where ``field`` is known.
    rings : int
        How many rings of pixels (8-connected) to add (>= 0).

    Returns
    -------
    (H, W, C) array
        The field on ``valid`` and its rings, NaN elsewhere.
    """
    integer("rings", rings, 0)
    valid = np.asarray(valid, bool)
    u = np.where(valid[..., None], np.asarray(field, float), np.nan)
    valid = valid & np.isfinite(u).all(axis=-1)
    if rings == 0 or not valid.any():
        return u
    h = rings + 1
    rows, cols = np.nonzero(valid)
    box = (slice(max(rows.min() - 2 * h, 0), rows.max() + 2 * h + 1),
           slice(max(cols.min() - 2 * h, 0), cols.max() + 2 * h + 1))
    u[box] = _extend_box(u[box], valid[box], rings, h)
    return u


def _extend_box(u, valid, rings, h):
    ring = ndimage.binary_dilation(valid, structure=np.ones((3, 3), bool), iterations=rings) & ~valid
    dy, dx = np.mgrid[-h:h + 1, -h:h + 1].astype(float)
    w = valid.astype(float)
    basis = [np.ones_like(dx), dx, dy]

    def corr(img, k):                    # sum over the window of img(p + d) k(d)
        return ndimage.correlate(img, k, mode="constant", cval=0.0)

    A = np.empty(valid.shape + (3, 3))
    for i in range(3):
        for j in range(3):
            A[..., i, j] = corr(w, basis[i] * basis[j])
    n = A[..., 0, 0]
    det = np.linalg.det(A)
    planar = ring & (n >= 3) & (np.abs(det) > 1e-6 * np.maximum(n, 1) ** 3)
    uz = np.where(valid[..., None], u, 0.0)
    for ch in range(u.shape[-1]):
        rhs = np.stack([corr(uz[..., ch], k) for k in basis], axis=-1)
        val = np.full(valid.shape, np.nan)
        if planar.any():
            val[planar] = np.linalg.solve(A[planar], rhs[planar][..., None])[:, 0, 0]
        mean_only = ring & ~planar & (n > 0)
        val[mean_only] = rhs[mean_only][:, 0] / n[mean_only]
        u[ring, ch] = val[ring]
    return u


def _bilinear(image, x, y) -> np.ndarray:
    """Bilinear interpolation of an (H, W) image at (x, y) pixels; NaN if any corner is NaN or outside."""
    return ndimage.map_coordinates(image, [y, x], order=1, mode="constant", cval=np.nan)


def invert_eulerian(field, points, start=None, max_iter: int = 100, tol: float = 1e-6) -> np.ndarray:
    """Lagrangian displacement of reference points from an Eulerian field: solve ``x = X + u(x)``.

    Fixed-point iteration ``x <- x + a (X + u(x) - x)`` with ``u`` interpolated bilinearly:
    first with ``a = 1`` (the plain iteration, which converges where the Eulerian gradient's
    spectral radius is below 1), then, for the points that did not converge (noisy gradients
    near 1 make the plain iteration oscillate), with ``a = 1/2`` and ``1/4``.

    Parameters
    ----------
    field : (H, W, 2) array
        Eulerian displacement (pixels), NaN where unknown.
    points : (P, 2) array
        Reference positions X (pixels, x = column, y = row).
    start : (P, 2) array, optional
        Initial displacements (pixels); default ``u(X)`` (zero where NaN).
    max_iter : int
        Most iterations per damping factor.
    tol : float
        Convergence: largest step (pixels).

    Returns
    -------
    (P, 2) array
        ``u = x - X`` (pixels); NaN where the iteration left the known field or did not
        converge (residual ``|x - X - u(x)|`` above ``max(10 tol, 1e-3)`` pixels).
    """
    X = np.asarray(points, float)
    ux, uy = field[..., 0], field[..., 1]

    def u_at(p):
        return np.stack([_bilinear(ux, p[:, 0], p[:, 1]), _bilinear(uy, p[:, 0], p[:, 1])], axis=1)

    if start is None:
        d0 = np.nan_to_num(u_at(X))
    else:
        d0 = np.where(np.isfinite(start), start, 0.0)
    out = np.full(X.shape, np.nan)
    todo = np.arange(len(X))
    for alpha in (1.0, 0.5, 0.25):
        Xt = X[todo]
        x = Xt + d0[todo]
        for _ in range(max_iter):
            target = Xt + u_at(x)
            step = alpha * (target - x)
            x = np.where(np.isfinite(step), x + step, x)        # a point that left the field stays put
            if np.max(np.where(np.isfinite(step), np.abs(step), 0.0), initial=0.0) < tol:
                break
        res = np.abs(x - Xt - u_at(x)).max(axis=1)
        ok = np.isfinite(res) & (res < max(10 * tol, 1e-3))
        out[todo[ok]] = (x - Xt)[ok]
        todo = todo[~ok]
        if todo.size == 0:
            break
    return out


# ---------------------------------------------------------------------------- noise and quality
def _wrap(a):
    """Wrap angles (rad) into [-pi, pi)."""
    return np.mod(np.asarray(a) + np.pi, 2 * np.pi) - np.pi


def estimate_noise_sd(phase, magnitude, masks) -> float:
    """Noise sd of the complex image's real components (magnitude units), from one encoding's phase.

    A complex Gaussian noise of sd ``sigma`` per component gives a phase sd ``sigma / m`` at a
    pixel of magnitude ``m`` (high SNR). The wrapped second difference ``r`` of the phase along
    rows and columns, where all three pixels lie in the frame's mask, cancels the smooth
    (linear) part of the phase and has variance ``sigma^2 (1/m_-^2 + 4/m_0^2 + 1/m_+^2)``; the
    estimate is the median of ``r^2 / (1/m_-^2 + 4/m_0^2 + 1/m_+^2)`` over the chi-square(1)
    median (robust to unwrapping edges). It includes any phase texture of the image formation.

    Parameters
    ----------
    phase : (F, H, W) array
        Wrapped phase (rad).
    magnitude : (F, H, W) array
        Magnitude (> 0 inside the masks).
    masks : (F, H, W) bool array
        The frames' masks.
    """
    k = np.asarray(masks, bool)
    rows, cols = np.nonzero(k.any(axis=0))
    if rows.size == 0:
        raise ValueError("masks: expected myocardium to estimate the noise in, got empty masks")
    box = (slice(None), slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    ph, m, k = np.asarray(phase, float)[box], np.asarray(magnitude, float)[box], k[box]
    vals = []
    for axis in (1, 2):
        sl = [slice(None)] * 3
        def s(a, b):
            sl_ = list(sl)
            sl_[axis] = slice(a, ph.shape[axis] + b if b <= 0 else b)
            return tuple(sl_)
        lo, mid, hi = s(0, -2), s(1, -1), s(2, 0)
        ok = k[lo] & k[mid] & k[hi] & (m[lo] > 0) & (m[mid] > 0) & (m[hi] > 0)
        r = _wrap(ph[hi] - ph[mid]) - _wrap(ph[mid] - ph[lo])
        with np.errstate(divide="ignore"):
            w = 1 / m[lo] ** 2 + 4 / m[mid] ** 2 + 1 / m[hi] ** 2
        vals.append((_wrap(r) ** 2 / w)[ok])
    v = np.concatenate(vals)
    if v.size == 0:
        raise ValueError("masks: expected some run of three pixels in a frame's mask to estimate the noise, got none")
    return float(np.sqrt(np.median(v) / _CHI2_1_MEDIAN))


def phase_quality(phase, masks) -> np.ndarray:
    """Confidence in [0, 1] of each pixel's phase, from the spread of its second differences.

    For each pixel ``p`` and each of the four axes through it (row, column, both diagonals)
    whose two neighbours lie in the mask, the detrended phase step ``r = wrap(wrap(phi(p+n) -
    phi(p)) - wrap(phi(p) - phi(p-n)))``; with ``s^2 = mean(r^2) / 6`` (the second difference of
    a phase with noise sd ``s`` has variance ``6 s^2``) the confidence is ``exp(-s^2 / 2)``: the
    mean resultant length that Eq. 39's local phase coherence takes for Gaussian phase noise of
    sd ``s``. Why not the paper's LPC itself (Eqs. 38-39, first differences): it drops with the
    phase gradient, which in DENSE is the strain (about 0.5 rad per pixel at 40% strain with
    ke = 0.1 cycles/mm and 1.75 mm pixels), and would mark the most deforming tissue as the
    least reliable; the second difference cancels a linear phase. And the variance form has no
    small-sample bias (a resultant length over one to four axes is 1 for a single axis, whatever
    the noise). A pixel with no such axis uses its first differences to in-mask neighbours
    (``s^2 = mean(d^2) / 2``); one with no in-mask neighbour, and every pixel outside the mask,
    gets 0.

    Parameters
    ----------
    phase : (F, H, W) array
        Wrapped phase (rad).
    masks : (F, H, W) bool array

    Returns
    -------
    (F, H, W) array
    """
    ph_full = np.asarray(phase, float)
    k_full = np.asarray(masks, bool)
    out = np.zeros(ph_full.shape)
    rows, cols = np.nonzero(k_full.any(axis=0))
    if rows.size == 0:
        return out
    box = (slice(None), slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    ph, k = ph_full[box], k_full[box]
    F, H, W = ph.shape
    pad = np.pad(ph, ((0, 0), (1, 1), (1, 1)))
    kp = np.pad(k, ((0, 0), (1, 1), (1, 1)))
    acc, n = np.zeros(ph.shape), np.zeros(ph.shape)
    nb_acc, nb_n = np.zeros(ph.shape), np.zeros(ph.shape)
    for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
        ap, am = pad[:, 1 + dr:1 + dr + H, 1 + dc:1 + dc + W], pad[:, 1 - dr:1 - dr + H, 1 - dc:1 - dc + W]
        kp_, km_ = kp[:, 1 + dr:1 + dr + H, 1 + dc:1 + dc + W], kp[:, 1 - dr:1 - dr + H, 1 - dc:1 - dc + W]
        both = k & kp_ & km_
        r = _wrap(_wrap(ap - ph) - _wrap(ph - am))
        acc += np.where(both, r ** 2, 0.0)
        n += both
        for a, ka in ((ap, kp_), (am, km_)):
            nb_acc += np.where(k & ka, _wrap(a - ph) ** 2, 0.0)
            nb_n += k & ka
    with np.errstate(invalid="ignore", divide="ignore"):
        s2 = np.where(n > 0, acc / (6 * np.maximum(n, 1)), nb_acc / (2 * np.maximum(nb_n, 1)))
    c = np.where(k & ((n > 0) | (nb_n > 0)), np.exp(-s2 / 2), 0.0)
    out[box] = c
    return out


# ------------------------------------------------------------------------------------- the result
@dataclass(frozen=True, eq=False)
class LagrangianDisplacement:
    """Lagrangian displacement of the reference myocardial pixels through the cycle.

    Attributes
    ----------
    points : (P, 2) array
        Reference pixel centres (pixels, x = column, y = row).
    displacement : (F, P, 2) array
        ``x - X`` at each frame (pixels); NaN where a point could not be tracked.
    sd : (F, P, 2) array
        Noise sd of each component (pixels), from the local magnitude SNR.
    confidence : (F, P) array
        Phase quality in [0, 1] at the tracked position (:func:`phase_quality`, the smaller
        of the two encodings); NaN where untracked.
    frame_times_s : (F,) array
    n_untracked : int
        Number of (frame, point) pairs with NaN displacement.
    noise_sd : (2,) array
        Estimated (or given) complex noise sd of each encoding (magnitude units).
    """

    points: np.ndarray
    displacement: np.ndarray
    sd: np.ndarray
    confidence: np.ndarray
    frame_times_s: np.ndarray
    n_untracked: int
    noise_sd: np.ndarray


def reference_points(mask) -> np.ndarray:
    """(P, 2) pixel centres (x = column, y = row) of a mask's pixels, in row-major order."""
    rows, cols = np.nonzero(np.asarray(mask, bool))
    return np.column_stack([cols, rows]).astype(float)


def truth_at_points(case: DenseCase) -> tuple:
    """Ground-truth (Ecc, Err), each (F, P), at the reference pixels (fraction)."""
    if not case.has_truth:
        raise ValueError("case: expected ground-truth strain (GT_Ecc.npy, GT_Err.npy), the case has none")
    rows, cols = np.nonzero(case.reference_mask)
    return case.truth_ecc[:, rows, cols], case.truth_err[:, rows, cols]


def phase_to_displacement(case: DenseCase, noise_sd=None, rings: int = 2) -> LagrangianDisplacement:
    """Lagrangian displacement of every reference myocardial pixel, with its sd and confidence.

    Steps: :func:`eulerian_displacement` (unwrap inside each frame's mask, carry the 2 pi
    offset, ``u = phi / (2 pi ke)`` over the pixel size); :func:`extend_field` by ``rings``
    pixels; :func:`invert_eulerian` from the previous frame's answer. The confidence of a datum
    is :func:`phase_quality` (the smaller over the encodings) at the pixel nearest its tracked
    position, or, where that pixel lies outside the frame's mask (an extrapolated datum), at the
    nearest mask pixel scaled by ``1 - d / (rings + 1)``, ``d`` the distance (pixels) to the
    mask. The sd of each datum:
    phase sd ``noise_sd / m(x)`` per encoding (``m`` the magnitude interpolated at the tracked
    position, capped at ``pi / sqrt 3``, the sd of a uniform phase), mapped through ``D^-1 /
    (2 pi ke)`` and the pixel size. ``noise_sd`` defaults to :func:`estimate_noise_sd` of each
    encoding.

    Parameters
    ----------
    case : DenseCase
    noise_sd : float or (2,) array, optional
        Complex noise sd per real component of each encoding (magnitude units).
    rings : int
        Pixels of extension beyond each frame's mask.
    """
    u_eul = eulerian_displacement(case)
    masks = case.frame_masks
    X = reference_points(case.reference_mask)
    F, P = case.n_frames, len(X)
    if noise_sd is None:
        noise = np.array([estimate_noise_sd(p, case.magnitude, masks) for p in case.phases])
    else:
        noise = np.broadcast_to(as_float_array("noise_sd", noise_sd), (2,)).astype(float)
        if np.any(noise <= 0):
            raise ValueError(f"noise_sd: expected positive noise sd (magnitude units), got {noise.tolist()}")
    quality = np.minimum(*(phase_quality(p, masks) for p in case.phases))
    dinv = np.linalg.inv(case.directions)
    to_px = 1.0 / (2 * np.pi * case.ke_per_m * case.pixel_size_m)
    disp = np.full((F, P, 2), np.nan)
    sd = np.full((F, P, 2), np.nan)
    conf = np.full((F, P), np.nan)
    prev = None
    for f in range(F):
        field = extend_field(u_eul[f], masks[f], rings)
        d = invert_eulerian(field, X, start=prev)
        disp[f] = d
        ok = np.isfinite(d).all(axis=1)
        x = X + np.nan_to_num(d)
        mag = np.maximum(_bilinear(case.magnitude[f], x[:, 0], x[:, 1]), 0.0)
        with np.errstate(divide="ignore"):
            sphi = np.minimum(noise[None, :] / mag[:, None], np.pi / np.sqrt(3))      # (P, 2) rad
        sd[f] = np.sqrt((sphi[:, None, :] ** 2 * dinv[None] ** 2).sum(axis=2)) * to_px
        r = np.clip(np.round(x[:, 1]).astype(int), 0, case.shape[0] - 1)
        c = np.clip(np.round(x[:, 0]).astype(int), 0, case.shape[1] - 1)
        dist, (nr, nc) = ndimage.distance_transform_edt(~masks[f], return_indices=True)
        conf[f] = quality[f, nr[r, c], nc[r, c]] * np.clip(1 - dist[r, c] / (rings + 1), 0.0, 1.0)
        sd[f][~ok] = np.nan
        conf[f][~ok] = np.nan
        prev = np.where(np.isfinite(d), d, prev if prev is not None else 0.0)
    n_bad = int((~np.isfinite(disp).all(axis=2)).sum())
    return LagrangianDisplacement(points=X, displacement=disp, sd=sd, confidence=conf,
                                  frame_times_s=case.frame_times_s.copy(), n_untracked=n_bad, noise_sd=noise)
