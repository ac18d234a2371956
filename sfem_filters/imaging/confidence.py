"""Confidence in image-derived data and the covariances it weights (Shi & Liu 2003, sec. 2.6).

Two kinds of datum, two measures:

* boundary displacements from shape matching: the bending energy of a match (Eq. 35), its
  goodness ``m_g`` and uniqueness ``m_u`` (Eq. 36), and the confidence ``c`` (Eq. 37);
* phase-contrast velocities: the local phase coherence ``LPC`` over the 8 neighbours of a pixel
  (Eqs. 38-39).

Each datum's error variance is then ``floor^2 + scale^2 (1 - c)`` (or ``1 - LPC``): the paper
weights the displacement and velocity error covariances by ``1 - c`` and ``1 - LPC``; the floor
keeps a perfectly confident datum from getting zero variance (a singular R).

The paper gives the structure of these measures; where it leaves a constant or a normalisation
open, the choice here is stated in the docstring.
"""
from __future__ import annotations

import numpy as np

from .._validate import as_float_array, non_negative, positive


# ---------------------------------------------------------------- shape matching (Eqs. 35-37)
def bending_energy(kappa_a, kappa_b) -> np.ndarray:
    """Bending energy of deforming a curve point of curvature ``kappa_a`` into ``kappa_b`` (Eq. 35).

    For a 2D contour the energy (per unit length, unit flexural rigidity) of bending a thin
    elastic rod from one curvature into the other is ``(kappa_a - kappa_b)^2 / 2``.

    Parameters
    ----------
    kappa_a, kappa_b : array_like
        Curvatures (1/px or 1/m, the same unit for both); broadcast against each other.
    """
    a = np.asarray(kappa_a, float)
    b = np.asarray(kappa_b, float)
    return 0.5 * (a - b) ** 2


def segment_bending_energy(kappa_a, kappa_b, i, j, half_width: int) -> np.ndarray:
    """Mean bending energy of matching the contour segment centred on ``i`` onto that centred on ``j``.

    The segments are ``i-h..i+h`` of contour a and ``j-h..j+h`` of contour b (indices wrap),
    ``h = half_width``; ``h = 0`` is the point-wise energy of Eq. 35. Averaging over a short
    segment makes the match robust to the pixel noise of a single curvature sample.

    Parameters
    ----------
    kappa_a, kappa_b : 1D arrays
        Curvature along each closed contour.
    i : int array, shape (p,)
        Points of contour a.
    j : int array, shape (p, w)
        Candidate points of contour b for each ``i``.
    """
    ka = np.asarray(kappa_a, float)
    kb = np.asarray(kappa_b, float)
    offs = np.arange(-int(half_width), int(half_width) + 1)
    i = np.asarray(i)[:, None, None] + offs                      # (p, 1, s)
    j = np.asarray(j)[:, :, None] + offs                         # (p, w, s)
    return bending_energy(ka[np.mod(i, len(ka))], kb[np.mod(j, len(kb))]).mean(axis=2)


def goodness_uniqueness(energies, tie_order=None) -> tuple:
    """Goodness ``m_g`` and uniqueness ``m_u`` of the best match among candidates (Eq. 36).

    Parameters
    ----------
    energies : (p, w) array
        Bending energy of each of ``w`` candidates in the search window of each of ``p`` points.
    tie_order : (w,) array, optional
        Among candidates of equal least energy (to 1e-12 relative) the one with the smallest
        ``tie_order`` wins (default: the first).

    Returns
    -------
    best : (p,) int
        Index of the candidate of least energy.
    m_g : (p,) array
        That least energy (small: a good match).
    m_u : (p,) array in [0, 1]
        ``m_g`` over the mean energy of the window (small: a unique match; 1: every candidate
        fits equally well, e.g. along a circular arc).
    """
    e = as_float_array("energies", energies, shape=(None, None))
    if e.shape[1] < 2:
        raise ValueError(f"energies: expected at least 2 candidates per point, got {e.shape[1]}")
    if tie_order is None:
        best = np.argmin(e, axis=1)
    else:
        least = e.min(axis=1, keepdims=True)
        tied = e <= least + 1e-12 * np.abs(least)
        best = np.argmin(np.where(tied, np.asarray(tie_order, float)[None], np.inf), axis=1)
    m_g = e[np.arange(len(e)), best]
    mean = e.mean(axis=1)
    m_u = np.divide(m_g, mean, out=np.ones_like(m_g), where=mean > 0)
    return best, m_g, m_u


