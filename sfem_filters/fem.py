"""Linear-elastic finite elements: plane strain, linear (constant-strain) triangles.

Small composable functions: element quantities are computed for all elements at once as
``(n_elements, 6, 6)`` stacks and scattered into scipy sparse matrices by :func:`assemble`.
All quantities are SI: metres, pascals, kilograms, newtons. The thickness is 1 m unless
given (plane strain: forces and masses are per metre of depth).

Equation numbers refer to Shi & Liu (2003), Medical Image Analysis 7:445-464.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ._validate import as_float_array, check_material, check_mesh, non_negative, positive
from .mesh import TriMesh


def _material_arrays(E, nu):
    """E (Pa, > 0) and nu (0 < nu < 0.5) as float arrays of their own shapes, checked."""
    E = np.asarray(as_float_array("E", E), float)
    nu = np.asarray(as_float_array("nu", nu), float)
    check_material(E.ravel(), nu.ravel())
    try:
        np.broadcast(E, nu)
    except ValueError:
        raise ValueError(f"nu: expected a shape that broadcasts with E {E.shape}, got {nu.shape}") from None
    return E, nu


def plane_strain_matrix(E, nu) -> np.ndarray:
    """Isotropic plane-strain constitutive matrix, Eq. (4).

    Parameters
    ----------
    E : float or (n,) array
        Young's modulus in Pa.
    nu : float or (n,) array
        Poisson's ratio, 0 < nu < 0.5.

    Returns
    -------
    (..., 3, 3) array
        Maps engineering strain (e_xx, e_yy, gamma_xy) to stress (Pa).
    """
    E, nu = _material_arrays(E, nu)
    f = E / ((1.0 + nu) * (1.0 - 2.0 * nu))
    D = np.zeros(np.broadcast(E, nu).shape + (3, 3))
    D[..., 0, 0] = D[..., 1, 1] = f * (1.0 - nu)
    D[..., 0, 1] = D[..., 1, 0] = f * nu
    D[..., 2, 2] = f * (1.0 - 2.0 * nu) / 2.0
    return D


def plane_strain_matrix_dnu(E, nu) -> np.ndarray:
    """Derivative of :func:`plane_strain_matrix` with respect to nu (Pa per unit nu)."""
    E, nu = _material_arrays(E, nu)
    g = (1.0 + nu) * (1.0 - 2.0 * nu)
    dg = -1.0 - 4.0 * nu  # d/dnu of (1 + nu)(1 - 2 nu)
    f = E / g
    df = -E * dg / g ** 2
    D = np.zeros(np.broadcast(E, nu).shape + (3, 3))
    D[..., 0, 0] = D[..., 1, 1] = df * (1.0 - nu) - f
    D[..., 0, 1] = D[..., 1, 0] = df * nu + f
    D[..., 2, 2] = (df * (1.0 - 2.0 * nu) - 2.0 * f) / 2.0
    return D


def strain_displacement(mesh: TriMesh) -> np.ndarray:
    """Constant strain-displacement matrices B of every triangle, shape (n_elements, 3, 6).

    ``B @ u_e`` gives (e_xx, e_yy, gamma_xy) for element dofs ordered x0 y0 x1 y1 x2 y2
    (displacements in metres, strains dimensionless).
    """
    check_mesh("mesh", mesh)
    p = mesh.nodes[mesh.elements]
    x, y = p[..., 0], p[..., 1]
    two_a = 2.0 * mesh.areas
    b = np.stack([y[:, 1] - y[:, 2], y[:, 2] - y[:, 0], y[:, 0] - y[:, 1]], axis=1) / two_a[:, None]
    c = np.stack([x[:, 2] - x[:, 1], x[:, 0] - x[:, 2], x[:, 1] - x[:, 0]], axis=1) / two_a[:, None]
    B = np.zeros((mesh.n_elements, 3, 6))
    B[:, 0, 0::2] = b
    B[:, 1, 1::2] = c
    B[:, 2, 0::2] = c
    B[:, 2, 1::2] = b
    return B


def element_stiffness(mesh: TriMesh, D: np.ndarray, thickness: float = 1.0) -> np.ndarray:
    """Element stiffness matrices ``t * A * B^T D B``, shape (n_elements, 6, 6), in N/m.

    Parameters
    ----------
    D : (n_elements, 3, 3) array
        Constitutive matrix of each element in Pa (or its derivative).
    thickness : float
        Out-of-plane thickness in metres.
    """
    check_mesh("mesh", mesh)
    D = as_float_array("D", D, shape=(mesh.n_elements, 3, 3))
    thickness = positive("thickness", thickness, "m")
    B = strain_displacement(mesh)
    return (thickness * mesh.areas)[:, None, None] * np.einsum("eki,ekl,elj->eij", B, D, B)


def element_mass(mesh: TriMesh, density, thickness: float = 1.0, lumped: bool = False) -> np.ndarray:
    """Element mass matrices in kg, shape (n_elements, 6, 6).

    Parameters
    ----------
    density : float or (n_elements,) array
        Mass density in kg/m^3.
    lumped : bool
        Row-sum lumped (diagonal, a third of the element mass per node) instead of consistent.
    """
    check_mesh("mesh", mesh)
    thickness = positive("thickness", thickness, "m")
    rho = as_float_array("density", density)
    if rho.ndim == 0:
        rho = np.full(mesh.n_elements, float(rho))
    rho = as_float_array("density", rho, shape=(mesh.n_elements,))
    if np.any(rho <= 0):
        raise ValueError(f"density: expected a positive mass density in kg/m^3, got minimum {float(rho.min())!r}")
    m = rho * thickness * mesh.areas
    if lumped:
        base = np.eye(3) / 3.0
    else:
        base = (np.ones((3, 3)) + np.eye(3)) / 12.0
    return m[:, None, None] * np.kron(base, np.eye(2))[None]


def assemble(mesh: TriMesh, element_matrices: np.ndarray) -> sp.csr_matrix:
    """Scatter (n_elements, 6, 6) element matrices into a sparse (n_dofs, n_dofs) matrix."""
    check_mesh("mesh", mesh)
    element_matrices = as_float_array("element_matrices", element_matrices, shape=(mesh.n_elements, 6, 6))
    dofs = mesh.element_dofs
    rows = np.repeat(dofs, 6, axis=1).ravel()
    cols = np.tile(dofs, (1, 6)).ravel()
    return sp.csr_matrix((np.asarray(element_matrices).ravel(), (rows, cols)),
                         shape=(mesh.n_dofs, mesh.n_dofs))


def stiffness_matrix(mesh: TriMesh, E, nu, thickness: float = 1.0) -> sp.csr_matrix:
    """Global stiffness K (N/m) for per-element E (Pa) and nu, Eqs. (3)-(5)."""
    check_mesh("mesh", mesh)
    E, nu = check_material(_per_element("E", E, mesh.n_elements),
                           _per_element("nu", nu, mesh.n_elements), mesh.n_elements)
    return assemble(mesh, element_stiffness(mesh, plane_strain_matrix(E, nu), thickness))


def _per_element(name, value, n):
    """A scalar or an (n,) array as an (n,) float array (shape checked, not finiteness)."""
    arr = as_float_array(name, value, finite=False)
    if arr.ndim == 0:
        return np.full(n, float(arr))
    return as_float_array(name, arr, shape=(n,), finite=False)


def mass_matrix(mesh: TriMesh, density, thickness: float = 1.0, lumped: bool = False) -> sp.csr_matrix:
    """Global mass M in kg, consistent or lumped (density in kg/m^3)."""
    return assemble(mesh, element_mass(mesh, density, thickness, lumped))


def element_stiffness_derivatives(mesh: TriMesh, E, nu, thickness: float = 1.0):
    """Analytic element sensitivities dK_e/dE_e (N/m per Pa) and dK_e/dnu_e (N/m).

    K is linear in each E_e, so ``dK_e/dE_e = K_e / E_e``; ``dK_e/dnu_e`` uses the
    derivative of Eq. (4). Each is (n_elements, 6, 6); the global derivative with respect
    to the parameter of element e is element e's matrix scattered alone.
    """
    check_mesh("mesh", mesh)
    E, nu = check_material(_per_element("E", E, mesh.n_elements),
                           _per_element("nu", nu, mesh.n_elements), mesh.n_elements)
    dKdE = element_stiffness(mesh, plane_strain_matrix(1.0, nu), thickness)
    dKdnu = element_stiffness(mesh, plane_strain_matrix_dnu(E, nu), thickness)
    return dKdE, dKdnu


def rayleigh_damping(M, K, alpha: float, beta: float):
    """Rayleigh damping ``C = alpha M + beta K`` (alpha in 1/s, beta in s)."""
    alpha = non_negative("alpha", alpha, "1/s")
    beta = non_negative("beta", beta, "s")
    return alpha * M + beta * K


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


def node_dofs(nodes, components: str = "xy") -> np.ndarray:
    """Dof indices of the given nodes, node-major, x before y (``components`` 'x', 'y' or 'xy')."""
    if components not in ("x", "y", "xy", "yx"):
        raise ValueError(f"components: expected 'x', 'y' or 'xy', got {components!r}")
    nodes = np.asarray(nodes).ravel()
    if nodes.size and (nodes.dtype.kind not in "iu" or nodes.min() < 0):
        raise ValueError(f"nodes: expected non-negative integer node indices, got {nodes.dtype} values "
                         f"down to {nodes.min().item()!r}")
    nodes = nodes.astype(np.int64)
    comp = [{"x": 0, "y": 1}[c] for c in components]
    return (2 * nodes[:, None] + np.asarray(comp)[None]).ravel()


@dataclass(frozen=True)
class DofMap:
    """Split of the global dofs into fixed (zero displacement) and free ones.

    Parameters
    ----------
    n_dofs : int
        Number of global dofs.
    fixed : array of int
        Global indices of dofs held at zero displacement.
    """

    n_dofs: int
    fixed: np.ndarray

    def __post_init__(self):
        fixed = np.unique(np.asarray(self.fixed, np.int64))
        if fixed.size and (fixed.min() < 0 or fixed.max() >= self.n_dofs):
            raise ValueError(f"fixed: expected dof indices in [0, {self.n_dofs - 1}], got range "
                             f"[{fixed.min()}, {fixed.max()}]")
        object.__setattr__(self, "fixed", fixed)

    @property
    def free(self) -> np.ndarray:
        mask = np.ones(self.n_dofs, bool)
        mask[self.fixed] = False
        return np.flatnonzero(mask)

    @property
    def n_free(self) -> int:
        return self.n_dofs - len(self.fixed)

    def free_index(self) -> np.ndarray:
        """For every global dof its index among the free dofs, or -1 if fixed."""
        out = -np.ones(self.n_dofs, np.int64)
        out[self.free] = np.arange(self.n_free)
        return out

    def restrict_matrix(self, A):
        """Rows and columns of the free dofs."""
        f = self.free
        return A[f][:, f]

    def restrict(self, v):
        """Entries (along the last axis) of the free dofs."""
        return np.asarray(v)[..., self.free]

    def expand(self, v_free):
        """Global vectors (last axis) with zeros at the fixed dofs."""
        v_free = np.asarray(v_free)
        out = np.zeros(v_free.shape[:-1] + (self.n_dofs,), dtype=v_free.dtype)
        out[..., self.free] = v_free
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
