"""Shared helpers of the figure modules (matplotlib with the Agg backend, loaded on first use).

Colour rules of every figure: one-signed data (a magnitude, a standard deviation, a modulus, a
strain that is negative everywhere) get a perceptually uniform sequential map
(:data:`SEQUENTIAL`); signed data get a diverging map centred at zero with symmetric limits
(:data:`DIVERGING`). :func:`colour_scale` decides from the data's sign, not from the figure. The one
exception is a quantity signed by definition (the prior check's z), marked :data:`SIGNED_BY_DEFINITION`.
"""
from __future__ import annotations

import os

import numpy as np

from ..fem.mesh import TriMesh

#: Sequential (perceptually uniform) and diverging colour maps the figures use.
SEQUENTIAL = ("viridis", "cividis", "magma", "plasma", "inferno", "viridis_r", "cividis_r", "magma_r", "plasma_r")
DIVERGING = ("RdBu_r", "RdBu", "coolwarm", "PuOr", "PuOr_r", "BrBG")
#: ``gid`` of a colour-mapped artist whose quantity is signed by definition (a z score: 0 means consistent,
#: the sign says which way), drawn on a diverging map centred at zero even when one run's values share a sign.
SIGNED_BY_DEFINITION = "signed-by-definition"


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


def colour_scale(*arrays, sequential: str = "viridis", diverging: str = "RdBu_r", vmin=None) -> dict:
    """``cmap``, ``vmin`` and ``vmax`` for one colour bar shared by ``arrays`` (NaN ignored).

    Data of one sign (all >= 0 or all <= 0) get the ``sequential`` map between their extremes
    (from ``vmin`` when given, for example 0 for a magnitude); data of both signs get the
    ``diverging`` map with limits symmetric about zero, so that white is zero.
    """
    v = np.concatenate([np.ravel(np.asarray(a, float)) for a in arrays])
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"cmap": sequential, "vmin": 0.0, "vmax": 1.0}
    lo, hi = float(v.min()), float(v.max())
    if lo >= 0.0 or hi <= 0.0:
        lo = lo if vmin is None else float(vmin)
        return {"cmap": sequential, "vmin": lo, "vmax": hi if hi > lo else lo + 1e-12}
    top = max(-lo, hi)
    return {"cmap": diverging, "vmin": -top, "vmax": top}


def _write_figures(obj, directory: str, figures) -> list:
    """Call each ``fn(obj, path)`` of ``(file name, fn)`` pairs into ``directory``; the paths."""
    os.makedirs(directory, exist_ok=True)
    out = []
    for name, fn in figures:
        path = os.path.join(directory, name)
        fn(obj, path)
        out.append(path)
    return out
