"""The names ``import sfem_filters`` offers, for type checkers and for :mod:`lazy_loader`, which reads this
stub to load each name's module on first use (see ``__init__.py``)."""
from .fem.material import Material, Parameterisation
from .fem.mesh import TriMesh, delaunay_mesh, rectangle_mesh
from .filtering.cyclic import CyclicEKF, cyclic_estimate
from .filtering.ekf import SFEMExtendedKalmanFilter
from .filtering.iterated import IteratedSmoother, iterated_smoother
from .model import SFEMModel
from .resources import blas_threads

__all__ = ["SFEMModel", "SFEMExtendedKalmanFilter", "CyclicEKF", "cyclic_estimate", "IteratedSmoother",
           "iterated_smoother", "Material", "Parameterisation",
           "TriMesh", "rectangle_mesh", "delaunay_mesh", "blas_threads"]
