"""DENSE images in: complex noise and phase to Lagrangian displacement (readers re-exported).

DENSE (displacement encoding with stimulated echoes) stores, for each encoding direction
``d_j`` (a unit vector in image axes, x = column, y = row), a phase ``phi_j = 2 pi ke d_j . u``
(rad), ``ke`` the encoding frequency (cycles per unit length) and ``u`` the displacement of the
tissue now at the pixel from its position at the encoding time (an Eulerian field). The readers
of DENSE-Sim case folders (Barbaroux et al., JCMR 2025) and DICOM phase and magnitude series into a
:class:`DenseCase` are in :mod:`sfem_filters.imaging.dense_io` (re-exported here). This module adds
complex Gaussian noise exactly as
``shared/specs/strain-ground-truth.md`` pins it (:func:`add_complex_noise`), and turns the
phase into Lagrangian displacements of every reference myocardial pixel
(:func:`phase_to_displacement`): spatial unwrapping inside each frame's mask, the 2 pi offset of
each connected piece carried from frame to frame, the Eulerian field extended two pixels beyond
the mask (local plane fits), the inversion ``x = X + u_t(x)`` by fixed-point iteration, and each datum's noise sd
(from the local magnitude SNR) and confidence (from the phase's local quality; section 2.6 of
Shi & Liu 2003, the confidence-weighted data of Eqs. 38-39). For the DENSE route's
resolution-aware observation operator it gives the acquisition's point spread
(:func:`psf_sigma_px`, :func:`psf_samples`, from :attr:`DenseCase.resolution_px`), the complex
signal around the myocardium that a border pixel mixes in (:func:`background_signal`), and a
cross-check of the acquired resolution from the magnitude's edge spread
(:func:`edge_spread_resolution`).

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

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize, special
from skimage.restoration import unwrap_phase

from .._validate import as_float_array, as_mask, integer, positive
from .dense_io import (DEFAULT_RESOLUTION_PX, DICOM_SUBFOLDERS, PHASE_TOLERANCE, DenseCase, check_resolution_px,
                       dense_masks, dense_series_kind, dicom_resolution_px, make_dense_case, read_dense_dicom,
                       read_dense_dicom_folder, read_dense_sim)

__all__ = ["DenseCase", "make_dense_case", "read_dense_sim", "read_dense_dicom", "read_dense_dicom_folder",
           "dense_masks", "dense_series_kind", "DICOM_SUBFOLDERS", "add_complex_noise",
           "LagrangianDisplacement", "unwrap_frames", "carry_offsets", "eulerian_displacement", "extend_field",
           "invert_eulerian", "interpolation_variance_factor", "estimate_noise_sd", "phase_quality",
           "phase_to_displacement", "reference_points",
           "tracks_on_pixel_grid", "truth_at_points", "PHASE_TOLERANCE", "DEFAULT_RESOLUTION_PX", "check_resolution_px",
           "dicom_resolution_px", "FWHM_PER_SD", "PSF_SAMPLES_PER_PX", "PSF_RADIUS_SD", "psf_sigma_px", "psf_samples",
           "BackgroundSignal", "background_signal", "BACKGROUND_COHERENCE_SE", "edge_spread_resolution"]

_CHI2_1_MEDIAN = 0.45493642311957283     # median of a chi-square variable with one degree of freedom


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
                     provenance=f"{case.provenance} + complex noise SNR {snr:g} seed {seed}",
                     resolution_px=case.resolution_px)


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


def interpolation_variance_factor(points) -> np.ndarray:
    """``sum w^2`` of the bilinear weights ``w`` at each point: the variance of an interpolated value over a pixel's.

    At ``(x, y)`` with fractional parts ``(a, b)`` the weights are the products of ``(1 - a, a)``
    and ``(1 - b, b)``, so ``sum w^2 = ((1 - a)^2 + a^2) ((1 - b)^2 + b^2)``: 1 at a pixel centre,
    1/4 midway between four, 4/9 on average over uniform positions (independent pixel noise).

    Parameters
    ----------
    points : (P, 2) array
        Positions (pixels, x = column, y = row); NaN gives NaN.

    Returns
    -------
    (P,) array in [1/4, 1]

    >>> interpolation_variance_factor([[3.0, 4.0], [3.5, 4.5], [3.5, 4.0]]).tolist()
    [1.0, 0.25, 0.5]
    """
    p = as_float_array("points", points, shape=(None, 2), allow_nan=True)
    a = p - np.floor(p)
    g = (1.0 - a) ** 2 + a ** 2
    return g[:, 0] * g[:, 1]


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
        Noise sd of each component (pixels) of the datum on its own: the phase noise of the pixels
        behind it (``pixel_sd``) through the bilinear interpolation at its tracked position, whose
        weights ``w`` (up to four pixels) reduce the variance by ``sum w^2`` (1 at a pixel centre, 1/4
        midway between four).
    confidence : (F, P) array
        Phase quality in [0, 1] at the tracked position (:func:`phase_quality`, the smaller
        of the two encodings); NaN where untracked.
    frame_times_s : (F,) array
    n_untracked : int
        Number of (frame, point) pairs with NaN displacement.
    noise_sd : (2,) array
        Estimated (or given) complex noise sd of each encoding (magnitude units).
    pixel_sd : (F, P, 2) array, optional
        Noise sd of each component (pixels) of the pixels behind the datum, from the local
        magnitude SNR; the weight of the data in a fit of a field that is smooth over a pixel
        (the DENSE route's nodal fit, the spline). Neighbouring tracks interpolate shared pixels,
        so their errors correlate: the interpolation smooths the noise at the pixel scale but
        keeps all of it at larger scales (the weights sum to 1), so a mean over many tracks has
        the error of independent data at ``pixel_sd``, not at ``sd``. Default (None): ``sd``, for
        data that share no pixels.
    """

    points: np.ndarray
    displacement: np.ndarray
    sd: np.ndarray
    confidence: np.ndarray
    frame_times_s: np.ndarray
    n_untracked: int
    noise_sd: np.ndarray
    pixel_sd: np.ndarray | None = None

    def __post_init__(self):
        if self.pixel_sd is None:
            object.__setattr__(self, "pixel_sd", self.sd)
        elif np.shape(self.pixel_sd) != np.shape(self.sd):
            raise ValueError(f"pixel_sd: expected the shape of sd {np.shape(self.sd)}, got {np.shape(self.pixel_sd)}")


