"""The workflow's settings: nominal values for what a sequence does not record, the choices of
drive, material map, estimator, observation and mesh, and the smoother's iteration limits."""
from __future__ import annotations

__all__ = ["NOMINAL", "EFFECT_STEP", "BASIS", "PARAMETERISATIONS", "ESTIMATORS", "DRIVES", "OBSERVE", "MESHES",
           "MAX_ITERATIONS", "ELEMENT_PX", "default_max_iterations"]


#: Values used when a sequence does not record them (documented in every report).
NOMINAL = {
    "pixel_spacing": 1.0e-3,    # m per pixel
    "frame_interval": 0.03,     # s
    "E": 10e3,                  # Pa, initial Young's modulus (scale only: not identifiable)
    "nu": 0.45,                 # initial Poisson's ratio
    "density": 1050.0,          # kg/m^3
    "alpha": 10.0,              # 1/s, Rayleigh mass coefficient
    "beta": 3e-3,               # s, Rayleigh stiffness coefficient: transients decay within a frame
    "penalty": 0.03,            # penalty springs in units of the median diagonal of K: soft, so
                                # that the tissue's own mechanics shape the landmark motion
    "foundation": 1e-3,         # ground springs (drive pressure/none) in the same units
    "E_level_sd": 1.5,          # prior sd of log E's global level when a measured pressure fixes the
                                # force scale: 5-100 kPa lie within 1.5 sd of 10 kPa
}

#: Per-frame random-walk step of effect amplitudes (units of NOMINAL["E"]): a myocardial active
#: strain of ~0.4 builds up over ~10 frames.
EFFECT_STEP = 0.04

#: The smooth material basis (``parameterisation="basis"``): leading modes of a squared-exponential
#: correlation over element centroids, its length a fraction of the mesh's diameter; relative
#: stiffness (mean log E fixed, as with the regions), Poisson's ratio absolute.
BASIS = {"modes_E": 6, "modes_nu": 3, "length_fraction": 0.25}

#: Material parameterisations by name (``parameterisation=``, ``--parameterisation``).
PARAMETERISATIONS = ("region", "basis", "element", "none")
#: How kinematics and material are estimated (``estimator=``, ``--estimator``): the iterated
#: smoother (one cycle, data counted once, Laplace posterior), the paper's cyclic joint EKF, or
#: Moireau & Chapelle's reduced-order UKF in the same cyclic driver.
ESTIMATORS = ("smoother", "cyclic", "roukf")
#: What drives the model besides its effects (``drive=``, ``--drive``): springs toward the
#: landmarks, springs toward the whole contours interpolated from the landmarks, a measured
#: cavity pressure, or nothing.
DRIVES = ("penalty", "contour", "pressure", "none")
#: Which points are observed (``observe=``, ``--observe``).
OBSERVE = ("boundary", "boundary+midwall")
#: How :func:`prepare` triangulates the points (its ``mesh`` argument).
MESHES = ("delaunay", "radial", "polar")


#: The smoother's iteration limit when none is given (``max_iterations=None``, ``--max-iterations``):
#: 20, and 80 under a measured pressure, where the stiffness level is a parameter and converges
#: slowly (the 100 kPa synthetic annulus of the rounds' validation needs 57 iterations), so that 20 could leave the
#: level's interval short of the truth.
MAX_ITERATIONS = {"default": 20, "pressure": 80}
#: Target element edge of ``mesh="polar"`` (:func:`prepare`), in the points' spacings (pixels).
ELEMENT_PX = 2.0


def default_max_iterations(drive: str) -> int:
    """The smoother's iteration limit for ``drive`` when none is given (:data:`MAX_ITERATIONS`)."""
    return MAX_ITERATIONS["pressure" if drive == "pressure" else "default"]
