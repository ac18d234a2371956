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


def sample_interpolation(mesh: TriMesh, points, offsets) -> tuple:
    """Shape-function weights at the sample points ``points[p] + offsets[s]``, and which lie in the mesh.

    The building block of :func:`blurred_observation_matrix` (Eq. 12 as a weighted average):
    each sample point inside the mesh gets the barycentric coordinates of its triangle (a point on
    an edge takes one of its triangles: the interpolation is continuous); one outside gets a zero
    row. Sample points shared by several ``points`` (a common lattice, as pixel centres plus
    sub-pixel offsets make) are located once.

    Parameters
    ----------
    points : (P, 2) array
        Centres (m).
    offsets : (S, 2) array
        Offsets of the sample points from each centre (m).

    Returns
    -------
    N : (P S, n_nodes) sparse matrix
        Row ``p S + s``: the nodal weights of the sample point ``points[p] + offsets[s]``.
    inside : (P, S) bool array
        Whether each sample point lies in the mesh.
    """
    check_mesh("mesh", mesh)
    pts = as_float_array("points", points, shape=(None, 2))
    off = as_float_array("offsets", offsets, shape=(None, 2))
    P, S = len(pts), len(off)
    q = (pts[:, None, :] + off[None, :, :]).reshape(-1, 2)
    scale = float(np.max(np.ptp(mesh.nodes, axis=0))) or 1.0
    _, first, inverse = np.unique(np.round(q / scale, 10), axis=0, return_index=True, return_inverse=True)
    uq = q[first]
    element = -np.ones(len(uq), np.int64)
    bary = np.zeros((len(uq), 3))
    tri = mesh.nodes[mesh.elements]
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    pad = 1e-9 * scale
    order = np.argsort(uq[:, 0])
    xs = uq[order, 0]
    for e in range(mesh.n_elements):
        cand = order[np.searchsorted(xs, lo[e, 0] - pad):np.searchsorted(xs, hi[e, 0] + pad, side="right")]
        cand = cand[(element[cand] < 0) & (uq[cand, 1] >= lo[e, 1] - pad) & (uq[cand, 1] <= hi[e, 1] + pad)]
        if cand.size == 0:
            continue
        v0 = tri[e, 0]
        Tinv = np.linalg.inv(np.column_stack([tri[e, 1] - v0, tri[e, 2] - v0]))
        lam12 = (uq[cand] - v0) @ Tinv.T
        lam = np.column_stack([1.0 - lam12.sum(axis=1), lam12])
        ok = lam.min(axis=1) >= -1e-9
        element[cand[ok]] = e
        bary[cand[ok]] = np.clip(lam[ok], 0.0, None) / np.clip(lam[ok], 0.0, None).sum(axis=1, keepdims=True)
    inside_u = element >= 0
    rows = np.repeat(np.flatnonzero(inside_u[inverse.ravel()]), 3)
    src = inverse.ravel()[inside_u[inverse.ravel()]]
    cols = mesh.elements[element[src]].ravel()
    vals = bary[src].ravel()
    N = sp.csr_matrix((vals, (rows, cols)), shape=(P * S, mesh.n_nodes))
    return N, inside_u[inverse.ravel()].reshape(P, S)


def blurred_observation_matrix(mesh: TriMesh, points, offsets, weights, background=None,
                               samples=None) -> sp.csr_matrix:
    """Rows observing a point-spread-weighted mean of the displacement around each point (Eq. 12 as an average).

    An image datum at a point is not the displacement there but the signal-weighted mean over the
    point spread function: with ``w_s`` the PSF weights at sample offsets ``o_s`` (summing to 1),
    the sample points in the tissue (the mesh) carrying the interpolated displacement ``N(x_p +
    o_s) U`` and those outside carrying a static background of relative signal ``b_ps`` (zero
    displacement),

    ``y_p = sum_in w_s N(x_p + o_s) U / (sum_in w_s + sum_out w_s b_ps)``.

    So with ``b = 0`` (a dark background) each row's weights sum to 1 (a mean over the tissue
    alone), with ``b = 1`` (a background as bright as the tissue) they sum to the tissue fraction
    ``sum_in w_s``; as the PSF narrows to one sample at ``o = 0`` the rows are
    :func:`point_observation_matrix`'s.

    Parameters
    ----------
    points : (P, 2) array
        Centres (m); rows are ordered point by point, x before y.
    offsets : (S, 2) array
        Sample offsets (m).
    weights : (S,) or (P, S) array
        PSF weights (>= 0, each row's summing to 1 over all its samples, inside and out).
    background : float, (P, S) array or None
        Relative signal (>= 0) of the static background at each sample point outside the mesh;
        None: 0 (the mean over the tissue alone).
    samples : tuple, optional
        :func:`sample_interpolation`'s answer for these points and offsets (reused across calls).

    Returns
    -------
    (2 P, n_dofs) sparse matrix
    """
    check_mesh("mesh", mesh)
    pts = as_float_array("points", points, shape=(None, 2))
    off = as_float_array("offsets", offsets, shape=(None, 2))
    P, S = len(pts), len(off)
    w = np.broadcast_to(as_float_array("weights", weights), (P, S))
    if np.any(w < 0) or not np.allclose(w.sum(axis=1), 1.0, atol=1e-9):
        raise ValueError("weights: expected non-negative PSF weights summing to 1 for each point")
    b = np.zeros((P, S)) if background is None else np.broadcast_to(as_float_array("background", background), (P, S))
    if np.any(b < 0):
        raise ValueError("background: expected a non-negative relative signal of the static background")
    N, inside = sample_interpolation(mesh, pts, off) if samples is None else samples
    norm = np.sum(np.where(inside, w, w * b), axis=1)
    if np.any(norm <= 0):
        k = int(np.flatnonzero(norm <= 0)[0])
        raise ValueError(f"points: expected every point's PSF to reach some tissue or lit background, point {k} "
                         f"at {tuple(pts[k].tolist())} m sees neither")
    vals = (np.where(inside, w, 0.0) / norm[:, None]).ravel()
    Wt = sp.csr_matrix((vals, (np.repeat(np.arange(P), S), np.arange(P * S))), shape=(P, P * S))
    nodal = (Wt @ N).tocoo()                                      # (P, n_nodes)
    rows = np.concatenate([2 * nodal.row, 2 * nodal.row + 1])
    cols = np.concatenate([2 * nodal.col, 2 * nodal.col + 1])
    return sp.csr_matrix((np.concatenate([nodal.data, nodal.data]), (rows, cols)), shape=(2 * P, mesh.n_dofs))
