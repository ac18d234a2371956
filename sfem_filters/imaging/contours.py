"""Myocardial borders of a mask: ordered, resampled closed contours and their curvature.

Coordinates are image coordinates in pixels: x = column, y = row (y grows downwards), the
pixel (row r, column c) being centred on (c, r). Multiply by the pixel spacing (m) to get
metres. Every contour is returned with positive signed area in (x, y), i.e. counter-clockwise
in the (x, y) plane (clockwise as drawn on an image with y down), without repeating its first
point, and starting at the point closest in angle to the +x direction seen from the cavity
centre, so that index k of two frames' contours points roughly the same way.
"""
from __future__ import annotations

import re
import warnings
from contextvars import ContextVar
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_closing, distance_transform_edt, gaussian_filter1d
from skimage.measure import find_contours, label

from .._validate import as_float_array, as_mask, integer, user_stacklevel
from ..geometry import polygon_centroid, signed_area


@dataclass(frozen=True, eq=False)
class Borders:
    """Endo- and epicardial contours of one frame (pixels) and the cavity centre."""

    endo: np.ndarray      # (n_endo, 2) x, y
    epi: np.ndarray       # (n_epi, 2)
    centre: np.ndarray    # (2,) centroid of the endocardial contour


def check_myocardium_mask(mask, name: str = "mask") -> np.ndarray:
    """Check a 2D myocardium mask: boolean, some tissue, one connected ring around one cavity.

    Raises ``ValueError`` naming ``name`` for an empty mask, several pieces of tissue, or a
    mask without exactly one enclosed cavity.
    """
    arr = as_mask(name, mask, 2)
    if not arr.any():
        raise ValueError(f"{name}: expected some tissue, got an empty mask")
    n = int(label(arr, connectivity=2).max())
    if n != 1:
        raise ValueError(f"{name}: expected one connected piece of myocardium, got {n} pieces")
    padded = np.pad(arr, 1)
    holes = int(label(~padded, connectivity=1).max()) - 1
    if holes != 1:
        raise ValueError(f"{name}: expected a ring around exactly one cavity, got {holes} enclosed "
                         f"background regions")
    return arr


#: The most of a mask :func:`repair_myocardium_mask` may change, as a fraction of its tissue pixels.
MAX_REPAIR_FRACTION = 0.05


def _pieces(arr) -> np.ndarray:
    return label(arr, connectivity=2)


def _enclosed(arr) -> np.ndarray:
    """Labels of the background regions (4-connected) that do not reach the image's edge."""
    lab = label(np.pad(~arr, 1, constant_values=True), connectivity=1)
    return label(((lab != 0) & (lab != lab[0, 0]))[1:-1, 1:-1], connectivity=1)


def _cavity(arr, budget: float) -> tuple:
    """The enclosed background regions of ``arr``, their sizes, and the label of the one that is clearly
    the cavity (larger than the holes the repair may fill, and at least twice any other), else None."""
    enc = _enclosed(arr)
    sizes = np.bincount(enc.ravel())[1:] if enc.max() else np.zeros(0, int)
    if sizes.size == 0:
        return enc, sizes, None
    top = np.sort(sizes)[::-1]
    if top[0] <= budget or (sizes.size > 1 and top[0] < 2 * top[1]):
        return enc, sizes, None
    return enc, sizes, 1 + int(np.argmax(sizes))


