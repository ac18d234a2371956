"""Shared helpers of the figure modules (matplotlib with the Agg backend, loaded on first use)."""
from __future__ import annotations

import os

from ..fem.mesh import TriMesh


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _triangulation(mesh: TriMesh, U=None, scale: float = 1.0, unit: float = 1e3):
    """matplotlib Triangulation of the (deformed) mesh, coordinates in mm by default (``unit``)."""
    import matplotlib.tri as mtri
    xy = mesh.nodes if U is None else mesh.nodes + scale * U.reshape(-1, 2)
    return mtri.Triangulation(xy[:, 0] * unit, xy[:, 1] * unit, mesh.elements)


def _write_figures(obj, directory: str, figures) -> list:
    """Call each ``fn(obj, path)`` of ``(file name, fn)`` pairs into ``directory``; the paths."""
    os.makedirs(directory, exist_ok=True)
    out = []
    for name, fn in figures:
        path = os.path.join(directory, name)
        fn(obj, path)
        out.append(path)
    return out


