"""Myocardium segmentation from intensity (and optionally velocity) images, for users without masks.

A level-set front propagation in the spirit of the paper's: the morphological Chan-Vese
active contour of scikit-image (a region-based level set evolved by morphological operators)
splits each frame into tissue and background; the front of frame t starts from the result of
frame t-1, so the contour is propagated through the cycle. When phase-contrast velocity is
given, its local phase coherence (high in tissue with signal, low in blood and air) is added
to the intensity as a second feature. The result is cleaned into one ring around one cavity.
"""
from __future__ import annotations

import numpy as np
from skimage.measure import label
from skimage.segmentation import morphological_chan_vese

from .._validate import as_float_array, non_negative
from .confidence import velocity_coherence
from .contours import check_myocardium_mask


def _normalise(img):
    lo, hi = np.percentile(img, [1, 99])
    return np.clip((img - lo) / max(hi - lo, 1e-12), 0.0, 1.0)


def clean_ring(mask, min_hole: int = 4) -> np.ndarray:
    """The largest connected piece of ``mask`` with holes smaller than ``min_hole`` pixels filled.

    The biggest enclosed background region (the cavity) is kept open whatever its size.
    """
    m = np.asarray(mask, bool)
    lab = label(m, connectivity=2)
    if lab.max() == 0:
        raise ValueError("mask: the segmentation found no tissue")
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    ring = lab == np.argmax(sizes)
    padded = label(np.pad(~ring, 1, constant_values=True), connectivity=1)
    bg, outside = padded[1:-1, 1:-1], padded[0, 0]
    hole_ids = [i for i in np.unique(bg[~ring]) if i != outside]
    if hole_ids:
        counts = {i: int(np.sum(bg == i)) for i in hole_ids}
        cavity = max(counts, key=counts.get)
        for i, n in counts.items():
            if i != cavity and n < min_hole:
                ring |= bg == i
    return ring


def segment_frame(image, init, smoothing: int = 2, iterations: int = 60, coherence=None,
                  coherence_weight: float = 1.0) -> np.ndarray:
    """Tissue mask of one frame by a morphological Chan-Vese level set started from ``init``.

    Parameters
    ----------
    image : (H, W) array
        Intensity (any unit: it is normalised to its 1-99 percentile range).
    init : (H, W) bool array
        Initial front (tissue inside).
    smoothing : int
        Morphological smoothing steps per iteration (contour regularity).
    iterations : int
        Level-set iterations.
    coherence : (H, W) array, optional
        Local phase coherence of the velocity in [0, 1], added as a second feature.
    coherence_weight : float
        Weight of that feature.
    """
    feat = _normalise(np.asarray(image, float))
    if coherence is not None:
        feat = (feat + coherence_weight * np.asarray(coherence, float)) / (1.0 + coherence_weight)
    ls = morphological_chan_vese(feat, num_iter=int(iterations), init_level_set=np.asarray(init, np.int8),
                                 smoothing=int(smoothing))
    tissue = ls.astype(bool)
    if feat[tissue].mean() < feat[~tissue].mean():      # Chan-Vese labels are arbitrary: tissue is bright
        tissue = ~tissue
    return clean_ring(tissue)


def initial_ring(shape, centre=None, r_inner=None, r_outer=None) -> np.ndarray:
    """A ring-shaped initial front (pixels), by default centred with radii 1/6 and 1/3 of the image."""
    H, W = shape
    cy, cx = ((H - 1) / 2.0, (W - 1) / 2.0) if centre is None else (centre[1], centre[0])
    r_in = min(H, W) / 6.0 if r_inner is None else r_inner
    r_out = min(H, W) / 3.0 if r_outer is None else r_outer
    yy, xx = np.mgrid[0:H, 0:W]
    r = np.hypot(xx - cx, yy - cy)
    return (r >= r_in) & (r <= r_out)


def segment_sequence(magnitude, velocity=None, venc: float | None = None, init=None, smoothing: int = 2,
                     iterations: int = 60, coherence_weight: float = 1.0) -> np.ndarray:
    """Myocardium masks of every frame by front propagation through the cycle.

    Parameters
    ----------
    magnitude : (F, H, W) array
        Intensity images.
    velocity : (F, H, W, 2) array, optional
        Phase-contrast velocity (m/s); needs ``venc`` (m/s).
    init : (H, W) bool array, optional
        Initial front for frame 0 (default :func:`initial_ring`).

    Returns
    -------
    (F, H, W) bool array
        Each frame checked to be one ring around one cavity.
    """
    mag = as_float_array("magnitude", magnitude, shape=(None, None, None))
    if len(mag) < 2:
        raise ValueError(f"magnitude: expected at least 2 frames, got {len(mag)}")
    non_negative("coherence_weight", coherence_weight)
    coh = None
    if velocity is not None:
        if venc is None:
            raise ValueError("venc: velocity images need their velocity encoding (m/s), got none")
        coh = velocity_coherence(velocity, venc)
    front = initial_ring(mag.shape[1:]) if init is None else np.asarray(init, bool)
    out = np.zeros(mag.shape, bool)
    for t in range(len(mag)):
        front = segment_frame(mag[t], front, smoothing, iterations, None if coh is None else coh[t],
                              coherence_weight)
        try:
            out[t] = check_myocardium_mask(front)
        except ValueError as exc:
            raise ValueError(f"magnitude[{t}]: segmentation failed: {str(exc).split(': ', 1)[-1]}") from None
    return out


def dice(a, b) -> float:
    """Dice overlap of two masks, in [0, 1]."""
    a = np.asarray(a, bool)
    b = np.asarray(b, bool)
    s = a.sum() + b.sum()
    return 1.0 if s == 0 else 2.0 * float(np.sum(a & b)) / float(s)