def repair_myocardium_mask(mask, name: str = "mask", max_fraction: float = MAX_REPAIR_FRACTION) -> tuple:
    """A myocardium mask made one ring around one cavity by the smallest changes, or an error.

    A mask drawn or resampled on a coarse grid can carry defects of a pixel or two that do not
    change the anatomy but break the ring the meshing and the border tracking need: a stray piece
    of tissue beside the wall, a pinhole in it, a one-pixel cut through it (a cut ring with one
    pinhole even passes :func:`check_myocardium_mask`, the pinhole as its cavity). A ring around a
    cavity is returned as it is; otherwise each defect is mended in turn, and only while all the changes together stay
    within ``max_fraction`` of the tissue:

    1. pieces of tissue other than the largest are removed (8-connected pieces);
    2. when no enclosed background region is clearly the cavity (larger than the holes this may
       fill and at least twice any other), the cavity has leaked through a cut: a 3 x 3
       morphological closing bridges a gap of a pixel or two (and fills one-pixel notches of the
       border), and must leave a region that is clearly the cavity (else a mask that was one
       piece around one small enclosed region is returned as given);
    3. enclosed background regions other than the cavity (pinholes) are filled.

    Parameters
    ----------
    mask : (H, W) array_like of bool
        Myocardium mask.
    name : str
        How errors name the mask.
    max_fraction : float
        Largest change allowed, as a fraction of the mask's tissue pixels.

    Returns
    -------
    (mask, changes) : ((H, W) bool ndarray, str)
        The ring, and what was changed ("" when the mask was one already).

    Raises
    ------
    ValueError
        Naming ``name``, for an empty mask, or when no change within ``max_fraction`` makes a ring
        (two large pieces, a second large cavity, a wide cut, no cavity at all).
    """
    arr = as_mask(name, mask, 2).copy()
    if not 0.0 <= max_fraction < 1.0:
        raise ValueError(f"max_fraction: expected a fraction of the tissue in [0, 1), got {max_fraction!r}")
    if not arr.any():
        raise ValueError(f"{name}: expected some tissue, got an empty mask")
    try:
        ring = check_myocardium_mask(arr, name).copy()       # one piece around one enclosed region
    except ValueError:
        ring = None
    budget = max_fraction * arr.sum()
    if ring is not None and _cavity(ring, budget)[2] is not None:
        return ring, ""                                      # a ring around a cavity: nothing to mend
    changes, changed = [], 0
    lab = _pieces(arr)
    if lab.max() > 1:
        sizes = np.bincount(lab.ravel())[1:]
        drop = np.isin(lab, 1 + np.flatnonzero(np.arange(sizes.size) != np.argmax(sizes)))
        changed += int(drop.sum())
        if changed > budget:
            raise ValueError(f"{name}: expected one connected piece of myocardium, got {sizes.size} pieces "
                             f"(sizes {sorted(sizes.tolist(), reverse=True)} px): more than a stray pixel or two")
        arr[drop] = False
        changes.append(f"removed {sizes.size - 1} stray piece(s) of {int(drop.sum())} px")
    enc, sizes, cavity = _cavity(arr, budget)
    if cavity is None:
        # no region that is clearly the cavity: a cut lets it out (what is enclosed are pinholes at most);
        # a 3 x 3 closing, on a padded copy so that the image's edge erodes nothing, bridges it
        closed = arr | binary_closing(np.pad(arr, 2), np.ones((3, 3), bool))[2:-2, 2:-2]
        added = int((closed & ~arr).sum())
        enc_c, sizes_c, cavity_c = _cavity(closed, budget)
        if (cavity_c is None or changed + added > budget) and ring is not None:
            return ring, ""                                  # a ring around a small cavity, as it was given
        if cavity_c is None or changed + added > budget:
            got = (f"{sizes.size} enclosed background regions (sizes {sorted(sizes.tolist(), reverse=True)} px), "
                   f"none clearly the cavity" if sizes.size else "no enclosed cavity")
            raise ValueError(f"{name}: expected a ring around exactly one cavity, got {got} (a cut of more than "
                             f"two pixels, a second cavity, or none)")
        arr, changed = closed, changed + added
        changes.append(f"closed a cut in the ring ({added} px added)")
        enc, sizes, cavity = enc_c, sizes_c, cavity_c
    fill = (enc > 0) & (enc != cavity)
    if fill.any():
        changed += int(fill.sum())
        if changed > budget:
            raise ValueError(f"{name}: expected a ring around exactly one cavity, got {sizes.size} enclosed "
                             f"background regions (sizes {sorted(sizes.tolist(), reverse=True)} px)")
        arr[fill] = True
        changes.append(f"filled {sizes.size - 1} hole(s) of {int(fill.sum())} px in the wall")
    check_myocardium_mask(arr, name)
    return arr, "; ".join(changes)