def reference_points(mask) -> np.ndarray:
    """(P, 2) pixel centres (x = column, y = row) of a mask's pixels, in row-major order."""
    rows, cols = np.nonzero(np.asarray(mask, bool))
    return np.column_stack([cols, rows]).astype(float)


def tracks_on_pixel_grid(points, displacement, frame_times_s, sd, confidence=None,
                         reference_mask=None) -> tuple:
    """Tracks of points on the pixel grid as the DENSE route takes them, with their reference mask.

    The DENSE route (:func:`sfem_filters.cardiac.dense_strain`) and the conventional analysis
    (finite differences on the reference pixel grid) take the reference myocardium's pixels, in
    row-major order, as the tracked points. So the points must be pixel centres (whole numbers,
    within 1e-6 px), distinct and >= 0; they are put in row-major order (the data with them).
    The mask is ``reference_mask`` when given (its tissue pixels must be exactly the points),
    else the points' pixels in an image with two background pixels beyond the largest point in
    each axis.

    Parameters
    ----------
    points : (P, 2) array
        Reference positions (pixels, x = column, y = row).
    displacement : (F, P, 2) array
        Lagrangian displacement (pixels); NaN where a point was not tracked.
    frame_times_s : (F,) array
        Frame times (s), increasing.
    sd : float, (P,), (F, P) or (F, P, 2) array
        Noise sd of each displacement component (pixels, > 0); the shapes without the last
        axis give both components the same sd.
    confidence : float, (P,) or (F, P) array, optional
        Confidence in [0, 1] of each datum; default 1.
    reference_mask : (H, W) bool array, optional

    Returns
    -------
    (LagrangianDisplacement, (H, W) bool array)
        The tracks (``noise_sd`` NaN: no image noise behind them) and the reference mask.

    >>> import numpy as np
    >>> pts = np.array([[2.0, 1.0], [0.0, 0.0], [1.0, 1.0]])          # (x, y), not in row-major order
    >>> t, mask = tracks_on_pixel_grid(pts, np.zeros((3, 3, 2)), [0.0, 0.1, 0.2], sd=0.1)
    >>> t.points.tolist(), mask.astype(int).tolist()[:3]
    ([[0.0, 0.0], [1.0, 1.0], [2.0, 1.0]], [[1, 0, 0, 0, 0], [0, 1, 1, 0, 0], [0, 0, 0, 0, 0]])
    """
    X = as_float_array("points", points, shape=(None, 2))
    P = len(X)
    if P == 0:
        raise ValueError("points: expected at least one point, got none")
    d = as_float_array("displacement", displacement, shape=(None, P, 2), allow_nan=True)
    F = d.shape[0]
    times = as_float_array("frame_times_s", frame_times_s, shape=(F,))
    if F > 1 and np.any(np.diff(times) <= 0):
        raise ValueError(f"frame_times_s: expected increasing frame times (s), got {times.tolist()}")
    off = float(np.max(np.abs(X - np.round(X))))
    if off > 1e-6:
        raise ValueError(f"points: expected pixel centres (whole numbers of pixels, x = column, y = row), as the DENSE "
                         f"route and the finite differences need, got points up to {off:.3g} px off the pixel grid")
    ij = np.round(X).astype(int)
    if ij.min() < 0:
        raise ValueError(f"points: expected pixel positions >= 0, got {int(ij.min())}")
    order = np.lexsort((ij[:, 0], ij[:, 1]))                       # row-major: by row (y), then column (x)
    ij, d = ij[order], d[:, order]
    dup = np.flatnonzero(np.all(np.diff(ij, axis=0) == 0, axis=1))
    if dup.size:
        raise ValueError(f"points: expected distinct pixels, got {dup.size} repeated (first at x, y = "
                         f"{ij[dup[0]].tolist()})")
    if reference_mask is None:
        mask = np.zeros((ij[:, 1].max() + 3, ij[:, 0].max() + 3), bool)
    else:
        mask = as_mask("reference_mask", reference_mask, 2)
        inside = (ij[:, 1] < mask.shape[0]) & (ij[:, 0] < mask.shape[1])
        on = np.zeros(P, bool)
        on[inside] = mask[ij[inside, 1], ij[inside, 0]]
        if not on.all() or mask.sum() != P:
            raise ValueError(f"reference_mask: expected its tissue pixels to be exactly the points (the DENSE route "
                             f"observes every reference pixel), got {int((~on).sum())} of {P} points off its tissue "
                             f"and {int(mask.sum())} tissue pixels")
        mask = np.zeros(mask.shape, bool)
    mask[ij[:, 1], ij[:, 0]] = True
    s = np.asarray(sd, float)
    if s.ndim == 1:
        s = s[order][None, :, None]
    elif s.ndim == 2:
        s = s[:, order][..., None]
    elif s.ndim == 3:
        s = s[:, order]
    try:
        s = np.array(np.broadcast_to(s, (F, P, 2)), float)
    except ValueError:
        raise ValueError(f"sd: expected a number, (P,), (F, P) or (F, P, 2) with F = {F}, P = {P}, got shape "
                         f"{np.shape(sd)}") from None
    tracked = np.isfinite(d).all(axis=2)
    if np.any(~(s[tracked] > 0)):
        raise ValueError("sd: expected positive noise sd (pixels) of every tracked datum")
    c = np.ones(P) if confidence is None else np.asarray(confidence, float)
    if c.ndim == 1:
        c = c[order]
    elif c.ndim == 2:
        c = c[:, order]
    try:
        c = np.array(np.broadcast_to(c, (F, P)), float)
    except ValueError:
        raise ValueError(f"confidence: expected a number, (P,) or (F, P) with F = {F}, P = {P}, got shape "
                         f"{np.shape(confidence)}") from None
    if np.any((c < 0) | (c > 1)):
        raise ValueError("confidence: expected values in [0, 1]")
    s[~tracked] = np.nan
    c[~tracked] = np.nan
    d = np.where(tracked[..., None], d, np.nan)
    tracks = LagrangianDisplacement(points=ij.astype(float), displacement=d, sd=s, confidence=c,
                                    frame_times_s=times, n_untracked=int((~tracked).sum()),
                                    noise_sd=np.full(2, np.nan))
    return tracks, mask


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
    mask. The sd of the pixels behind each datum (``pixel_sd``): phase sd ``noise_sd / m(x)`` per
    encoding (``m`` the magnitude interpolated at the tracked position, capped at ``pi / sqrt 3``,
    the sd of a uniform phase), mapped through ``D^-1 / (2 pi ke)`` and the pixel size; the
    datum's own (``sd``) is that times ``sqrt(sum w^2)``, ``w`` the bilinear weights at the tracked
    position (:func:`interpolation_variance_factor`). To first order in the noise; the inversion's
    own Jacobian (the deformation gradient, which maps an Eulerian error at ``x`` to the
    Lagrangian one) is left out. ``noise_sd`` defaults to :func:`estimate_noise_sd` of each
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
    psd = np.full((F, P, 2), np.nan)
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
        psd[f] = np.sqrt((sphi[:, None, :] ** 2 * dinv[None] ** 2).sum(axis=2)) * to_px
        sd[f] = psd[f] * np.sqrt(interpolation_variance_factor(x))[:, None]
        r = np.clip(np.round(x[:, 1]).astype(int), 0, case.shape[0] - 1)
        c = np.clip(np.round(x[:, 0]).astype(int), 0, case.shape[1] - 1)
        dist, (nr, nc) = ndimage.distance_transform_edt(~masks[f], return_indices=True)
        conf[f] = quality[f, nr[r, c], nc[r, c]] * np.clip(1 - dist[r, c] / (rings + 1), 0.0, 1.0)
        sd[f][~ok] = np.nan
        psd[f][~ok] = np.nan
        conf[f][~ok] = np.nan
        prev = np.where(np.isfinite(d), d, prev if prev is not None else 0.0)
    n_bad = int((~np.isfinite(disp).all(axis=2)).sum())
    return LagrangianDisplacement(points=X, displacement=disp, sd=sd, confidence=conf,
                                  frame_times_s=case.frame_times_s.copy(), n_untracked=n_bad, noise_sd=noise,
                                  pixel_sd=psd)


