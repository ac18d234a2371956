"""Input validation at the public entry points (issue 6): every bad input gives an error that
names the argument, says what was expected and what was given. Table-driven: each row calls
one entry point with one bad argument and checks the type and the message."""
from functools import lru_cache

import numpy as np
import pytest

from sfem_filters import fem
from sfem_filters.benchmark import statistics
from sfem_filters.cardiac import effects, myocardium
from sfem_filters.fem import observation as observations
from sfem_filters.fem import strain
from sfem_filters.fem.material import Material, Parameterisation, correlated_prior
from sfem_filters.fem.mesh import (
    TriMesh,
    delaunay_mesh,
    mesh_quality,
    rectangle_mesh,
    triangle_angles,
)
from sfem_filters.filtering import (
    ENGINES,
    History,
    LinearGaussianModel,
    Safeguards,
    cyclic_estimate,
    diagnostics,
    filter_loop,
    nearest_psd,
)
from sfem_filters.model import SFEMModel

NAN = float("nan")


@lru_cache(None)
def square():
    """2 x 2 cm square, 3 x 3 nodes, 8 triangles."""
    return rectangle_mesh(0.02, 0.02, 3, 3)


@lru_cache(None)
def ring():
    """A myocardium-like annulus meshed from a ring mask (1 mm pixels)."""
    r, c = np.mgrid[:24, :24]
    d = np.hypot(r - 11.5, c - 11.5)
    mesh = myocardium.mesh_from_mask((d > 5) & (d < 10), 1e-3)
    return mesh, myocardium.lv_geometry(mesh)


def model_kwargs(**change):
    mesh = square()
    kw = dict(mesh=mesh, material=Material.uniform(mesh.n_elements, 1e4, 0.4),
              loads=np.zeros((3, mesh.n_dofs)), observation_operator=np.eye(mesh.n_dofs)[6:],
              frame_interval=0.03, fixed_dofs=np.arange(6))
    kw.update(change)
    return kw


def build_model(**change):
    kw = model_kwargs(**change)
    return SFEMModel(kw.pop("mesh"), kw.pop("material"), kw.pop("loads"), kw.pop("observation_operator"),
                     kw.pop("frame_interval"), kw.pop("fixed_dofs"), **kw)


@lru_cache(None)
def good_model():
    return build_model(parameterisation=Parameterisation.per_element(square().n_elements))


@lru_cache(None)
def history():
    m = good_model()
    h = History()
    eng = ENGINES["structured"](m)
    eng.reset(m.x0, m.P0)
    filter_loop(eng, m, np.zeros((m.n_frames, m.dim_obs)), history=h)
    return h


def one_frame_history():
    h = History()
    full = history()
    h.append(0, 0, full.x[0], np.eye(len(full.x[0])), full.innovation[0], full.S[0], full.nis[0], full.n_obs[0])
    return h


def folded():
    # triangles (0, 1, 2) and (0, 1, 3) lie on the same side of their shared edge: node 3 is
    # inside the first triangle, the second is inverted relative to its neighbour
    return TriMesh([[0, 0], [1, 0], [0.5, 1], [0.5, 0.4]], [[0, 1, 2], [0, 1, 3]])


def two_pieces():
    m = np.zeros((12, 12), bool)
    m[1:5, 1:5] = m[7:11, 7:11] = True
    return m


def toy(**change):
    kw = dict(transition=np.eye(2), H=[[1.0, 0.0]], Q=np.eye(2), R=[[1.0]], x0=np.zeros(2), P0=np.eye(2),
              n_frames=4)
    kw.update(change)
    return LinearGaussianModel(**kw)


