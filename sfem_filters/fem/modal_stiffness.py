"""Modal stiffness derivatives: how to make them (:func:`stiffness_plan`), and whether they pay.

:meth:`sfem_filters.fem.statespace.ModalSystem.modal_stiffness_derivatives` makes
``G_k = Phi^T dK^(k) Phi`` for the k parameters of a material map, either one projection per
parameter or one per group of element directions that act together; :func:`stiffness_plan`
chooses the cheaper and says what it costs (:class:`StiffnessPlan`). The element directions of
a material, d/dlog E_e and d/dnu_e, are :func:`stiffness_directions`. With them, every
sensitivity of one material skips an O(n^3) product: :func:`modal_stiffness_pays` says whether
that is worth their cost and memory (:func:`modal_stiffness_budget`) over a number of frames.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .._validate import integer
from ..resources import available_memory
from .elasticity import element_stiffness, plane_strain_matrix, plane_strain_matrix_dnu
from .material import Material
from .mesh import TriMesh

__all__ = ["stiffness_directions", "StiffnessPlan", "stiffness_plan", "modal_stiffness_budget", "modal_stiffness_pays",
           "MODAL_STIFFNESS_BYTES", "MODAL_STIFFNESS_FLOOR", "MODAL_STIFFNESS_SHARE", "PARAMETER_COST"]


def stiffness_directions(mesh: TriMesh, mat: Material, thickness: float) -> np.ndarray:
    """Element stiffness sensitivities of a material: d/dlog E_e (= K_e) and d/dnu_e, (2 n_el, 6, 6).

    The element-level directions (N/m per unit log E_e, per unit nu_e) that
    :meth:`~sfem_filters.fem.statespace.ModalSystem.sensitivity` and
    :meth:`~sfem_filters.fem.statespace.ModalSystem.modal_stiffness_derivatives` take, E_e's
    first; ``thickness`` in m.
    """
    Ke = element_stiffness(mesh, plane_strain_matrix(mat.E, mat.nu), thickness)
    dKnu = element_stiffness(mesh, plane_strain_matrix_dnu(mat.E, mat.nu), thickness)
    return np.concatenate([Ke, dKnu])


@dataclass(frozen=True, eq=False)
class StiffnessPlan:
    """How :meth:`ModalSystem.modal_stiffness_derivatives` makes ``G`` (:func:`stiffness_plan`)."""

    n_directions: int               # P, rows of combine
    n_params: int                   # k, columns of combine
    by_param: sp.csc_matrix         # combine, by column
    rows: np.ndarray                # (groups, k) the distinct rows of combine
    group: np.ndarray               # (P,) the group of each direction
    by_group: bool                  # made group by group (else parameter by parameter)
    products: int                   # dofs its projections touch, plus groups * k if grouped:
                                    # its cost in units of one row of an N x N product


def stiffness_plan(combine, dofs) -> StiffnessPlan:
    """Plan the modal stiffness derivatives of a parameter map: per parameter or per group.

    Directions with the same row of ``combine`` (a region's elements, say) act together, so one
    projection per such group over the dofs it touches, then ``G_k = sum_g combine[g, k] G_g``,
    is cheaper than one projection per parameter when the parameters reach many groups each (the
    orthonormal contrasts of a regional map reach every region). The cheaper is chosen.

    Parameters
    ----------
    combine : (P, k) array or sparse matrix
        The chain rule from the P element directions to the k parameters.
    dofs : (P, 6) int array
        Free dofs of each direction's element (-1: fixed).
    """
    C = sp.csr_matrix(combine)
    dofs = np.asarray(dofs)
    if dofs.ndim != 2 or dofs.shape != (C.shape[0], 6):
        raise ValueError(f"dofs: expected shape ({C.shape[0]}, 6), one row per row of combine, got {dofs.shape}")
    k = C.shape[1]
    rows, group = np.unique(C.toarray(), axis=0, return_inverse=True)
    group = np.asarray(group).ravel()
    Cc = C.tocsc()
    per_param = sum(np.unique(dofs[Cc.indices[Cc.indptr[j]:Cc.indptr[j + 1]]]).size for j in range(k))
    per_group = sum(np.unique(dofs[group == g]).size for g in range(len(rows))) + len(rows) * k
    by_group = per_group < per_param
    return StiffnessPlan(C.shape[0], k, Cc, rows, group, by_group, per_group if by_group else per_param)


#: Largest memory :meth:`sfem_filters.model.SFEMModel.linearise` spends on modal stiffness
#: derivatives (bytes): ``8 (k + groups) n^2`` while they are made (:func:`stiffness_plan`).
#: ``None`` (the default): :func:`modal_stiffness_budget`, a share of the memory available.
MODAL_STIFFNESS_BYTES: int | None = None

#: The budget's floor (bytes), and the share of the memory available it takes where that is more.
MODAL_STIFFNESS_FLOOR = 512 * 2 ** 20
MODAL_STIFFNESS_SHARE = 0.25


def modal_stiffness_budget() -> float:
    """Bytes the modal stiffness derivatives may take while made: :data:`MODAL_STIFFNESS_BYTES`
    where set, else a quarter of the memory available
    (:func:`sfem_filters.resources.available_memory`) and at least 512 MiB.

    A larger state needs them most (without them every frame's sensitivity is an O(n^3)
    product), and they grow as n^2, so a fixed cap would refuse them exactly there.
    """
    if MODAL_STIFFNESS_BYTES is not None:
        return float(MODAL_STIFFNESS_BYTES)
    available = available_memory()
    return float(MODAL_STIFFNESS_FLOOR if available is None else max(MODAL_STIFFNESS_FLOOR,
                                                                      MODAL_STIFFNESS_SHARE * available))


#: What a parameter costs a frame's sensitivity with modal stiffness derivatives, relative to
#: what a dof costs it without: a pass over G's ``k N`` row per parameter (memory-bound) against
#: a row of the ``n N`` matrix product per dof (BLAS). Measured on the shipped slice (n = 664,
#: k = 23): about 0.29 ms a parameter against 0.075 ms a dof, so 4.
PARAMETER_COST = 4.0


def modal_stiffness_pays(plan: StiffnessPlan, frames: int, n: int, budget: float | None = None) -> bool:
    """Whether modal stiffness derivatives made by ``plan`` pay for themselves over ``frames``
    sensitivities of one material.

    Without them a frame's sensitivity costs a product of ``n`` rows (one per dof, in units of a
    row of an N x N product); with them it costs a pass over G, ``PARAMETER_COST k`` rows, after
    ``plan.products`` rows made once. They are made when that costs less than half, and the
    memory they take while made fits in :func:`modal_stiffness_budget`.

    Parameters
    ----------
    plan : StiffnessPlan
        :func:`stiffness_plan` of the parameter map.
    frames : int
        Sensitivities to be taken with this material (>= 1).
    n : int
        Free dofs (>= 1).
    budget : float, optional
        Bytes they may take while made (default :func:`modal_stiffness_budget`).

    Returns
    -------
    bool
    """
    frames = integer("frames", frames, 1)
    n = integer("n", n, 1)
    k = plan.n_params
    held = k + (len(plan.rows) if plan.by_group else 0)
    if k == 0 or 8 * held * n * n > (modal_stiffness_budget() if budget is None else budget):
        return False
    return plan.products / frames + PARAMETER_COST * k < 0.5 * n
