"""sfem_filters: stochastic finite-element filters for cardiac kinematics and material.

Shi & Liu (2003), "Stochastic finite element framework for simultaneous estimation of
cardiac kinematic functions and material parameters", Medical Image Analysis 7:445-464.

Subpackages: :mod:`~sfem_filters.fem` (finite elements, knows no filter),
:mod:`~sfem_filters.filtering` (engines and drivers, knows the model only through its
protocol), :mod:`~sfem_filters.imaging` (images to contours and velocities),
:mod:`~sfem_filters.cardiac` (the measured-data workflow), :mod:`~sfem_filters.benchmark`
(the paper's pinned experiment); :mod:`~sfem_filters.model` bridges fem and filtering.
"""
import lazy_loader as _lazy

# The names below are loaded on first use: ``import sfem_filters`` (and the console script, which
# says it has started before anything heavy loads) costs milliseconds, not the 1-2 s of numpy,
# scipy and filterpy. The names and their modules are written once, as imports, in __init__.pyi.
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
__version__ = "0.1.0"
