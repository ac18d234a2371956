"""Myocardial geometry of a short-axis slice: mesh, contours, wall layers and directions.

Coordinates are in metres (convert pixels with the pixel spacing first). The cavity centre is
the centroid of the endocardial contour. The radial direction points away from it; the
circumferential direction is the radial one turned by +90 degrees in the (x, y) plane
(counter-clockwise when y points up; on an image with y down it appears clockwise).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import scipy.sparse as sp
from scipy.spatial import cKDTree
from skimage.measure import label

from .._validate import as_float_array, as_mask, integer, positive
from ..fem.mesh import TriMesh, check_mesh, delaunay_mesh, delaunay_triangles, lattice_offset, mesh_quality
from ..fem.strain import nodal_strain_operator
from ..geometry import polygon_centroid, radius_by_angle, signed_area


def mesh_from_points(points, max_edge: float, inside=None, min_angle_deg: float = 10.0,
                     interior_min_angle_deg: float | None = None) -> TriMesh:
    """Delaunay mesh of tissue points, keeping triangles that lie in the tissue.

    Parameters
    ----------
    points : (n, 2) array
        Node positions in metres (for example the centres of the myocardial pixels).
    max_edge : float
        Longest admissible edge in metres: triangles bridging the cavity or a concavity have
        longer edges and are removed (1.5 pixel spacings suits a pixel lattice).
    inside : callable, optional
        ``inside(xy) -> bool array``: an extra test of triangle centroids (for example a mask).
    min_angle_deg, interior_min_angle_deg : float
        Quality bounds passed to :func:`sfem_filters.fem.mesh.delaunay_mesh` (the hull's slivers
        are peeled; an interior triangle below the second, default the first, is an error).

    Returns
    -------
    TriMesh
        Nodes are the given points in their order when every point is used; points that end up
        in no triangle are dropped (check ``mesh.n_nodes``).
    """
    return delaunay_mesh(points, keep=inside, min_angle_deg=min_angle_deg, max_edge=max_edge,
                         interior_min_angle_deg=interior_min_angle_deg)


def tissue_mesh(points, edge_factor: float = 1.5, max_factor: float = 4.0,
                min_angle_deg: float = 10.0, interior_min_angle_deg: float = 1.0) -> tuple:
    """Mesh an annular slice's tissue points, on a pixel lattice or scattered, using every point.

    The longest admissible edge starts at ``edge_factor`` times the median nearest-neighbour
    distance ``h`` (on a pixel lattice, 1.5 spacings: the cells and their diagonals, nothing that
    bridges the cavity). Scattered material points (tracked features, jittered samples) leave
    some points in no such triangle, or holes inside the wall; the bound then grows through the
    Delaunay triangles' longest edges, smallest first, until every point lies in a triangle and
    the mesh is an annulus (one outer contour, one cavity: :func:`lv_geometry`), at most to
    ``max_factor * h``. The cavity is many spacings across, so it is not bridged first. Points on
    a square lattice (pixel centres) keep the first bound: there a point left out is an isolated
    pixel, and a gap a hole in the wall, which are errors, not reasons to bridge concavities.

    Parameters
    ----------
    points : (n, 2) array
        Tissue points in metres, distinct.
    edge_factor : float
        First bound on the edge length, in median nearest-neighbour distances.
    max_factor : float
        Largest bound tried, in the same unit; beyond it the points are reported as not forming
        one annular wall.
    min_angle_deg : float
        Quality bound of :func:`sfem_filters.fem.mesh.delaunay_mesh`: slivers on the hull are
        peeled.
    interior_min_angle_deg : float
        Smallest angle accepted inside the wall, degrees: scattered points give interior
        slivers that no triangulation of them avoids (a pixel lattice has none).

    Returns
    -------
    mesh : TriMesh
        Nodes in the order of ``points``.
    max_edge : float
        The edge bound used, m.
    spacing : float
        The median nearest-neighbour distance ``h``, m (on a pixel lattice, its spacing).
    """
    pts = as_float_array("points", points, shape=(None, 2))
    if len(pts) < 3:
        raise ValueError(f"points: expected at least 3 tissue points, got {len(pts)}")
    edge_factor = positive("edge_factor", edge_factor)
    max_factor = positive("max_factor", max_factor)
    if max_factor < edge_factor:
        raise ValueError(f"max_factor: expected at least edge_factor={edge_factor}, got {max_factor}")
    dist, _ = cKDTree(pts).query(pts, k=2)
    if np.any(dist[:, 1] == 0):
        raise ValueError(f"points: expected distinct points, got {int(np.sum(dist[:, 1] == 0))} with a duplicate")
    h = float(np.median(dist[:, 1]))
    tri = delaunay_triangles(pts)
    q = pts[tri]
    longest = np.linalg.norm(q - q[:, [1, 2, 0]], axis=2).max(axis=1)
    bounds = np.array([edge_factor * h])
    on_lattice = lattice_offset(pts, h)[0] <= 1e-6
    if not on_lattice:       # a pixel lattice keeps its one bound: an isolated pixel or a hole is an error
        bounds = np.concatenate([bounds, np.unique(longest[(longest > edge_factor * h) & (longest <= max_factor * h)])])
    last = ["no bound tried"]

    def annulus(i):
        try:
            mesh = mesh_from_points(pts, bounds[i], min_angle_deg=min_angle_deg,
                                    interior_min_angle_deg=interior_min_angle_deg)
            if mesh.n_nodes != len(pts):
                raise ValueError(f"{len(pts) - mesh.n_nodes} points lie in no triangle")
            lv_geometry(mesh)
        except ValueError as exc:
            last[0] = str(exc)
            return None
        return mesh

    # a ladder of at most 16 bounds, then bisection below the first that works: more triangles
    # only close gaps, until the cavity itself is bridged far above these bounds
    ladder = np.unique(np.round(np.geomspace(1, len(bounds), min(16, len(bounds)))).astype(int) - 1)
    lo = -1
    for hi in ladder:
        mesh = annulus(hi)
        if mesh is None:
            lo = hi
            continue
        while hi - lo > 1:
            mid = (lo + hi) // 2
            found = annulus(mid)
            if found is None:
                lo = mid
            else:
                hi, mesh = mid, found
        return mesh, float(bounds[hi]), h
    if on_lattice:
        raise ValueError(f"points: at {edge_factor} spacings of their pixel lattice the tissue mesh is not one annular "
                         f"wall with every point a node ({last[0]}); remove isolated pixels, fill holes in the wall")
    raise ValueError(f"points: no edge bound up to {max_factor} median point spacings ({max_factor * h:.3g} m) meshes "
                     f"every point into one annular wall (at the largest: {last[0]}); expected the tissue points of a "
                     "short-axis slice, without isolated points or gaps wider than that")


def mask_inside(mask, spacing: float, origin=(0.0, 0.0)):
    """A test ``inside(xy)`` of whether points (m) fall on pixels of a boolean mask.

    Pixel (row r, column c) covers ``x in origin_x + spacing (c +- 1/2)`` and
    ``y in origin_y + spacing (r +- 1/2)``.
    """
    mask = as_mask("mask", mask, 2, nonempty=True)
    spacing = positive("spacing", spacing, "m")
    origin = as_float_array("origin", origin, shape=(2,))

    def inside(xy):
        xy = np.asarray(xy, float)
        c = np.round((xy[:, 0] - origin[0]) / spacing).astype(int)
        r = np.round((xy[:, 1] - origin[1]) / spacing).astype(int)
        ok = (r >= 0) & (r < mask.shape[0]) & (c >= 0) & (c < mask.shape[1])
        out = np.zeros(len(xy), bool)
        out[ok] = mask[r[ok], c[ok]]
        return out

    return inside


def mesh_from_mask(mask, spacing: float, step: int = 1) -> TriMesh:
    """Mesh a myocardium mask: every ``step``-th tissue pixel centre becomes a node.

    Parameters
    ----------
    mask : (H, W) bool array
        Tissue pixels (row = y, column = x); must be one connected piece.
    spacing : float
        Pixel size in metres.
    step : int
        Subsampling of the pixel lattice (1 keeps every pixel).
    """
    mask = as_mask("mask", mask, 2, nonempty=True)
    spacing = positive("spacing", spacing, "m")
    step = integer("step", step, 1)
    n_pieces = label(mask, connectivity=2).max()
    if n_pieces != 1:
        raise ValueError(f"mask: expected one connected piece of tissue, got {n_pieces}")
    rows, cols = np.nonzero(mask)
    sel = (rows % step == 0) & (cols % step == 0)
    pts = np.column_stack([cols[sel], rows[sel]]).astype(float) * spacing
    return mesh_from_points(pts, 1.5 * step * spacing)


def boundary_loops(mesh: TriMesh) -> list:
    """Closed boundary loops as ordered node arrays, tissue on the left of each step."""
    check_mesh("mesh", mesh)
    edges = mesh.boundary_edges()
    nxt = {}
    for a, b in edges.tolist():
        if a in nxt:
            raise ValueError("mesh: a boundary node is shared by two boundary loops (pinched boundary)")
        nxt[a] = b
    loops, seen = [], set()
    for start in nxt:
        if start in seen:
            continue
        loop = [start]
        seen.add(start)
        node = nxt[start]
        while node != start:
            loop.append(node)
            seen.add(node)
            node = nxt[node]
        loops.append(np.array(loop))
    return loops


@dataclass(frozen=True, eq=False)
class LVGeometry:
    """Wall layers and local directions of a short-axis myocardial mesh."""

    centre: np.ndarray            # (2,) m, centroid of the endocardial contour
    endo: np.ndarray              # ordered endocardial boundary nodes
    epi: np.ndarray               # ordered epicardial boundary nodes
    midwall: np.ndarray           # nodes on neither contour
    radial: np.ndarray            # (n_nodes, 2) unit vectors away from the centre
    circumferential: np.ndarray   # (n_nodes, 2) radial turned by +90 degrees
    endo_edges: np.ndarray        # boundary edges of the endocardium (tissue on the left)
    epi_edges: np.ndarray

    def angle(self, xy) -> np.ndarray:
        """Angle (rad, in [0, 2 pi)) of points about the centre."""
        d = np.asarray(xy, float) - self.centre
        return np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)


def lv_geometry(mesh: TriMesh) -> LVGeometry:
    """Classify the boundary of an annular mesh into endocardium (inner) and epicardium (outer).

    The epicardium is the loop traversed counter-clockwise with the tissue on its left
    (positive signed area); the endocardium is the hole (negative signed area). Exactly one of
    each is required.
    """
    loops = boundary_loops(mesh)
    areas = [signed_area(mesh.nodes[lp]) for lp in loops]
    outer = [lp for lp, a in zip(loops, areas) if a > 0]
    holes = [lp for lp, a in zip(loops, areas) if a < 0]
    if len(outer) != 1 or len(holes) != 1:
        raise ValueError(f"mesh: expected an annulus (one outer contour and one cavity), got "
                         f"{len(outer)} outer and {len(holes)} inner boundary loops")
    epi, endo = outer[0], holes[0]
    centre = polygon_centroid(mesh.nodes[endo])
    d = mesh.nodes - centre
    radial = d / np.linalg.norm(d, axis=1, keepdims=True)
    circ = np.column_stack([-radial[:, 1], radial[:, 0]])
    on = np.zeros(mesh.n_nodes, bool)
    on[endo] = on[epi] = True
    edges = mesh.boundary_edges()
    in_endo = np.isin(edges[:, 0], endo) & np.isin(edges[:, 1], endo)
    return LVGeometry(centre=centre, endo=endo, epi=epi, midwall=np.flatnonzero(~on), radial=radial,
                      circumferential=circ, endo_edges=edges[in_endo], epi_edges=edges[~in_endo])


def transmural_depth(mesh: TriMesh, geometry: LVGeometry, xy=None) -> np.ndarray:
    """Transmural depth: 0 at the endocardium, 1 at the epicardium (clipped to [0, 1]).

    At each point (default: the element centroids, m) the radius about the cavity centre is
    set between the endo- and epicardial radii in the same direction
    (:func:`sfem_filters.geometry.radius_by_angle`).
    """
    c = (mesh.centroids if xy is None else np.asarray(xy, float)) - geometry.centre
    ang = np.arctan2(c[:, 1], c[:, 0])
    r = np.linalg.norm(c, axis=1)
    r_in = radius_by_angle(mesh.nodes[geometry.endo], geometry.centre, ang)
    r_out = radius_by_angle(mesh.nodes[geometry.epi], geometry.centre, ang)
    return np.clip((r - r_in) / np.maximum(r_out - r_in, 1e-12), 0.0, 1.0)


def polar_strains(geometry: LVGeometry, nodal_strain) -> np.ndarray:
    """Radial, circumferential and shear strain (E_rr, E_cc, 2 E_rc) from nodal (e_xx, e_yy, gamma_xy).

    ``nodal_strain`` is (..., n_nodes, 3) with engineering shear; the result has the same
    shape, the shear again engineering (twice the tensor component), in the node's radial and
    circumferential directions.
    """
    eps = np.asarray(nodal_strain, float)
    exx, eyy, gxy = eps[..., 0], eps[..., 1], eps[..., 2]
    er, ec = geometry.radial, geometry.circumferential

    def proj(a, b):
        return (exx * a[:, 0] * b[:, 0] + eyy * a[:, 1] * b[:, 1]
                + 0.5 * gxy * (a[:, 0] * b[:, 1] + a[:, 1] * b[:, 0]))

    return np.stack([proj(er, er), proj(ec, ec), 2 * proj(er, ec)], axis=-1)


def polar_strain_operator(mesh: TriMesh, geometry: LVGeometry) -> sp.csr_matrix:
    """The linear map from displacements (m) to nodal (E_rr, E_cc, 2 E_rc), sparse (3 n_nodes, n_dofs).

    :func:`polar_strains` of :func:`sfem_filters.fem.strain.nodal_strain_operator`: row
    ``3 i + c`` is component c at node i, so a displacement covariance maps to the polar strains'
    covariance.
    """
    er, ec = geometry.radial, geometry.circumferential

    def row(a, b):   # coefficients of (e_xx, e_yy, gamma_xy) in a.E.b
        return np.stack([a[:, 0] * b[:, 0], a[:, 1] * b[:, 1], 0.5 * (a[:, 0] * b[:, 1] + a[:, 1] * b[:, 0])], axis=1)

    blocks = np.stack([row(er, er), row(ec, ec), 2.0 * row(er, ec)], axis=1)        # (n_nodes, 3, 3)
    n = mesh.n_nodes
    r = (3 * np.arange(n)[:, None, None] + np.arange(3)[None, :, None]) * np.ones((1, 1, 3), int)
    c = (3 * np.arange(n)[:, None, None] + np.arange(3)[None, None, :]) * np.ones((1, 3, 1), int)
    P = sp.csr_matrix((blocks.ravel(), (r.ravel(), c.ravel())), shape=(3 * n, 3 * n))
    return sp.csr_matrix(P @ nodal_strain_operator(mesh))


def contour_landmarks(geometry: LVGeometry, mesh: TriMesh, n_per_contour: int, offset_deg: float = 0.0,
                      eligible=None):
    """``n_per_contour`` evenly spaced landmark nodes on each contour (endo, epi).

    Landmark k of a contour is the contour node whose angle about the cavity centre is
    closest to ``offset + 360 k / n`` degrees, as shape tracking would give sparse points.
    ``eligible`` (bool per node, optional): only these nodes may be landmarks (for example the
    points with data in some frame). Every landmark that is eligible stays where it is; one that
    is not is replaced by the eligible contour node closest to its target angle that is not
    already a landmark, so one missing point moves one landmark.

    Returns
    -------
    (endo_nodes, epi_nodes) : two int arrays
    """
    if int(n_per_contour) != n_per_contour or n_per_contour < 3:
        raise ValueError(f"n_per_contour: expected an integer >= 3, got {n_per_contour!r}")
    ok = np.ones(mesh.n_nodes, bool) if eligible is None else np.asarray(eligible, bool)
    targets = np.radians(offset_deg + 360.0 * np.arange(int(n_per_contour)) / n_per_contour)
    out = []
    for name, loop in (("endocardial", geometry.endo), ("epicardial", geometry.epi)):
        if n_per_contour > len(loop):
            raise ValueError(f"n_per_contour: a contour has only {len(loop)} nodes, asked for {n_per_contour}")
        if n_per_contour > int(ok[loop].sum()):
            raise ValueError(f"eligible: the {name} contour has {int(ok[loop].sum())} of its {len(loop)} points "
                             f"eligible, fewer than the {n_per_contour} landmarks asked for")
        ang = geometry.angle(mesh.nodes[loop])
        diff = np.abs(np.angle(np.exp(1j * (ang[None, :] - targets[:, None]))))
        chosen = []
        for row in diff:
            order = np.argsort(row)
            pick = next(i for i in order if loop[i] not in chosen)
            chosen.append(loop[pick])
        for k, node in enumerate(list(chosen)):
            if not ok[node]:
                pick = next(i for i in np.argsort(diff[k]) if ok[loop[i]] and loop[i] not in chosen)
                chosen[k] = loop[pick]
        out.append(np.array(chosen))
    return out[0], out[1]


def _winding(contour_xy, centre) -> tuple:
    """Net turn (rad) of a closed contour about ``centre`` and the turn it takes backwards."""
    d = np.asarray(contour_xy, float) - np.asarray(centre, float)
    a = np.arctan2(d[:, 1], d[:, 0])
    step = np.angle(np.exp(1j * np.diff(np.append(a, a[0]))))
    net = float(step.sum())
    return net, float(-step[step * np.sign(net) < 0].sum() * np.sign(net))


class NotStarShapedError(ValueError):
    """A contour that is not star-shaped about the cavity centre, which :func:`polar_mesh` cannot mesh
    (a ray from the centre would cross it more than once): mesh through the points instead."""


def polar_mesh(endo_xy, epi_xy, centre, size: float, margin: float = 0.0) -> TriMesh:
    """A structured mesh of the wall between two contours seen from the cavity centre.

    Node rings at ``n`` equal angles about ``centre``; on each ray, ``layers + 1`` nodes at equal
    fractions of the wall from the endocardial radius (minus ``margin``) to the epicardial radius
    (plus ``margin``), both radii interpolated in angle (:func:`sfem_filters.geometry.radius_by_angle`);
    each cell of the (angle, layer) grid split into two triangles, the diagonal alternating in a
    checkerboard so that no direction is favoured. ``n`` and ``layers`` make edges of about
    ``size``: ``n = round(mid-wall circumference / size)`` (at least 12) and ``layers =
    round(mean thickness / size)`` (at least 2, so that the wall can bend and thicken across its
    depth). The mesh's cost is set by ``size``, not by the image's pixels, and its elements follow
    the wall's own radial and circumferential directions.

    Parameters
    ----------
    endo_xy, epi_xy : (n, 2) arrays
        The endo- and epicardial contours (m), each star-shaped about ``centre``: a ray from the
        centre crosses it once (the usual short-axis slice).
    centre : (2,) array
        Cavity centre (m).
    size : float
        Target element edge (m, > 0).
    margin : float
        Widening of the wall on both sides (m, >= 0); half a pixel spacing makes the mesh cover
        every pixel whose centre lies on the contours.

    Raises
    ------
    NotStarShapedError
        (a ValueError) Contours that are not star-shaped about the centre (a ray would cross one
        twice), or a wall of non-positive thickness in some direction.
    ValueError
        A non-positive ``size``, a negative ``margin``, a contour of fewer than 3 points.
    """
    size = positive("size", size, "m")
    margin = float(as_float_array("margin", margin, shape=()))
    if margin < 0:
        raise ValueError(f"margin: expected >= 0 m, got {margin}")
    c = as_float_array("centre", centre, shape=(2,))
    loops = {}
    for name, xy in (("endo_xy", endo_xy), ("epi_xy", epi_xy)):
        xy = as_float_array(name, xy, shape=(None, 2))
        if len(xy) < 3:
            raise ValueError(f"{name}: expected a closed contour of at least 3 points, got {len(xy)}")
        net, back = _winding(xy, c)
        if abs(abs(net) - 2 * np.pi) > 1e-6 or back > 0.2:
            raise NotStarShapedError(f"{name}: expected a contour star-shaped about the cavity centre (winding once "
                             f"around it), got a net turn of {np.degrees(net):.0f} degrees with {np.degrees(back):.0f} "
                             "degrees backwards; use a mesh through the points instead")
        loops[name] = xy
    probe = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
    r_in = radius_by_angle(loops["endo_xy"], c, probe) - margin
    r_out = radius_by_angle(loops["epi_xy"], c, probe) + margin
    if np.any(r_out - r_in <= 0) or np.any(r_in <= 0):
        raise NotStarShapedError("epi_xy: expected the epicardium outside the endocardium in every direction from "
                                 "the centre")
    n = max(12, int(round(np.pi * np.mean(r_in + r_out) / size)))
    layers = max(2, int(round(np.mean(r_out - r_in) / size)))
    theta = 2 * np.pi * np.arange(n) / n
    a = radius_by_angle(loops["endo_xy"], c, theta) - margin
    b = radius_by_angle(loops["epi_xy"], c, theta) + margin
    frac = np.arange(layers + 1) / layers
    r = a[:, None] + (b - a)[:, None] * frac[None, :]                          # (n, layers + 1)
    nodes = (c[None, None, :] + r[..., None] * np.stack([np.cos(theta), np.sin(theta)], axis=1)[:, None, :])
    idx = np.arange(n * (layers + 1)).reshape(n, layers + 1)
    elements = []
    for i in range(n):
        i1 = (i + 1) % n
        for j in range(layers):
            p, q, s_, t = idx[i, j], idx[i1, j], idx[i1, j + 1], idx[i, j + 1]
            elements += [[p, q, s_], [p, s_, t]] if (i + j) % 2 == 0 else [[p, q, t], [q, s_, t]]
    return TriMesh(nodes.reshape(-1, 2), np.array(elements))


def describe(mesh: TriMesh, geometry: LVGeometry) -> dict:
    """Counts and quality of a myocardial mesh (for reports)."""
    q = mesh_quality(mesh)
    return {"nodes": mesh.n_nodes, "elements": mesh.n_elements, "endo_nodes": len(geometry.endo),
            "epi_nodes": len(geometry.epi), "midwall_nodes": len(geometry.midwall), **q}
