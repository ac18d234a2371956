"""The paper's literal route to the exact discretisation: dense matrices and exponentials.

:func:`continuous_matrices`, :func:`discretize_zoh` and :func:`reference_sensitivity` follow
Shi & Liu (2003) literally (Eqs. (9)-(11), (14)-(16), (33)) with dense matrix exponentials and
scipy's ``expm_frechet``. They are the reference for tests and benchmarks of the modal route,
:class:`sfem_filters.fem.statespace.ModalSystem`, which gives the same numbers.
:func:`scatter_direction` makes the dense stiffness direction of one element that
:func:`reference_sensitivity` takes.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla
from scipy.linalg import expm, expm_frechet

from .._validate import positive

__all__ = ["continuous_matrices", "discretize_zoh", "reference_sensitivity", "scatter_direction"]


def continuous_matrices(M, K, C):
    """Continuous-time matrices A_c and B_c of Eqs. (9)-(11).

    Parameters
    ----------
    M, K, C : (n, n) arrays
        Mass (kg), stiffness (N/m) and damping (N s/m) over the free dofs.

    Returns
    -------
    A_c : (2n, 2n) array
        ``[[0, I], [-M^-1 K, -M^-1 C]]`` (1/s and 1/s^2 blocks).
    B_c : (2n, n) array
        ``[[0], [M^-1]]`` (1/kg).
    """
    M, K, C = (np.asarray(a.toarray() if hasattr(a, "toarray") else a, float) for a in (M, K, C))
    n = M.shape[0]
    cho = sla.cho_factor(M)
    A_c = np.zeros((2 * n, 2 * n))
    A_c[:n, n:] = np.eye(n)
    A_c[n:, :n] = -sla.cho_solve(cho, K)
    A_c[n:, n:] = -sla.cho_solve(cho, C)
    B_c = np.zeros((2 * n, n))
    B_c[n:] = sla.cho_solve(cho, np.eye(n))
    return A_c, B_c


def discretize_zoh(A_c, B_c, T: float):
    """Exact zero-order-hold discretisation, Eqs. (14)-(16), with one block exponential.

    ``expm([[A_c, B_c], [0, 0]] T) = [[A, B], [0, I]]`` gives ``A = e^{A_c T}`` and
    ``B = int_0^T e^{A_c s} ds B_c`` without inverting A_c.

    Parameters
    ----------
    T : float
        Frame interval in seconds.
    """
    T = positive("T", T, "s")
    n, m = B_c.shape
    G = np.zeros((n + m, n + m))
    G[:n, :n] = A_c * T
    G[:n, n:] = B_c * T
    E = expm(G)
    return E[:n, :n], E[:n, n:]


def reference_sensitivity(M, K, alpha: float, beta: float, T: float, x, w, dK_list):
    """d(A x + B w)/d p_j for stiffness perturbations ``dK_j = dK/dp_j`` (Eq. 33), via expm_frechet.

    The input is folded into the exponential, ``A x + B w = [I 0] expm(X) [x; 1]`` with
    ``X = [[A_c, B_c w], [0, 0]] T``, so each column is one Frechet derivative of a
    (2n+1)-square exponential. Slow (one ``expm_frechet`` per parameter); exact in exact
    arithmetic, but in floating point it loses digits when ``||A_c T||`` is large (about 1e-7
    relative error at 5e4, heavily damped stiff modes), where the modal route stays accurate.
    The reference for :meth:`ModalSystem.sensitivity` in moderate regimes.

    Parameters
    ----------
    M, K : (n, n) arrays
        Mass (kg) and stiffness (N/m) over the free dofs; damping is ``alpha M + beta K``.
    alpha, beta : float
        Rayleigh coefficients in 1/s and s.
    T : float
        Frame interval in s.
    x : (2n,) array
        State [U (m); U' (m/s)] at the start of the interval.
    w : (n,) array
        Load (N) held over the interval.
    dK_list : sequence of (n, n) arrays
        Stiffness derivatives (N/m per unit parameter).

    Returns
    -------
    (2n, len(dK_list)) array
    """
    M = np.asarray(M.toarray() if hasattr(M, "toarray") else M, float)
    K = np.asarray(K.toarray() if hasattr(K, "toarray") else K, float)
    n = M.shape[0]
    A_c, B_c = continuous_matrices(M, K, alpha * M + beta * K)
    # Balance positions (m) against velocities (m/s): with S = diag(w_s I, I, 1) the matrix
    # S X S^-1 has norm ~ w_max T instead of w_max^2 T, and L(X, E) = S^-1 L(SXS^-1, SES^-1) S.
    ws = np.sqrt(max(np.abs(np.diag(A_c[n:, :n])).max(), 1e-300))
    sc = np.concatenate([np.full(n, ws), np.ones(n), [1.0]])
    X = np.zeros((2 * n + 1, 2 * n + 1))
    X[:2 * n, :2 * n] = A_c * T
    X[:2 * n, 2 * n] = (B_c @ np.asarray(w, float)) * T
    Xs = sc[:, None] * X / sc[None, :]
    v = np.append(np.asarray(x, float), 1.0) * sc
    cho = sla.cho_factor(M)
    out = np.zeros((2 * n, len(dK_list)))
    for j, dK in enumerate(dK_list):
        dK = np.asarray(dK.toarray() if hasattr(dK, "toarray") else dK, float)
        E = np.zeros_like(X)
        MdK = sla.cho_solve(cho, dK)
        E[n:2 * n, :n] = -MdK * T
        E[n:2 * n, n:2 * n] = -beta * MdK * T
        Es = sc[:, None] * E / sc[None, :]
        out[:, j] = (expm_frechet(Xs, Es, compute_expm=False) @ v)[:2 * n] / sc[:2 * n]
    return out


def scatter_direction(Ke, dofs, n: int) -> np.ndarray:
    """An element's (6, 6) stiffness direction ``Ke`` (N/m per unit parameter) scattered to a dense
    (n, n) matrix over the free dofs; ``dofs`` (6,) are its free-dof indices, -1 where fixed."""
    out = np.zeros((n, n))
    ok = dofs >= 0
    out[np.ix_(dofs[ok], dofs[ok])] = Ke[np.ix_(ok, ok)]
    return out
