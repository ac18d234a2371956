"""Small strains from nodal displacements.

Linear triangles have constant strain; nodal strains are the area-weighted mean of the
strains of the elements around each node.
"""
from __future__ import annotations

import numpy as np

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
