"""Tests of sfem_filters.fem.strain: element and nodal strains."""
import numpy as np
import pytest
from conftest import jittered_grid_meshes, lattice_point_clouds
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.fem.mesh import TriMesh, delaunay_mesh, rectangle_mesh
from sfem_filters.fem.strain import element_strains, nodal_average, nodal_strains

FAST = settings(max_examples=25, deadline=None)


def linear_field(mesh, a, G):
    """Global dof vector (node-major, x before y) of u(x) = a + G x."""
    return (np.asarray(a)[None, :] + mesh.nodes @ np.asarray(G).T).ravel()


gradients = st.lists(st.floats(-0.2, 0.2), min_size=4, max_size=4).map(lambda v: np.reshape(v, (2, 2)))
any_mesh = st.one_of(jittered_grid_meshes(),
                     lattice_point_clouds().map(lambda p: delaunay_mesh(p, min_angle_deg=0.0)))


# --- strain ----------------------------------------------------------------------------------

@FAST
@given(mesh=any_mesh, G=gradients)
def test_nodal_strains_of_linear_field_are_constant(mesh, G):
    """u = a + G x: every node gets (G11, G22, G12 + G21), engineering shear."""
    a = np.array([1e-4, -2e-4])
    eps = nodal_strains(mesh, linear_field(mesh, a, G))
    assert eps.shape == (mesh.n_nodes, 3)
    expected = np.array([G[0, 0], G[1, 1], G[0, 1] + G[1, 0]])
    scale = max(np.abs(G).max(), np.abs(a).max() / np.ptp(mesh.nodes, axis=0).max())
    np.testing.assert_allclose(eps, np.broadcast_to(expected, eps.shape), rtol=0, atol=1e-12 * scale)


def test_element_strains_simple_shear_and_stretch():
    """Known fields on a rectangle: uniaxial stretch and simple shear."""
    mesh = rectangle_mesh(0.02, 0.01, 5, 3)
    x, y = mesh.nodes.T
    stretch = np.column_stack([0.01 * x, np.zeros_like(y)]).ravel()
    np.testing.assert_allclose(element_strains(mesh, stretch), [[0.01, 0.0, 0.0]] * mesh.n_elements,
                               atol=1e-15)
    shear = np.column_stack([0.03 * y, np.zeros_like(x)]).ravel()
    np.testing.assert_allclose(element_strains(mesh, shear), [[0.0, 0.0, 0.03]] * mesh.n_elements,
                               atol=1e-15)


def test_element_strains_batched_and_linear():
    """Leading axes are batch axes; strains are linear in U."""
    mesh = rectangle_mesh(0.02, 0.01, 4, 3)
    rng = np.random.default_rng(1)
    U = rng.standard_normal((3, 2, mesh.n_dofs)) * 1e-4
    eps = element_strains(mesh, U)
    assert eps.shape == (3, 2, mesh.n_elements, 3)
    np.testing.assert_allclose(eps[1, 0], element_strains(mesh, U[1, 0]))
    np.testing.assert_allclose(element_strains(mesh, 2 * U[0, 0] - U[2, 1]),
                               2 * eps[0, 0] - eps[2, 1], atol=1e-15)
    assert nodal_strains(mesh, U).shape == (3, 2, mesh.n_nodes, 3)


def test_element_strains_rejects_wrong_length():
    """U must have n_dofs entries along its last axis; the error says how many."""
    mesh = rectangle_mesh(0.02, 0.01, 4, 3)
    with pytest.raises(ValueError, match=r"U: expected last axis of length 24 \(n_dofs\), got 23"):
        element_strains(mesh, np.zeros(23))


def test_nodal_average_is_area_weighted_two_elements():
    """Triangles of area 0.5 (value 1) and 1.5 (value 5) sharing an edge: shared nodes get
    (0.5*1 + 1.5*5)/2 = 4, not the plain mean 3."""
    mesh = TriMesh([[0, 0], [1, 0], [0, 1], [2, 2]], [[0, 1, 2], [1, 3, 2]])
    np.testing.assert_allclose(mesh.areas, [0.5, 1.5])
    out = nodal_average(mesh, [[1.0], [5.0]])
    np.testing.assert_allclose(out[:, 0], [1.0, 4.0, 4.0, 5.0])


@FAST
@given(mesh=jittered_grid_meshes(), c=st.floats(-10, 10))
def test_nodal_average_preserves_constants_and_bounds(mesh, c):
    """A constant element field averages to the constant; averages lie within the element range."""
    np.testing.assert_allclose(nodal_average(mesh, np.full((mesh.n_elements, 1), c)), c, atol=1e-12)
    v = np.sin(np.arange(mesh.n_elements, dtype=float))[:, None]
    avg = nodal_average(mesh, v)
    assert np.all(avg >= v.min() - 1e-12) and np.all(avg <= v.max() + 1e-12)
