"""Triangle meshes of the myocardium (or of the synthetic rectangle).

A :class:`TriMesh` holds node coordinates in metres and counter-clockwise linear triangles.
Degrees of freedom are numbered node-major, x before y: dof ``2*i`` is the x displacement of
node ``i`` and ``2*i + 1`` its y displacement.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import Delaunay

from .._validate import as_float_array, positive
from ..geometry import triangle_angles_deg, triangle_double_areas


@dataclass(frozen=True, eq=False)
class TriMesh:
    """A 2D mesh of linear triangles.

    Parameters
    ----------
    nodes : (n_nodes, 2) array of float
        Node coordinates in metres.
    elements : (n_elements, 3) array of int
        Node indices of each triangle. Clockwise triangles are reoriented to
        counter-clockwise; degenerate triangles, duplicate nodes and nodes that belong to no
        triangle are rejected. Meshes compare by identity.
    """

    nodes: np.ndarray
    elements: np.ndarray
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        nodes = as_float_array("nodes", self.nodes, shape=(None, 2))
        try:
            elements = np.asarray(self.elements)
            if elements.dtype.kind not in "iu":
                if elements.size and not np.all(np.asarray(elements, float) == np.round(elements)):
                    raise TypeError
            elements = elements.astype(np.int64)
        except (TypeError, ValueError):
            raise TypeError("elements: expected an integer array of node indices") from None
        if elements.ndim != 2 or elements.shape[1] != 3:
            raise ValueError(f"elements: expected shape (any, 3), got shape {elements.shape}")
        if len(elements) == 0:
            raise ValueError("elements: expected at least one triangle, got none")
        if elements.min() < 0 or elements.max() >= len(nodes):
            raise ValueError(
                f"elements: expected node indices in [0, {len(nodes) - 1}], "
                f"got range [{elements.min()}, {elements.max()}]")
        if np.any((elements[:, 0] == elements[:, 1]) | (elements[:, 1] == elements[:, 2])
                  | (elements[:, 0] == elements[:, 2])):
            raise ValueError("elements: a triangle repeats a node index")
        unused = np.setdiff1d(np.arange(len(nodes)), elements)
        if unused.size:
            raise ValueError(f"nodes: node {int(unused[0])} belongs to no triangle "
                             f"({unused.size} unused nodes); drop them")
        rounded = np.round(nodes / max(np.ptp(nodes), 1e-300), 12)
        uniq, first, inverse = np.unique(rounded, axis=0, return_index=True, return_inverse=True)
        if len(uniq) != len(nodes):
            dup = int(np.flatnonzero(first[inverse.ravel()] != np.arange(len(nodes)))[0])
            raise ValueError(f"nodes: expected distinct node coordinates, got duplicate nodes "
                             f"({int(first[inverse.ravel()[dup]])} and {dup} at {tuple(nodes[dup].tolist())} m)")
        area2 = triangle_double_areas(nodes, elements)
        scale = max(np.ptp(nodes[:, 0]), np.ptp(nodes[:, 1])) ** 2
        if np.any(np.abs(area2) <= 1e-12 * scale):
            bad = int(np.argmin(np.abs(area2)))
            raise ValueError(f"elements: triangle {bad} is degenerate (zero area): expected triangles of "
                             f"non-zero area, got collinear nodes {tuple(elements[bad].tolist())}")
        elements = elements.copy()
        cw = area2 < 0
        elements[cw] = elements[cw][:, [0, 2, 1]]
        _check_not_folded(elements)
        nodes.setflags(write=False)
        elements.setflags(write=False)
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "elements", elements)

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return len(self.nodes)

    @property
    def n_elements(self) -> int:
        """Number of triangles."""
        return len(self.elements)

    @property
    def n_dofs(self) -> int:
        """Number of global dofs: two per node (x and y displacement)."""
        return 2 * len(self.nodes)

    @property
    def areas(self) -> np.ndarray:
        """Element areas in m^2."""
        return 0.5 * triangle_double_areas(self.nodes, self.elements)

    @property
    def centroids(self) -> np.ndarray:
        """Element centroids in metres, shape (n_elements, 2)."""
        return self.nodes[self.elements].mean(axis=1)

    @property
    def element_dofs(self) -> np.ndarray:
        """Global dof indices of each element, shape (n_elements, 6), ordered x0 y0 x1 y1 x2 y2."""
        e = self.elements
        return np.stack([2 * e[:, 0], 2 * e[:, 0] + 1, 2 * e[:, 1], 2 * e[:, 1] + 1,
                         2 * e[:, 2], 2 * e[:, 2] + 1], axis=1)

    def boundary_edges(self) -> np.ndarray:
        """Boundary edges as (n_edges, 2) node pairs, oriented with the tissue on the left."""
        if "boundary_edges" not in self._cache:
            e = self.elements
            edges = np.concatenate([e[:, [0, 1]], e[:, [1, 2]], e[:, [2, 0]]])
            key = np.sort(edges, axis=1)
            _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
            self._cache["boundary_edges"] = edges[counts[inverse.ravel()] == 1]
        return self._cache["boundary_edges"]

    def boundary_nodes(self) -> np.ndarray:
        """Sorted indices of nodes on the boundary."""
        return np.unique(self.boundary_edges())

    def nodes_where(self, predicate) -> np.ndarray:
        """Sorted indices of nodes whose coordinates satisfy ``predicate(x, y)`` (metres)."""
        return np.flatnonzero(predicate(self.nodes[:, 0], self.nodes[:, 1]))

    def edges_where(self, predicate) -> np.ndarray:
        """Boundary edges both of whose nodes satisfy ``predicate(x, y)``."""
        edges = self.boundary_edges()
        ok = predicate(self.nodes[:, 0], self.nodes[:, 1])
        return edges[ok[edges[:, 0]] & ok[edges[:, 1]]]


def check_mesh(name: str, mesh) -> "TriMesh":
    """Check that the argument ``name`` is a :class:`TriMesh` (a ``TypeError`` naming it if not)."""
    if not isinstance(mesh, TriMesh):
        raise TypeError(f"{name}: expected a TriMesh, got {type(mesh).__name__}")
    return mesh


def _check_not_folded(elements: np.ndarray) -> None:
    """Reject inverted (folded) triangles: with every triangle counter-clockwise, two
    triangles sharing an edge must traverse it in opposite directions; the same direction
    means they lie on the same side of it, i.e. one is inverted and they overlap."""
    edges = np.concatenate([elements[:, [0, 1]], elements[:, [1, 2]], elements[:, [2, 0]]])
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    if np.any(counts > 1):
        k = int(np.flatnonzero(counts[inverse.ravel()] > 1)[0])
        owners = np.flatnonzero(inverse.ravel() == inverse.ravel()[k]) % len(elements)
        raise ValueError(f"elements: expected a mesh without inverted (folded) triangles, got triangles "
                         f"{int(owners[0])} and {int(owners[1])} overlapping across edge {tuple(edges[k].tolist())}")


def rectangle_mesh(width: float, height: float, nx: int, ny: int) -> TriMesh:
    """Structured mesh of a rectangle ``[0, width] x [0, height]``.

    Parameters
    ----------
    width, height : float
        Side lengths in metres.
    nx, ny : int
        Number of nodes along x and y (at least 2 each).

    Returns
    -------
    TriMesh
        Nodes numbered row by row from the lower-left corner, x fastest
        (node ``j*nx + i`` is at ``(i*width/(nx-1), j*height/(ny-1))``); each cell is
        split into two triangles along its lower-left to upper-right diagonal.
    """
    width = positive("width", width, "m")
    height = positive("height", height, "m")
    for name, v in (("nx", nx), ("ny", ny)):
        if int(v) != v or v < 2:
            raise ValueError(f"{name}: expected an integer >= 2, got {v!r}")
    nx, ny = int(nx), int(ny)
    x = np.linspace(0.0, width, nx)
    y = np.linspace(0.0, height, ny)
    X, Y = np.meshgrid(x, y)
    nodes = np.column_stack([X.ravel(), Y.ravel()])
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    a = (j * nx + i).ravel()
    b, c, d = a + 1, a + nx + 1, a + nx
    tri = np.empty((2 * a.size, 3), dtype=np.int64)
    tri[0::2] = np.column_stack([a, b, c])
    tri[1::2] = np.column_stack([a, c, d])
    return TriMesh(nodes, tri)


def triangle_angles(mesh: TriMesh) -> np.ndarray:
    """Interior angles of every triangle in degrees, shape (n_elements, 3)."""
    check_mesh("mesh", mesh)
    return triangle_angles_deg(mesh.nodes, mesh.elements)


def mesh_quality(mesh: TriMesh) -> dict:
    """Quality summary: minimum angle (degrees), maximum aspect ratio, area range (m^2).

    The aspect ratio is ``L_max * perimeter / (4 * sqrt(3) * area)``, which is 1 for an
    equilateral triangle and grows without bound as a triangle flattens.
    """
    check_mesh("mesh", mesh)
    p = mesh.nodes[mesh.elements]
    lengths = np.linalg.norm(p - p[:, [1, 2, 0]], axis=2)
    area = mesh.areas
    aspect = lengths.max(axis=1) * lengths.sum(axis=1) / (4.0 * np.sqrt(3.0) * area)
    return {"min_angle_deg": float(triangle_angles(mesh).min()),
            "max_aspect_ratio": float(aspect.max()),
            "min_area_m2": float(area.min()),
            "max_area_m2": float(area.max())}


def delaunay_triangles(points) -> np.ndarray:
    """Delaunay triangles (m, 3) of points (n, 2) (scipy's Qhull), a named error where none exist.

    Collinear or otherwise degenerate point sets raise ``ValueError`` naming ``points`` instead
    of Qhull's own exception."""
    try:
        return Delaunay(np.asarray(points, float)).simplices
    except Exception as exc:  # scipy's QhullError: all points collinear, or too few distinct
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"points: cannot be triangulated (collinear or degenerate point set; Qhull: {first})") from None


