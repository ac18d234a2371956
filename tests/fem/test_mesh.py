"""Tests of sfem_filters.fem.mesh: numbering, orientation, boundaries, Delaunay meshing, validation."""
import numpy as np
import pytest
from conftest import jittered_grid_meshes, lattice_point_clouds
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull, Delaunay

from sfem_filters.fem.elasticity import stiffness_matrix
from sfem_filters.fem.mesh import (
    TriMesh,
    delaunay_mesh,
    lattice_mesh,
    mesh_quality,
    rectangle_mesh,
    triangle_angles,
)

FAST = settings(max_examples=25, deadline=None)


# --- helpers ---------------------------------------------------------------------------------

def signed_areas(nodes, elements):
    """Signed triangle areas computed independently of the library (positive = CCW)."""
    p = np.asarray(nodes)[np.asarray(elements)]
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])


def triangle_set(nodes, elements):
    """Triangles as a set of frozensets of vertex coordinate tuples (numbering independent)."""
    return {frozenset(map(tuple, np.asarray(nodes)[t])) for t in np.asarray(elements)}


def adjacent_element(mesh, edge):
    """Index of the single element containing both nodes of a boundary edge."""
    hits = [e for e, tri in enumerate(mesh.elements) if edge[0] in tri and edge[1] in tri]
    assert len(hits) == 1, f"boundary edge {edge} belongs to {len(hits)} elements"
    return hits[0]


def assert_boundary_outward(mesh):
    """Every boundary edge has its outward normal (dy, -dx) pointing away from its triangle."""
    centroids = mesh.centroids
    for a, b in mesh.boundary_edges():
        d = mesh.nodes[b] - mesh.nodes[a]
        normal = np.array([d[1], -d[0]])
        away = 0.5 * (mesh.nodes[a] + mesh.nodes[b]) - centroids[adjacent_element(mesh, (a, b))]
        assert normal @ away > 0


def assert_boundary_closed(mesh):
    """Boundary edges form closed loops: each boundary node starts as many edges as it ends."""
    edges = mesh.boundary_edges()
    starts = np.bincount(edges[:, 0], minlength=mesh.n_nodes)
    ends = np.bincount(edges[:, 1], minlength=mesh.n_nodes)
    np.testing.assert_array_equal(starts, ends)


# --- rectangle_mesh --------------------------------------------------------------------------

def test_rectangle_mesh_counts_and_node_numbering():
    """7x5 nodes: 35 nodes, 48 triangles; node j*nx+i sits at (i*w/(nx-1), j*h/(ny-1))."""
    w, h, nx, ny = 0.06, 0.02, 7, 5
    mesh = rectangle_mesh(w, h, nx, ny)
    assert (mesh.n_nodes, mesh.n_elements, mesh.n_dofs) == (35, 48, 70)
    for j in range(ny):
        for i in range(nx):
            np.testing.assert_allclose(mesh.nodes[j * nx + i], [i * w / (nx - 1), j * h / (ny - 1)],
                                       rtol=0, atol=1e-15)


def test_rectangle_mesh_diagonal_layout():
    """Each cell is split along its lower-left -> upper-right diagonal, first triangle below it."""
    nx, ny = 7, 5
    mesh = rectangle_mesh(0.06, 0.02, nx, ny)
    for j in range(ny - 1):
        for i in range(nx - 1):
            a = j * nx + i
            b, c, d = a + 1, a + nx + 1, a + nx
            k = 2 * (j * (nx - 1) + i)
            np.testing.assert_array_equal(mesh.elements[k], [a, b, c])
            np.testing.assert_array_equal(mesh.elements[k + 1], [a, c, d])