# ------------------------------------------------------------------ the acquisition's point spread
#: FWHM of a Gaussian over its sd, ``2 sqrt(2 ln 2)``.
FWHM_PER_SD = 2.0 * np.sqrt(2.0 * np.log(2.0))
#: Sub-samples per pixel (each axis) of the point spread function (:func:`psf_samples`).
PSF_SAMPLES_PER_PX = 3
#: Radius (in sd) at which the Gaussian point spread function is cut (:func:`psf_samples`).
PSF_RADIUS_SD = 3.0


def psf_sigma_px(resolution_px) -> float:
    """sd (reconstructed pixels) of the Gaussian point spread beyond the pixel grid, from the acquired resolution.

    The acquisition's point spread function is modelled as a Gaussian whose FWHM is the acquired
    pixel, ``resolution_px`` reconstructed pixels wide (the PSF of a k-space disc of radius
    ``1 / (2 w)``, the jinc, has a FWHM of 1.03 ``w``; a Cartesian box's sinc, 1.21 ``w``; the
    Gaussian keeps its main lobe and drops the side lobes). Observing the model at a pixel centre
    already stands for one reconstructed pixel (FWHM 1), so the blur the observation operator adds
    is the Gaussian that convolved with that one gives the acquired FWHM:
    ``sd = sqrt(w^2 - 1) / (2 sqrt(2 ln 2))``, zero (point observation) at ``w = 1``.

    Parameters
    ----------
    resolution_px : float
        Acquired resolution in reconstructed pixels (>= 1).
    """
    w = check_resolution_px(resolution_px)
    return float(np.sqrt(max(w * w - 1.0, 0.0)) / FWHM_PER_SD)


