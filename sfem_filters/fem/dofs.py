"""Degrees of freedom: node-major numbering (dof ``2 i`` is the x displacement of node ``i``,
``2 i + 1`` its y displacement) and the split into fixed and free dofs.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
        """Global indices of the free dofs, ascending."""
        mask = np.ones(self.n_dofs, bool)
        mask[self.fixed] = False
        return np.flatnonzero(mask)

    @property
    def n_free(self) -> int:
        """Number of free dofs."""
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