def test_rectangle_mesh_ccw_and_area():
    """All triangles are counter-clockwise, equal in area, and their areas sum to width*height."""
    w, h = 0.06, 0.02
    mesh = rectangle_mesh(w, h, 7, 5)
    area = signed_areas(mesh.nodes, mesh.elements)
    assert np.all(area > 0)
    np.testing.assert_allclose(area, w * h / 48, rtol=1e-12)
    np.testing.assert_allclose(mesh.areas, area, rtol=1e-12)
    assert mesh.areas.sum() == pytest.approx(w * h, rel=1e-12)
    np.testing.assert_allclose(mesh.centroids, mesh.nodes[mesh.elements].mean(axis=1))


def test_rectangle_element_dofs_node_major():
    """element_dofs lists x0 y0 x1 y1 x2 y2 with dof 2i = x and 2i+1 = y of node i."""
    mesh = rectangle_mesh(1.0, 1.0, 3, 3)
    e = mesh.elements
    expected = np.column_stack([2 * e[:, 0], 2 * e[:, 0] + 1, 2 * e[:, 1], 2 * e[:, 1] + 1,
                                2 * e[:, 2], 2 * e[:, 2] + 1])
    np.testing.assert_array_equal(mesh.element_dofs, expected)


def test_rectangle_boundary_edges_and_nodes():
    """The 7x5 rectangle has 20 boundary edges, oriented with the tissue on the left."""
    nx, ny = 7, 5
    mesh = rectangle_mesh(0.06, 0.02, nx, ny)
    edges = mesh.boundary_edges()
    assert edges.shape == (2 * (nx - 1) + 2 * (ny - 1), 2)
    assert_boundary_outward(mesh)
    assert_boundary_closed(mesh)
    x, y = mesh.nodes.T
    on_perimeter = np.flatnonzero(np.isclose(x, 0) | np.isclose(x, 0.06) | np.isclose(y, 0)
                                  | np.isclose(y, 0.02))
    np.testing.assert_array_equal(mesh.boundary_nodes(), on_perimeter)


def test_rectangle_bottom_edges_run_left_to_right():
    """With tissue on the left, the bottom edge is walked in +x and the top edge in -x."""
    mesh = rectangle_mesh(0.06, 0.02, 7, 5)
    bottom = mesh.edges_where(lambda x, y: np.isclose(y, 0.0))
    top = mesh.edges_where(lambda x, y: np.isclose(y, 0.02))
    assert len(bottom) == len(top) == 6
    assert np.all(mesh.nodes[bottom[:, 1], 0] > mesh.nodes[bottom[:, 0], 0])
    assert np.all(mesh.nodes[top[:, 1], 0] < mesh.nodes[top[:, 0], 0])


def test_nodes_where_selects_by_coordinates():
    """nodes_where returns the sorted indices whose coordinates satisfy the predicate."""
    mesh = rectangle_mesh(0.06, 0.02, 7, 5)
    left = mesh.nodes_where(lambda x, y: x < 1e-12)
    np.testing.assert_array_equal(left, np.arange(5) * 7)


@pytest.mark.parametrize("kwargs, match", [
    (dict(width=0.0, height=1.0, nx=3, ny=3), "width: expected a positive finite number in m"),
    (dict(width=1.0, height=-2.0, nx=3, ny=3), "height: expected a positive"),
    (dict(width=float("nan"), height=1.0, nx=3, ny=3), "width"),
    (dict(width=1.0, height=1.0, nx=1, ny=3), r"nx: expected an integer >= 2, got 1"),
    (dict(width=1.0, height=1.0, nx=3, ny=2.5), r"ny: expected an integer >= 2, got 2.5"),
])
def test_rectangle_mesh_rejects_bad_arguments(kwargs, match):
    """rectangle_mesh names the offending argument."""
    with pytest.raises(ValueError, match=match):
        rectangle_mesh(**kwargs)


# --- TriMesh orientation and validation -------------------------------------------------------

UNIT_SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])


