"""Synthetic short-axis sequences with a known answer: an annulus moved by the filter's own model.

:func:`annulus_sequence` draws a sequence from exactly the generative model that
:func:`sfem_filters.cardiac.measured.build_model` assumes (penalty drive by the landmarks'
previous measurement, elastically correlated process noise, measurement noise), optionally
with an undeclared effect on top; :func:`deformed_masks` rasterises its myocardium per frame
for the image front end. Sequences are in pixels, as measured ones are.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
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


def annulus_sequence(effect=None, amplitude=(0.15, -0.3), seed: int = 0, n_frames: int = 24,
                     noise_px: float = 0.05, landmark_step_px: float = 0.15, landmarks: int = 8,
                     frame_interval: float = 0.03, pixel_spacing: float = 1e-3, return_truth: bool = False,
                     beta: float | None = None, material=None, drive: str = "penalty", peak_pressure: float = 2e3,
                     truth_element_px: float | None = None):
    """A sequence drawn from the filter's own generative model on a synthetic annulus.

    Every pixel of :func:`annulus_mask` is a point. The motion follows exactly the model that
    :func:`sfem_filters.cardiac.measured.build_model` builds for ``drive``:

    * ``"penalty"``: causal penalty drive by the landmarks' previous measurement, elastically
      correlated process noise of the spring targets with ``landmark_step_px`` per frame;
    * ``"pressure"``: a cavity pressure ``peak_pressure sin^2(pi t / (F - 1))`` (Pa) on the
      endocardium, recorded in the sequence's ``pressure``, and the model's own process noise;

    with measurement noise ``noise_px``, plus undeclared loads: ``effect`` names one effect of
    :data:`sfem_filters.cardiac.effects.CATALOGUE` (with ``amplitude`` its amplitudes, units of
    ``NOMINAL["E"]``) or several (a sequence of names, ``amplitude`` a sequence of amplitude
    tuples), each shaped as a systolic bell in time. With ``effect=None`` a correct baseline
    filter is consistent with the data by construction: what the diagnostics must not flag.

    ``beta`` (s) overrides the model's Rayleigh stiffness coefficient and ``material`` (a
    :class:`sfem_filters.fem.material.Material` of the annulus mesh, for example another stiffness
    scale) the nominal uniform material of the motion (see
    :func:`sfem_filters.cardiac.measured.build_model`); the process noise stays the filter model's
    (whose random spring loads act through the nominal material's dynamics), so that a model
    estimating the material is right about everything else.

    ``truth_element_px`` (pixels) draws the motion on a mesh chosen apart from the pixels instead
    (:func:`sfem_filters.cardiac.myocardium.polar_mesh` with edges of about that size, finer than
    any estimator's), sampled at the pixel centres through its shape functions, the springs pulling
    at the landmarks through them too: then every estimator's mesh, the node-per-pixel one
    included, pays its own discretisation error (no inverse crime in favour of the generator's
    mesh). The default ``None`` draws on the node-per-pixel mesh, as every frozen result so far.

    Returns a :class:`sfem_filters.cardiac.sequence.Sequence` in pixels; with ``return_truth`` also a
    dict of the noise-free ``displacement`` (F, P, 2) px and ``velocity`` (F, P, 2) px/s.
    """
    if drive not in ("penalty", "pressure"):
        raise ValueError(f"drive: expected 'penalty' or 'pressure', got {drive!r}")
    names = [] if effect is None else [effect] if isinstance(effect, str) else list(effect)
    amps = [amplitude] if isinstance(effect, str) else list(amplitude) if names else []
    if len(amps) != len(names):
        raise ValueError(f"amplitude: expected one amplitude tuple per effect ({len(names)}), got {len(amps)}")
    rng = np.random.default_rng(seed)
    mask = annulus_mask()
    rows, cols = np.nonzero(mask)
    pts = np.column_stack([cols, rows]).astype(float)
    bell = np.sin(np.pi * np.arange(n_frames) / (n_frames - 1)) ** 2
    extra = {"pressure": peak_pressure * bell} if drive == "pressure" else {}
    stub = make_sequence(pts, np.zeros((n_frames, len(pts), 2)), frame_interval=frame_interval,
                         pixel_spacing=pixel_spacing, reference_mask=mask, **extra)
    if truth_element_px is None:
        setup = measured.prepare(stub, landmarks)
    else:
        if not (np.isfinite(truth_element_px) and truth_element_px > 0):
            raise ValueError(f"truth_element_px: expected a positive element size in pixels or None, "
                             f"got {truth_element_px!r}")
        setup = measured.prepare(stub, landmarks, mesh="polar", element_px=float(truth_element_px))
    setup.noise_px = noise_px
    opts = {"landmark_step_px": landmark_step_px, "beta": beta}
    model, _ = measured.build_model(setup, (), drive, "none", **opts)
    s = pixel_spacing
    nx = model.dim_x
    # the process noise of the filter's model (its random spring loads reach the tissue through the
    # nominal material's dynamics, as the model assumes), the motion through the given material's
    L = np.linalg.cholesky(model.Q[:nx, :nx] + 1e-30 * np.eye(nx))
    if material is not None:
        model, _ = measured.build_model(setup, (), drive, "none", material=material, **opts)
    system = model.system()
    n_dofs = setup.mesh.n_dofs
    G, a = [np.zeros((n_dofs, 0))], [np.zeros((n_frames, 0))]
    for name, amp in zip(names, amps):
        eff = build_effects([name], setup.mesh, setup.geometry, scale=measured.NOMINAL["E"])[0]
        k_eff = eff.loads.shape[1]
        G.append(eff.loads)
        a.append(bell[:, None] * np.broadcast_to(np.asarray(amp, float)[:k_eff], (k_eff,))[None])
    G, a = np.hstack(G), np.hstack(a)
    k = measured.NOMINAL["penalty"] * np.median(stiffness_matrix(
        setup.mesh, measured.NOMINAL["E"] * np.ones(setup.mesh.n_elements),
        measured.NOMINAL["nu"] * np.ones(setup.mesh.n_elements)).diagonal())
    # the springs' pull at the landmarks: on their nodes, or through the shape functions (D^T k b)
    spread = (sp.csr_matrix((np.ones(2 * len(setup.landmarks)), (node_dofs(setup.landmarks),
                                                                   np.arange(2 * len(setup.landmarks)))),
                            shape=(n_dofs, 2 * len(setup.landmarks)))
              if setup.interpolation is None else measured.point_rows(setup, setup.landmarks).T.tocsr())
    x = model.x0[:nx].copy()
    disp = np.empty((n_frames, len(pts), 2))
    true_u = np.empty_like(disp)
    true_v = np.empty_like(disp)
    for t in range(n_frames):
        if t > 0:
            if drive == "penalty":
                w = spread @ (k * disp[t - 1][setup.landmarks].reshape(-1) * s)    # measured, previous frame
            else:
                w = model.loads[t].copy()
            w = w + G @ a[t]
            x = system.step(x, model.dofmap.restrict(w)) + L @ rng.standard_normal(nx)
        U = measured.at_points(setup, model.displacements(x).reshape(-1, 2)) / s
        true_u[t] = U
        true_v[t] = measured.at_points(setup, model.velocities(x).reshape(-1, 2)) / s
        disp[t] = U + rng.standard_normal(U.shape) * noise_px / np.sqrt(2.0)
    seq = make_sequence(pts, disp, frame_interval=frame_interval, pixel_spacing=pixel_spacing,
                        reference_mask=mask, provenance=f"sfem_filters annulus_sequence(effect={effect!r}, "
                                                        f"drive={drive!r}, seed={seed}"
                                                        + (f", truth_element_px={truth_element_px!r})"
                                                           if truth_element_px is not None else ")"), **extra)
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

