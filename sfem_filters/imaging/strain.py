"""Green-Lagrange strain on the reference pixel grid, radial and circumferential, global and segmental curves.

Points are reference pixel centres on the integer grid (pixels, x = column, y = row), as
:func:`sfem_filters.imaging.dense.reference_points` gives them; displacements are in pixels,
so the displacement gradient, and the strain, are dimensionless. The deformation gradient is
``F = I + grad u`` (``grad`` with respect to the reference position X), and the Green-Lagrange
strain ``E = (F^T F - I) / 2``, the DENSE and clinical convention, exact for large
deformation and rotation (the small strain ``(grad u + grad u^T) / 2`` is not rotation-free).
Directions about a centre ``c`` (default the centre of mass of the reference mask): radial
``e_r = (X - c) / |X - c|``, circumferential ``e_c`` = ``e_r`` turned by +90 degrees in image
axes, ``(-e_r,y, e_r,x)``; ``Err = e_r . E e_r``, ``Ecc = e_c . E e_c``, ``Ecr = e_c . E e_r``.

>>> import numpy as np
>>> from sfem_filters.imaging.strain import green_strain, strain_on_grid
>>> yy, xx = np.mgrid[0:20, 0:20]
>>> ring = (np.hypot(xx - 9.5, yy - 9.5) >= 4) & (np.hypot(xx - 9.5, yy - 9.5) <= 8)
>>> rows, cols = np.nonzero(ring)
>>> X = np.column_stack([cols, rows]).astype(float)
>>> u = 0.1 * (X - [9.5, 9.5])                                  # a 10% dilation about the centre
>>> s = strain_on_grid(X, u[None])
>>> round(float(s.Ecc.mean()), 6), round(float(s.Err.mean()), 6)  # ((1.1)^2 - 1) / 2
(0.105, 0.105)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy import ndimage

from .._validate import as_float_array, non_negative

__all__ = ["displacement_gradient", "green_strain", "small_strain", "mask_centre", "radial_circumferential",
           "project_strain", "smooth_in_mask", "StrainField", "strain_on_grid", "segment_labels", "global_curve",
           "segment_curves", "curve_peak", "N_SEGMENTS", "StrainEstimate", "json_list", "Z95"]

N_SEGMENTS = 6
#: Two-sided 95% normal quantile.
Z95 = 1.959963984540054


def _grid(points) -> tuple:
    X = as_float_array("points", points, shape=(None, 2))
    if X.size == 0:
        raise ValueError("points: expected at least one reference pixel, got none")
    ij = np.round(X).astype(int)
    if not np.allclose(X, ij, atol=1e-9) or ij.min() < 0:
        raise ValueError("points: expected pixel centres on the non-negative integer grid (x = column, y = row)")
    H, W = ij[:, 1].max() + 3, ij[:, 0].max() + 3
    index = np.full((H, W), -1)
    index[ij[:, 1], ij[:, 0]] = np.arange(len(ij))
    if len(np.unique(index[index >= 0])) != len(ij):
        raise ValueError("points: expected distinct pixels, got repeated ones")
    return ij, index


def _as_frames(displacement, P: int):
    u = as_float_array("displacement", displacement, allow_nan=True)
    single = u.ndim == 2
    u = u[None] if single else u
    if u.ndim != 3 or u.shape[1:] != (P, 2):
        raise ValueError(f"displacement: expected shape (F, {P}, 2) or ({P}, 2) pixels, got {np.shape(displacement)}")
    return u, single


def displacement_gradient(points, displacement) -> np.ndarray:
    """Gradient of the displacement on the reference pixel grid by finite differences.

    Along each axis: central difference ``(u(X + e) - u(X - e)) / 2`` where both neighbours are
    reference points with finite displacement, one-sided where only one is, NaN where none is
    (or the point's own displacement is NaN).

    Parameters
    ----------
    points : (P, 2) array
        Reference pixel centres (integers; x = column, y = row).
    displacement : (F, P, 2) or (P, 2) array
        Displacements (pixels), NaN where untracked.

    Returns
    -------
    (F, P, 2, 2) or (P, 2, 2) array
        ``G[..., i, j] = d u_i / d X_j`` (dimensionless; i, j = 0 for x, 1 for y).
    """
    ij, index = _grid(points)
    P = len(ij)
    u, single = _as_frames(displacement, P)
    ok = np.isfinite(u).all(axis=2)                                  # (F, P)
    upad = np.concatenate([u, np.full((u.shape[0], 1, 2), np.nan)], axis=1)
    okpad = np.concatenate([ok, np.zeros((u.shape[0], 1), bool)], axis=1)
    G = np.full(u.shape[:2] + (2, 2), np.nan)
    for j, (dx, dy) in enumerate(((1, 0), (0, 1))):
        plus = index[ij[:, 1] + dy, ij[:, 0] + dx]
        minus = index[ij[:, 1] - dy, ij[:, 0] - dx]          # index -1 wraps to the padding: -1
        plus, minus = np.where(plus < 0, P, plus), np.where(minus < 0, P, minus)
        okp, okm = okpad[:, plus], okpad[:, minus]
        central = (upad[:, plus] - upad[:, minus]) / 2
        forward = upad[:, plus] - u
        backward = u - upad[:, minus]
        g = np.where((okp & okm)[..., None], central,
                     np.where(okp[..., None], forward, np.where(okm[..., None], backward, np.nan)))
        g[~ok] = np.nan
        G[..., :, j] = g
    return G[0] if single else G


def green_strain(grad) -> np.ndarray:
    """Green-Lagrange strain ``E = (F^T F - I) / 2`` with ``F = I + grad`` (dimensionless, (..., 2, 2))."""
    G = np.asarray(grad, float)
    Fd = np.eye(2) + G
    return 0.5 * (np.swapaxes(Fd, -1, -2) @ Fd - np.eye(2))


def small_strain(grad) -> np.ndarray:
    """Small (infinitesimal) strain ``(grad + grad^T) / 2`` (dimensionless, (..., 2, 2)), for comparison."""
    G = np.asarray(grad, float)
    return 0.5 * (G + np.swapaxes(G, -1, -2))


def mask_centre(mask) -> np.ndarray:
    """Centre of mass (x = column, y = row) of a 2D mask, in pixels."""
    rows, cols = np.nonzero(np.asarray(mask, bool))
    if rows.size == 0:
        raise ValueError("mask: expected some myocardium to take the centre of, got an empty mask")
    return np.array([cols.mean(), rows.mean()])


def radial_circumferential(points, centre) -> tuple:
    """Unit radial and circumferential directions (P, 2) at points about a centre (pixels).

    ``e_c`` is ``e_r`` turned by +90 degrees in image axes (x right, y down): ``(-e_r,y, e_r,x)``.
    A point at the centre itself has no radial direction: an error.
    """
    X = as_float_array("points", points, shape=(None, 2))
    c = as_float_array("centre", centre, shape=(2,))
    d = X - c
    r = np.linalg.norm(d, axis=1)
    if np.any(r < 1e-9):
        raise ValueError(f"centre: expected a centre off every point, got {c.tolist()} on a point")
    er = d / r[:, None]
    ec = np.column_stack([-er[:, 1], er[:, 0]])
    return er, ec


def project_strain(E, points, centre) -> tuple:
    """``(Ecc, Err, Ecr)`` of strain tensors ``E`` (..., P, 2, 2) at points about ``centre``."""
    er, ec = radial_circumferential(points, centre)
    E = np.asarray(E, float)
    err = np.einsum("pi,...pij,pj->...p", er, E, er)
    ecc = np.einsum("pi,...pij,pj->...p", ec, E, ec)
    ecr = np.einsum("pi,...pij,pj->...p", ec, E, er)
    return ecc, err, ecr


def smooth_in_mask(points, values, sigma: float) -> np.ndarray:
    """Gaussian smoothing of values on the reference pixels by normalised convolution.

    The values (with NaN as absent) are scattered on the pixel grid with a weight image that is
    1 where a value is known; ``smoothed = G * (v w) / G * w`` at each point, ``G`` a Gaussian of
    ``sigma`` pixels (truncated at 4 sigma), so nothing outside the mask leaks in.

    Parameters
    ----------
    points : (P, 2) array
        Reference pixel centres (integers).
    values : (F, P, ...) array
        Values at the points per frame (any unit; trailing axes smoothed separately).
    sigma : float
        Gaussian sd (pixels, >= 0); 0 returns the values unchanged.
    """
    non_negative("sigma", sigma, "pixels")
    v = np.asarray(values, float)
    if sigma == 0:
        return v.copy()
    ij, index = _grid(points)
    H, W = index.shape
    F, P = v.shape[:2]
    flat = v.reshape(F, P, -1)
    out = np.full(flat.shape, np.nan)
    for f in range(F):
        for k in range(flat.shape[2]):
            ok = np.isfinite(flat[f, :, k])
            img, w = np.zeros((H, W)), np.zeros((H, W))
            img[ij[ok, 1], ij[ok, 0]] = flat[f, ok, k]
            w[ij[ok, 1], ij[ok, 0]] = 1.0
            num = ndimage.gaussian_filter(img, sigma, mode="constant", truncate=4.0)
            den = ndimage.gaussian_filter(w, sigma, mode="constant", truncate=4.0)
            s = num[ij[:, 1], ij[:, 0]] / np.maximum(den[ij[:, 1], ij[:, 0]], 1e-300)
            out[f, :, k] = np.where(ok, s, np.nan)
    return out.reshape(v.shape)


@dataclass(frozen=True, eq=False)
class StrainField:
    """Strain of every reference pixel at every frame.

    Attributes
    ----------
    points : (P, 2) array
        Reference pixel centres (pixels).
    centre : (2,) array
        Centre of the radial directions (pixels, x, y).
    E : (F, P, 2, 2) array
        Green-Lagrange strain tensor in image axes (fraction).
    Ecc, Err, Ecr : (F, P) arrays
        Circumferential, radial and shear components (fraction); NaN where not computable.
    sigma : float
        Gaussian smoothing (pixels; 0 none) and ``smoothed`` what was smoothed.
    """

    points: np.ndarray
    centre: np.ndarray
    E: np.ndarray
    Ecc: np.ndarray
    Err: np.ndarray
    Ecr: np.ndarray
    sigma: float = 0.0
    smoothed: str = "none"


def strain_on_grid(points, displacement, centre=None, sigma: float = 0.0, smooth: str = "displacement") -> StrainField:
    """Green-Lagrange strain of reference pixels from their displacements, optionally smoothed.

    Parameters
    ----------
    points : (P, 2) array
        Reference pixel centres (integers; x = column, y = row).
    displacement : (F, P, 2) array
        Lagrangian displacements (pixels), NaN where untracked.
    centre : (2,) array, optional
        Centre (pixels, x, y) of the radial directions; default the points' centre of mass.
    sigma : float
        Gaussian smoothing (pixels) inside the mask by :func:`smooth_in_mask`; 0 none.
    smooth : {"displacement", "strain"}
        What is smoothed when ``sigma > 0``: the displacement before differencing, or the
        strain tensor after.
    """
    if smooth not in ("displacement", "strain"):
        raise ValueError(f"smooth: expected 'displacement' or 'strain', got {smooth!r}")
    X = as_float_array("points", points, shape=(None, 2))
    u, _ = _as_frames(displacement, len(X))
    c = X.mean(axis=0) if centre is None else as_float_array("centre", centre, shape=(2,))
    if sigma > 0 and smooth == "displacement":
        u = smooth_in_mask(X, u, sigma)
    E = green_strain(displacement_gradient(X, u))
    if sigma > 0 and smooth == "strain":
        E = smooth_in_mask(X, E, sigma)
    ecc, err, ecr = project_strain(E, X, c)
    return StrainField(points=X, centre=c, E=E, Ecc=ecc, Err=err, Ecr=ecr, sigma=float(sigma),
                       smoothed=smooth if sigma > 0 else "none")


def segment_labels(points, centre, start_deg: float = 0.0) -> np.ndarray:
    """Segment 0-5 of each point: ``floor(((angle - start) mod 360) / 60)``.

    ``angle = atan2(y - cy, x - cx)`` in degrees (image axes: x right, y down, so counted
    from +x towards +y); ``start_deg`` the start of segment 0 (degrees).
    """
    X = as_float_array("points", points, shape=(None, 2))
    c = as_float_array("centre", centre, shape=(2,))
    ang = np.degrees(np.arctan2(X[:, 1] - c[1], X[:, 0] - c[0]))
    k = np.floor(np.mod(ang - float(start_deg), 360.0) / (360.0 / N_SEGMENTS)).astype(int)
    return np.minimum(k, N_SEGMENTS - 1)


def global_curve(values) -> np.ndarray:
    """Mean over points of (F, P) values at each frame, ignoring NaN; NaN only where a frame has none."""
    v = np.asarray(values, float)
    n = np.isfinite(v).sum(axis=1)
    s = np.where(np.isfinite(v), v, 0.0).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, s / np.maximum(n, 1), np.nan)


def segment_curves(values, labels) -> np.ndarray:
    """(6, F) mean of (F, P) values over each segment's points at each frame (NaN ignored)."""
    v = np.asarray(values, float)
    lab = np.asarray(labels, int)
    return np.stack([global_curve(v[:, lab == k]) if np.any(lab == k) else np.full(v.shape[0], np.nan)
                     for k in range(N_SEGMENTS)])


def curve_peak(curve, kind: str) -> tuple:
    """Peak of a curve over frames: ``("min" | "max")`` value and its frame index (NaN ignored)."""
    c = np.asarray(curve, float)
    if kind not in ("min", "max"):
        raise ValueError(f"kind: expected 'min' (Ecc) or 'max' (Err), got {kind!r}")
    if not np.isfinite(c).any():
        return np.nan, -1
    i = int(np.nanargmin(c) if kind == "min" else np.nanargmax(c))
    return float(c[i]), i


@dataclass(frozen=True, eq=False)
class StrainEstimate:
    """Strain of every reference pixel and frame with its sd, and the global and segment curves:
    what every strain route returns (the strain report's JSON names, :meth:`to_dict`; the docs' how-to
    'Strain from your DENSE images' tables them). Strains are
    Green-Lagrange fractions; the curves' ``*_lo`` and ``*_hi`` their 95% band.

    Attributes
    ----------
    points : (P, 2) array
        Reference pixel centres (pixels, x = column, y = row).
    frame_times_s : (F,) array
        Frame times (s); NaN when not given.
    centre : (2,) array
        Centre (pixels) of the radial directions and segments.
    start_deg : float
        Where segment 0 starts (degrees from +x towards +y).
    labels : (P,) int array
        Segment of each point.
    Ecc, Err, Ecr, Ecc_sd, Err_sd : (F, P) arrays
        Strain and sd (NaN where unknown, ``None`` in the JSON).
    global_curves, segment_curves : dict
        ``Ecc``, ``Err``, ``*_sd``, ``*_lo``, ``*_hi``: (F,) and (6, F) arrays.
    displacement : (F, P, 2) array
        The estimate's displacement at the points (pixels).
    seconds : float
        Wall-clock time of the route.
    settings : dict
        The settings used and what was derived from the data.
    """

    ROUTE: ClassVar[str] = ""

    points: np.ndarray
    frame_times_s: np.ndarray
    centre: np.ndarray
    start_deg: float
    labels: np.ndarray
    Ecc: np.ndarray
    Err: np.ndarray
    Ecr: np.ndarray
    Ecc_sd: np.ndarray
    Err_sd: np.ndarray
    global_curves: dict
    segment_curves: dict
    displacement: np.ndarray
    seconds: float
    settings: dict

    def band(self, quantity: str, which: str = "segments") -> tuple:
        """``(lo, hi)`` of a 95% band: quantity ``"Ecc"`` or ``"Err"``; ``"segments"``, ``"global"`` or
        ``"pixels"`` (``+- 1.96`` of the pixels' sd)."""
        if which == "pixels":
            v, sd = getattr(self, quantity), getattr(self, f"{quantity}_sd")
            return v - Z95 * sd, v + Z95 * sd
        d = self.segment_curves if which == "segments" else self.global_curves
        return d[f"{quantity}_lo"], d[f"{quantity}_hi"]

    def to_dict(self) -> dict:
        """The strain report's JSON names (lists, ``None`` for NaN), ``route`` the class's :attr:`ROUTE`;
        ``labels`` the segment of each point, ``displacement`` the estimate's (F, P, 2) in pixels."""
        seg = {"start_deg": self.start_deg, **{k: json_list(v) for k, v in self.segment_curves.items()}}
        return {"route": self.ROUTE, "points": json_list(self.points), "frame_times_s": json_list(self.frame_times_s),
                "centre": json_list(self.centre), "labels": np.asarray(self.labels, int).tolist(),
                "strain": {q: json_list(getattr(self, q)) for q in ("Ecc", "Err", "Ecr", "Ecc_sd", "Err_sd")},
                "global": {k: json_list(v) for k, v in self.global_curves.items()}, "segments": seg,
                "displacement": json_list(self.displacement), "seconds": self.seconds, "settings": self.settings}


def json_list(a) -> list:
    """An array as nested lists for JSON, ``None`` where it is not finite."""
    a = np.asarray(a, float)
    return np.where(np.isfinite(a), a.astype(object), None).tolist()
