"""Tests of sfem_filters.fem: constitutive law, patch test, K and M properties, loads, dof maps,
penalty constraints, and an independent assembly of K and M with scikit-fem."""
import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse as sp
from conftest import (
    element_materials,
    jittered_grid_meshes,
    lattice_point_clouds,
    meshes_with_materials,
)
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters import fem
from sfem_filters.fem.mesh import TriMesh, delaunay_mesh, rectangle_mesh
from sfem_filters.fem.strain import element_strains

FAST = settings(max_examples=25, deadline=None)
E_TISSUE, NU_TISSUE, RHO_TISSUE = 7.5e4, 0.4, 1050.0      # Pa, -, kg/m^3


# --- helpers ---------------------------------------------------------------------------------

def dense(A):
    return A.toarray() if sp.issparse(A) else np.asarray(A)


def textbook_D(E, nu):
    """Plane-strain D of a textbook: E/((1+nu)(1-2nu)) [[1-nu, nu, 0], [nu, 1-nu, 0], [0, 0, (1-2nu)/2]]."""
    f = E / ((1 + nu) * (1 - 2 * nu))
    return f * np.array([[1 - nu, nu, 0], [nu, 1 - nu, 0], [0, 0, (1 - 2 * nu) / 2]])


def lame_D(E, nu):
    """The same matrix from the Lame parameters: [[l+2m, l, 0], [l, l+2m, 0], [0, 0, m]]."""
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    return np.array([[lam + 2 * mu, lam, 0], [lam, lam + 2 * mu, 0], [0, 0, mu]])


def linear_field(mesh, a, G):
    """Global dof vector (node-major, x before y) of u(x) = a + G x."""
    return (np.asarray(a)[None, :] + mesh.nodes @ np.asarray(G).T).ravel()


def rigid_body_modes(mesh):
    """x translation, y translation and infinitesimal rotation about the centroid, (n_dofs, 3)."""
    x = mesh.nodes - mesh.nodes.mean(axis=0)
    tx = np.tile([1.0, 0.0], mesh.n_nodes)
    ty = np.tile([0.0, 1.0], mesh.n_nodes)
    rot = np.column_stack([-x[:, 1], x[:, 0]]).ravel()
    return np.column_stack([tx, ty, rot])


def interior_nodes(mesh):
    return np.setdiff1d(np.arange(mesh.n_nodes), mesh.boundary_nodes())


def single_element_global(mesh, element_matrices, e):
    """Global matrix of element e's matrix scattered alone."""
    only = np.zeros_like(element_matrices)
    only[e] = element_matrices[e]
    return dense(fem.assemble(mesh, only))


def gradients():
    """Displacement gradients G (2x2) with entries of a few percent (small strain)."""
    return st.lists(st.floats(-0.2, 0.2), min_size=4, max_size=4).map(lambda v: np.reshape(v, (2, 2)))


def translations():
    return st.lists(st.floats(-1e-3, 1e-3), min_size=2, max_size=2).map(np.array)


any_mesh = st.one_of(jittered_grid_meshes(),
                     lattice_point_clouds().map(lambda p: delaunay_mesh(p, min_angle_deg=0.0)))


# --- constitutive matrix ----------------------------------------------------------------------

@FAST
@given(E=st.floats(1.0, 1e9), nu=st.floats(1e-4, 0.5 - 1e-4))
def test_plane_strain_matrix_textbook_and_spd(E, nu):
    """D equals the textbook formula (and its Lame form) and is symmetric positive definite."""
    D = fem.plane_strain_matrix(E, nu)
    np.testing.assert_allclose(D, textbook_D(E, nu), rtol=1e-13, atol=0)
    np.testing.assert_allclose(D, lame_D(E, nu), rtol=1e-9, atol=1e-12 * np.abs(D).max())
    np.testing.assert_array_equal(D, D.T)
    assert np.linalg.eigvalsh(D).min() > 0


def test_plane_strain_matrix_broadcasts_per_element():
    """Arrays of E and nu give a stack of matrices, one per element."""
    E = np.array([1e4, 2e4, 5e4])
    nu = np.array([0.1, 0.3, 0.45])
    D = fem.plane_strain_matrix(E, nu)
    assert D.shape == (3, 3, 3)
    for k in range(3):
        np.testing.assert_allclose(D[k], textbook_D(E[k], nu[k]), rtol=1e-13)
    assert fem.plane_strain_matrix(E, 0.3).shape == (3, 3, 3)


