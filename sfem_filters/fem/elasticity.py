"""Linear-elastic finite elements: plane strain, linear (constant-strain) triangles.

Small composable functions: element quantities are computed for all elements at once as
``(n_elements, 6, 6)`` stacks and scattered into scipy sparse matrices by :func:`assemble`.
All quantities are SI: metres, pascals, kilograms, newtons. The thickness is 1 m unless
given (plane strain: forces and masses are per metre of depth).

Equation numbers refer to Shi & Liu (2003), Medical Image Analysis 7:445-464.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .._validate import as_float_array, check_material, non_negative, positive
from .mesh import TriMesh, check_mesh


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