def resample_closed(xy, n: int) -> np.ndarray:
    """``n`` points equally spaced in arc length along a closed polyline, starting at ``xy[0]``."""
    xy = as_float_array("xy", xy, shape=(None, 2))
    if len(xy) < 3:
        raise ValueError(f"xy: expected a closed polyline of at least 3 points, got {len(xy)}")
    if int(n) != n or n < 3:
        raise ValueError(f"n: expected an integer >= 3, got {n!r}")
    closed = np.vstack([xy, xy[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        raise ValueError("xy: the polyline has zero length")
    t = np.arange(int(n)) * s[-1] / n
    return np.column_stack([np.interp(t, s, closed[:, 0]), np.interp(t, s, closed[:, 1])])


def smooth_closed(xy, sigma: float) -> np.ndarray:
    """Gaussian smoothing (standard deviation ``sigma`` in points) of a closed contour.

    Removes the pixel staircase of a mask border before curvature is taken; ``sigma = 0``
    returns the contour unchanged.
    """
    if sigma < 0:
        raise ValueError(f"sigma: expected a non-negative smoothing width in points, got {sigma!r}")
    if sigma == 0:
        return np.array(xy, float)
    return gaussian_filter1d(np.asarray(xy, float), sigma, axis=0, mode="wrap")


def curvature(xy) -> np.ndarray:
    """Signed discrete curvature (1/px) of a closed, uniformly sampled contour.

    ``kappa = (x' y'' - y' x'') / (x'^2 + y'^2)^(3/2)`` with periodic central differences; a
    circle of radius r traversed counter-clockwise in (x, y) has ``kappa = +1/r`` everywhere.
    """
    xy = as_float_array("xy", xy, shape=(None, 2))
    d1 = (np.roll(xy, -1, axis=0) - np.roll(xy, 1, axis=0)) / 2.0
    d2 = np.roll(xy, -1, axis=0) - 2 * xy + np.roll(xy, 1, axis=0)
    num = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    den = np.sum(d1 ** 2, axis=1) ** 1.5
    if np.any(den == 0):
        raise ValueError("xy: repeated consecutive points; curvature is undefined there")
    return num / den


def _orient_and_start(xy, centre, start_rad: float = 0.0):
    if signed_area(xy) < 0:
        xy = xy[::-1]
    d = xy - centre
    k = int(np.argmin(np.abs(np.angle(np.exp(1j * (np.arctan2(d[:, 1], d[:, 0]) - start_rad))))))
    return np.roll(xy, -k, axis=0)


_MENDED = ": not one ring around one cavity; mended before its borders are taken: "


#: The mendings collected by an open :class:`mended_masks_summarised` (None: none open, each mending warns).
_COLLECTING: ContextVar = ContextVar("sfem_filters_mended_masks", default=None)


class mended_masks_summarised:
    """Within this context the mendings of :func:`mask_borders` (one warning per mask) are collected and given
    as one warning when it closes, naming every mended mask with what was changed.

    A sequence of coarse masks may carry the same defect in every frame (a stray pixel, a pinhole): one
    line, not one per frame. A single mended mask keeps :func:`mask_borders`'s own message. Nothing
    else is caught: other warnings pass as they are, the warning filters are not touched, and the
    warning points at the code that opened the context (its caller outside sfem_filters). When an
    error leaves the context, the summary is still given, but never in place of that error.
    """

    def __enter__(self):
        self._token = _COLLECTING.set([])
        return self

    def __exit__(self, exc_type, exc, tb):
        mended = _COLLECTING.get()
        _COLLECTING.reset(self._token)
        try:
            _summarise_mended(mended)
        except Exception:                               # a warning made an error: the error leaving wins
            if exc_type is None:
                raise
        return False


def _summarise_mended(mended) -> None:
    groups = {}
    for name, changes in mended:
        groups.setdefault(changes, []).append(name)
    names = [n for group in groups.values() for n in group]
    if len(names) == 1:
        warnings.warn(names[0] + _MENDED + next(iter(groups)), RuntimeWarning, stacklevel=user_stacklevel())
    elif names:
        what = "; ".join(f"{changes} ({_mask_names(group)})" if len(groups) > 1 else changes
                         for changes, group in groups.items())
        warnings.warn(f"{len(names)} masks ({_mask_names(names)}): not one ring around one cavity; mended before "
                      f"their borders are taken: {what}", RuntimeWarning, stacklevel=user_stacklevel())


def _mask_names(names) -> str:
    """``masks[0-5, 7]`` for names ``masks[i]`` (runs of indices joined), else the names joined by commas."""
    found = [re.fullmatch(r"masks\[(\d+)\]", n) for n in names]
    if not all(found):
        return ", ".join(names)
    idx = sorted(int(f.group(1)) for f in found)
    runs, start = [], idx[0]
    for a, b in zip(idx, idx[1:] + [None]):
        if b != a + 1:
            runs.append(str(start) if start == a else f"{start}-{a}")
            start = b
    return f"masks[{', '.join(runs)}]"


def mask_borders(mask, n_endo: int = 64, n_epi: int = 96, smooth: float = 0.0, name: str = "mask",
                 start_deg: float = 0.0) -> Borders:
    """Endo- and epicardial contours of a myocardium mask (marching squares at level 1/2).

    A mask with a defect of a pixel or two (a stray piece, a pinhole, a one-pixel cut) is mended
    first by :func:`repair_myocardium_mask`, with a ``RuntimeWarning`` saying what changed (one for
    every mask mended within a :class:`mended_masks_summarised` context).

    Parameters
    ----------
    mask : (H, W) bool array
        Myocardium (one ring around one cavity, up to small defects).
    n_endo, n_epi : int
        Points of each contour after resampling at equal arc length.
    smooth : float
        Gaussian smoothing of the raw border, in raw border points (0: none).
    name : str
        How errors and the repair's warning name the mask.
    start_deg : float
        Where the contours start (and their resampling begins): the point closest in angle to
        this direction about the cavity centre, degrees from +x towards +y (default 0, the
        module's rule). The points of a binary border resampled at equal arc length depend on it
        by a fraction of their spacing.

    Returns
    -------
    Borders
        Contours in pixels (x = column, y = row), oriented and started as the module says.
    """
    arr, changes = repair_myocardium_mask(mask, name)
    collecting = _COLLECTING.get()
    if changes and collecting is not None:              # one warning for them all (mended_masks_summarised)
        collecting.append((name, changes))
    elif changes:
        warnings.warn(name + _MENDED + changes, RuntimeWarning, stacklevel=2)
    raw = find_contours(np.pad(arr, 1).astype(float), 0.5)
    loops = [np.column_stack([c[:, 1], c[:, 0]]) - 1.0 for c in raw]      # (x, y), undo the padding
    loops = [c[:-1] if np.allclose(c[0], c[-1]) else c for c in loops]
    loops = [c for c in loops if len(c) >= 3]
    areas = np.array([abs(signed_area(c)) for c in loops])
    if len(loops) < 2:
        raise ValueError(f"{name}: expected an inner and an outer border, found fewer than two contours")
    order = np.argsort(areas)[::-1]
    epi = loops[order[0]]
    # the endocardium is the largest remaining loop lying inside the epicardium
    endo = loops[order[1]]
    centre = polygon_centroid(endo)
    a = np.deg2rad(float(start_deg))
    if not np.isfinite(a):
        raise ValueError(f"start_deg: expected a finite angle in degrees, got {start_deg!r}")
    endo = _orient_and_start(smooth_closed(endo, smooth), centre, a)
    epi = _orient_and_start(smooth_closed(epi, smooth), centre, a)
    endo = _orient_and_start(resample_closed(endo, n_endo), centre, a)
    epi = _orient_and_start(resample_closed(epi, n_epi), centre, a)
    return Borders(endo=endo, epi=epi, centre=polygon_centroid(endo))


def closest_on_polyline(xy, points):
    """Closest point of a closed polyline to each of ``points`` (px).

    Returns
    -------
    closest : (p, 2) array
    segment : (p,) int, index i of the segment from ``xy[i]`` to ``xy[i + 1]``
    fraction : (p,) float in [0, 1], position along that segment
    """
    xy = as_float_array("xy", xy, shape=(None, 2))
    pts = as_float_array("points", points, shape=(None, 2))
    a = xy
    b = np.roll(xy, -1, axis=0)
    ab = b - a
    L2 = np.maximum(np.sum(ab ** 2, axis=1), 1e-300)
    f = np.clip(np.einsum("psk,sk->ps", pts[:, None] - a[None], ab) / L2[None], 0.0, 1.0)
    proj = a[None] + f[..., None] * ab[None]
    d2 = np.sum((proj - pts[:, None]) ** 2, axis=2)
    seg = np.argmin(d2, axis=1)
    rows = np.arange(len(pts))
    return proj[rows, seg], seg, f[rows, seg]


def pixel_depth(mask) -> np.ndarray:
    """Transmural depth of every pixel of a ring mask: 0 at the cavity side, 1 at the outside."""
    m = np.asarray(mask, bool)
    background = np.pad(~m, 1, constant_values=True)
    lab = label(background, connectivity=1)
    outside = lab == lab[0, 0]
    cavity = background & ~outside
    d_in = distance_transform_edt(~cavity)[1:-1, 1:-1]
    d_out = distance_transform_edt(~outside)[1:-1, 1:-1]
    return np.clip((d_in - 0.5) / np.maximum(d_in + d_out - 1.0, 1e-12), 0.0, 1.0)


def midwall_pixels(mask, depth_range=(0.25, 0.75)) -> np.ndarray:
    """Pixel centres (x, y) of the tissue whose transmural depth lies in ``depth_range``."""
    m = np.asarray(mask, bool)
    d = pixel_depth(m)
    rows, cols = np.nonzero(m & (d >= depth_range[0]) & (d <= depth_range[1]))
    return np.column_stack([cols, rows]).astype(float)


def border_length(mask) -> float:
    """Length (pixels) of every border of a mask: its marching-squares contours at level 0.5, summed."""
    m = np.pad(as_mask("mask", mask, 2).astype(float), 1)
    return float(sum(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1)) for c in find_contours(m, 0.5)))


def reference_mask_mismatch(masks, name: str = "masks", exclude=()) -> str | None:
    """Why the reference mask (index 0) may not be the frames' own, or None when nothing says so.

    The reference configuration comes just before the first frame (DENSE encodes there), so the
    reference mask's area should differ from the first frame's by less than the frames' areas vary
    over the whole sequence, and by less than half a pixel of every border (the pixels' own
    quantisation). Frames whose mask is empty, and those in ``exclude`` (masks a route leaves out, such
    as ones that cannot be mended), are passed over. A reference mask dilated or eroded by a pixel, or
    drawn by another segmentation with another border convention, breaks both: its area departs by about
    a pixel of border. Routes that read the wall's thickness from the masks take it as the zero of radial
    strain, so every radial strain would be off by about a pixel over the wall's thickness, without the
    data saying so. The check compares areas only: a reference of the right area drawn on another image,
    or shifted, passes it.

    Parameters
    ----------
    masks : (F + 1, H, W) bool array
        Myocardium masks of the reference (index 0) and of each frame (index f + 1).
    name : str
        The argument's name in the message.
    exclude : sequence of int, optional
        Indices in ``masks`` (>= 1) of frames to pass over (None: none).

    Returns
    -------
    str or None
        A sentence naming the areas (pixels) and the two scales, or None.
    """
    m = as_mask(name, masks, 3)
    if len(m) == 0:
        raise ValueError(f"{name}: expected the reference mask first, (F + 1, H, W), got no mask (shape {m.shape})")
    skip = {integer("exclude", v, 1) for v in (() if exclude is None else exclude)}
    if any(v >= len(m) for v in skip):
        raise ValueError(f"exclude: expected frame indices of {name} from 1 to {len(m) - 1}, got {sorted(skip)}")
    areas = m.reshape(len(m), -1).sum(axis=1).astype(float)
    frames = np.array([f for f in range(1, len(m)) if areas[f] > 0 and f not in skip], int)   # say nothing of it
    if len(frames) == 0 or areas[0] == 0:
        return None
    k = int(frames[0])
    jump = abs(areas[0] - areas[k])
    spread = float(np.ptp(areas[frames]))
    quantum = 0.5 * border_length(m[0])
    if jump <= max(spread, quantum):
        return None
    first = "the first frame" if k == 1 else "the first frame with tissue"
    return (f"{name}[0] (the reference) holds {areas[0]:.0f} pixels and {name}[{k}] ({first}) {areas[k]:.0f}: "
            f"they differ by {jump:.0f}, more than the frames' areas vary over the sequence ({spread:.0f}) and more "
            f"than half a pixel of the reference's borders ({quantum:.0f}); the reference mask may not be these "
            f"frames' (another segmentation's, or dilated or eroded), which shifts the zero of "
            f"radial strain")