V, T = ValueError, TypeError
CASES = [
    # ---------------- meshes: non-finite, shapes, degenerate, inverted, duplicate nodes
    ("TriMesh nodes NaN", lambda: TriMesh([[0, 0], [1, 0], [NAN, 1]], [[0, 1, 2]]), V,
     r"nodes: expected finite values, got 1 non-finite entries"),
    ("TriMesh nodes shape", lambda: TriMesh(np.zeros((3, 3)), [[0, 1, 2]]), V,
     r"nodes: expected shape \(any, 2\), got shape \(3, 3\)"),
    ("TriMesh elements shape", lambda: TriMesh([[0, 0], [1, 0], [0, 1], [1, 1]], [[0, 1, 2, 3]]), V,
     r"elements: expected shape \(any, 3\), got shape \(1, 4\)"),
    ("TriMesh degenerate", lambda: TriMesh([[0, 0], [1, 0], [2, 0]], [[0, 1, 2]]), V,
     r"elements: triangle 0 is degenerate \(zero area\): expected triangles of non-zero area, got collinear nodes \(0, 1, 2\)"),
    ("TriMesh inverted", folded, V,
     r"elements: expected a mesh without inverted \(folded\) triangles, got triangles 0 and 1 overlapping across edge \(0, 1\)"),
    ("TriMesh duplicate nodes",
     lambda: TriMesh([[0, 0], [1, 0], [0, 1], [1, 1], [1, 0]], [[0, 1, 2], [4, 3, 2]]), V,
     r"nodes: expected distinct node coordinates, got duplicate nodes \(1 and 4 at \(1.0, 0.0\) m\)"),
    ("TriMesh index range", lambda: TriMesh([[0, 0], [1, 0], [0, 1]], [[0, 1, 3]]), V,
     r"elements: expected node indices in \[0, 2\], got range \[0, 3\]"),
    ("delaunay_mesh inf", lambda: delaunay_mesh([[0, 0], [1, 0], [0, np.inf]]), V,
     r"points: expected finite values, got 1 non-finite"),
    ("delaunay_mesh duplicates", lambda: delaunay_mesh([[0, 0], [1, 0], [0, 1], [1, 0]]), V,
     r"points: expected distinct points, got duplicates \(1 repeated\)"),
    ("delaunay_mesh shape", lambda: delaunay_mesh(np.zeros((5, 3))), V,
     r"points: expected shape \(any, 2\), got shape \(5, 3\)"),
    ("delaunay_mesh max_edge", lambda: delaunay_mesh([[0, 0], [1, 0], [0, 1]], max_edge=0.0), V,
     r"max_edge: expected a positive finite number in m, got 0.0"),
    ("rectangle_mesh width", lambda: rectangle_mesh(0.0, 1.0, 3, 3), V,
     r"width: expected a positive finite number in m, got 0.0"),
    ("rectangle_mesh height NaN", lambda: rectangle_mesh(1.0, NAN, 3, 3), V,
     r"height: expected a positive finite number in m, got nan"),
    ("rectangle_mesh nx", lambda: rectangle_mesh(1.0, 1.0, 1, 3), V, r"nx: expected an integer >= 2, got 1"),
    ("triangle_angles mesh", lambda: triangle_angles("mesh"), T, r"mesh: expected a TriMesh, got str"),
    ("mesh_quality mesh", lambda: mesh_quality(np.zeros((3, 2))), T, r"mesh: expected a TriMesh, got ndarray"),
    # ---------------- materials: E <= 0, nu outside (0, 0.5)
    ("Material E negative", lambda: Material([-1.0], [0.3]), V, r"E: expected Young's moduli > 0 Pa, got minimum -1.0"),
    ("Material E zero", lambda: Material([0.0, 1.0], [0.3, 0.3]), V, r"E: expected Young's moduli > 0 Pa, got minimum 0.0"),
    ("Material nu 0.5", lambda: Material([1e4], [0.5]), V,
     r"nu: expected Poisson's ratios in the open interval \(0, 0.5\), got 0.5"),
    ("Material nu 0", lambda: Material([1e4], [0.0]), V,
     r"nu: expected Poisson's ratios in the open interval \(0, 0.5\), got 0.0"),
    ("Material E NaN", lambda: Material([NAN], [0.3]), V, r"E: expected finite values"),
    ("Material shapes", lambda: Material([1e4, 2e4], [0.3]), V, r"nu: expected the shape of E \(2,\), got \(1,\)"),
    ("Material.uniform n", lambda: Material.uniform(0, 1e4, 0.3), V, r"n_elements: expected an integer >= 1, got 0"),
    ("Material.uniform nu", lambda: Material.uniform(3, 1e4, 0.7), V,
     r"nu: expected Poisson's ratios in the open interval \(0, 0.5\), got 0.7"),
    ("per_element n", lambda: Parameterisation.per_element(-2), V, r"n_elements: expected an integer >= 1, got -2"),
    ("relative_regions E_reference", lambda: Parameterisation.relative_regions([0, 1], -5.0), V,
     r"E_reference: expected a positive finite number in Pa, got -5.0"),
    ("relative_regions one region", lambda: Parameterisation.relative_regions([0, 0], 1e4), V,
     r"labels: expected at least two regions for relative stiffness, got 1"),
    ("correlated_prior length", lambda: correlated_prior(Parameterisation.per_element(8), square().centroids, 0.0), V,
     r"length: expected a positive finite number in m, got 0.0"),
    ("correlated_prior centroids", lambda: correlated_prior(Parameterisation.per_element(8), np.zeros((3, 2)), 1.0), V,
     r"centroids: expected shape \(8, 2\), got shape \(3, 2\)"),
    # ---------------- finite elements
    ("plane_strain_matrix E", lambda: fem.plane_strain_matrix(-1.0, 0.3), V, r"E: expected Young's moduli > 0 Pa, got minimum -1.0"),
    ("plane_strain_matrix nu", lambda: fem.plane_strain_matrix(1e4, 0.6), V,
     r"nu: expected Poisson's ratios in the open interval \(0, 0.5\), got 0.6"),
    ("plane_strain_matrix_dnu nu", lambda: fem.plane_strain_matrix_dnu(1e4, -0.1), V,
     r"nu: expected Poisson's ratios in the open interval \(0, 0.5\), got -0.1"),
    ("plane_strain_matrix NaN", lambda: fem.plane_strain_matrix([1e4, NAN], 0.3), V, r"E: expected finite values"),
    ("stiffness_matrix E zero", lambda: fem.stiffness_matrix(square(), 0.0, 0.3), V,
     r"E: expected Young's moduli > 0 Pa, got minimum 0.0"),
    ("stiffness_matrix E shape", lambda: fem.stiffness_matrix(square(), np.full(3, 1e4), 0.3), V,
     r"E: expected shape \(8\), got shape \(3,\)"),
    ("stiffness_matrix nu", lambda: fem.stiffness_matrix(square(), 1e4, 0.5), V,
     r"nu: expected Poisson's ratios in the open interval \(0, 0.5\), got 0.5"),
    ("stiffness_matrix thickness", lambda: fem.stiffness_matrix(square(), 1e4, 0.3, thickness=0.0), V,
     r"thickness: expected a positive finite number in m, got 0.0"),
    ("element_derivatives E", lambda: fem.element_stiffness_derivatives(square(), -3.0, 0.3), V,
     r"E: expected Young's moduli > 0 Pa, got minimum -3.0"),
    ("element_stiffness D", lambda: fem.element_stiffness(square(), np.zeros((8, 3, 2))), V,
     r"D: expected shape \(8, 3, 3\), got shape \(8, 3, 2\)"),
    ("mass_matrix density", lambda: fem.mass_matrix(square(), -1.0), V,
     r"density: expected a positive mass density in kg/m\^3, got minimum -1.0"),
    ("mass_matrix density NaN", lambda: fem.mass_matrix(square(), NAN), V, r"density: expected finite values"),
    ("assemble shape", lambda: fem.assemble(square(), np.zeros((8, 6, 5))), V,
     r"element_matrices: expected shape \(8, 6, 6\), got shape \(8, 6, 5\)"),
    ("pressure_load edges", lambda: fem.pressure_load(square(), [[0, 99]], 1.0), V,
     r"edges: expected node indices in \[0, 8\], got range \[0, 99\]"),
    ("pressure_load pressure", lambda: fem.pressure_load(square(), [[0, 1]], NAN), V, r"pressure: expected finite values"),
    ("node_dofs components", lambda: fem.node_dofs([0], "z"), V, r"components: expected 'x', 'y' or 'xy', got 'z'"),
    ("node_dofs negative", lambda: fem.node_dofs([-1]), V, r"nodes: expected non-negative integer node indices"),
    ("DofMap fixed", lambda: fem.DofMap(10, [3, 12]), V, r"fixed: expected dof indices in \[0, 9\], got range \[3, 12\]"),
    ("rayleigh alpha", lambda: fem.rayleigh_damping(1.0, 1.0, -1.0, 0.0), V,
     r"alpha: expected a non-negative finite number in 1/s, got -1.0"),
    ("penalty stiffness", lambda: fem.penalty_stiffness(4, [0], 0.0), V,
     r"stiffness: expected a positive finite number in N/m, got 0.0"),
    ("penalty targets NaN", lambda: fem.penalty_load(4, [0], 1.0, [NAN]), V, r"targets: expected finite values"),
    # ---------------- observations: points outside the mesh, non-finite, shapes
    ("point outside", lambda: observations.point_observation_matrix(square(), [[0.01, 0.01], [0.05, 0.01]]), V,
     r"points: expected points inside the mesh, got point 1 at \(0.05, 0.01\) m outside it"),
    ("point NaN", lambda: observations.locate_points(square(), [[NAN, 0.0]]), V, r"points: expected finite values"),
    ("point shape", lambda: observations.locate_points(square(), [0.0, 0.0, 0.0]), V,
     r"points: expected shape \(any, 2\), got shape \(3,\)"),
    ("node observation range", lambda: observations.node_observation_matrix(square(), [0, 9]), V,
     r"nodes: expected node indices in \[0, 8\], got range \[0, 9\]"),
    ("node observation dtype", lambda: observations.node_observation_matrix(square(), [0.5]), T,
     r"nodes: expected integer node indices, got dtype float64"),
    # ---------------- strains and statistics
    ("element_strains NaN", lambda: strain.element_strains(square(), np.full(18, NAN)), V, r"U: expected finite values"),
    ("element_strains shape", lambda: strain.element_strains(square(), np.zeros(17)), V,
     r"U: expected last axis of length 18 \(n_dofs\), got 17"),
    ("nodal_average shape", lambda: strain.nodal_average(square(), np.zeros((5, 3))), V,
     r"element_values: expected shape \(\.\.\., 8, k\) \(n_elements rows\), got shape \(5, 3\)"),
    ("ks_test NaN", lambda: statistics.ks_test([1.0, NAN, 2.0], [1.0, 2.0]), V, r"a: expected finite values"),
    ("ks_test too few", lambda: statistics.ks_test([1.0], [1.0, 2.0, 3.0]), V,
     r"a, b: expected at least 2 samples each, got 1 and 3"),
    ("ks_test shape", lambda: statistics.ks_test(np.zeros((2, 2)), [1.0, 2.0]), V, r"a: expected shape \(any\), got shape \(2, 2\)"),
    ("kolmogorov D", lambda: statistics.kolmogorov_asymptotic_p(1.5, 3, 3), V, r"D: expected a KS statistic in \[0, 1\], got 1.5"),
    ("kolmogorov n", lambda: statistics.kolmogorov_asymptotic_p(0.5, 0, 3), V, r"n: expected an integer >= 1, got 0"),
    # ---------------- effects
    ("stress_loads shape", lambda: fem.stress_loads(square(), np.zeros((8, 2))), V,
     r"element_stress: expected shape \(8, 3\), got shape \(8, 2\)"),
    ("stress_loads NaN", lambda: fem.stress_loads(square(), np.full((8, 3), NAN)), V, r"element_stress: expected finite values"),
    ("Effect initial_std", lambda: effects.Effect("e", np.ones((18, 1)), "Pa", process_std=1.0, initial_std=0.0), V,
     r"initial_std: expected standard deviations > 0 \(Pa\), got minimum 0.0"),
    ("Effect process_std", lambda: effects.Effect("e", np.ones((18, 1)), "Pa", process_std=-1.0, initial_std=1.0), V,
     r"process_std: expected standard deviations >= 0 \(Pa\), got minimum -1.0"),
    ("Effect loads NaN", lambda: effects.Effect("e", np.full((18, 1), NAN), "Pa", 1.0, 1.0), V, r"loads: expected finite values"),
    ("active_stress direction", lambda: effects.active_stress(ring()[0], ring()[1], "axial"), V,
     r"direction: expected 'circumferential' or 'radial', got 'axial'"),
    ("active_stress scale", lambda: effects.active_stress(ring()[0], ring()[1], scale=0.0), V,
     r"scale: expected a positive finite number in Pa, got 0.0"),
    ("build_effects name", lambda: effects.build_effects(["glue"], *ring()), V, r"effects: unknown effect 'glue'; expected one of"),
    # ---------------- myocardium: masks without tissue or in several pieces
    ("mask no tissue", lambda: myocardium.mesh_from_mask(np.zeros((6, 6), bool), 1e-3), V,
     r"mask: expected a mask holding some tissue, got no tissue pixel in \(6, 6\)"),
    ("mask two pieces", lambda: myocardium.mesh_from_mask(two_pieces(), 1e-3), V,
     r"mask: expected one connected piece of tissue, got 2"),
    ("mask 3D", lambda: myocardium.mesh_from_mask(np.ones((3, 3, 3), bool), 1e-3), V,
     r"mask: expected a 2D mask \(boolean, rows = y, columns = x\), got shape \(3, 3, 3\)"),
    ("mask spacing", lambda: myocardium.mesh_from_mask(np.ones((4, 4), bool), 0.0), V,
     r"spacing: expected a positive finite number in m, got 0.0"),
    ("mask step", lambda: myocardium.mesh_from_mask(np.ones((4, 4), bool), 1e-3, step=0), V,
     r"step: expected an integer >= 1, got 0"),
    ("mask_inside no tissue", lambda: myocardium.mask_inside(np.zeros((4, 4)), 1e-3), V,
     r"mask: expected a mask holding some tissue, got no tissue pixel"),
    ("mask_inside spacing", lambda: myocardium.mask_inside(np.ones((4, 4)), -1e-3), V,
     r"spacing: expected a positive finite number in m, got -0.001"),
    ("mask_inside origin", lambda: myocardium.mask_inside(np.ones((4, 4)), 1e-3, origin=(0.0, NAN)), V,
     r"origin: expected finite values"),
    ("mesh_from_points max_edge", lambda: myocardium.mesh_from_points(np.eye(3)[:, :2], -1.0), V,
     r"max_edge: expected a positive finite number in m, got -1.0"),
    ("lv_geometry not annulus", lambda: myocardium.lv_geometry(square()), V,
     r"mesh: expected an annulus \(one outer contour and one cavity\), got 1 outer and 0 inner"),
    ("boundary_loops mesh", lambda: myocardium.boundary_loops(None), T, r"mesh: expected a TriMesh, got NoneType"),
    ("contour_landmarks n", lambda: myocardium.contour_landmarks(ring()[1], ring()[0], 2), V,
     r"n_per_contour: expected an integer >= 3, got 2"),
    # ---------------- the model: frame interval, noise, loads, sequences of < 2 frames
    ("model frame_interval 0", lambda: build_model(frame_interval=0.0), V,
     r"frame_interval: expected a positive finite number in s, got 0.0"),
    ("model frame_interval < 0", lambda: build_model(frame_interval=-0.03), V,
     r"frame_interval: expected a positive finite number in s, got -0.03"),
    ("model measurement_std", lambda: build_model(measurement_std=0.0), V,
     r"measurement_std: expected standard deviations > 0 m, got minimum 0.0"),
    ("model measurement_std shape", lambda: build_model(measurement_std=np.ones(3)), V,
     r"measurement_std: expected shape \(12\), got shape \(3,\)"),
    ("model process_std", lambda: build_model(process_std=(0.0, 1e-3)), V,
     r"process_std\[0\]: expected a positive finite number in m, got 0.0"),
    ("model initial_std", lambda: build_model(initial_std=(1e-4, -1.0)), V,
     r"initial_std\[1\]: expected a positive finite number in m/s, got -1.0"),
    ("model prior_std", lambda: build_model(parameterisation=Parameterisation.per_element(8), prior_std=(0.0, 1.0)), V,
     r"prior_std\[0\]: expected a positive finite number, got 0.0"),
    ("model material_process_std", lambda: build_model(parameterisation=Parameterisation.per_element(8),
                                                       material_process_std=(-0.1, 0.0)), V,
     r"material_process_std\[0\]: expected a non-negative finite number, got -0.1"),
    ("model loads NaN", lambda: build_model(loads=np.full((3, 18), NAN)), V, r"loads: expected finite values, got 54 non-finite"),
    ("model loads one frame", lambda: build_model(loads=np.zeros((1, 18))), V, r"loads: expected at least 2 frames, got 1"),
    ("model loads shape", lambda: build_model(loads=np.zeros((3, 5))), V, r"loads: expected shape \(any, 18\), got shape \(3, 5\)"),
    ("model observation columns", lambda: build_model(observation_operator=np.eye(5)), V,
     r"observation_operator: expected 18 columns \(n_dofs\), got 5"),
    ("model observation NaN", lambda: build_model(observation_operator=np.full((2, 18), NAN)), V,
     r"observation_operator: expected finite values"),
    ("model alpha", lambda: build_model(alpha=-1.0), V, r"alpha: expected a non-negative finite number in 1/s, got -1.0"),
    ("model material count", lambda: build_model(material=Material.uniform(3, 1e4, 0.3)), V,
     r"material: expected 8 elements, got 3"),
    ("model mesh type", lambda: build_model(mesh="square"), T, r"mesh: expected a TriMesh, got str"),
    ("model density", lambda: build_model(density=0.0), V, r"density: expected a positive finite number in kg/m\^3, got 0.0"),
    # ---------------- filters
    ("cyclic observations inf", lambda: cyclic_estimate(good_model(), np.full((3, 12), np.inf)), V,
     r"observations: expected finite values or NaN for missing ones, got 36 infinite entries"),
    ("cyclic observations shape", lambda: cyclic_estimate(good_model(), np.zeros((1, 12))), V,
     r"observations: expected shape \(3, 12\), got shape \(1, 12\)"),
    ("cyclic engine", lambda: cyclic_estimate(good_model(), np.zeros((3, 12)), engine="fast"), V,
     r"engine: expected one of \['filterpy', 'roukf', 'structured', 'ud', 'ukf'\], got 'fast'"),
    ("cyclic tol", lambda: cyclic_estimate(good_model(), np.zeros((3, 12)), tol=0.0), V,
     r"tol: expected a positive relative tolerance, got 0.0"),
    ("filter_loop observations", lambda: filter_loop(ENGINES["ud"](good_model()), good_model(), np.zeros((3, 4))), V,
     r"observations: expected shape \(3, 12\), got shape \(3, 4\)"),
    ("Safeguards level", lambda: Safeguards(divergence_level=1.5), V,
     r"divergence_level: expected a number in the open interval \(0, 1\), got 1.5"),
    ("Safeguards frames", lambda: Safeguards(divergence_frames=0), V, r"divergence_frames: expected an integer >= 1, got 0"),
    ("Safeguards jitter", lambda: Safeguards(jitter=-1.0), V, r"jitter: expected a non-negative finite number, got -1.0"),
    ("nearest_psd shape", lambda: nearest_psd(np.zeros((2, 3))), V, r"P: expected a square matrix, got shape \(2, 3\)"),
    ("nearest_psd NaN", lambda: nearest_psd(np.full((2, 2), NAN)), V, r"P: expected finite values"),
    ("toy n_frames", lambda: toy(n_frames=1), V, r"n_frames: expected an integer >= 2, got 1"),
    ("toy R", lambda: toy(R=[[0.0]]), V, r"R: expected a positive definite measurement noise covariance"),
    # ---------------- diagnostics: short or foreign histories, levels
    ("nis level", lambda: diagnostics.nis_summary(history(), level=1.5), V,
     r"level: expected a number in the open interval \(0, 1\), got 1.5"),
    ("nis loop", lambda: diagnostics.nis_summary(history(), loop=4), V,
     r"loop: expected one of the loops in the history \(0-0\), got 4"),
    ("nis history type", lambda: diagnostics.nis_summary({"nis": []}), T, r"history: expected a sfem_filters.filtering.History, got dict"),
    ("nis empty history", lambda: diagnostics.nis_summary(History()), V,
     r"history: expected a run with at least one frame, got an empty history"),
    ("whiteness one frame", lambda: diagnostics.whiteness(one_frame_history()), V,
     r"history: expected at least 3 frames in the loop, got 1"),
    ("prior_conflict theta0", lambda: diagnostics.prior_conflict([0.0, 1.0], np.eye(2), [0.0], np.eye(2)), V,
     r"theta0: expected shape \(2\), got shape \(1,\)"),
    ("prior_conflict level", lambda: diagnostics.prior_conflict([0.0], [[0.5]], [0.0], [[1.0]], level=0.0), V,
     r"level: expected a number in the open interval \(0, 1\), got 0.0"),
    ("prior_conflict P_prior", lambda: diagnostics.prior_conflict([0.0], [[0.5]], [0.0], [[-1.0]]), V,
     r"P_prior: expected a symmetric positive definite prior covariance"),
    ("whiteness max_lag", lambda: diagnostics.whiteness(history(), max_lag=0), V, r"max_lag: expected an integer >= 1, got 0"),
    ("consistency one frame", lambda: diagnostics.consistency(one_frame_history()), V,
     r"history: expected at least 2 frames in the loop, got 1"),
    ("consistency threshold", lambda: diagnostics.consistency(history(), threshold=0.0), V,
     r"threshold: expected a positive finite number, got 0.0"),
    ("effect_score load shape", lambda: diagnostics.effect_score(good_model(), history(), np.zeros((5, 1))), V,
     r"load_matrix: expected shape \(18, any\), got shape \(5, 1\)"),
    ("effect_score one frame", lambda: diagnostics.effect_score(good_model(), one_frame_history(), np.zeros((18, 1))), V,
     r"history: expected at least 2 frames in the loop, got 1"),
    ("effect_score time courses shape", lambda: diagnostics.effect_score(good_model(), history(), np.zeros((18, 1)),
                                                                         time_courses=np.ones(3)), V,
     r"time_courses: expected shape \(n_frames >= \d+, m >= 1\), got \(3,\)"),
    ("effect_score time courses NaN", lambda: diagnostics.effect_score(
        good_model(), history(), np.zeros((18, 1)), time_courses=np.full((50, 1), NAN)), V,
     r"time_courses: expected finite values, got NaN or inf"),
    ("chi2_logsf q", lambda: diagnostics.chi2_logsf(-1.0, 3), V, r"q: expected a non-negative finite number, got -1.0"),
    ("chi2_z df", lambda: diagnostics.chi2_z(3.0, 2.5), V, r"df: expected an integer >= 0, got 2.5"),
]


@pytest.mark.parametrize("call, exc, message", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_is_named_with_expectation_and_value(call, exc, message):
    with pytest.raises(exc, match=message):
        call()


def test_good_inputs_of_the_table_are_accepted():
    """The fixtures the table perturbs are themselves valid (so each row tests one fault)."""
    assert build_model().dim_obs == 12
    assert good_model().dim_theta == 16
    assert len(history().loop) == 3
    assert toy().n_frames == 4
    mesh, geo = ring()
    assert len(geo.endo) > 3 and len(geo.epi) > 3
    effects.active_stress(mesh, geo)
    myocardium.mask_inside(np.ones((4, 4)), 1e-3)(np.zeros((1, 2)))
    fem.pressure_load(square(), [[0, 1]], 1.0)
    TriMesh([[0, 0], [1, 0], [1, 1], [0, 1]], [[0, 1, 2], [0, 3, 2]])   # mixed orientation: reoriented, fine