def test_trimesh_reorients_clockwise_triangles():
    """Clockwise input triangles become counter-clockwise with the same vertices."""
    cw = np.array([[0, 2, 1], [0, 3, 2]])
    mesh = TriMesh(UNIT_SQUARE, cw)
    assert np.all(signed_areas(mesh.nodes, mesh.elements) > 0)
    assert [set(t) for t in mesh.elements] == [set(t) for t in cw]
    assert mesh.areas.sum() == pytest.approx(1.0)


def test_trimesh_is_read_only():
    """Node and element arrays are frozen so cached boundary data cannot go stale."""
    mesh = TriMesh(UNIT_SQUARE, [[0, 1, 2], [0, 2, 3]])
    with pytest.raises(ValueError):
        mesh.nodes[0, 0] = 5.0
    with pytest.raises(ValueError):
        mesh.elements[0, 0] = 3


@pytest.mark.parametrize("nodes, elements, match", [
    (np.array([[0, 0], [1, 0], [1, 0], [0, 1.0]]), [[0, 1, 3], [1, 2, 3]],
     "nodes: expected distinct node coordinates, got duplicate nodes"),
    (np.array([[0, 0], [1, 0], [2, 0], [0, 1.0]]), [[0, 1, 3], [0, 1, 2]],
     r"elements: triangle 1 is degenerate \(zero area\)"),
    (np.array([[0, 0], [1, 0], [np.nan, 1.0]]), [[0, 1, 2]],
     r"nodes: expected finite values, got 1 non-finite entries \(NaN or inf\)"),
    (np.array([[0, 0], [1, 0], [0, np.inf]]), [[0, 1, 2]], "nodes: expected finite values"),
    (np.zeros((3, 3)), [[0, 1, 2]], r"nodes: expected shape \(any, 2\), got shape \(3, 3\)"),
    (np.zeros(6), [[0, 1, 2]], r"nodes: expected shape \(any, 2\), got shape \(6,\)"),
    (UNIT_SQUARE, [[0, 1, 2, 3]], r"elements: expected shape \(any, 3\), got shape \(1, 4\)"),
    (UNIT_SQUARE, [0, 1, 2], r"elements: expected shape \(any, 3\), got shape \(3,\)"),
    (UNIT_SQUARE, np.zeros((0, 3), int), "elements: expected at least one triangle"),
    (UNIT_SQUARE, [[0, 1, 4]], r"elements: expected node indices in \[0, 3\], got range \[0, 4\]"),
    (UNIT_SQUARE, [[-1, 1, 2]], r"elements: expected node indices in \[0, 3\]"),
    (UNIT_SQUARE, [[0, 1, 1]], "elements: a triangle repeats a node index"),
])
def test_trimesh_rejects_bad_input(nodes, elements, match):
    """TriMesh raises ValueError naming the bad argument and what was wrong."""
    with pytest.raises(ValueError, match=match):
        TriMesh(nodes, elements)


def test_trimesh_rejects_fractional_element_indices():
    """Non-integer node indices are a TypeError naming `elements`; integral floats are accepted."""
    with pytest.raises(TypeError, match="elements: expected an integer array"):
        TriMesh(UNIT_SQUARE, [[0, 1, 2.5]])
    mesh = TriMesh(UNIT_SQUARE, np.array([[0.0, 1.0, 2.0], [0.0, 2.0, 3.0]]))
    assert mesh.elements.dtype.kind == "i"


def test_trimesh_rejects_unused_nodes():
    """A node outside every triangle would make K singular: an error naming `nodes`."""
    with pytest.raises(ValueError, match="nodes: node 3 belongs to no triangle"):
        TriMesh(UNIT_SQUARE, [[0, 1, 2]])


def test_trimesh_rejects_non_numeric_nodes():
    """Non-numeric coordinates are a TypeError naming `nodes`."""
    with pytest.raises(TypeError, match="nodes: expected an array of numbers"):
        TriMesh([["a", "b"], ["c", "d"], ["e", "f"]], [[0, 1, 2]])


