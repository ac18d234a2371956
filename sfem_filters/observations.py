"""Observation operators: which combinations of the state the data measure (Eqs. 12-13, 21-22).

An observation matrix D maps the global displacement vector (m) to the measured numbers.
Node observations select dofs; point observations interpolate linearly (barycentric
coordinates) inside the triangle that holds the point.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ._validate import as_float_array, check_mesh, non_negative
from .fem import node_dofs
from .mesh import TriMesh


class LinearObservation:
    """The measurement side of a filter model with a linear, state-independent ``y = H z``.

    Mixed into the model classes (they set ``self._H``, the dense (dim_obs, dim_state)
    matrix [D 0] of Eq. 22) so that filterpy's EKF and the engines see one ``hx``,
    ``H_jacobian`` and ``make_ekf``.
    """

    def hx(self, z, t=None):
        """Predicted observation H z (Eq. 21) of state z (m, m/s); same ndim as z."""
        z = np.asarray(z, float)
        y = self._H @ z.ravel()
        return y.reshape(-1, 1) if z.ndim == 2 else y

    def H_jacobian(self, z=None, t=None) -> np.ndarray:
        """H = [D 0] (Eq. 22), dense (dim_obs, dim_state)."""
        return self._H

    def make_ekf(self):
        """A filterpy ``ExtendedKalmanFilter`` set up with this model's x0, P0, Q and R.

        Drive it as::

            ekf = model.make_ekf()
            for t, y in enumerate(observations):
                if t > 0:
                    ekf.predict(u=t - 1)          # u is the frame the step starts from
                ekf.update(y.reshape(-1, 1), model.H_jacobian, model.hx, args=t, hx_args=t)
        """
        from .filters import SFEMExtendedKalmanFilter
        return SFEMExtendedKalmanFilter(self)


def node_observation_matrix(mesh: TriMesh, nodes) -> sp.csr_matrix:
    """Rows observing the x and y displacement of the given nodes.

    Parameters
    ----------
    nodes : array of int
        Node indices; rows are ordered by node number, x before y.

    Returns
    -------
    (2 len(nodes), n_dofs) sparse matrix
    """
    check_mesh("mesh", mesh)
    nodes = np.asarray(nodes)
    if nodes.size and nodes.dtype.kind not in "iu":
        raise TypeError(f"nodes: expected integer node indices, got dtype {nodes.dtype}")
    nodes = np.unique(nodes.astype(np.int64))
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
