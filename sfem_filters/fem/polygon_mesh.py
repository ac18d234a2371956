"""Quality triangle meshes of a polygonal region with holes at a chosen element size (Gmsh).

A region (the reference myocardium: an epicardial polygon with the endocardial polygon as a
hole) is meshed at an element size ``size`` chosen apart from the pixels, so that the cost of
a filter on it is set by the mesh and not by the image. Points anywhere in
the region are then observed through the element shape functions
(:func:`sfem_filters.fem.observation.point_observation_matrix`, Eq. 12 as an interpolation).

The mesher is Gmsh (Geuzaine & Remacle 2009, https://gmsh.info), its Frontal-Delaunay
algorithm for 2D (``Mesh.Algorithm = 6``), through the ``gmsh`` package on PyPI, whose wheel
ships the Gmsh library itself (no compiler, no system package). Why Gmsh: it is actively kept
(releases several times a year), it places nodes on the boundary at the requested spacing and
fills the interior with near-equilateral triangles (minimum angles typically above 30 degrees),
and it is the only candidate here with an unambiguous open-source licence: Gmsh is GPL-2.0-or-
later, an *optional* dependency of this BSD-3-Clause library (it is imported only when a mesh is
asked of it, and nothing of Gmsh is copied into or shipped with this package; a user who installs
it accepts its licence). The alternatives were rejected for their licences: ``triangle`` and
``meshpy`` wrap J. R. Shewchuk's Triangle, whose licence forbids commercial use without the
author's permission (``meshpy`` also bundles TetGen, AGPL); ``cgal``/``pygalmesh`` are GPL too
and heavier; ``dmsh`` is GPL and slow. Without ``gmsh`` installed, :func:`polygon_mesh` raises
an ``ImportError`` saying how to install it; the node-per-pixel mesh
(:func:`sfem_filters.cardiac.myocardium.tissue_mesh`) needs nothing beyond SciPy.

Units: whatever the polygons are in (metres for a :class:`~sfem_filters.fem.mesh.TriMesh` that
goes into the model); Gmsh itself meshes the region scaled by ``1 / size``, so that its absolute
geometric tolerances (1e-8) never merge points of a region measured in metres.

>>> import numpy as np
>>> from sfem_filters.fem.polygon_mesh import polygon_mesh, circle_polygon
>>> mesh = polygon_mesh(circle_polygon([0, 0], 10.0, 1.0), [circle_polygon([0, 0], 5.0, 1.0)], size=1.0)
>>> bool(abs(mesh.areas.sum() / (np.pi * (10 ** 2 - 5 ** 2)) - 1) < 0.01)
True
"""
from __future__ import annotations

import numpy as np

from .._validate import as_float_array, positive
from ..geometry import signed_area
from .mesh import TriMesh

__all__ = ["polygon_mesh", "circle_polygon", "resample_polygon", "edge_lengths", "GMSH_REQUIREMENT"]

#: The requirement to install for :func:`polygon_mesh` (an optional extra of this package).
GMSH_REQUIREMENT = "gmsh>=4.11"


def _polygon(name: str, xy) -> np.ndarray:
    p = as_float_array(name, xy, shape=(None, 2))
    if len(p) >= 2 and np.allclose(p[0], p[-1]):
        p = p[:-1]
    if len(p) < 3:
        raise ValueError(f"{name}: expected a closed polygon of at least 3 distinct vertices, got {len(p)}")
    if np.any(np.linalg.norm(np.diff(np.vstack([p, p[:1]]), axis=0), axis=1) <= 0):
        raise ValueError(f"{name}: expected distinct consecutive vertices, got a repeated vertex")
    if abs(signed_area(p)) <= 0:
        raise ValueError(f"{name}: expected a polygon enclosing some area, got zero area")
    return p


def circle_polygon(centre, radius: float, spacing: float) -> np.ndarray:
    """Vertices (n, 2) of a regular polygon inscribed in a circle, about ``spacing`` apart (n >= 8)."""
    c = as_float_array("centre", centre, shape=(2,))
    r = positive("radius", radius)
    h = positive("spacing", spacing)
    n = max(8, int(np.ceil(2 * np.pi * r / h)))
    a = 2 * np.pi * np.arange(n) / n
    return c + r * np.column_stack([np.cos(a), np.sin(a)])


def resample_polygon(xy, spacing: float) -> np.ndarray:
    """A closed polygon resampled at equal arc length, ``ceil(perimeter / spacing)`` vertices (>= 3).

    Starts at ``xy[0]``; the vertices lie on the original polygon (no smoothing).
    """
    p = _polygon("xy", xy)
    h = positive("spacing", spacing)
    closed = np.vstack([p, p[:1]])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
    n = max(3, int(np.ceil(s[-1] / h)))
    t = np.arange(n) * s[-1] / n
    return np.column_stack([np.interp(t, s, closed[:, 0]), np.interp(t, s, closed[:, 1])])


