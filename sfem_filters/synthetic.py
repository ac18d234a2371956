"""The pinned synthetic benchmark of Shi & Liu (2003), section 3.1.

Follows ``shared/specs/synthetic-benchmark.md``: a 60 mm x 40 mm plane-strain rectangle,
stiffer middle part, bottom edge fixed, a cyclic pressure on the top edge, 16 frames at
31.25 ms, noisy displacements of the free boundary nodes. Everything is in SI units; the
spec's millimetres and mmHg are converted here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._validate import positive
from .fem import node_dofs, pressure_load, stiffness_matrix
from .material import Material, Parameterisation
from .mesh import TriMesh, rectangle_mesh
from .model import SFEMModel
from .observations import node_observation_matrix
from .strain import nodal_strains

MM = 1e-3
MMHG = 133.322  # Pa

WIDTH, HEIGHT = 60 * MM, 40 * MM
N_FRAMES = 16
FRAME_INTERVAL = 31.25e-3      # s
DENSITY = 1050.0               # kg/m^3
ALPHA, BETA = 10.0, 1e-3       # Rayleigh damping, 1/s and s
E_OUT, NU_OUT = 75e3, 0.40     # Pa, -
E_MID, NU_MID = 105e3, 0.49
PEAK_MMHG = 58.2
STRATEGIES = ("uniform_kf", "perfect_kf", "joint_ekf")


def pressure_mmhg(n_frames: int = N_FRAMES) -> np.ndarray:
    """P(k) = 58.2 (1 - cos((k - 1) pi / n)) mmHg for k = 1..n (index k - 1)."""
    k = np.arange(1, n_frames + 1)
    return PEAK_MMHG * (1.0 - np.cos((k - 1) * np.pi / n_frames))


@dataclass(frozen=True)
class Benchmark:
    """The synthetic experiment: setup, noisy observations and ground truth (SI units)."""

    mesh: TriMesh
    fixed_dofs: np.ndarray
    true_material: Material
    uniform_material: Material
    middle: np.ndarray          # bool per element: the stiffer middle part
    loads: np.ndarray           # (n_frames, n_dofs) N
    observed_nodes: np.ndarray
    observation: object         # D, sparse (n_obs, n_dofs)
    observations: np.ndarray    # (n_frames, n_obs) m, noisy
    U: np.ndarray               # (n_frames, n_dofs) true displacement, m
    V: np.ndarray               # (n_frames, n_dofs) true velocity, m/s
    strain: np.ndarray          # (n_frames, n_nodes, 3) true nodal strain
    seed: int
    refine: int
    noise_std: float            # m

    @property
    def n_frames(self) -> int:
        return len(self.loads)


def benchmark_mesh(refine: int = 1) -> TriMesh:
    """(6r+1) x (4r+1) nodes over 60 mm x 40 mm."""
    if int(refine) != refine or refine < 1:
        raise ValueError(f"refine: expected an integer >= 1, got {refine!r}")
    return rectangle_mesh(WIDTH, HEIGHT, 6 * int(refine) + 1, 4 * int(refine) + 1)


def true_material(mesh: TriMesh):
    """The pinned material and the middle-part mask (centroid 20 mm < x < 40 mm)."""
    cx = mesh.centroids[:, 0]
    middle = (cx > 20 * MM) & (cx < 40 * MM)
    E = np.where(middle, E_MID, E_OUT)
    nu = np.where(middle, NU_MID, NU_OUT)
    return Material(E, nu), middle


def pinned_benchmark(seed: int = 0, refine: int = 1, noise_mm: float = 0.1) -> Benchmark:
    """Generate the benchmark for a noise seed, refinement factor and noise level (mm)."""
    noise = positive("noise_mm", noise_mm, "mm") * MM
    mesh = benchmark_mesh(refine)
    tol = 1e-9
    bottom = mesh.nodes_where(lambda x, y: y < tol)
    fixed = node_dofs(bottom)
    top_edges = mesh.edges_where(lambda x, y: y > HEIGHT - tol)
    p = pressure_mmhg() * MMHG
    unit = pressure_load(mesh, top_edges, 1.0)
    loads = p[:, None] * unit[None, :]
    boundary = mesh.boundary_nodes()
    observed = np.setdiff1d(boundary, bottom)
    D = node_observation_matrix(mesh, observed)
    mat, middle = true_material(mesh)
    # Ground truth with the true material and the same exact discretisation.
    model = SFEMModel(mesh, mat, loads, D, FRAME_INTERVAL, fixed, density=DENSITY, alpha=ALPHA, beta=BETA)
    system = model.system()
    x = np.zeros(model.dim_x)
    states = [x]
    w = model.dofmap.restrict(loads)
    for t in range(1, N_FRAMES):
        x = system.step(x, w[t])
        states.append(x)
    states = np.array(states)
    U = model.displacements(states)
    V = model.velocities(states)
    rng = np.random.default_rng(seed)
    obs = (D @ U.T).T + rng.standard_normal((N_FRAMES, D.shape[0])) * noise
    return Benchmark(mesh=mesh, fixed_dofs=fixed, true_material=mat,
                     uniform_material=Material.uniform(mesh.n_elements, E_OUT, NU_OUT), middle=middle,
                     loads=loads, observed_nodes=observed, observation=D, observations=obs, U=U, V=V,
                     strain=nodal_strains(mesh, U), seed=int(seed), refine=int(refine), noise_std=noise)


def benchmark_model(bench: Benchmark, strategy: str, parameterisation: Parameterisation | None = None,
                    jacobian: str = "modal") -> SFEMModel:
    """The pinned filter configuration of one strategy.

    Parameters
    ----------
    strategy : {"uniform_kf", "perfect_kf", "joint_ekf"}
        Uniform material fixed, true material fixed, or material estimated from the uniform
        start (per element unless ``parameterisation`` says otherwise).
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy: expected one of {STRATEGIES}, got {strategy!r}")
    material = bench.true_material if strategy == "perfect_kf" else bench.uniform_material
    estimate = None
    if strategy == "joint_ekf":
        estimate = parameterisation or Parameterisation.per_element(bench.mesh.n_elements)
    return SFEMModel(
        bench.mesh, material, bench.loads, bench.observation, FRAME_INTERVAL, bench.fixed_dofs,
        density=DENSITY, alpha=ALPHA, beta=BETA,
        measurement_std=bench.noise_std,            # R = (true noise)^2 I
        process_std=(0.05 * MM, 5 * MM),            # Q_v: 0.05 mm, 5 mm/s per frame
        initial_std=(0.1 * MM, 1 * MM),             # P1(0): 0.1 mm, 1 mm/s
        estimate=estimate, prior_std=(0.3, 1.0),    # P3(0): log E 0.3, logit(2 nu) 1.0
        jacobian=jacobian)