@FAST
@given(E=st.floats(1e2, 1e7), nu=st.floats(0.01, 0.48))
def test_plane_strain_matrix_dnu_matches_central_differences(E, nu):
    """dD/dnu agrees with a central finite difference of plane_strain_matrix."""
    h = 1e-6
    fd = (fem.plane_strain_matrix(E, nu + h) - fem.plane_strain_matrix(E, nu - h)) / (2 * h)
    exact = fem.plane_strain_matrix_dnu(E, nu)
    np.testing.assert_allclose(exact, fd, rtol=0, atol=1e-6 * np.abs(exact).max())


# --- patch test and stiffness -----------------------------------------------------------------

@FAST
@given(mesh=any_mesh, a=translations(), G=gradients())
def test_patch_test_element_strains_exact(mesh, a, G):
    """For u = a + G x every element has the constant strain (G11, G22, G12 + G21)."""
    eps = element_strains(mesh, linear_field(mesh, a, G))
    expected = np.array([G[0, 0], G[1, 1], G[0, 1] + G[1, 0]])
    # Relative to the strain scale of u: |G|, or |a| / diameter when G vanishes.
    diameter = np.ptp(mesh.nodes, axis=0).max()
    scale = max(np.abs(G).max(), np.abs(a).max() / diameter, 1e-300)
    np.testing.assert_allclose(eps, np.broadcast_to(expected, eps.shape), rtol=0, atol=1e-12 * scale)


@FAST
@given(mesh=any_mesh, a=translations(), G=gradients(),
       E=st.floats(1e3, 1e6), nu=st.floats(0.05, 0.49))
def test_patch_test_no_interior_forces(mesh, a, G, E, nu):
    """K u for a linear field has zero force at every interior node (uniform material)."""
    K = fem.stiffness_matrix(mesh, E, nu)
    u = linear_field(mesh, a, G)
    f = (K @ u).reshape(-1, 2)
    # The scale of single element contributions: |K| |G x| per node.
    scale = abs(K).max() * np.abs(mesh.nodes - mesh.nodes.mean(0)).max() * max(np.abs(G).max(), 1e-3)
    np.testing.assert_allclose(f[interior_nodes(mesh)], 0.0, atol=1e-10 * scale)
    # The boundary forces are in equilibrium (zero resultant) and not all zero for G != 0.
    np.testing.assert_allclose(f.sum(axis=0), 0.0, atol=1e-10 * scale)


@FAST
@given(meshes_with_materials())
def test_stiffness_symmetric_psd_with_three_rigid_modes(case):
    """K is symmetric PSD; its null space is exactly the 3 rigid-body modes (free mesh)."""
    mesh, E, nu = case
    K = dense(fem.stiffness_matrix(mesh, E, nu))
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-13 * np.abs(K).max())
    R = rigid_body_modes(mesh)
    np.testing.assert_allclose(K @ R, 0.0, atol=1e-10 * np.abs(K).max() * np.abs(R).max())
    w = np.linalg.eigvalsh(K)
    assert w.min() > -1e-10 * w.max()
    n_zero = np.count_nonzero(np.abs(w) < 1e-10 * w.max())
    assert n_zero == 3, f"{n_zero} zero eigenvalues, spectrum starts {w[:5] / w.max()}"


@FAST
@given(meshes_with_materials(), st.floats(0.1, 10.0))
def test_stiffness_scales_with_E_and_thickness(case, factor):
    """K is linear in the (common) scaling of E and in the thickness."""
    mesh, E, nu = case
    K = dense(fem.stiffness_matrix(mesh, E, nu))
    np.testing.assert_allclose(dense(fem.stiffness_matrix(mesh, factor * E, nu)), factor * K,
                               rtol=0, atol=1e-12 * factor * np.abs(K).max())
    np.testing.assert_allclose(dense(fem.stiffness_matrix(mesh, E, nu, thickness=factor)), factor * K,
                               rtol=0, atol=1e-12 * factor * np.abs(K).max())


def test_stiffness_matrix_broadcasts_scalars():
    """Scalar E and nu mean the same value in every element."""
    mesh = rectangle_mesh(0.02, 0.01, 4, 3)
    K1 = dense(fem.stiffness_matrix(mesh, E_TISSUE, NU_TISSUE))
    K2 = dense(fem.stiffness_matrix(mesh, np.full(mesh.n_elements, E_TISSUE),
                                    np.full(mesh.n_elements, NU_TISSUE)))
    np.testing.assert_array_equal(K1, K2)


