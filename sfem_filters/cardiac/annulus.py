"""Synthetic short-axis sequences with a known answer: an annulus moved by the filter's own model.

:func:`annulus_sequence` draws a sequence from exactly the generative model that
:func:`sfem_filters.cardiac.measured.build_model` assumes (penalty drive by the landmarks'
previous measurement, elastically correlated process noise, measurement noise), optionally
with an undeclared effect on top; :func:`deformed_masks` rasterises its myocardium per frame
for the image front end. Sequences are in pixels, as measured ones are.
"""
from __future__ import annotations

import numpy as np
from matplotlib.path import Path

from ..fem.dofs import node_dofs
from ..fem.elasticity import stiffness_matrix
from . import measured
from .effects import build_effects
from .sequence import make_sequence

__all__ = ["annulus_mask", "annulus_sequence", "deformed_masks"]


def annulus_mask(r_inner: float = 8.0, r_outer: float = 12.0, size: int = 32) -> np.ndarray:
    """A ring of pixels (radii in pixels) like a short-axis myocardium."""
    yy, xx = np.mgrid[0:size, 0:size]
    c = (size - 1) / 2.0
    r = np.hypot(xx - c, yy - c)
    return (r >= r_inner) & (r <= r_outer)


def annulus_sequence(effect: str | None = None, amplitude=(0.15, -0.3), seed: int = 0, n_frames: int = 24,
                     noise_px: float = 0.05, landmark_step_px: float = 0.15, landmarks: int = 8,
                     frame_interval: float = 0.03, pixel_spacing: float = 1e-3, return_truth: bool = False,
                     beta: float | None = None):
    """A sequence drawn from the filter's own generative model on a synthetic annulus.

    Every pixel of :func:`annulus_mask` is a point. The motion follows exactly the model that
    :func:`sfem_filters.cardiac.measured.build_model` builds (causal penalty drive by the landmarks'
    previous measurement, elastically correlated process noise of the spring targets with
    ``landmark_step_px`` per frame, measurement noise ``noise_px``), plus, when ``effect`` names
    one, that undeclared load with amplitudes ``amplitude`` (units of ``NOMINAL["E"]``) shaped
    as a systolic bell in time. With ``effect=None`` a correct baseline filter is consistent
    with the data by construction: what the diagnostics must not flag.

    ``beta`` (s) overrides the model's Rayleigh stiffness coefficient (see
    :func:`sfem_filters.cardiac.measured.build_model`).

    Returns a :class:`sfem_filters.cardiac.sequence.Sequence` in pixels; with ``return_truth`` also a
    dict of the noise-free ``displacement`` (F, P, 2) px and ``velocity`` (F, P, 2) px/s.
    """
    rng = np.random.default_rng(seed)
    mask = annulus_mask()
    rows, cols = np.nonzero(mask)
    pts = np.column_stack([cols, rows]).astype(float)
    stub = make_sequence(pts, np.zeros((n_frames, len(pts), 2)), frame_interval=frame_interval,
                         pixel_spacing=pixel_spacing, reference_mask=mask)
    setup = measured.prepare(stub, landmarks)
    setup.noise_px = noise_px
    model, _ = measured.build_model(setup, (), "penalty", "none", landmark_step_px=landmark_step_px, beta=beta)
    s = pixel_spacing
    system = model.system()
    nx = model.dim_x
    L = np.linalg.cholesky(model.Q[:nx, :nx] + 1e-30 * np.eye(nx))
    n_dofs = setup.mesh.n_dofs
    G = np.zeros((n_dofs, 0))
    a = np.zeros((n_frames, 0))
    if effect is not None:
        eff = build_effects([effect], setup.mesh, setup.geometry, scale=measured.NOMINAL["E"])[0]
        G = eff.loads
        bell = np.sin(np.pi * np.arange(n_frames) / (n_frames - 1)) ** 2
        a = bell[:, None] * np.broadcast_to(np.asarray(amplitude, float)[: G.shape[1]], (G.shape[1],))[None]
    k = measured.NOMINAL["penalty"] * np.median(
        stiffness_matrix(setup.mesh, model.material.E, model.material.nu).diagonal())
    lm_dofs = node_dofs(setup.landmarks)
    x = model.x0[:nx].copy()
    disp = np.empty((n_frames, len(pts), 2))
    true_u = np.empty_like(disp)
    true_v = np.empty_like(disp)
    for t in range(n_frames):
        if t > 0:
            w = np.zeros(n_dofs)
            w[lm_dofs] = k * disp[t - 1][setup.landmarks].reshape(-1) * s      # measured, previous frame
            w = w + G @ a[t]
            x = system.step(x, model.dofmap.restrict(w)) + L @ rng.standard_normal(nx)
        U = model.displacements(x).reshape(-1, 2) / s
        true_u[t] = U
        true_v[t] = model.velocities(x).reshape(-1, 2) / s
        disp[t] = U + rng.standard_normal(U.shape) * noise_px / np.sqrt(2.0)
    seq = make_sequence(pts, disp, frame_interval=frame_interval, pixel_spacing=pixel_spacing,
                         reference_mask=mask, provenance=f"sfem_filters.synthetic.annulus_sequence(effect={effect!r}, "
                                                         f"seed={seed})")
    return (seq, {"displacement": true_u, "velocity": true_v}) if return_truth else seq


def deformed_masks(seq, displacement=None) -> np.ndarray:
    """Myocardium masks of every frame of a pixel-lattice sequence, from its deformed borders.

    The boundary loops of the sequence's mesh (nodes at the tissue pixel centres) are moved by
    ``displacement`` (F, P, 2) px (default the sequence's), pushed half a pixel outward (the
    epicardium) or inward into the cavity (the endocardium) so that they enclose whole pixels,
    and rasterised at the pixel centres of an image the size of ``seq.reference_mask``.
    """
    if seq.reference_mask is None:
        raise ValueError("seq: expected a sequence with a reference_mask (it sets the image size)")
    U = seq.displacement if displacement is None else np.asarray(displacement, float)
    setup = measured.prepare(seq, 3)
    geo = setup.geometry
    s = setup.spacing
    H, W = seq.reference_mask.shape
    yy, xx = np.mgrid[0:H, 0:W]
    grid = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    out = np.zeros((len(U), H, W), bool)
    centre = geo.centre / s
    for t in range(len(U)):
        X = seq.points + np.nan_to_num(U[t])
        loops = []
        for loop, sign in ((geo.epi, 0.5), (geo.endo, -0.5)):
            P = X[loop]
            r = P - centre
            loops.append(P + sign * r / np.linalg.norm(r, axis=1, keepdims=True))
        inside = Path(loops[0]).contains_points(grid) & ~Path(loops[1]).contains_points(grid)
        out[t] = inside.reshape(H, W)
    return out