def test_duplicate_detection_is_scale_invariant():
    """Distinct nodes a micrometre apart on a 1 cm mesh are accepted; exact duplicates are not."""
    nodes = np.array([[0, 0], [0.01, 0], [0, 0.01], [1e-6, 0.01]])
    mesh = TriMesh(nodes, [[0, 1, 2], [1, 3, 2]])
    assert mesh.n_nodes == 4


# --- quality measures -------------------------------------------------------------------------

def test_quality_of_equilateral_and_right_triangles():
    """Equilateral: angles 60, aspect ratio 1. Right isosceles: angles 45/45/90."""
    eq = TriMesh([[0, 0], [1, 0], [0.5, np.sqrt(3) / 2]], [[0, 1, 2]])
    np.testing.assert_allclose(triangle_angles(eq), 60.0, atol=1e-9)
    q = mesh_quality(eq)
    assert q["max_aspect_ratio"] == pytest.approx(1.0)
    assert q["min_angle_deg"] == pytest.approx(60.0)
    right = TriMesh([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]])
    np.testing.assert_allclose(np.sort(triangle_angles(right)[0]), [45, 45, 90], atol=1e-9)
    assert mesh_quality(right)["min_area_m2"] == pytest.approx(0.5)


# --- delaunay_mesh ----------------------------------------------------------------------------

@FAST
@given(lattice_point_clouds())
def test_delaunay_covers_convex_hull(points):
    """Without sliver removal the triangles are CCW and tile the convex hull exactly."""
    mesh = delaunay_mesh(points, min_angle_deg=0.0)
    area = signed_areas(mesh.nodes, mesh.elements)
    assert np.all(area > 0)
    assert area.sum() == pytest.approx(ConvexHull(points).volume, rel=1e-9)
    # the very triangles of scipy's Delaunay, none dropped or altered
    assert triangle_set(mesh.nodes, mesh.elements) == triangle_set(points, Delaunay(points).simplices)
    assert_boundary_outward(mesh)
    assert_boundary_closed(mesh)


@FAST
@given(lattice_point_clouds(min_points=8))
def test_delaunay_respects_keep(points):
    """Only the Delaunay triangles whose centroid passes `keep` remain; unused nodes are dropped."""
    cut = np.median(points[:, 0])

    def keep(c):
        return c[:, 0] <= cut

    all_tri = Delaunay(points).simplices
    kept = all_tri[keep(points[all_tri].mean(axis=1))]
    if len(kept) == 0:
        with pytest.raises(ValueError, match="keep: no triangle is left inside the tissue"):
            delaunay_mesh(points, keep=keep, min_angle_deg=0.0)
        return
    mesh = delaunay_mesh(points, keep=keep, min_angle_deg=0.0)
    assert np.all(mesh.centroids[:, 0] <= cut)
    assert triangle_set(mesh.nodes, mesh.elements) == triangle_set(points, kept)
    assert mesh.n_nodes == len(np.unique(kept))          # no orphan nodes
    assert mesh.areas.sum() == pytest.approx(np.abs(signed_areas(points, kept)).sum(), rel=1e-12)
    assert_boundary_outward(mesh)
    assert_boundary_closed(mesh)


@FAST
@given(jittered_grid_meshes())
def test_delaunay_meets_min_angle(mesh):
    """After hull sliver removal every angle is at least min_angle_deg and all triangles CCW."""
    assert triangle_angles(mesh).min() >= 1.0
    assert np.all(signed_areas(mesh.nodes, mesh.elements) > 0)
    assert_boundary_outward(mesh)


def test_delaunay_peels_hull_slivers():
    """A nearly flat Delaunay triangle on the hull is removed, the rest is kept."""
    pts = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.99]]) * 0.01
    full = delaunay_mesh(pts, min_angle_deg=0.0)
    peeled = delaunay_mesh(pts, min_angle_deg=5.0)
    assert triangle_angles(full).min() < 5.0
    assert peeled.n_elements == full.n_elements - 1
    assert triangle_angles(peeled).min() >= 5.0
    assert peeled.areas.sum() == pytest.approx(0.995e-4)          # square minus the sliver