@pytest.mark.parametrize("E, nu, match", [
    (-1.0, 0.3, "E: expected Young's moduli > 0 Pa"),
    (1e4, 0.5, r"nu: expected Poisson's ratios in the open interval \(0, 0.5\), got (np\.float64\()?0\.5"),
    (1e4, 0.0, r"nu: expected Poisson's ratios in the open interval \(0, 0.5\)"),
    (np.nan, 0.3, "E: expected finite values"),
])
def test_stiffness_matrix_rejects_bad_material(E, nu, match):
    """Non-positive E, nu outside (0, 0.5) and NaN are ValueErrors naming E or nu."""
    with pytest.raises(ValueError, match=match):
        fem.stiffness_matrix(rectangle_mesh(1.0, 1.0, 3, 3), E, nu)


def test_stiffness_matrix_rejects_wrong_number_of_elements():
    """Per-element arrays of the wrong length are rejected."""
    mesh = rectangle_mesh(1.0, 1.0, 3, 3)                    # 8 elements
    with pytest.raises(ValueError):
        fem.stiffness_matrix(mesh, np.full(5, 1e4), 0.3)


def test_single_element_stiffness_by_hand():
    """Right triangle (0,0),(1,0),(0,1), t=1: K = A B^T D B with the textbook B."""
    mesh = TriMesh([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]])
    B = np.array([[-1, 0, 1, 0, 0, 0],
                  [0, -1, 0, 0, 0, 1],
                  [-1, -1, 0, 1, 1, 0]], float)
    np.testing.assert_allclose(fem.strain_displacement(mesh)[0], B, atol=1e-15)
    K = dense(fem.stiffness_matrix(mesh, 2.0, 0.25))
    np.testing.assert_allclose(K, 0.5 * B.T @ textbook_D(2.0, 0.25) @ B, rtol=1e-14, atol=1e-15)


# --- sensitivities ---------------------------------------------------------------------------

@FAST
@given(meshes_with_materials(), st.data())
def test_element_stiffness_derivatives_match_central_differences(case, data):
    """dK/dE_e and dK/dnu_e (scattered alone) match central differences of stiffness_matrix."""
    mesh, E, nu = case
    dKdE, dKdnu = fem.element_stiffness_derivatives(mesh, E, nu)
    assert dKdE.shape == dKdnu.shape == (mesh.n_elements, 6, 6)
    e = data.draw(st.integers(0, mesh.n_elements - 1), label="element")
    unit = np.eye(mesh.n_elements)[e]

    hE = 1e-3 * E[e]
    fd_E = (dense(fem.stiffness_matrix(mesh, E + hE * unit, nu))
            - dense(fem.stiffness_matrix(mesh, E - hE * unit, nu))) / (2 * hE)
    exact_E = single_element_global(mesh, dKdE, e)
    np.testing.assert_allclose(exact_E, fd_E, rtol=0, atol=1e-7 * np.abs(exact_E).max())

    hnu = 1e-6
    fd_nu = (dense(fem.stiffness_matrix(mesh, E, nu + hnu * unit))
             - dense(fem.stiffness_matrix(mesh, E, nu - hnu * unit))) / (2 * hnu)
    exact_nu = single_element_global(mesh, dKdnu, e)
    np.testing.assert_allclose(exact_nu, fd_nu, rtol=0, atol=1e-5 * np.abs(exact_nu).max())


# --- mass ------------------------------------------------------------------------------------

@FAST
@given(mesh=jittered_grid_meshes(), rho=st.floats(100.0, 5000.0), t=st.floats(0.1, 2.0))
def test_mass_matrices_total_mass(mesh, rho, t):
    """Sum of all entries = 2 rho t area (two dofs per node); each direction carries rho t area."""
    area = mesh.areas.sum()
    ex = np.tile([1.0, 0.0], mesh.n_nodes)
    for lumped in (False, True):
        M = fem.mass_matrix(mesh, rho, thickness=t, lumped=lumped)
        assert M.sum() == pytest.approx(2 * rho * t * area, rel=1e-12)
        assert ex @ (M @ ex) == pytest.approx(rho * t * area, rel=1e-12)
        assert abs(ex @ (M @ (1 - ex))) < 1e-12 * rho * t * area      # no x-y coupling