def delaunay_mesh(points, keep=None, min_angle_deg: float = 5.0, max_edge: float | None = None,
                  interior_min_angle_deg: float | None = None) -> TriMesh:
    """Mesh arbitrary points by Delaunay triangulation (scipy), then check quality.

    Parameters
    ----------
    points : (n, 2) array of float
        Node coordinates in metres; must be distinct.
    keep : callable, optional
        ``keep(centroids) -> bool array`` selecting the triangles that lie in the tissue
        (for example inside a myocardium mask); triangles outside are removed, and nodes
        left without a triangle are dropped.
    min_angle_deg : float
        Triangles with a smaller interior angle than this (degrees) are slivers: they are
        removed from the hull; if one remains inside the tissue an error is raised.
    max_edge : float, optional
        Triangles with an edge longer than this (metres) are removed first (they bridge a
        cavity or a concavity of the tissue).
    interior_min_angle_deg : float, optional
        The bound for triangles inside the tissue, which are not peeled (default
        ``min_angle_deg``): scattered points give Delaunay slivers that no triangulation of
        those points avoids; a lower bound here accepts them while the hull is still peeled.

    Returns
    -------
    TriMesh
    """
    pts = as_float_array("points", points, shape=(None, 2))
    if len(pts) < 3:
        raise ValueError(f"points: expected at least 3 points, got {len(pts)}")
    if len(np.unique(pts, axis=0)) != len(pts):
        raise ValueError(f"points: expected distinct points, got duplicates ({len(pts) - len(np.unique(pts, axis=0))} repeated)")
    min_angle_deg = float(min_angle_deg)
    if not 0 <= min_angle_deg < 60:
        raise ValueError(f"min_angle_deg: expected an angle in [0, 60) degrees, got {min_angle_deg!r}")
    interior = min_angle_deg if interior_min_angle_deg is None else float(interior_min_angle_deg)
    if not 0 <= interior <= min_angle_deg:
        raise ValueError(f"interior_min_angle_deg: expected an angle in [0, min_angle_deg={min_angle_deg}] degrees, "
                         f"got {interior_min_angle_deg!r}")
    tri = delaunay_triangles(pts)
    if max_edge is not None:
        q = pts[tri]
        longest = np.linalg.norm(q - q[:, [1, 2, 0]], axis=2).max(axis=1)
        tri = tri[longest <= positive("max_edge", max_edge, "m") * (1 + 1e-9)]
    if keep is not None:
        tri = tri[np.asarray(keep(pts[tri].mean(axis=1)), bool)]
    scale = max(np.ptp(pts[:, 0]), np.ptp(pts[:, 1])) ** 2
    while True:
        if len(tri) == 0:
            raise ValueError("keep: no triangle is left inside the tissue" if keep is not None else
                             "points: no triangle of acceptable quality is left")
        flat = np.abs(triangle_double_areas(pts, tri)) <= 1e-12 * scale
        angles = np.where(flat, 0.0, triangle_angles_deg(pts, tri).min(axis=1))
        # Slivers and flat triangles on the hull are artefacts of Delaunay: peel those that
        # touch the boundary, layer by layer; a bad triangle that never reaches the boundary
        # lies inside the tissue and is a real quality problem.
        peel = (flat | (angles < min_angle_deg)) & _touches_boundary(tri)
        if peel.any():
            tri = tri[~peel]
            continue
        bad = flat | (angles < interior)
        if bad.any():
            raise ValueError(
                f"points: the triangulation has an interior triangle with a {angles[bad].min():.2f} "
                f"degree angle ({'min_angle_deg' if interior_min_angle_deg is None else 'interior_min_angle_deg'}"
                f"={interior}); add or move points")
        break
    used = np.unique(tri)
    remap = -np.ones(len(pts), np.int64)
    remap[used] = np.arange(len(used))
    return TriMesh(pts[used], remap[tri])


