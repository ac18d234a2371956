"""The pinned synthetic benchmark of Shi & Liu (2003), section 3.1.

Follows ``shared/specs/synthetic-benchmark.md``: a 60 mm x 40 mm plane-strain rectangle,
stiffer middle part, bottom edge fixed, a cyclic pressure on the top edge, 16 frames at
31.25 ms, noisy displacements of the free boundary nodes. Everything is in SI units; the
spec's millimetres and mmHg are converted here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validate import positive
from ..fem.dofs import node_dofs
from ..fem.loads import pressure_load
from ..fem.material import Material, Parameterisation
from ..fem.mesh import TriMesh, rectangle_mesh
from ..fem.observation import node_observation_matrix
from ..fem.strain import nodal_strains
from ..model import SFEMModel

__all__ = ["Benchmark", "pinned_benchmark", "benchmark_model", "benchmark_mesh", "true_material", "pressure_mmhg",
           "STRATEGIES"]

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
    observation_operator: object  # D, sparse (n_obs, n_dofs)
    observations: np.ndarray    # (n_frames, n_obs) m, noisy
    U: np.ndarray               # (n_frames, n_dofs) true displacement, m
    V: np.ndarray               # (n_frames, n_dofs) true velocity, m/s
    strain: np.ndarray          # (n_frames, n_nodes, 3) true nodal strain
    seed: int
    refine: int
    noise_std: float            # m

    @property
    def n_frames(self) -> int:
        """Number of frames (rows of ``loads``)."""
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
                     loads=loads, observed_nodes=observed, observation_operator=D, observations=obs, U=U, V=V,
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
    param = None
    if strategy == "joint_ekf":
        param = parameterisation or Parameterisation.per_element(bench.mesh.n_elements)
    return SFEMModel(
        bench.mesh, material, bench.loads, bench.observation_operator, FRAME_INTERVAL, bench.fixed_dofs,
        density=DENSITY, alpha=ALPHA, beta=BETA,
        measurement_std=bench.noise_std,            # R = (true noise)^2 I
        process_std=(0.05 * MM, 5 * MM),            # Q_v: 0.05 mm, 5 mm/s per frame
        initial_std=(0.1 * MM, 1 * MM),             # P1(0): 0.1 mm, 1 mm/s
        parameterisation=param, prior_std=(0.3, 1.0),  # P3(0): log E 0.3, logit(2 nu) 1.0
        jacobian=jacobian)