@FAST
@given(mesh=jittered_grid_meshes(), data=st.data())
def test_consistent_mass_spd_and_lumped_diagonal(mesh, data):
    """Consistent M is symmetric positive definite; lumped M is its row-sum diagonal."""
    rho = data.draw(element_materials(mesh.n_elements).map(lambda m: m[0] / 100.0), label="rho")
    Mc = dense(fem.mass_matrix(mesh, rho))
    Ml = dense(fem.mass_matrix(mesh, rho, lumped=True))
    np.testing.assert_allclose(Mc, Mc.T, rtol=0, atol=1e-15 * np.abs(Mc).max())
    assert np.linalg.eigvalsh(Mc).min() > 0
    np.testing.assert_array_equal(Ml, np.diag(np.diag(Ml)))
    np.testing.assert_allclose(np.diag(Ml), Mc.sum(axis=1), rtol=1e-12)
    # a third of each element's mass per node
    node_mass = np.zeros(mesh.n_nodes)
    np.add.at(node_mass, mesh.elements.ravel(), np.repeat(rho * mesh.areas / 3.0, 3))
    np.testing.assert_allclose(np.diag(Ml)[0::2], node_mass, rtol=1e-12)


def test_consistent_element_mass_by_hand():
    """Unit right triangle, rho=12: M_e = rho A / 12 * [[2,1,1],[1,2,1],[1,1,2]] per direction."""
    mesh = TriMesh([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]])
    M = dense(fem.mass_matrix(mesh, 12.0))
    base = 0.5 * np.array([[2, 1, 1], [1, 2, 1], [1, 1, 2]], float)
    np.testing.assert_allclose(M[0::2, 0::2], base)
    np.testing.assert_allclose(M[1::2, 1::2], base)
    np.testing.assert_allclose(M[0::2, 1::2], 0.0)


@pytest.mark.parametrize("density, match", [
    (0.0, "density: expected a positive mass density in kg/m\\^3"),
    (-5.0, "density: expected a positive"),
    (np.nan, "density: expected finite values"),
])
def test_mass_matrix_rejects_bad_density(density, match):
    """Non-positive or NaN density is a ValueError naming `density`."""
    with pytest.raises(ValueError, match=match):
        fem.mass_matrix(rectangle_mesh(1.0, 1.0, 3, 3), density)


# --- damping ---------------------------------------------------------------------------------

def test_rayleigh_damping_is_modal():
    """C = alpha M + beta K; for M-orthonormal modes phi^T C phi = alpha + beta omega^2."""
    mesh = rectangle_mesh(0.02, 0.01, 4, 3)
    dm = fem.DofMap(mesh.n_dofs, fem.node_dofs(mesh.nodes_where(lambda x, y: x < 1e-12)))
    K = dm.restrict_matrix(fem.stiffness_matrix(mesh, E_TISSUE, NU_TISSUE))
    M = dm.restrict_matrix(fem.mass_matrix(mesh, RHO_TISSUE))
    alpha, beta = 10.0, 1e-3
    C = fem.rayleigh_damping(M, K, alpha, beta)
    np.testing.assert_allclose(dense(C), alpha * dense(M) + beta * dense(K), rtol=1e-15)
    omega2, phi = sla.eigh(dense(K), dense(M))
    modal = phi.T @ dense(C) @ phi
    np.testing.assert_allclose(np.diag(modal), alpha + beta * omega2, rtol=1e-9)
    np.testing.assert_allclose(modal - np.diag(np.diag(modal)), 0.0, atol=1e-9 * np.abs(modal).max())


@pytest.mark.parametrize("alpha, beta, match", [
    (-1.0, 0.0, "alpha: expected a non-negative finite number in 1/s"),
    (0.0, -1e-3, "beta: expected a non-negative finite number in s"),
    (np.inf, 0.0, "alpha"),
])
def test_rayleigh_damping_rejects_negative(alpha, beta, match):
    """Negative or infinite alpha/beta are ValueErrors naming the coefficient and unit."""
    M = sp.identity(2, format="csr")
    with pytest.raises(ValueError, match=match):
        fem.rayleigh_damping(M, M, alpha, beta)


# --- pressure loads --------------------------------------------------------------------------