def match_confidence(m_g, m_u, g_scale: float, k_g: float = 1.0, k_u: float = 1.0) -> np.ndarray:
    """Confidence ``c`` in [0, 1] of a shape match (Eq. 37).

    ``c = 1 / ((1 + k_g m_g / g_scale) (1 + k_u m_u))``: the paper's product of a goodness and a
    uniqueness term, each of the form ``1 / (k1 + k2 m)``, with ``k1 = 1`` so that a perfect,
    unique match (``m_g = m_u = 0``) has ``c = 1`` and ``c`` decreases towards 0 as either gets
    worse; ``g_scale`` makes ``m_g`` dimensionless (for example the median ``m_g`` of the
    frame, in the unit of ``m_g``).
    """
    m_g = as_float_array("m_g", m_g)
    m_u = as_float_array("m_u", m_u)
    if np.any(m_g < 0) or np.any(m_u < 0):
        raise ValueError("m_g, m_u: expected non-negative goodness and uniqueness measures")
    positive("g_scale", g_scale)
    non_negative("k_g", k_g)
    non_negative("k_u", k_u)
    return 1.0 / ((1.0 + k_g * m_g / g_scale) * (1.0 + k_u * m_u))


# ------------------------------------------------------------- phase coherence (Eqs. 38-39)
_NEIGHBOURS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


def phase_of_velocity(v, venc: float) -> np.ndarray:
    """MR phase (rad) that encodes velocity ``v`` (m/s): ``phi = pi v / venc`` (``venc`` in m/s)."""
    positive("venc", venc, "m/s")
    return np.pi * np.asarray(v, float) / venc


def local_phase_coherence(phase) -> np.ndarray:
    """Local phase coherence of a phase image over each pixel's 8 neighbours (Eqs. 38-39).

    Eq. 38 (phase differences): ``d_n = wrap(phi(n) - phi(p))`` for the 8 neighbours ``n`` of
    pixel ``p``. Eq. 39 (coherence): the mean resultant length of those differences,
    ``LPC(p) = |mean_n exp(i d_n)|`` in [0, 1]: 1 where the phase is locally smooth (tissue
    with good signal), low where it is random (noise, low signal, borders). Neighbours outside
    the image are left out of the mean.

    Parameters
    ----------
    phase : (H, W) or (F, H, W) array
        Phase in radians (wrapped or not), per frame when 3D.
    """
    ph = np.asarray(phase, float)
    if ph.ndim not in (2, 3):
        raise ValueError(f"phase: expected an (H, W) or (F, H, W) array, got shape {ph.shape}")
    if not np.all(np.isfinite(ph)):
        raise ValueError("phase: expected finite phases, got NaN or inf")
    single = ph.ndim == 2
    ph = ph[None] if single else ph
    z = np.exp(1j * ph)
    pad = np.pad(z, ((0, 0), (1, 1), (1, 1)))                  # zeros outside: left out of the sum
    cnt = np.pad(np.ones(ph.shape[1:]), 1)
    H, W = ph.shape[1:]
    acc = np.zeros(ph.shape, complex)
    n = np.zeros((H, W))
    for dr, dc in _NEIGHBOURS:
        acc += pad[:, 1 + dr:1 + dr + H, 1 + dc:1 + dc + W]
        n += cnt[1 + dr:1 + dr + H, 1 + dc:1 + dc + W]
    lpc = np.abs(acc * np.conj(z)) / n
    return lpc[0] if single else lpc


def velocity_coherence(velocity, venc: float) -> np.ndarray:
    """LPC of a two-component velocity image: the smaller of the x and y coherences.

    Parameters
    ----------
    velocity : (..., H, W, 2) array
        Phase-contrast velocity (m/s), x then y component.
    venc : float
        Velocity encoding (m/s): the velocity that maps to a phase of pi.
    """
    v = np.asarray(velocity, float)
    if v.ndim not in (3, 4) or v.shape[-1] != 2:
        raise ValueError(f"velocity: expected an (H, W, 2) or (F, H, W, 2) array, got shape {v.shape}")
    cx = local_phase_coherence(phase_of_velocity(v[..., 0], venc))
    cy = local_phase_coherence(phase_of_velocity(v[..., 1], venc))
    return np.minimum(cx, cy)


# ----------------------------------------------------------------------- covariance weights
def weighted_std(confidence, scale: float, floor: float) -> np.ndarray:
    """Error standard deviation of data with confidence ``c``: ``sqrt(floor^2 + scale^2 (1 - c))``.

    The paper weights a datum's error covariance by ``1 - c`` (``c`` the shape-match
    confidence, or the LPC of a velocity); ``floor`` (> 0) is the error of a fully trusted
    datum. ``scale`` and ``floor`` share the data's unit (px, m, or m/s).
    """
    c = as_float_array("confidence", confidence)
    if np.any((c < 0) | (c > 1)):
        raise ValueError("confidence: expected values in [0, 1]")
    non_negative("scale", scale)
    positive("floor", floor)
    return np.sqrt(floor ** 2 + scale ** 2 * (1.0 - c))