def psf_samples(resolution_px, per_px: int = PSF_SAMPLES_PER_PX, radius_sd: float = PSF_RADIUS_SD) -> tuple:
    """Sample offsets (pixels) and weights of the Gaussian point spread of :func:`psf_sigma_px`.

    A square lattice of ``per_px`` samples per pixel (offsets ``k / per_px``, so pixel centres plus
    offsets share one lattice), cut at ``radius_sd`` sd, weights ``exp(-|o|^2 / (2 sd^2))``
    normalised to sum 1. At ``resolution_px = 1`` (no blur) one sample at the centre.

    Returns
    -------
    offsets : (S, 2) array
        (x, y) offsets in pixels.
    weights : (S,) array
    """
    sd = psf_sigma_px(resolution_px)
    n = integer("per_px", per_px, 1)
    r = positive("radius_sd", radius_sd)
    if sd == 0.0:
        return np.zeros((1, 2)), np.ones(1)
    k = int(np.ceil(r * sd * n))
    g = np.arange(-k, k + 1) / n
    off = np.stack(np.meshgrid(g, g, indexing="xy"), axis=-1).reshape(-1, 2)
    off = off[np.hypot(off[:, 0], off[:, 1]) <= r * sd + 1e-12]
    w = np.exp(-0.5 * np.sum(off ** 2, axis=1) / sd ** 2)
    return off, w / w.sum()