@pytest.mark.parametrize("p", [1.0e3, -250.0])
def test_pressure_on_top_edge_of_rectangle(p):
    """Pressure on the top edge: total force (0, -p*width) per metre depth, half shares at the ends."""
    w, h, nx = 0.06, 0.02, 7
    mesh = rectangle_mesh(w, h, nx, 5)
    top = mesh.edges_where(lambda x, y: np.isclose(y, h))
    f = fem.pressure_load(mesh, top, p).reshape(-1, 2)
    assert f[:, 0].sum() == pytest.approx(0.0, abs=1e-12 * abs(p) * w)
    assert f[:, 1].sum() == pytest.approx(-p * w, rel=1e-12)
    top_nodes = mesh.nodes_where(lambda x, y: np.isclose(y, h))
    dx = w / (nx - 1)
    expected = np.full(nx, -p * dx)
    expected[[0, -1]] = -p * dx / 2
    np.testing.assert_allclose(f[top_nodes, 1], expected, rtol=1e-12)
    others = np.setdiff1d(np.arange(mesh.n_nodes), top_nodes)
    assert np.all(f[others] == 0.0)
    f2 = fem.pressure_load(mesh, top, p, thickness=0.5).reshape(-1, 2)
    np.testing.assert_allclose(f2, 0.5 * f)