def edge_lengths(mesh: TriMesh) -> np.ndarray:
    """Lengths of the mesh's distinct edges (the mesh's units)."""
    e = mesh.elements
    edges = np.unique(np.sort(np.concatenate([e[:, [0, 1]], e[:, [1, 2]], e[:, [2, 0]]]), axis=1), axis=0)
    return np.linalg.norm(mesh.nodes[edges[:, 0]] - mesh.nodes[edges[:, 1]], axis=1)


def _import_gmsh():
    try:
        import gmsh                                   # optional dependency (GPL-2.0-or-later)
    except ImportError as exc:                        # pragma: no cover - depends on the environment
        raise ImportError(f"polygon_mesh needs Gmsh: pip install '{GMSH_REQUIREMENT}' (GPL-2.0-or-later, an optional "
                          "dependency); or use the node-per-pixel mesh, which needs nothing more (in the DENSE route "
                          "only with the point observation, resolution_px=1)") from exc
    return gmsh


def polygon_mesh(outer, holes=(), size: float = 1.0, boundary_spacing: float | None = None) -> TriMesh:
    """Mesh the region inside ``outer`` and outside every hole with triangles of edge about ``size``.

    The boundary polygons are first resampled at equal arc length (:func:`resample_polygon`,
    spacing ``boundary_spacing``, default ``size``), so the boundary nodes lie on the given
    polygons and the boundary edges have about the target length; Gmsh's Frontal-Delaunay
    algorithm (``Mesh.Algorithm = 6``) then fills the interior at a uniform target size.

    Parameters
    ----------
    outer : (n, 2) array
        Vertices of the outer boundary (any orientation, not repeating the first).
    holes : sequence of (m, 2) arrays
        Vertices of each hole (for the myocardium: the endocardium), inside ``outer``.
    size : float
        Target element edge length (same units as the vertices, > 0).
    boundary_spacing : float, optional
        Spacing of the boundary nodes (default ``size``).

    Returns
    -------
    TriMesh
        Counter-clockwise linear triangles; nodes in the polygons' units.

    Raises
    ------
    ImportError
        When ``gmsh`` is not installed (the message gives the requirement).
    ValueError
        Degenerate polygons, a non-positive size, or a mesh Gmsh could not make.
    """
    h = positive("size", size)
    hb = h if boundary_spacing is None else positive("boundary_spacing", boundary_spacing)
    loops = [resample_polygon(_polygon("outer", outer), hb)]
    for k, hole in enumerate(holes):
        loops.append(resample_polygon(_polygon(f"holes[{k}]", hole), hb))
    origin = loops[0].mean(axis=0)
    gmsh = _import_gmsh()
    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.option.setNumber("Mesh.Algorithm", 6)                 # Frontal-Delaunay
        gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
        gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
        gmsh.option.setNumber("Mesh.MeshSizeMin", 1.0)
        gmsh.option.setNumber("Mesh.MeshSizeMax", 1.0)
        gmsh.model.add("region")
        curve_loops = []
        for poly in loops:
            q = (poly - origin) / h                                  # units of the target size
            tags = [gmsh.model.geo.addPoint(float(x), float(y), 0.0, 1.0) for x, y in q]
            lines = [gmsh.model.geo.addLine(tags[i], tags[(i + 1) % len(tags)]) for i in range(len(tags))]
            curve_loops.append(gmsh.model.geo.addCurveLoop(lines))
        gmsh.model.geo.addPlaneSurface(curve_loops)
        gmsh.model.geo.synchronize()
        gmsh.model.mesh.generate(2)
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        types, _, elem_nodes = gmsh.model.mesh.getElements(2)
    except Exception as exc:
        raise ValueError(f"outer, holes: Gmsh could not mesh the region ({exc}); expected a simple outer polygon "
                         "with simple holes inside it, none crossing another") from None
    finally:
        gmsh.finalize()
    if 2 not in list(types):
        raise ValueError("outer, holes: Gmsh made no triangle; expected a region of positive area")
    tri_tags = np.asarray(elem_nodes[list(types).index(2)], np.int64).reshape(-1, 3)
    xyz = np.asarray(coords, float).reshape(-1, 3)
    used = np.unique(tri_tags)
    index = np.full(int(np.max(node_tags)) + 1, -1, np.int64)
    index[np.asarray(node_tags, np.int64)] = np.arange(len(node_tags))
    keep = index[used]
    remap = np.full(len(node_tags), -1, np.int64)
    remap[keep] = np.arange(len(keep))
    nodes = xyz[keep, :2] * h + origin
    return TriMesh(nodes, remap[index[tri_tags]])