def lattice_offset(points, spacing: float) -> tuple:
    """How far points (n, 2) lie from an axis-aligned square lattice of ``spacing`` (both m).

    Returns the largest distance of a point from its nearest lattice node, in spacings (per
    axis), and the integer lattice indices (n, 2) of those nodes, counted from the points' lower
    corner (the lattice's origin is taken from the points themselves)."""
    pts = np.asarray(points, float)
    grid = (pts - pts.min(axis=0)) / spacing
    ij = np.rint(grid).astype(np.int64)
    return float(np.abs(grid - ij).max()), ij


def lattice_mesh(points, spacing: float, centre, max_offset: float = 1e-6) -> TriMesh:
    """Mesh the points of an axis-aligned square lattice, every diagonal chosen by one rule.

    The four corners of a lattice cell are cocircular, so a Delaunay triangulation
    (:func:`delaunay_mesh`) may split a full cell along either diagonal, and which one it takes
    depends on the floating-point coordinates: translating, rotating by 90 or 180 degrees or
    mirroring the same points on the lattice changes about a third of the triangles (and with
    them the stiffness). Here a cell whose 4 corners are points gives two triangles split along
    its *radial* diagonal, the one that points towards ``centre``: with ``r`` the offset of the
    cell's centre from ``centre``, the diagonal (1, 1) where ``r_x r_y > 0`` and (1, -1) where
    ``r_x r_y < 0``. A cell with 3 corners gives its one triangle; fewer, none. The result is
    equivariant: moving the points and ``centre`` together by a translation, a rotation by a
    multiple of 90 degrees or a reflection of the lattice moves the mesh with them, triangle for
    triangle. The one exception are ties, cells whose centre lies on the horizontal or vertical
    line through ``centre`` (``|r_x r_y| <= 1e-9 spacing^2``): they take the diagonal (1, 1),
    which a translation and a rotation by 180 degrees keep but a quarter turn or a reflection
    does not. Apart from the diagonals the triangles are those of :func:`delaunay_mesh` with
    ``max_edge = 1.5 spacing``: the same cells, the same boundary.

    Parameters
    ----------
    points : (n, 2) array of float
        Node coordinates in metres, on a square lattice of ``spacing`` aligned with the axes
        (any origin); distinct.
    spacing : float
        Lattice spacing in metres (> 0).
    centre : (2,) array of float
        The point the diagonals point towards, in metres (for a myocardium, the cavity centre).
    max_offset : float
        Largest admissible distance of a point from the lattice, in spacings.

    Returns
    -------
    TriMesh
        Nodes are the given points in their order; points in no triangle are dropped.

    Raises
    ------
    ValueError
        Points off the lattice (naming the largest offset), duplicates, or no triangle at all.
    """
    pts = as_float_array("points", points, shape=(None, 2))
    h = positive("spacing", spacing, "m")
    c = as_float_array("centre", centre, shape=(2,))
    if len(pts) < 3:
        raise ValueError(f"points: expected at least 3 points, got {len(pts)}")
    off, ij = lattice_offset(pts, h)
    if off > max_offset:
        raise ValueError(f"points: expected points on an axis-aligned square lattice of spacing {h:g} m, got a "
                         f"point {off:.3g} spacings off it")
    shape = ij.max(axis=0) + 2
    index = -np.ones(shape, np.int64)
    index[ij[:, 0], ij[:, 1]] = np.arange(len(pts))
    if np.count_nonzero(index >= 0) != len(pts):
        raise ValueError(f"points: expected distinct points, got {len(pts) - np.count_nonzero(index >= 0)} "
                         "repeated on the lattice")
    # corners of every cell (i, j): a = (i, j), b = (i+1, j), q = (i+1, j+1), d = (i, j+1)
    a, b = index[:-1, :-1], index[1:, :-1]
    q, d = index[1:, 1:], index[:-1, 1:]
    corners = np.stack([a, b, q, d], axis=-1).reshape(-1, 4)
    present = corners >= 0
    n_present = present.sum(axis=1)
    cells = np.stack(np.meshgrid(np.arange(shape[0] - 1), np.arange(shape[1] - 1), indexing="ij"),
                     axis=-1).reshape(-1, 2)
    full = n_present == 4
    r = pts.min(axis=0) + (cells[full] + 0.5) * h - c      # the lattice's origin, as lattice_offset's
    radial_11 = r[:, 0] * r[:, 1] >= -1e-9 * h * h          # ties (on an axis line) take (1, 1)
    k = corners[full]
    tri_11 = np.concatenate([k[radial_11][:, [0, 1, 2]], k[radial_11][:, [0, 2, 3]]])
    tri_1m = np.concatenate([k[~radial_11][:, [0, 1, 3]], k[~radial_11][:, [1, 2, 3]]])
    three = corners[n_present == 3]
    tri_3 = three[three >= 0].reshape(-1, 3)               # the 3 present corners, in cell order
    tri = np.concatenate([tri_11, tri_1m, tri_3])
    if len(tri) == 0:
        raise ValueError("points: no lattice cell has 3 of its corners among the points; nothing to mesh")
    used = np.unique(tri)
    remap = -np.ones(len(pts), np.int64)
    remap[used] = np.arange(len(used))
    return TriMesh(pts[used], remap[tri])


def _touches_boundary(tri: np.ndarray) -> np.ndarray:
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    _, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    single = (counts[inverse.ravel()] == 1).reshape(3, len(tri))
    return single.any(axis=0)