@FAST
@given(points=lattice_point_clouds(min_points=6), p=st.floats(-1e4, 1e4), cut=st.floats(0.3, 1.0))
def test_uniform_pressure_on_closed_boundary(points, p, cut):
    """Uniform pressure on every boundary edge of a closed (possibly non-convex) body:
    zero resultant force, zero moment, and the work on u = x is -2 p t area."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    cx = lo[0] + cut * (hi[0] - lo[0]) + 1e-9

    def keep(c):                                               # notch the body: non-convex
        return ~((c[:, 0] > cx) & (c[:, 1] > 0.5 * (lo[1] + hi[1])))

    try:
        mesh = delaunay_mesh(points, keep=keep, min_angle_deg=0.0)
    except ValueError:
        mesh = delaunay_mesh(points, min_angle_deg=0.0)       # notch removed everything
    t = 0.7
    f = fem.pressure_load(mesh, mesh.boundary_edges(), p, thickness=t)
    F = f.reshape(-1, 2)
    size = np.abs(mesh.nodes).max()
    perimeter = np.linalg.norm(np.diff(mesh.nodes[mesh.boundary_edges()], axis=1), axis=2).sum()
    tol = 1e-12 * abs(p) * t * perimeter * size + 1e-300
    np.testing.assert_allclose(F.sum(axis=0), 0.0, atol=tol)
    moment = np.sum(mesh.nodes[:, 0] * F[:, 1] - mesh.nodes[:, 1] * F[:, 0])
    assert abs(moment) <= tol * size + 1e-300
    work = f @ mesh.nodes.ravel()
    assert work == pytest.approx(-2.0 * p * t * mesh.areas.sum(), rel=1e-9, abs=tol * size)


def test_positive_pressure_pushes_into_tissue():
    """On every boundary edge of a square, p > 0 gives nodal forces pointing inwards."""
    mesh = rectangle_mesh(1.0, 1.0, 2, 2)
    F = fem.pressure_load(mesh, mesh.boundary_edges(), 2.0).reshape(-1, 2)
    inward = mesh.nodes.mean(axis=0) - mesh.nodes
    assert np.all(np.sum(F * inward, axis=1) > 0)
    np.testing.assert_allclose(np.abs(F), 1.0)                   # p * L / 2 in x and in y at corners


# --- dof bookkeeping --------------------------------------------------------------------------

def test_node_dofs():
    """node_dofs is node-major, x before y, and can select one component."""
    np.testing.assert_array_equal(fem.node_dofs([3, 5]), [6, 7, 10, 11])
    np.testing.assert_array_equal(fem.node_dofs([3, 5], "x"), [6, 10])
    np.testing.assert_array_equal(fem.node_dofs([3, 5], "y"), [7, 11])
    np.testing.assert_array_equal(fem.node_dofs(4), [8, 9])


@FAST
@given(st.integers(1, 40).flatmap(
    lambda n: st.tuples(st.just(n), st.lists(st.integers(0, n - 1), max_size=2 * n))))
def test_dofmap_round_trip(case):
    """restrict(expand(v)) == v, expand(restrict(u)) zeroes exactly the fixed dofs."""
    n, fixed = case
    dm = fem.DofMap(n, fixed)
    fixed_set = sorted(set(fixed))
    np.testing.assert_array_equal(dm.fixed, fixed_set)
    np.testing.assert_array_equal(dm.free, [i for i in range(n) if i not in fixed_set])
    assert dm.n_free == n - len(fixed_set)
    rng = np.random.default_rng(n)
    v = rng.standard_normal((2, dm.n_free))                     # batched along leading axis
    np.testing.assert_array_equal(dm.restrict(dm.expand(v)), v)
    u = rng.standard_normal(n)
    back = dm.expand(dm.restrict(u))
    np.testing.assert_array_equal(back[dm.free], u[dm.free])
    assert np.all(back[dm.fixed] == 0)
    idx = dm.free_index()
    np.testing.assert_array_equal(idx[dm.free], np.arange(dm.n_free))
    assert np.all(idx[dm.fixed] == -1)
    A = rng.standard_normal((n, n))
    np.testing.assert_array_equal(dense(dm.restrict_matrix(sp.csr_matrix(A))), A[np.ix_(dm.free, dm.free)])


def test_dofmap_rejects_out_of_range():
    """Fixed dofs outside [0, n_dofs) are a ValueError naming `fixed`."""
    with pytest.raises(ValueError, match=r"fixed: expected dof indices in \[0, 9\]"):
        fem.DofMap(10, [0, 10])
    with pytest.raises(ValueError, match="fixed"):
        fem.DofMap(10, [-1])


# --- penalty constraints ----------------------------------------------------------------------

def test_penalty_stiffness_and_load_confidence_weighting():
    """Diagonal k*c; two constraints on one dof give the confidence-weighted mean target."""
    k = 1e6
    P = fem.penalty_stiffness(6, [1, 4, 4], k, confidence=[0.5, 0.25, 0.75])
    np.testing.assert_allclose(dense(P), np.diag([0, 0.5 * k, 0, 0, k, 0]))
    b = fem.penalty_load(6, [1, 4, 4], k, [2e-3, 1e-3, 5e-3], confidence=[0.5, 0.25, 0.75])
    np.testing.assert_allclose(b, [0, 0.5 * k * 2e-3, 0, 0, k * (0.25e-3 + 0.75 * 5e-3), 0])
    u = b[[1, 4]] / dense(P)[[1, 4], [1, 4]]
    np.testing.assert_allclose(u, [2e-3, 0.25 * 1e-3 + 0.75 * 5e-3])
    zero = fem.penalty_stiffness(6, [2], k, confidence=0.0)
    assert zero.nnz == 0 or np.all(zero.data == 0)


@FAST
@given(mesh=jittered_grid_meshes(), a=translations(), G=gradients())
def test_penalty_boundary_reproduces_linear_field(mesh, a, G):
    """Penalising every boundary dof to a linear field yields that field inside (patch test)."""
    K = fem.stiffness_matrix(mesh, E_TISSUE, NU_TISSUE)
    u_exact = linear_field(mesh, a, G)
    dofs = fem.node_dofs(mesh.boundary_nodes())
    k = 1e10 * abs(K).max()
    A = K + fem.penalty_stiffness(mesh.n_dofs, dofs, k)
    rhs = fem.penalty_load(mesh.n_dofs, dofs, k, u_exact[dofs])
    u = np.linalg.solve(dense(A), rhs)
    np.testing.assert_allclose(u, u_exact, rtol=0, atol=1e-7 * np.abs(u_exact).max() + 1e-15)


@pytest.mark.parametrize("confidence", [1.5, -0.1, [0.5, 2.0]])
def test_penalty_stiffness_rejects_confidence_outside_unit_interval(confidence):
    """Confidence weights outside [0, 1] are a ValueError naming `confidence`."""
    with pytest.raises(ValueError, match=r"confidence: expected values in \[0, 1\]"):
        fem.penalty_stiffness(6, [1, 2], 1e6, confidence=confidence)


@pytest.mark.parametrize("stiffness", [0.0, -1.0])
def test_penalty_stiffness_rejects_non_positive_stiffness(stiffness):
    """The penalty stiffness must be positive (N/m)."""
    with pytest.raises(ValueError, match="stiffness: expected a positive finite number in N/m"):
        fem.penalty_stiffness(6, [1], stiffness)


def test_penalty_load_rejects_wrong_target_shape():
    """One target per penalised dof."""
    with pytest.raises(ValueError, match=r"targets: expected shape \(2\)"):
        fem.penalty_load(6, [1, 2], 1e6, [1.0, 2.0, 3.0])


def test_penalty_load_rejects_confidence_outside_unit_interval():
    """penalty_load should reject the same bad confidence as penalty_stiffness."""
    with pytest.raises(ValueError, match=r"confidence: expected values in \[0, 1\]"):
        fem.penalty_load(6, [1], 1e6, [1e-3], confidence=1.5)


# --- independent assembly with scikit-fem ----------------------------------------------------

try:                                  # scikit-fem is a test extra; only these tests need it
    from skfem import (
        Basis,
        BilinearForm,
        ElementTriP0,
        ElementTriP1,
        ElementVector,
        MeshTri,
        asm,
    )
    from skfem.helpers import ddot, dot, eye, sym_grad, trace
    from skfem.models.elasticity import lame_parameters
except ImportError:                   # pragma: no cover
    BilinearForm = None
needs_skfem = pytest.mark.skipif(BilinearForm is None, reason="scikit-fem is not installed")


def _skfem_elasticity(u, v, w):
    """Linear elasticity with element-wise Lame parameters w.lam, w.mu."""
    strain = sym_grad(u)
    return ddot(2.0 * w.mu * strain + w.lam * eye(trace(strain), 2), sym_grad(v))


def _skfem_mass(u, v, w):
    return w.rho * dot(u, v)


def skfem_matrices(mesh, E, nu, rho):
    """K and consistent M assembled by scikit-fem, permuted to node-major x-before-y dofs."""
    m = MeshTri(np.ascontiguousarray(mesh.nodes.T), np.ascontiguousarray(mesh.elements.T))
    basis = Basis(m, ElementVector(ElementTriP1()))
    b0 = basis.with_element(ElementTriP0())
    # P0 dof e must be element e, i.e. scikit-fem keeps the element order.
    np.testing.assert_array_equal(b0.element_dofs.ravel(), np.arange(mesh.n_elements))
    lam, mu = lame_parameters(np.asarray(E, float), np.asarray(nu, float))
    K = asm(BilinearForm(_skfem_elasticity), basis, lam=b0.interpolate(lam), mu=b0.interpolate(mu))
    M = asm(BilinearForm(_skfem_mass), basis, rho=b0.interpolate(np.broadcast_to(rho, (mesh.n_elements,)).astype(float)))
    # nodal_dofs[c, i] is scikit-fem's dof of component c at node i; ours is 2 i + c.
    perm = basis.nodal_dofs.T.ravel()
    assert sorted(perm) == list(range(mesh.n_dofs))
    return dense(K)[np.ix_(perm, perm)], dense(M)[np.ix_(perm, perm)]


@needs_skfem
@FAST
@given(case=meshes_with_materials(), rho=st.floats(500.0, 2000.0))
def test_stiffness_and_mass_match_scikit_fem(case, rho):
    """K (per-element E, nu) and consistent M equal an independent scikit-fem assembly."""
    mesh, E, nu = case
    K_ref, M_ref = skfem_matrices(mesh, E, nu, rho)
    K = dense(fem.stiffness_matrix(mesh, E, nu))
    M = dense(fem.mass_matrix(mesh, rho))
    np.testing.assert_allclose(K, K_ref, rtol=0, atol=1e-10 * np.abs(K_ref).max())
    np.testing.assert_allclose(M, M_ref, rtol=0, atol=1e-12 * np.abs(M_ref).max())


@needs_skfem
@FAST
@given(points=lattice_point_clouds(), data=st.data())
def test_stiffness_matches_scikit_fem_on_arbitrary_delaunay_meshes(points, data):
    """Same comparison on unstructured lattice-point meshes with per-element density."""
    mesh = delaunay_mesh(points, min_angle_deg=0.0)
    E, nu = data.draw(element_materials(mesh.n_elements), label="material")
    rho = E / 50.0
    K_ref, M_ref = skfem_matrices(mesh, E, nu, rho)
    np.testing.assert_allclose(dense(fem.stiffness_matrix(mesh, E, nu)), K_ref,
                               rtol=0, atol=1e-10 * np.abs(K_ref).max())
    np.testing.assert_allclose(dense(fem.mass_matrix(mesh, rho)), M_ref,
                               rtol=0, atol=1e-12 * np.abs(M_ref).max())
