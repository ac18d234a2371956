"""Observation operators: which combinations of the displacements the data measure (Eq. 12).

An observation operator D (a sparse matrix) maps the global displacement vector (m) to the
measured numbers; the measured numbers themselves are the *observations*.
Node observations select dofs; point observations interpolate linearly (barycentric
coordinates) inside the triangle that holds the point.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .._validate import as_float_array, non_negative
from .dofs import node_dofs
from .mesh import TriMesh, check_mesh


def node_observation_matrix(mesh: TriMesh, nodes, keep_order: bool = False) -> sp.csr_matrix:
    """Rows observing the x and y displacement of the given nodes.

    Parameters
    ----------
    nodes : array of int
        Node indices; rows are ordered by node number, x before y.
    keep_order : bool
        Keep the nodes in the order given (rows ``2 k`` and ``2 k + 1`` observe ``nodes[k]``)
        instead of sorting them; the nodes must then be distinct.

    Returns
    -------
    (2 len(nodes), n_dofs) sparse matrix
    """
    check_mesh("mesh", mesh)
    nodes = np.asarray(nodes)
    if nodes.size and nodes.dtype.kind not in "iu":
        raise TypeError(f"nodes: expected integer node indices, got dtype {nodes.dtype}")
    nodes = nodes.astype(np.int64).ravel()
    if keep_order:
        if len(np.unique(nodes)) != len(nodes):
            raise ValueError("nodes: expected distinct node indices with keep_order=True, got repeats")
    else:
        nodes = np.unique(nodes)
    if nodes.size and (nodes.min() < 0 or nodes.max() >= mesh.n_nodes):
        raise ValueError(f"nodes: expected node indices in [0, {mesh.n_nodes - 1}], got range "
                         f"[{nodes.min()}, {nodes.max()}]")
    cols = node_dofs(nodes)
    return sp.csr_matrix((np.ones(len(cols)), (np.arange(len(cols)), cols)),
                         shape=(len(cols), mesh.n_dofs))


def locate_points(mesh: TriMesh, points, tol: float = 1e-9):
    """Triangle and barycentric coordinates of each point.

    Parameters
    ----------
    points : (p, 2) array
        Positions in metres.
    tol : float
        Relative tolerance on barycentric coordinates for points on edges.

    Returns
    -------
    element : (p,) int array
    bary : (p, 3) array
    """
    check_mesh("mesh", mesh)
    pts = as_float_array("points", points, shape=(None, 2))
    tol = non_negative("tol", tol)
    tri = mesh.nodes[mesh.elements]
    v0 = tri[:, 0]
    T = np.stack([tri[:, 1] - v0, tri[:, 2] - v0], axis=2)       # (n_el, 2, 2)
    Tinv = np.linalg.inv(T)
    element = -np.ones(len(pts), np.int64)
    bary = np.zeros((len(pts), 3))
    for k, p in enumerate(pts):
        lam12 = np.einsum("eij,ej->ei", Tinv, p[None] - v0)
        lam = np.column_stack([1.0 - lam12.sum(axis=1), lam12])
        worst = lam.min(axis=1)
        e = int(np.argmax(worst))
        if worst[e] < -tol:
            raise ValueError(f"points: expected points inside the mesh, got point {k} at "
                             f"{tuple(p.tolist())} m outside it")
        element[k] = e
        bary[k] = lam[e]
    return element, bary


def point_observation_matrix(mesh: TriMesh, points) -> sp.csr_matrix:
    """Rows observing the interpolated x and y displacement at arbitrary points (m).

    Rows are ordered point by point, x before y. Points must lie in the mesh.
    """
    element, bary = locate_points(mesh, points)
    rows, cols, vals = [], [], []
    for k, (e, lam) in enumerate(zip(element, bary)):
        for a in range(3):
            node = mesh.elements[e, a]
            for c in range(2):
                rows.append(2 * k + c)
                cols.append(2 * node + c)
                vals.append(lam[a])
    return sp.csr_matrix((vals, (rows, cols)), shape=(2 * len(element), mesh.n_dofs))


def interpolation_matrix(mesh: TriMesh, points, max_outside: float = 0.0) -> sp.csr_matrix:
    """Shape-function weights of each point: the sparse (p, n_nodes) map from nodal values to the
    values at ``points`` (m), each row the barycentric coordinates of the point in its triangle.

    A point outside the mesh by at most ``max_outside`` (m) takes the weights of the nearest point
    of the triangle that holds it most nearly (its negative barycentric coordinates clipped to 0
    and the rest renormalised): a data point on a jagged pixel border that the mesh's smoother
    boundary leaves a fraction of a pixel outside. Farther out is an error.

    Parameters
    ----------
    points : (p, 2) array
        Positions in metres.
    max_outside : float
        Largest distance (m, >= 0) a point may lie outside the mesh.
    """
    check_mesh("mesh", mesh)
    pts = as_float_array("points", points, shape=(None, 2))
    max_outside = non_negative("max_outside", max_outside)
    tri = mesh.nodes[mesh.elements]
    v0 = tri[:, 0]
    Tinv = np.linalg.inv(np.stack([tri[:, 1] - v0, tri[:, 2] - v0], axis=2))
    rows, cols, vals = [], [], []
    for k, p in enumerate(pts):
        lam12 = np.einsum("eij,ej->ei", Tinv, p[None] - v0)
        lam = np.column_stack([1.0 - lam12.sum(axis=1), lam12])
        e = int(np.argmax(lam.min(axis=1)))
        w = lam[e]
        if w.min() < -1e-9:
            w = np.clip(w, 0.0, None)
            w = w / w.sum()
            gap = float(np.linalg.norm(w @ tri[e] - p))
            if gap > max_outside:
                raise ValueError(f"points: point {k} at {tuple(p.tolist())} m lies {gap:.3g} m outside the mesh; "
                                 f"expected at most max_outside={max_outside:.3g} m")
        rows.extend([k] * 3)
        cols.extend(mesh.elements[e].tolist())
        vals.extend(w.tolist())
    return sp.csr_matrix((vals, (rows, cols)), shape=(len(pts), mesh.n_nodes))
