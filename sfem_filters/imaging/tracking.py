"""Shape-based tracking of the myocardial borders through a cycle (Shi & Liu 2003, Eqs. 35-37).

Each point of frame t's contour is matched to the point of frame t+1's contour, within a search
window, whose neighbourhood needs the least bending energy to deform into its own (Eq. 35).
The goodness and uniqueness of the match (Eq. 36) give its confidence (Eq. 37). The raw match
vectors are then smoothed along the contour with the confidences as weights (the optimal
smoothing step of shape-based tracking: a confident match pulls its neighbours, an ambiguous
one follows them), and the points move on to the next frame. Chaining the steps gives
trajectories over the whole cycle.

Units are pixels (x = column, y = row), as in :mod:`sfem_filters.imaging.contours`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .._validate import non_negative, positive
from .confidence import goodness_uniqueness, match_confidence, segment_bending_energy, weighted_std
from .contours import closest_on_polyline, curvature, mask_borders, mended_masks_summarised, smooth_closed


@dataclass(frozen=True)
class TrackingOptions:
    """Settings of boundary tracking (lengths in pixels unless said otherwise).

    Attributes
    ----------
    n_endo, n_epi : int
        Contour points per frame (equal arc length): the tracked points are frame 0's.
    window : int
        Search window: candidates are the ``2 window + 1`` contour points around the one
        nearest to the point's position (in contour points).
    half_width : int
        Half-length (contour points) of the segment whose bending energy is compared.
    curvature_smoothing : float
        Gaussian smoothing (contour points) of each contour before curvature is taken.
    regularisation : float
        Weight of the first-difference penalty in the confidence-weighted smoothing of match
        vectors (dimensionless; 0 keeps the raw matches).
    k_g, k_u : float
        Constants of the confidence (Eq. 37).
    sigma_floor, sigma_scale : float
        Error model of one tracking step: ``sqrt(floor^2 + scale^2 (1 - c))`` px.
    start_deg : float
        Where every frame's contours start (:func:`sfem_filters.imaging.mask_borders`), degrees
        about the cavity centre from +x towards +y.
    """

    n_endo: int = 48
    n_epi: int = 64
    window: int = 2
    half_width: int = 3
    curvature_smoothing: float = 2.0
    regularisation: float = 50.0
    k_g: float = 1.0
    k_u: float = 1.0
    sigma_floor: float = 0.3
    sigma_scale: float = 1.0
    start_deg: float = 0.0

    def __post_init__(self):
        for name in ("n_endo", "n_epi"):
            v = getattr(self, name)
            if int(v) != v or v < 8:
                raise ValueError(f"{name}: expected an integer >= 8 contour points, got {v!r}")
        for name in ("window", "half_width"):
            v = getattr(self, name)
            if int(v) != v or v < (1 if name == "window" else 0):
                raise ValueError(f"{name}: expected a {'positive' if name == 'window' else 'non-negative'} "
                                 f"integer number of contour points, got {v!r}")
        for name in ("curvature_smoothing", "regularisation", "k_g", "k_u", "sigma_scale"):
            non_negative(name, getattr(self, name))
        positive("sigma_floor", self.sigma_floor, "px")
        if not np.isfinite(float(self.start_deg)):
            raise ValueError(f"start_deg: expected a finite angle in degrees, got {self.start_deg!r}")


@dataclass(frozen=True, eq=False)
class Match:
    """One frame-to-frame match of contour a onto contour b."""

    target: np.ndarray        # (p, 2) matched point of contour b for each point (px)
    index: np.ndarray         # (p,) its index on contour b
    m_g: np.ndarray           # (p,) goodness (bending energy of the best candidate, 1/px^2)
    m_u: np.ndarray           # (p,) uniqueness in [0, 1]


@dataclass(frozen=True, eq=False)
class BoundaryTracks:
    """Trajectories of tracked border points over a sequence of frames.

    Attributes
    ----------
    points : (P, 2) array
        Frame-0 position (px) of each tracked point, endocardium first.
    contour : (P,) int array
        0 for endocardial, 1 for epicardial points.
    positions : (F, P, 2) array
        Position (px) in each frame.
    step_confidence : (F, P) array in [0, 1]
        Confidence c (Eq. 37) of the match that brought the point into frame t (1 at frame 0).
    m_g, m_u : (F, P) arrays
        Goodness and uniqueness of those matches (0 at frame 0).
    sigma : (F, P) array
        Displacement error standard deviation (px): the step errors ``floor^2 + scale^2 (1 - c)``
        accumulated along the chain of matches.
    borders : list of Borders
        The contours of every frame.
    """

    points: np.ndarray
    contour: np.ndarray
    positions: np.ndarray
    step_confidence: np.ndarray
    m_g: np.ndarray
    m_u: np.ndarray
    sigma: np.ndarray
    borders: list

    @property
    def displacement(self) -> np.ndarray:
        """(F, P, 2) displacement from frame 0 (px), Lagrangian."""
        return self.positions - self.points[None]


def contour_curvature(xy, smoothing: float) -> np.ndarray:
    """Curvature (1/px) of a closed contour after Gaussian smoothing of ``smoothing`` points."""
    return curvature(smooth_closed(xy, smoothing))


def _nearest_index(xy, points):
    d = np.sum((np.asarray(points)[:, None] - xy[None]) ** 2, axis=2)
    return np.argmin(d, axis=1)


def match_points(points, a, kappa_a, b, kappa_b, window: int, half_width: int) -> Match:
    """Match points lying on contour ``a`` to contour ``b`` by least bending energy (Eqs. 35-36).

    Parameters
    ----------
    points : (p, 2) array
        Positions (px) on or near contour ``a``.
    a, b : (na, 2), (nb, 2) arrays
        Closed contours of frames t and t+1 (px), same orientation.
    kappa_a, kappa_b : arrays
        Their curvatures (1/px).
    window, half_width : int
        Candidates ``nearest +- window`` on b; segments of ``2 half_width + 1`` points.
    """
    i = _nearest_index(a, points)
    j0 = _nearest_index(b, points)
    offs = np.arange(-int(window), int(window) + 1)
    cand = np.mod(j0[:, None] + offs[None], len(b))
    e = segment_bending_energy(kappa_a, kappa_b, i, cand, half_width)
    # ties (equal energies, e.g. along a circular arc) go to the candidate nearest the point
    best, m_g, m_u = goodness_uniqueness(e, tie_order=np.abs(offs))
    j = cand[np.arange(len(cand)), best]
    return Match(target=b[j], index=j, m_g=m_g, m_u=np.minimum(m_u, 1.0))


def smooth_vectors(vectors, weights, regularisation: float) -> np.ndarray:
    """Confidence-weighted smoothing of vectors along a closed contour.

    Minimises ``sum_i w_i |d_i - v_i|^2 + lambda sum_i |d_(i+1) - d_i|^2`` (indices wrap), i.e.
    solves ``(W + lambda L) d = W v`` with L the periodic path Laplacian.

    Parameters
    ----------
    vectors : (p, 2) array
        Raw match vectors (px).
    weights : (p,) array
        Non-negative weights (the match confidences); not all zero.
    regularisation : float
        ``lambda`` (>= 0).
    """
    v = np.asarray(vectors, float)
    w = np.asarray(weights, float)
    if not np.any(w > 0):
        raise ValueError("weights: expected some positive confidence on the contour, got all zero")
    if regularisation == 0:
        return v.copy()
    p = len(v)
    idx = np.arange(p)
    nxt = np.mod(idx + 1, p)
    L = sp.coo_matrix((np.concatenate([np.full(p, 2.0), -np.ones(p), -np.ones(p)]),
                       (np.concatenate([idx, idx, nxt]), np.concatenate([idx, nxt, idx]))), shape=(p, p))
    A = (sp.diags(w) + regularisation * L).tocsc()
    return np.column_stack([spla.spsolve(A, w * v[:, k]) for k in range(2)])


def _step(points, a, ka, b, kb, opts, g_scale):
    m = match_points(points, a, ka, b, kb, opts.window, opts.half_width)
    c = match_confidence(m.m_g, m.m_u, g_scale, opts.k_g, opts.k_u)
    d = smooth_vectors(m.target - points, c, opts.regularisation)
    new, _, _ = closest_on_polyline(b, points + d)
    return new, m, c


def track_borders(borders, options: TrackingOptions | None = None) -> BoundaryTracks:
    """Track frame 0's contour points through a sequence of :class:`Borders` (Eqs. 35-37).

    The goodness scale of Eq. 37 is the median goodness of matching every contour point of
    every frame pair, so that confidences are comparable across frames.
    """
    opts = options or TrackingOptions()
    if len(borders) < 2:
        raise ValueError(f"borders: expected at least 2 frames, got {len(borders)}")
    kap = [(contour_curvature(b.endo, opts.curvature_smoothing), contour_curvature(b.epi, opts.curvature_smoothing))
           for b in borders]
    # goodness scale over the whole sequence
    all_g = []
    for t in range(len(borders) - 1):
        for k, name in enumerate(("endo", "epi")):
            a, b = getattr(borders[t], name), getattr(borders[t + 1], name)
            all_g.append(match_points(a, a, kap[t][k], b, kap[t + 1][k], opts.window, opts.half_width).m_g)
    g_scale = float(np.median(np.concatenate(all_g)))
    if not g_scale > 0:
        g_scale = float(np.mean(np.concatenate(all_g))) or 1.0
    F = len(borders)
    start = [borders[0].endo, borders[0].epi]
    P = sum(len(s) for s in start)
    pos = np.empty((F, P, 2))
    conf = np.ones((F, P))
    mg = np.zeros((F, P))
    mu = np.zeros((F, P))
    pos[0] = np.concatenate(start)
    sl = [slice(0, len(start[0])), slice(len(start[0]), P)]
    for t in range(F - 1):
        for k, name in enumerate(("endo", "epi")):
            a, b = getattr(borders[t], name), getattr(borders[t + 1], name)
            new, m, c = _step(pos[t, sl[k]], a, kap[t][k], b, kap[t + 1][k], opts, g_scale)
            pos[t + 1, sl[k]] = new
            conf[t + 1, sl[k]] = c
            mg[t + 1, sl[k]] = m.m_g
            mu[t + 1, sl[k]] = m.m_u
    step_sd = weighted_std(conf, opts.sigma_scale, opts.sigma_floor)
    step_var = step_sd ** 2
    step_var[0] = opts.sigma_floor ** 2                 # the frame-0 contour's own position error
    sigma = np.sqrt(np.cumsum(step_var, axis=0))
    contour = np.concatenate([np.zeros(len(start[0]), int), np.ones(len(start[1]), int)])
    return BoundaryTracks(points=pos[0].copy(), contour=contour, positions=pos, step_confidence=conf,
                          m_g=mg, m_u=mu, sigma=sigma, borders=list(borders))


def track_masks(masks, options: TrackingOptions | None = None) -> BoundaryTracks:
    """Contours of every mask (:func:`sfem_filters.imaging.contours.mask_borders`), then :func:`track_borders`.

    Parameters
    ----------
    masks : (F, H, W) bool array
        Myocardium mask of each frame (one ring around one cavity each).
    """
    opts = options or TrackingOptions()
    m = np.asarray(masks)
    if m.ndim != 3:
        raise ValueError(f"masks: expected an (F, H, W) mask sequence, got shape {m.shape}")
    if len(m) < 2:
        raise ValueError(f"masks: expected at least 2 frames, got {len(m)}")
    with mended_masks_summarised():                     # one warning for every mended mask, not one each
        borders = [mask_borders(m[t], opts.n_endo, opts.n_epi, name=f"masks[{t}]", start_deg=opts.start_deg)
                   for t in range(len(m))]
    return track_borders(borders, opts)
