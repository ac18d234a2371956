"""Results that open in ParaView: meshes with per-frame fields, as VTU files and a ``.pvd`` index.

>>> import tempfile, numpy as np
>>> from sfem_filters.export import write_series, read_series
>>> pts = np.array([[0.0, 0.0], [1e-3, 0.0], [0.0, 1e-3]])
>>> d = tempfile.mkdtemp()
>>> pvd = write_series(d, "tri", pts, [[0, 1, 2]], times=[0.0, 0.03],
...                    point_data={"displacement_m": np.zeros((2, 3, 2))}, cell_data={"E_Pa": [1e4]})
>>> [(t, m.point_data["displacement_m"].shape) for t, m in read_series(pvd)]
[(0.0, (3, 3)), (0.03, (3, 3))]

:func:`export_dense` writes a measured-data run (``sfem-filters dense --export DIR``),
:func:`export_comparison` the synthetic comparison (``sfem-filters compare --export DIR``).
Needs meshio.
"""
from .paraview import read_series, write_series
from .results import export_comparison, export_dense

__all__ = ["write_series", "read_series", "export_dense", "export_comparison"]
