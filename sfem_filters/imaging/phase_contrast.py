"""Phase-contrast MR velocity as filter data: sampling, coherence, covariance (sec. 2.6, Eq. 13).

Velocity images hold the in-plane velocity (vx, vy) in m/s of every pixel of every frame,
``(F, H, W, 2)``; the phase that encoded them is ``pi v / venc``. At chosen points (pixels,
x = column, y = row) the velocity is sampled bilinearly and its local phase coherence (Eqs.
38-39, :func:`sfem_filters.confidence.velocity_coherence`) sets its error standard deviation
``sqrt(floor^2 + scale^2 (1 - LPC))``. Sequence files store velocities in pixels per second,
so sampled values are divided by the pixel spacing.

The images are sampled at each point's reference (frame-0) position: the myocardium moves a
few pixels over a cycle, small against the scale on which its velocity field varies; the
error this leaves is part of the datum's noise.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates

from .._validate import as_float_array, positive
from .confidence import velocity_coherence, weighted_std


@dataclass(frozen=True, eq=False)
class VelocityData:
    """Velocities sampled at points, with their coherence and error model."""

    points: np.ndarray       # (P, 2) px
    velocity: np.ndarray     # (F, P, 2) px/s
    lpc: np.ndarray          # (F, P) in [0, 1]
    sigma: np.ndarray        # (F, P) px/s, per component


def check_velocity_images(velocity, name: str = "velocity") -> np.ndarray:
    """Check an ``(F, H, W, 2)`` velocity image sequence (m/s, finite)."""
    v = as_float_array(name, velocity, shape=(None, None, None, 2))
    if len(v) < 2:
        raise ValueError(f"{name}: expected at least 2 frames, got {len(v)}")
    return v


def sample_bilinear(image, points) -> np.ndarray:
    """Bilinear samples of ``image`` (H, W, ...) at points (px, x = column, y = row).

    Points must lie within the image (``0 <= x <= W - 1``, ``0 <= y <= H - 1``).
    """
    img = np.asarray(image, float)
    pts = as_float_array("points", points, shape=(None, 2))
    H, W = img.shape[:2]
    if np.any((pts[:, 0] < 0) | (pts[:, 0] > W - 1) | (pts[:, 1] < 0) | (pts[:, 1] > H - 1)):
        raise ValueError(f"points: expected positions inside the {H} x {W} image (x in [0, {W - 1}], "
                         f"y in [0, {H - 1}] px)")
    coords = np.vstack([pts[:, 1], pts[:, 0]])
    if img.ndim == 2:
        return map_coordinates(img, coords, order=1)
    flat = img.reshape(H, W, -1)
    out = np.column_stack([map_coordinates(flat[..., k], coords, order=1) for k in range(flat.shape[2])])
    return out.reshape((len(pts),) + img.shape[2:])


def sample_velocity(velocity, points, venc: float, pixel_spacing: float, floor: float,
                    scale: float | None = None) -> VelocityData:
    """Velocities, LPC and error standard deviations at points (Eqs. 38-39).

    Parameters
    ----------
    velocity : (F, H, W, 2) array
        Phase-contrast velocity images, m/s.
    points : (P, 2) array
        Sample positions, px.
    venc : float
        Velocity encoding, m/s (phase pi).
    pixel_spacing : float
        Pixel size, m.
    floor : float
        Error standard deviation of a fully coherent velocity, m/s (> 0).
    scale : float, optional
        Error model ``sqrt(floor^2 + scale^2 (1 - LPC))``, m/s. The default ``venc / pi``
        makes it the noise that explains the coherence: a phase noise of standard deviation
        ``s`` (rad) on each pixel gives neighbour differences of variance ``2 s^2`` and an
        expected coherence ``exp(-s^2)``, so ``1 - LPC ~ s^2`` and the velocity noise
        ``venc s / pi`` has variance ``(venc / pi)^2 (1 - LPC)`` for small noise.

    Returns
    -------
    VelocityData
        Velocities and standard deviations converted to px/s.
    """
    v = check_velocity_images(velocity)
    positive("pixel_spacing", pixel_spacing, "m")
    lpc_img = velocity_coherence(v, venc)
    pts = as_float_array("points", points, shape=(None, 2))
    samples = np.stack([sample_bilinear(v[t], pts) for t in range(len(v))])
    r = np.rint(pts).astype(int)
    lpc = np.clip(lpc_img[:, r[:, 1], r[:, 0]], 0.0, 1.0)
    sigma = weighted_std(lpc, venc / np.pi if scale is None else scale, floor)
    return VelocityData(points=pts, velocity=samples / pixel_spacing, lpc=lpc, sigma=sigma / pixel_spacing)


def wrap_velocity(v, venc: float) -> np.ndarray:
    """Velocity (m/s) as phase contrast measures it: aliased into ``[-venc, venc)``."""
    positive("venc", venc, "m/s")
    return np.mod(np.asarray(v, float) + venc, 2 * venc) - venc


def synthetic_phase_contrast(velocity, mask, venc: float, noise_mid: float, noise_border: float,
                             depth, seed: int = 0) -> np.ndarray:
    """Noisy phase-contrast velocity images of a known velocity field.

    Inside the tissue the noise standard deviation grows from ``noise_mid`` at mid-wall to
    ``noise_border`` at the borders, quadratically in ``|2 depth - 1|`` (``depth`` 0 at the
    endocardium, 1 at the epicardium), as partial volume and low signal make the borders noisy
    in practice; outside the tissue there is no signal and the phase is uniformly random.

    Parameters
    ----------
    velocity : (F, H, W, 2) array
        True velocity, m/s (values outside the tissue are ignored).
    mask : (H, W) bool array
        Tissue pixels.
    venc : float
        Velocity encoding, m/s.
    noise_mid, noise_border : float
        Noise standard deviations, m/s.
    depth : (H, W) array
        Transmural depth of each tissue pixel in [0, 1].
    seed : int
        Seed of the noise (numpy default_rng).
    """
    v = check_velocity_images(velocity)
    m = np.asarray(mask, bool)
    positive("noise_mid", noise_mid, "m/s")
    positive("noise_border", noise_border, "m/s")
    rng = np.random.default_rng(seed)
    sd = noise_mid + (noise_border - noise_mid) * np.abs(2 * np.asarray(depth, float) - 1) ** 2
    noisy = v + rng.standard_normal(v.shape) * sd[None, :, :, None]
    out = wrap_velocity(noisy, venc)
    outside = ~m
    out[:, outside] = rng.uniform(-venc, venc, size=(len(v), int(outside.sum()), 2))
    return out
