"""sfem_filters: stochastic finite-element filters for cardiac kinematics and material.

Shi & Liu (2003), "Stochastic finite element framework for simultaneous estimation of
cardiac kinematic functions and material parameters", Medical Image Analysis 7:445-464.
"""
from .filters import SFEMExtendedKalmanFilter, cyclic_estimate
from .material import Material, Parameterisation
from .mesh import TriMesh, delaunay_mesh, rectangle_mesh
from .model import SFEMModel

__all__ = ["SFEMModel", "SFEMExtendedKalmanFilter", "cyclic_estimate", "Material", "Parameterisation",
           "TriMesh", "rectangle_mesh", "delaunay_mesh"]
__version__ = "0.1.0"
