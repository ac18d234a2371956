"""Loads on the mesh: pressure on boundary edges, prescribed (active) stresses, penalty springs.

Every load is a global nodal force vector in N (per metre of depth in plane strain), dofs
numbered node-major, x before y. Equation numbers refer to Shi & Liu (2003).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .._validate import as_float_array, positive
from .elasticity import strain_displacement
from .mesh import TriMesh, check_mesh


def pressure_load(mesh: TriMesh, edges, pressure: float, thickness: float = 1.0) -> np.ndarray:
    """Consistent nodal forces (N) of a uniform pressure on boundary edges.

    Parameters
    ----------
    edges : (n_edges, 2) int array
        Boundary edges oriented with the tissue on their left (as
        :meth:`TriMesh.boundary_edges` returns them).
    pressure : float
        Pressure in Pa; positive pushes into the tissue (against the outward normal).

    Returns
    -------
    (n_dofs,) array
        Each edge of length L gives ``-p * n * L * t / 2`` to each of its nodes, n the outward
        unit normal (exact for linear elements under uniform pressure).
    """
    check_mesh("mesh", mesh)
    edges = np.asarray(edges)
    if edges.size == 0:
        edges = edges.reshape(0, 2)
    if edges.ndim != 2 or edges.shape[1] != 2 or (edges.size and edges.dtype.kind not in "iu"):
        raise ValueError(f"edges: expected an (n_edges, 2) integer array of node pairs, got {edges.dtype} "
                         f"array of shape {edges.shape}")
    edges = edges.astype(np.int64)
    if edges.size and (edges.min() < 0 or edges.max() >= mesh.n_nodes):
        raise ValueError(f"edges: expected node indices in [0, {mesh.n_nodes - 1}], got range "
                         f"[{edges.min()}, {edges.max()}]")
    pressure = float(as_float_array("pressure", pressure, shape=()))
    thickness = positive("thickness", thickness, "m")
    d = mesh.nodes[edges[:, 1]] - mesh.nodes[edges[:, 0]]
    outward_times_length = np.column_stack([d[:, 1], -d[:, 0]])
    f = -float(pressure) * thickness * 0.5 * outward_times_length
    out = np.zeros(mesh.n_dofs)
    for k in range(2):
        np.add.at(out, 2 * edges[:, k], f[:, 0])
        np.add.at(out, 2 * edges[:, k] + 1, f[:, 1])
    return out


def stress_loads(mesh: TriMesh, element_stress, thickness: float = 1.0) -> np.ndarray:
    """Equivalent nodal loads (n_dofs,) in N of a per-element stress (n_el, 3) in Pa, Voigt xx yy xy.

    ``f_e = -t A_e B_e^T sigma_e``: the elastic stress then balances the prescribed one, so a
    positive (tensile) prescribed stress along a direction shortens the tissue along it.
    """
    check_mesh("mesh", mesh)
    sigma = as_float_array("element_stress", element_stress, shape=(mesh.n_elements, 3))
    thickness = positive("thickness", thickness, "m")
    B = strain_displacement(mesh)
    fe = -(thickness * mesh.areas)[:, None] * np.einsum("eki,ek->ei", B, sigma)
    out = np.zeros(mesh.n_dofs)
    np.add.at(out, mesh.element_dofs.ravel(), fe.ravel())
    return out


def penalty_stiffness(n_dofs: int, dofs, stiffness: float, confidence=1.0) -> sp.csr_matrix:
    """Diagonal penalty springs ``k * c_i`` on the given dofs, section 2.7.

    Boundary displacements b from shape tracking enter as the constraint ``k U_b = k b``:
    add this matrix to K and :func:`penalty_load` to the load. ``stiffness`` k is in N/m and
    ``confidence`` (0..1 per dof) weights each constraint by how far its datum is trusted.
    """
    positive("stiffness", stiffness, "N/m")
    dofs = np.asarray(dofs, np.int64).ravel()
    c = np.broadcast_to(as_float_array("confidence", confidence), dofs.shape)
    if np.any((c < 0) | (c > 1)):
        raise ValueError("confidence: expected values in [0, 1]")
    return sp.csr_matrix((stiffness * c, (dofs, dofs)), shape=(n_dofs, n_dofs))


def penalty_load(n_dofs: int, dofs, stiffness: float, targets, confidence=1.0) -> np.ndarray:
    """Load ``k * c_i * b_i`` (N) that pulls the penalised dofs towards ``targets`` (m)."""
    positive("stiffness", stiffness, "N/m")
    dofs = np.asarray(dofs, np.int64).ravel()
    b = as_float_array("targets", targets, shape=dofs.shape)
    c = np.broadcast_to(as_float_array("confidence", confidence), dofs.shape)
    if np.any((c < 0) | (c > 1)):
        raise ValueError("confidence: expected values in [0, 1]")
    out = np.zeros(n_dofs)
    np.add.at(out, dofs, stiffness * c * b)
    return out