def test_delaunay_peels_nested_hull_slivers():
    """Two stacked slivers along a slightly concave straight side are both peeled (docstring:
    'peel them off while they touch the boundary')."""
    pts = np.array([[0, 0], [0, 1], [0.5, 0], [0.5, 1], [0.5, 0.5],
                    [1, 0], [1, 1], [0.995, 0.4], [0.99, 0.6]]) * 0.01
    mesh = delaunay_mesh(pts)
    assert triangle_angles(mesh).min() >= 5.0


def test_delaunay_rejects_interior_sliver():
    """A sliver inside the tissue is an error that names `points` and min_angle_deg."""
    inner = np.radians([0, 1, 90, 180, 270])            # two points 1 degree apart on a circle
    outer = np.radians(np.arange(8) * 45 + 22.5)
    pts = 0.01 * np.vstack([np.column_stack([np.cos(inner), np.sin(inner)]),
                            3 * np.column_stack([np.cos(outer), np.sin(outer)])])
    with pytest.raises(ValueError, match=r"points: the triangulation has an interior triangle "
                                         r"with a 0\.\d+ degree angle \(min_angle_deg=5\.0\)"):
        delaunay_mesh(pts)
    assert delaunay_mesh(pts, min_angle_deg=0.1).n_nodes == len(pts)
    # the interior bound alone accepts it, while the hull keeps the stricter bound
    kept = delaunay_mesh(pts, interior_min_angle_deg=0.1)
    assert kept.n_nodes == len(pts) and len(kept.elements) == len(delaunay_mesh(pts, min_angle_deg=0.1).elements)
    with pytest.raises(ValueError, match=r"interior_min_angle_deg: expected an angle in \[0, min_angle_deg=5.0\]"):
        delaunay_mesh(pts, interior_min_angle_deg=6.0)


@pytest.mark.parametrize("points, match", [
    ([[0, 0], [1, 0], [0, 1], [1, 0]], "points: expected distinct points, got duplicates"),
    ([[0, 0], [1, 0]], "points: expected at least 3 points, got 2"),
    ([[0, 0], [1, 0], [0, np.nan]], "points: expected finite values"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], r"points: expected shape \(any, 2\), got shape \(3, 3\)"),
])
def test_delaunay_rejects_bad_points(points, match):
    """delaunay_mesh names `points` in its errors."""
    with pytest.raises(ValueError, match=match):
        delaunay_mesh(np.asarray(points, float))


def test_delaunay_keep_everything_removed():
    """A keep mask rejecting every triangle is an error naming `keep`."""
    pts = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], float)
    with pytest.raises(ValueError, match="keep: no triangle is left inside the tissue"):
        delaunay_mesh(pts, keep=lambda c: np.zeros(len(c), bool))


def test_delaunay_rejects_collinear_points():
    """All-collinear points cannot be triangulated: expect a ValueError naming `points`."""
    with pytest.raises(ValueError, match="points"):
        delaunay_mesh(np.array([[0.0, 0.0], [0.01, 0.0], [0.02, 0.0]]))


def test_delaunay_nearly_collinear_hull():
    """Three collinear hull points given in metres (1 mm lattice): Delaunay returns a flat hull
    triangle, which is a sliver and should be peeled, leaving the two real triangles."""
    pts = np.array([[-0.075, 0.017], [-0.073, 0.023], [-0.068, 0.038], [-0.064, 0.0]])
    mesh = delaunay_mesh(pts)
    assert mesh.areas.sum() == pytest.approx(ConvexHull(pts).volume)


# --- lattice meshes: one rule for every diagonal -------------------------------------------------