@dataclass(frozen=True, eq=False)
class BackgroundSignal:
    """The signal around the myocardium, as the DENSE route's observation operator needs it.

    Attributes
    ----------
    signal : (F, H, W, 2) complex array
        Per frame and encoding (x, then y), the complex signal of what surrounds the myocardium
        (magnitude times ``exp(i phase)``) over the frame's median myocardial magnitude: its
        modulus is the background's relative signal, its argument the phase it encodes (zero for
        static material).
    phase_per_px : float
        Phase (rad) that one pixel of displacement along an encoding direction encodes,
        ``2 pi ke`` times the pixel size.
    """

    signal: np.ndarray
    phase_per_px: float


#: How many standard errors of their mean a background region's complex signals must stand above zero to be read
#: as a coherent level (:func:`background_signal`); below it the region's signal is incoherent and mixes in nothing.
BACKGROUND_COHERENCE_SE = 3.0


def background_signal(case: DenseCase, resolution_px=None) -> BackgroundSignal:
    """The complex signal around the myocardium that a border pixel's point spread mixes in, per frame and pixel.

    What the DENSE route's observation operator weights the point spread's reach outside the
    tissue by (:func:`sfem_filters.cardiac.dense_model.observation_operator`). The image near the
    myocardium is the tissue's own signal blurred outwards, so the background is read where the
    myocardium's blur has faded: for each connected piece of a frame's non-myocardium (the
    cavity, the outside), its pixels between ``r`` and ``r + 2`` pixels from the frame's mask,
    ``r`` the acquired resolution rounded up (or the piece's farthest distance if it is thinner).
    There the piece has one level per encoding, the complex mean ``mu_j`` of ``m exp(i phi_j)``
    over those pixels (a complex mean: noise averages out without the magnitude's Rician bias),
    divided by the frame's median myocardial magnitude; it is carried to every pixel of the piece
    and to the mask's pixels next to it. Its phase is kept: what surrounds the heart need not be
    static (DENSE-Sim's cavity early in the cycle is bright and carries a phase).

    Only a coherent signal mixes into a border pixel as a phase: a level is kept when it stands
    above the piece's own incoherent spread, ``sum_j |mu_j|^2 > c^2 sum_j s_j^2 / n_eff`` with
    ``s_j^2 = mean |z_j - mu_j|^2`` over the pixels, ``c`` =
    :data:`BACKGROUND_COHERENCE_SE` standard errors and ``n_eff`` the pixels over the area of the
    acquisition's point spread (``4 pi (w / 2.355)^2``, ``w`` the acquired resolution: pixels
    closer than that share their signal); otherwise the level is zero (dark). Why: a background
    of random phase (thermal noise, the incoherent floor of an image's reconstruction, which is
    all that remains of DENSE-Sim's static cavity blood once its signal has decayed over the
    cycle) sums to nearly nothing over a point spread, but its pixels' own values are large; read
    pixel by pixel it would feed random phases into the border data as if they were the wall's
    surroundings. The rule holds for any case: it asks only whether the signal is coherent, and
    its threshold is a significance level, not a number fitted to data.

    Parameters
    ----------
    case : DenseCase
    resolution_px : float, optional
        Acquired resolution (reconstructed pixels); default ``case.resolution_px``.

    Returns
    -------
    BackgroundSignal
    """
    w = check_resolution_px(case.resolution_px if resolution_px is None else resolution_px)
    reach = int(np.ceil(w))
    psf_area = max(4.0 * np.pi * (w / FWHM_PER_SD) ** 2, 1.0)            # px^2 sharing one acquired sample
    masks = case.frame_masks
    out = np.zeros(case.magnitude.shape + (2,), complex)
    for f in range(case.n_frames):
        m, k = case.magnitude[f], masks[f]
        tissue = float(np.median(m[k]))
        if not tissue > 0:
            continue
        z = np.stack([m * np.exp(1j * case.phases[j, f]) for j in range(2)], axis=-1) / tissue
        dist = ndimage.distance_transform_edt(~k)
        labels, n = ndimage.label(~k)
        level = np.zeros(z.shape, complex)
        rings = np.zeros(m.shape, bool)
        for piece in range(1, n + 1):
            sel = labels == piece
            r0 = min(reach, float(dist[sel].max()))
            ring = sel & (dist >= r0) & (dist <= r0 + 2)
            if not ring.any():
                continue
            level[sel] = _coherent_level(z[ring], psf_area)
            rings |= ring
        if rings.any():
            _, (ir, ic) = ndimage.distance_transform_edt(~rings, return_indices=True)
            level[k] = level[ir, ic][k]
        out[f] = level
    return BackgroundSignal(signal=out, phase_per_px=float(2 * np.pi * case.ke_per_m * case.pixel_size_m))


