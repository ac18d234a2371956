"""Finite elements of the myocardium: meshes, elasticity, material maps, exact dynamics, strain.

Knows nothing of filters. Everything is SI (m, Pa, kg, s, N); degrees of freedom are numbered
node-major, x before y. A walk through one model's pieces (Shi & Liu 2003, section 2):

>>> import numpy as np
>>> from sfem_filters.fem import (Material, ModalSystem, DofMap, mass_matrix, node_dofs,
...                               node_observation_matrix, nodal_strains, rectangle_mesh, stiffness_matrix)
>>> mesh = rectangle_mesh(0.06, 0.04, 7, 5)                 # 60 x 40 mm, 48 triangles
>>> mat = Material.uniform(mesh.n_elements, E=75e3, nu=0.4)  # Pa, -
>>> K = stiffness_matrix(mesh, mat.E, mat.nu)               # Eqs. (3)-(5), sparse, N/m
>>> M = mass_matrix(mesh, density=1050.0)                   # kg
>>> bottom = mesh.nodes_where(lambda x, y: y == 0.0)
>>> dofs = DofMap(mesh.n_dofs, node_dofs(bottom))           # fixed bottom edge
>>> system = ModalSystem(dofs.restrict_matrix(M), dofs.restrict_matrix(K), alpha=10.0, beta=1e-3, T=0.03125)
>>> x1 = system.step(np.zeros(2 * dofs.n_free), np.ones(dofs.n_free))   # exact ZOH step, Eq. (14)
>>> D = node_observation_matrix(mesh, mesh.boundary_nodes())  # an observation operator, Eq. (12)
>>> nodal_strains(mesh, dofs.expand(x1[:dofs.n_free])).shape  # (e_xx, e_yy, gamma_xy) per node
(35, 3)

Modules: :mod:`~sfem_filters.fem.mesh` (triangle meshes),
:mod:`~sfem_filters.fem.polygon_mesh` (a region meshed at a chosen element size, Gmsh),
:mod:`~sfem_filters.fem.elasticity` (constitutive law, element and global K, M, damping), :mod:`~sfem_filters.fem.loads`
(pressure, prescribed stress, penalty springs), :mod:`~sfem_filters.fem.dofs` (numbering,
fixed and free dofs), :mod:`~sfem_filters.fem.material` (material and its parameterisations
theta), :mod:`~sfem_filters.fem.statespace` (state-space form, exact discretisation, exact
sensitivity M_t; with :mod:`~sfem_filters.fem.reference_zoh`, the paper's dense route,
:mod:`~sfem_filters.fem.modal_exp`, the modal oscillators' exponentials,
:mod:`~sfem_filters.fem.modal_stiffness`, planning the modal stiffness derivatives, and
:mod:`~sfem_filters.fem.restart_state`, the outputs and modal coordinates of the kinematic state),
:mod:`~sfem_filters.fem.observation` (observation operators),
:mod:`~sfem_filters.fem.strain` (element and nodal strains).
"""
from .dofs import DofMap, node_dofs
from .elasticity import (assemble, element_mass, element_stiffness, element_stiffness_derivatives, mass_matrix,
                         plane_strain_matrix, plane_strain_matrix_dnu, rayleigh_damping, stiffness_matrix,
                         strain_displacement)
from .loads import penalty_load, penalty_stiffness, pressure_load, stress_loads
from .material import Material, Parameterisation, correlated_prior
from .mesh import (TriMesh, check_mesh, delaunay_mesh, delaunay_triangles, lattice_mesh, lattice_offset, mesh_quality,
                   rectangle_mesh, triangle_angles)
from .observation import (blurred_observation_matrix, interpolation_matrix, locate_points, node_observation_matrix,
                          point_observation_matrix, sample_interpolation)
from .polygon_mesh import circle_polygon, edge_lengths, polygon_mesh, resample_polygon
from .statespace import (ModalSystem, StiffnessPlan, continuous_matrices, discretize_zoh, reference_sensitivity,
                         stiffness_plan)
from .strain import element_strains, nodal_average, nodal_strains

from .restart_state import restart_outputs
from .strain import nodal_strain_operator
__all__ = ["TriMesh", "check_mesh", "rectangle_mesh", "delaunay_mesh", "delaunay_triangles", "lattice_mesh",
           "lattice_offset", "mesh_quality", "triangle_angles", "polygon_mesh", "circle_polygon", "resample_polygon",
           "edge_lengths",
           "plane_strain_matrix", "plane_strain_matrix_dnu", "strain_displacement", "element_stiffness",
           "element_mass", "assemble", "stiffness_matrix", "mass_matrix", "element_stiffness_derivatives",
           "rayleigh_damping", "pressure_load", "stress_loads", "penalty_stiffness", "penalty_load",
           "node_dofs", "DofMap", "Material", "Parameterisation", "correlated_prior", "ModalSystem",
           "StiffnessPlan", "stiffness_plan", "continuous_matrices", "discretize_zoh", "reference_sensitivity",
           "node_observation_matrix", "interpolation_matrix",
           "point_observation_matrix", "locate_points", "blurred_observation_matrix", "sample_interpolation",
           "element_strains", "nodal_average", "nodal_strains",
           "restart_outputs",
           "nodal_strain_operator"]
