"""Linear maps of the model's restart state: its outputs and its modal coordinates.

The restart state ``r = [U; U'; eta]`` holds the displacements and velocities over the free dofs
(m and m/s) and the effect states of loads ``G eta``. :func:`restart_outputs` gives linear
functions of it whose uncertainty a smoother reports (displacement, velocity, nodal strains), and
:func:`load_patterns` the random nodal loads whose response is a spatially smooth process noise.
With the material fixed, ``r = V xi``, ``xi = [q; p; eta]`` with ``q = Phi^T M U`` and
``p = Phi^T M U'`` in the modes of a :class:`~sfem_filters.fem.statespace.ModalSystem`: the
transition is then sparse (the 2 x 2 modal blocks, Eq. 15, plus the effects' held loads).
:func:`modal_coordinates` gives every part of the model in ``xi``;
:meth:`sfem_filters.model.SFEMModel.linearise` uses them.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .._validate import as_float_array
from .dofs import DofMap
from .mesh import TriMesh
from .strain import nodal_strain_operator

__all__ = ["restart_outputs", "load_patterns", "modal_coordinates"]


def restart_outputs(mesh: TriMesh, dofmap: DofMap, n_restart: int, extra=None) -> dict:
    """Linear functions of the restart state ``[U; U'; eta]``, sparse (k, n_restart).

    ``displacement`` and ``velocity`` (the free dofs, m and m/s), ``strain``, the nodal strains
    (e_xx, e_yy, gamma_xy) of every node, row ``3 i + c``
    (:func:`~sfem_filters.fem.strain.nodal_strain_operator`), and each of ``extra``, a dict of
    (k, n_dofs) sparse matrices on the global displacements, on the free ones.
    """
    n, nr = dofmap.n_free, n_restart
    eye = sp.identity(n, format="csr")

    def on_displacement(op):
        op = op[:, dofmap.free]
        return sp.hstack([op, sp.csr_matrix((op.shape[0], nr - n))], format="csr")

    out = {"displacement": sp.hstack([eye, sp.csr_matrix((n, nr - n))], format="csr"),
           "velocity": sp.hstack([sp.csr_matrix((n, n)), eye, sp.csr_matrix((n, nr - 2 * n))], format="csr"),
           "strain": on_displacement(nodal_strain_operator(mesh))}
    out.update({k: on_displacement(v) for k, v in (extra or {}).items()})
    return out


def load_patterns(process_load_std, n: int) -> np.ndarray:
    """Random nodal loads as independent unit-variance patterns: W (n, k) with ``Sigma_w = W W^T``.

    Their response through the dynamics, ``B Sigma_w B^T``, is a spatially smooth (elastically
    correlated) displacement and velocity noise.

    Parameters
    ----------
    process_load_std : float, (n,) or (n, k) array
        Standard deviations (N per frame, zero allowed) of independent loads on the n free dofs
        (W diagonal), or the matrix W itself (loads correlated in space: ``W xi``, ``xi ~ N(0, I)``).
    n : int
        Free dofs.
    """
    sw = as_float_array("process_load_std", process_load_std)
    if sw.ndim == 2:                   # correlated loads W xi, xi ~ N(0, I): Sigma_w = W W^T
        if sw.shape[0] != n:
            raise ValueError(f"process_load_std: expected a (n_free, k) = ({n}, k) load matrix, "
                             f"got shape {sw.shape}")
        return sw
    sw = np.broadcast_to(sw, (n,))
    if np.any(sw < 0):
        raise ValueError("process_load_std: expected standard deviations >= 0 N")
    return np.diag(sw)


def modal_coordinates(system, G, eta_transition, loads, H, Q, P0, x0) -> dict:
    """The model's parts in the modal coordinates ``xi = W r``, ``W = diag(Phi^T M, Phi^T M, I)``.

    Parameters
    ----------
    system : ModalSystem
        The discretised dynamics over the n free dofs (:class:`~sfem_filters.fem.statespace.ModalSystem`).
    G : (n, n_eta) array
        Loads (N per unit state) of the effect states on the free dofs.
    eta_transition : (n_eta, n_eta) array
        Transition of the effect states.
    loads : (n_frames, n) array
        External loads (N) on the free dofs; ``loads[t + 1]`` is held from frame t to t + 1.
    H : (m, >= n_r) array
        Observation matrix whose first ``n_r = 2 n + n_eta`` columns act on the restart state.
    Q, P0 : (>= n_r, >= n_r) arrays
        Process noise and initial covariance whose leading ``n_r`` block is the restart state's.
    x0 : (>= n_r,) array
        Initial state, restart state first.

    Returns
    -------
    dict
        ``V`` (n_r, n_r), ``r = V xi``; ``A``, the sparse transition of ``xi``; ``c``
        (n_frames - 1, n_r), the held loads' response; ``H``, ``H V``; ``Q`` and ``P0``, the
        congruences ``W Q W^T`` and ``W P0 W^T``; ``xi0``, ``W x0``.
    """
    nx, ne = 2 * system.n, np.shape(G)[1]
    nr = nx + ne
    n = nx // 2
    V = np.zeros((nr, nr))
    blocks = [slice(0, n), slice(n, nx), slice(nx, nr)]
    Wb = [system.PhiTM, system.PhiTM, np.eye(ne)]
    for k, sl in enumerate(blocks):
        V[sl, sl] = system.Phi if k < 2 else np.eye(ne)

    def congruence(C):
        """W C W^T for W = diag(Phi^T M, Phi^T M, I), block by block, zero blocks skipped."""
        out = np.zeros((nr, nr))
        for i, si in enumerate(blocks):
            for j, sj in enumerate(blocks):
                Cij = C[si, sj]
                if j < i or not Cij.size or not np.any(Cij):
                    continue
                out[si, sj] = Wb[i] @ Cij @ Wb[j].T
                out[sj, si] = out[si, sj].T
        return out

    A = system.modal_transition()
    if ne:
        A = sp.bmat([[A, sp.csr_matrix(system.modal_input(G))],
                     [None, sp.csr_matrix(eta_transition)]], format="csr")
    frames = len(loads)
    c = np.zeros((frames - 1, nr))
    for t in range(frames - 1):
        c[t, :nx] = system.modal_input(loads[t + 1])
    Q, P0 = np.asarray(Q), np.asarray(P0)
    x0 = np.asarray(x0, float)
    return {"V": V, "A": A, "c": c, "H": H[:, :nr] @ V, "Q": congruence(Q[:nr, :nr]), "P0": congruence(P0[:nr, :nr]),
            "xi0": np.concatenate([Wb[k] @ x0[sl] for k, sl in enumerate(blocks)])}
