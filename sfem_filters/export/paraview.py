"""Time series of meshes and fields for ParaView: one VTU file per frame and a ``.pvd`` index.

ParaView opens the ``.pvd`` file as one time series (File > Open, then Apply; the time slider
steps through the frames). Files are written with meshio (VTU, binary), read back with
``meshio.read``. Everything is SI: positions and displacements in m, velocities in m/s, E in Pa.
"""
from __future__ import annotations

import os
import re
from xml.sax.saxutils import quoteattr

import numpy as np

from .._validate import as_float_array

__all__ = ["write_series", "read_series"]


def _xyz(a) -> np.ndarray:
    """(..., 2) -> (..., 3) with a zero third component (ParaView's vectors are 3D)."""
    a = np.asarray(a, float)
    if a.shape[-1] != 2:
        return a
    return np.concatenate([a, np.zeros(a.shape[:-1] + (1,))], axis=-1)


def _frame_field(name, value, n_frames, n_items, t):
    v = np.asarray(value)
    if v.ndim >= 1 and v.shape[0] == n_frames and (v.ndim > 1 and v.shape[1] == n_items):
        v = v[t]
    elif v.shape[0] != n_items:
        raise ValueError(f"{name}: expected ({n_frames}, {n_items}, ...) per frame or ({n_items}, ...) constant, "
                         f"got shape {v.shape}")
    v = np.asarray(v, float) if v.dtype.kind == "f" else np.asarray(v)
    return _xyz(v) if v.ndim == 2 and v.shape[1] == 2 else v


def write_series(directory, name: str, points, cells, times, point_data=None, cell_data=None,
                 cell_type: str = "triangle") -> str:
    """Write a mesh with per-frame fields as ``name_XXXX.vtu`` files and ``name.pvd``.

    Parameters
    ----------
    directory : path
        Created if missing.
    name : str
        File stem (letters, digits, ``_`` and ``-``).
    points : (N, 2) or (N, 3) array
        Node positions (m).
    cells : (E, 3) int array for triangles, or (N, 1) for a point cloud (``cell_type="vertex"``)
    times : (F,) array
        Time of each frame (s).
    point_data, cell_data : dict name -> array
        Per frame ``(F, N, ...)`` / ``(F, E, ...)`` or constant ``(N, ...)`` / ``(E, ...)``;
        2-vectors are padded to 3D.

    Returns
    -------
    str
        The path of the ``.pvd`` file.
    """
    import meshio  # an optional heavy dependency: only the export needs it

    if not name or any(not (c.isalnum() or c in "_-") for c in name):
        raise ValueError(f"name: expected letters, digits, '_' or '-', got {name!r}")
    pts = _xyz(as_float_array("points", points))
    cells = np.asarray(cells, int)
    times = as_float_array("times", times, shape=(None,))
    F, N, E = len(times), len(pts), len(cells)
    os.makedirs(directory, exist_ok=True)
    entries = []
    for t in range(F):
        pd = {k: _frame_field(k, v, F, N, t) for k, v in (point_data or {}).items()}
        cd = {k: [_frame_field(k, v, F, E, t)] for k, v in (cell_data or {}).items()}
        fname = f"{name}_{t:04d}.vtu"
        meshio.write(os.path.join(directory, fname), meshio.Mesh(pts, [(cell_type, cells)], point_data=pd,
                                                                   cell_data=cd), binary=True)
        entries.append(f'    <DataSet timestep="{float(times[t])!r}" part="0" file={quoteattr(fname)}/>')
    pvd = os.path.join(directory, f"{name}.pvd")
    with open(pvd, "w") as f:
        f.write('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n'
                + "\n".join(entries) + "\n  </Collection>\n</VTKFile>\n")
    return pvd


def read_series(pvd) -> list:
    """``(time, meshio.Mesh)`` per frame of a ``.pvd`` file written by :func:`write_series`."""
    import meshio

    text = open(pvd).read()
    base = os.path.dirname(os.path.abspath(pvd))
    return [(float(t), meshio.read(os.path.join(base, f)))
            for t, f in re.findall(r'timestep="([^"]+)"[^>]*file="([^"]+)"', text)]