def _coherent_level(z, psf_area: float):
    """(2,) complex: the mean of ``z`` (n, 2) if it stands above its standard error's
    :data:`BACKGROUND_COHERENCE_SE` times (``n / psf_area`` independent samples), else zero."""
    mu = z.mean(axis=0)
    spread2 = np.mean(np.abs(z - mu) ** 2, axis=0)
    n_eff = max(len(z) / psf_area, 1.0)
    coherent = np.sum(np.abs(mu) ** 2) > BACKGROUND_COHERENCE_SE ** 2 * np.sum(spread2) / n_eff
    return mu if coherent else np.zeros_like(mu)


def edge_spread_resolution(case: DenseCase, frames=None, band_px: float = 4.0) -> dict:
    """The acquired resolution estimated from the magnitude's edge spread (a cross-check of the file's).

    For each frame, the magnitude (over its median in the myocardium) as a function of the signed
    distance to the border of the filled myocardium (epicardium; the cavity excluded), within
    ``band_px`` pixels, is fitted by a blurred step ``b + (a - b) Phi((d - d0) / s)``; the edge's
    sd ``s`` (median over the frames) gives the FWHM ``2.355 s`` and, in the convention of
    :func:`psf_sigma_px`, the resolution ``sqrt(1 + (2.355 s)^2)``. Not used by the route: the
    border of a mask is itself only known to a pixel, so this is a check of the acquisition's
    number, not a replacement.

    Returns
    -------
    dict
        ``sd_px``, ``fwhm_px``, ``resolution_px`` (medians over the frames), ``per_frame_sd_px``.
    """
    fs = range(case.n_frames) if frames is None else frames
    sds = []
    for f in fs:
        k = case.frame_masks[f]
        fill = ndimage.binary_fill_holes(k)
        d = np.where(fill, ndimage.distance_transform_edt(fill) - 0.5, -(ndimage.distance_transform_edt(~fill) - 0.5))
        sel = (np.abs(d) <= band_px) & (k | ~fill)
        tissue = float(np.median(case.magnitude[f][k]))
        if sel.sum() < 8 or not tissue > 0:
            continue
        x, y = d[sel], case.magnitude[f][sel] / tissue

        def resid(p):
            return p[2] + (p[3] - p[2]) * 0.5 * (1 + special.erf((x - p[0]) / (np.sqrt(2) * abs(p[1]) + 1e-9))) - y
        p = optimize.least_squares(resid, [0.0, 1.0, 0.1, 1.0]).x
        sds.append(abs(float(p[1])))
    if not sds:
        raise ValueError("case: expected frames with a myocardium border to fit the edge spread, got none")
    sd = float(np.median(sds))
    return {"sd_px": sd, "fwhm_px": FWHM_PER_SD * sd, "resolution_px": float(np.sqrt(1 + (FWHM_PER_SD * sd) ** 2)),
            "per_frame_sd_px": sds}