@st.composite
def lattice_tissue(draw, max_side=14):
    """Random tissue on a pixel lattice (integer coordinates), a generic centre, a spacing (m).

    The tissue is a random set of lattice points thickened so that most cells are full; the
    centre is kept off the half-integer lines so that no cell is a tie."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    w, h = draw(st.integers(3, max_side)), draw(st.integers(3, max_side))
    mask = rng.random((w, h)) < draw(st.floats(0.6, 1.0))
    mask[[0, 1, 0, 1], [0, 0, 1, 1]] = True                       # at least one full cell
    ij = np.argwhere(mask).astype(float)
    centre = np.array([draw(st.integers(-3, max_side + 3)), draw(st.integers(-3, max_side + 3))], float) \
        + np.array([draw(st.floats(0.01, 0.49)), draw(st.floats(0.01, 0.49))])
    return ij, centre, draw(st.sampled_from([1e-3, 1.5e-3, 0.7]))


#: The eight symmetries of the square lattice, as 2 x 2 integer matrices.
D4 = [np.array(m) for m in ([[1, 0], [0, 1]], [[0, -1], [1, 0]], [[-1, 0], [0, -1]], [[0, 1], [-1, 0]],
                            [[-1, 0], [0, 1]], [[1, 0], [0, -1]], [[0, 1], [1, 0]], [[0, -1], [-1, 0]])]


@FAST
@given(lattice_tissue(), st.integers(0, 7), st.tuples(st.integers(-50, 50), st.integers(-50, 50)))
def test_lattice_mesh_moves_with_its_points(tissue, k, shift):
    """Turning, mirroring or shifting the points and the centre on the lattice moves the mesh with
    them, triangle for triangle (a Delaunay triangulation does not: its ties follow the floats)."""
    ij, centre, h = tissue
    Rm, t = D4[k], np.array(shift, float)
    mesh = lattice_mesh(ij * h, h, centre * h)
    moved = lattice_mesh((ij @ Rm.T + t) * h, h, (centre @ Rm.T + t) * h)
    back = (np.asarray(moved.nodes) / h - t) @ Rm              # Rm is orthogonal: its inverse is Rm.T
    want = {frozenset(map(tuple, np.rint(np.asarray(mesh.nodes)[e] / h).astype(int).tolist()))
            for e in mesh.elements}
    got = {frozenset(map(tuple, np.rint(back[e]).astype(int).tolist())) for e in moved.elements}
    assert got == want


@FAST
@given(lattice_tissue())
def test_lattice_mesh_is_delaunay_but_for_the_diagonals(tissue):
    """The same nodes, the same number of triangles, the same boundary and area as Delaunay with
    max_edge 1.5 spacings; every full cell split along the diagonal that points to the centre."""
    ij, centre, h = tissue
    mesh = lattice_mesh(ij * h, h, centre * h)
    ref = delaunay_mesh(ij * h, max_edge=1.5 * h, min_angle_deg=10.0)
    assert triangle_set(mesh.nodes, mesh.boundary_edges()) == triangle_set(ref.nodes, ref.boundary_edges())
    assert mesh.n_elements == ref.n_elements
    assert {tuple(p) for p in np.asarray(mesh.nodes)} == {tuple(p) for p in np.asarray(ref.nodes)}
    np.testing.assert_allclose(signed_areas(mesh.nodes, mesh.elements).sum(),
                               signed_areas(ref.nodes, ref.elements).sum(), rtol=1e-12)
    assert np.all(signed_areas(mesh.nodes, mesh.elements) > 0)
    # the diagonal of every full cell: the edge of length sqrt(2) spacings shared by two triangles
    nodes = np.asarray(mesh.nodes) / h
    edges = np.sort(np.concatenate([mesh.elements[:, [0, 1]], mesh.elements[:, [1, 2]], mesh.elements[:, [2, 0]]]), 1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    diag = uniq[(counts == 2) & np.isclose(np.linalg.norm(nodes[uniq[:, 0]] - nodes[uniq[:, 1]], axis=1), np.sqrt(2))]
    assert len(diag) > 0
    d = nodes[diag[:, 1]] - nodes[diag[:, 0]]
    r = 0.5 * (nodes[diag[:, 0]] + nodes[diag[:, 1]]) - centre
    radial = np.abs(np.sum(d * r, axis=1)) / np.linalg.norm(d, axis=1)
    other = np.abs(d[:, 0] * r[:, 1] - d[:, 1] * r[:, 0]) / np.linalg.norm(d, axis=1)   # r on the other diagonal
    assert np.all(radial > other)


def test_lattice_mesh_ties_take_one_diagonal_that_a_half_turn_keeps():
    """A ring centred on a lattice cell's centre: the cells on its axes are ties, split along (1, 1)."""
    yy, xx = np.mgrid[0:16, 0:16]
    ring = np.hypot(xx - 7.5, yy - 7.5)
    ij = np.argwhere((ring >= 4) & (ring <= 7)).astype(float)
    mesh = lattice_mesh(ij * 1e-3, 1e-3, np.array([7.5, 7.5]) * 1e-3)
    turned = lattice_mesh((15 - ij) * 1e-3, 1e-3, np.array([7.5, 7.5]) * 1e-3)
    assert triangle_set(np.rint(np.asarray(mesh.nodes) * 1e3), mesh.elements) == \
        triangle_set(15 - np.rint(np.asarray(turned.nodes) * 1e3), turned.elements)
    # a tie cell: lower-left corner (7, 1), centre (7.5, 1.5) on the vertical axis line
    cell = {(7.0, 1.0), (8.0, 1.0), (8.0, 2.0), (7.0, 2.0)}
    n = np.rint(np.asarray(mesh.nodes) * 1e3)
    inside = [set(map(tuple, n[e])) for e in mesh.elements if set(map(tuple, n[e])) <= cell]
    assert len(inside) == 2 and all({(7.0, 1.0), (8.0, 2.0)} <= t for t in inside)


