"""sfem_filters: stochastic finite-element filters for cardiac kinematics and material.

Shi & Liu (2003), "Stochastic finite element framework for simultaneous estimation of
cardiac kinematic functions and material parameters", Medical Image Analysis 7:445-464.

Subpackages: :mod:`~sfem_filters.fem` (finite elements, knows no filter),
:mod:`~sfem_filters.filtering` (engines and drivers, knows the model only through its
protocol), :mod:`~sfem_filters.imaging` (images to contours and velocities),
:mod:`~sfem_filters.cardiac` (the measured-data workflow), :mod:`~sfem_filters.benchmark`
(the paper's pinned experiment); :mod:`~sfem_filters.model` bridges fem and filtering.
"""
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
__version__ = "0.1.0"