# ---------------------------------------------------------------------------- annulus sequences
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
    :func:`sfem_filters.dense.build_model` builds (causal penalty drive by the landmarks'
    previous measurement, elastically correlated process noise of the spring targets with
    ``landmark_step_px`` per frame, measurement noise ``noise_px``), plus, when ``effect`` names
    one, that undeclared load with amplitudes ``amplitude`` (units of ``NOMINAL["E"]``) shaped
    as a systolic bell in time. With ``effect=None`` a correct baseline filter is consistent
    with the data by construction: what the diagnostics must not flag.

    ``beta`` (s) overrides the model's Rayleigh stiffness coefficient (see
    :func:`sfem_filters.dense.build_model`).

    Returns a :class:`sfem_filters.datasets.Sequence` in pixels; with ``return_truth`` also a
    dict of the noise-free ``displacement`` (F, P, 2) px and ``velocity`` (F, P, 2) px/s.
    """
    from . import dense
    from .datasets import make_sequence
    from .effects import build_effects

    rng = np.random.default_rng(seed)
    mask = annulus_mask()
    rows, cols = np.nonzero(mask)
    pts = np.column_stack([cols, rows]).astype(float)
    stub = make_sequence(pts, np.zeros((n_frames, len(pts), 2)), frame_interval=frame_interval,
                         pixel_spacing=pixel_spacing, reference_mask=mask)
    setup = dense.prepare(stub, landmarks)
    setup.noise_px = noise_px
    model, _ = dense.build_model(setup, (), "penalty", "none", landmark_step_px=landmark_step_px, beta=beta)
    s = pixel_spacing
    system = model.system()
    nx = model.dim_x
    L = np.linalg.cholesky(model.Q[:nx, :nx] + 1e-30 * np.eye(nx))
    n_dofs = setup.mesh.n_dofs
    G = np.zeros((n_dofs, 0))
    a = np.zeros((n_frames, 0))
    if effect is not None:
        eff = build_effects([effect], setup.mesh, setup.geometry, scale=dense.NOMINAL["E"])[0]
        G = eff.loads
        bell = np.sin(np.pi * np.arange(n_frames) / (n_frames - 1)) ** 2
        a = bell[:, None] * np.broadcast_to(np.asarray(amplitude, float)[: G.shape[1]], (G.shape[1],))[None]
    k = dense.NOMINAL["penalty"] * np.median(
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
    from matplotlib.path import Path

    from . import dense

    if seq.reference_mask is None:
        raise ValueError("seq: expected a sequence with a reference_mask (it sets the image size)")
    U = seq.displacement if displacement is None else np.asarray(displacement, float)
    setup = dense.prepare(seq, 3)
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

