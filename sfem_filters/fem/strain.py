"""Small strains from nodal displacements.

Linear triangles have constant strain; nodal strains are the area-weighted mean of the
strains of the elements around each node.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .._validate import as_float_array
from .elasticity import strain_displacement
from .mesh import TriMesh, check_mesh


def element_strains(mesh: TriMesh, U) -> np.ndarray:
    """Strain (e_xx, e_yy, gamma_xy) of every element.

    Parameters
    ----------
    U : (..., n_dofs) array
        Global nodal displacements in metres (node-major, x before y).

    Returns
    -------
    (..., n_elements, 3) array (dimensionless; gamma_xy is the engineering shear strain)
    """
    check_mesh("mesh", mesh)
    U = as_float_array("U", U)
    if U.ndim == 0 or U.shape[-1] != mesh.n_dofs:
        raise ValueError(f"U: expected last axis of length {mesh.n_dofs} (n_dofs), got {U.shape[-1] if U.ndim else 'a scalar'}")
    ue = U[..., mesh.element_dofs]                               # (..., n_el, 6)
    return np.einsum("eij,...ej->...ei", strain_displacement(mesh), ue)


def nodal_average(mesh: TriMesh, element_values) -> np.ndarray:
    """Area-weighted mean over the elements around each node, (..., n_el, k) -> (..., n_nodes, k)."""
    check_mesh("mesh", mesh)
    v = as_float_array("element_values", element_values)
    if v.ndim < 2 or v.shape[-2] != mesh.n_elements:
        raise ValueError(f"element_values: expected shape (..., {mesh.n_elements}, k) (n_elements rows), "
                         f"got shape {v.shape}")
    w = np.zeros((mesh.n_nodes, mesh.n_elements))
    for a in range(3):
        w[mesh.elements[:, a], np.arange(mesh.n_elements)] += mesh.areas
    w /= w.sum(axis=1, keepdims=True)
    return np.einsum("ne,...ek->...nk", w, v)


def nodal_strains(mesh: TriMesh, U) -> np.ndarray:
    """Area-weighted nodal strains, (..., n_nodes, 3), from displacements U (m)."""
    return nodal_average(mesh, element_strains(mesh, U))


def nodal_averaging_matrix(mesh: TriMesh) -> sp.csr_matrix:
    """Sparse (n_nodes, n_elements) area weights of :func:`nodal_average` (rows sum to 1)."""
    check_mesh("mesh", mesh)
    rows = mesh.elements.T.ravel()
    cols = np.tile(np.arange(mesh.n_elements), 3)
    W = sp.csr_matrix((np.tile(mesh.areas, 3), (rows, cols)), shape=(mesh.n_nodes, mesh.n_elements))
    return sp.csr_matrix(sp.diags(1.0 / np.asarray(W.sum(axis=1)).ravel()) @ W)


def nodal_strain_operator(mesh: TriMesh) -> sp.csr_matrix:
    """The linear map from displacements to nodal strains, sparse (3 n_nodes, n_dofs).

    Row ``3 i + c`` gives component c (e_xx, e_yy, gamma_xy) of node i's area-weighted strain,
    so ``(S @ U).reshape(-1, 3)`` equals :func:`nodal_strains` of ``U`` (m); a covariance C of U
    gives the strains' covariance ``S C S^T``.
    """
    B = strain_displacement(mesh)                                # (n_el, 3, 6)
    W = nodal_averaging_matrix(mesh).tocoo()
    dofs = mesh.element_dofs                                     # (n_el, 6)
    rows = (3 * W.row[:, None, None] + np.arange(3)[None, :, None]) * np.ones((1, 1, 6), int)
    cols = np.broadcast_to(dofs[W.col][:, None, :], rows.shape)
    vals = W.data[:, None, None] * B[W.col]
    return sp.csr_matrix((vals.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * mesh.n_nodes, mesh.n_dofs))