def test_lattice_mesh_stiffness_has_only_rigid_motions_in_its_kernel():
    yy, xx = np.mgrid[0:12, 0:12]
    ring = np.hypot(xx - 5.3, yy - 5.8)
    ij = np.argwhere((ring >= 3) & (ring <= 5.5)).astype(float)
    mesh = lattice_mesh(ij * 1e-3, 1e-3, np.array([5.3, 5.8]) * 1e-3)
    K = stiffness_matrix(mesh, np.full(mesh.n_elements, 10e3), np.full(mesh.n_elements, 0.4)).toarray()
    np.testing.assert_allclose(K, K.T, rtol=0, atol=1e-12 * np.abs(K).max())
    lam = np.linalg.eigvalsh(K)
    assert np.sum(lam < 1e-9 * lam.max()) == 3 and lam.min() > -1e-9 * lam.max()


@pytest.mark.parametrize("args, match", [
    ((np.array([[0.0, 0.0], [1e-3, 0.0], [0.0, 1.2e-3]]), 1e-3, [0.0, 0.0]), "points: expected points on an axis-aligned"),
    ((np.array([[0.0, 0.0], [1e-3, 0.0], [1e-3, 0.0]]), 1e-3, [0.0, 0.0]), "points: expected distinct"),
    ((np.array([[0.0, 0.0], [1e-3, 0.0], [2e-3, 0.0]]), 1e-3, [0.0, 0.0]), "points: no lattice cell"),
    ((np.array([[0.0, 0.0], [1e-3, 0.0], [0.0, 1e-3]]), 0.0, [0.0, 0.0]), "spacing"),
    ((np.array([[0.0, 0.0], [1e-3, 0.0], [0.0, 1e-3]]), 1e-3, [0.0]), "centre"),
])
def test_lattice_mesh_rejects_bad_input(args, match):
    with pytest.raises(ValueError, match=match):
        lattice_mesh(*args)
