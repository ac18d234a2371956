"""The filter model of measured point-wise motion (DENSE, tagging, tracking), and its evaluation.

Steps 1-4 of the paper's section 3.2 workflow on a :class:`sfem_filters.cardiac.sequence.Sequence`
(:mod:`sfem_filters.cardiac.closing` adds the residual diagnosis and the missing effects):

1. :func:`prepare`: mesh the myocardium on the measured points, find endo- and epicardium, the
   cavity centre and the radial / circumferential directions; observe sparse landmarks on
   each contour (as shape tracking gives) and, optionally, a seeded half of the mid-wall
   points; hold every other point out for validation;
2. :func:`build_model`: drive the elastic model with the landmarks through
   confidence-weighted penalty springs (section 2.7), with a measured cavity pressure, or
   with nothing but its effects; the material map is a parameterisation (regions, a smooth
   basis, per element or fixed);
3. :func:`run`: estimate kinematics and material from one cycle with the iterated smoother
   (the default: the MAP of the cycle, its data counted once, with a Laplace posterior) or the
   paper's cyclic joint EKF (``estimator="cyclic"``, reported with the covariance of one cycle);
4. :func:`evaluate`: held-out error, innovations, NIS and whiteness, the posterior sd of the
   material and of the strains, and the material against its prior (:func:`material_conflict`:
   a region pushed further than the data's information allows, typically to mimic a missing
   effect, is named).

Units: the sequence is in pixels unless it says otherwise. Inside, everything is SI: a pixel
is ``pixel_spacing`` metres and frames are ``frame_interval`` seconds apart, taken from the
file or, when it does not record them, from :data:`NOMINAL` (reported as such). Errors are
reported in pixels. Without a pressure measurement absolute stiffness is not identifiable, so
the nominal Young's modulus only sets the scale of the estimated map.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .._validate import as_float_array, integer, positive
from ..fem.dofs import node_dofs
from ..fem.elasticity import stiffness_matrix
from ..fem.loads import penalty_load, penalty_stiffness, pressure_load
from ..fem.material import Material, Parameterisation
from ..fem.mesh import lattice_mesh
from ..fem.observation import interpolation_matrix, node_observation_matrix
from ..fem.strain import nodal_strains
from ..filtering import diagnostics
from ..filtering.cyclic import cyclic_estimate
from ..filtering.iterated import NOISE_LEVELS, IteratedSmoother, exact_laplace
from ..filtering.iterated import with_covariance as smoother_with_covariance
from ..filtering.marginal import log_posterior
from ..filtering.protocol import parameter_prior
from ..geometry import polygon_centroid, radius_by_angle, triangle_double_areas
from ..model import SFEMModel
from .effects import build_effects, segment_labels
from .myocardium import (
    contour_landmarks,
    lv_geometry,
    polar_mesh,
    polar_strain_operator,
    polar_strains,
    tissue_mesh,
    transmural_depth,
)
from .reference import contour_interpolant, heldout_errors, residual_spline
from .sequence import Sequence

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


def noise_floor(displacement) -> float:
    """Measurement noise estimated from the data (per-point vector RMS, data units).

    The second difference of a smooth trajectory is small, that of white noise has variance
    1.5 sigma^2 per component for ``u_t - (u_{t-1} + u_{t+1}) / 2``; the per-point figure is
    ``sqrt(2) sigma``.
    """
    u = np.asarray(displacement, float)
    d2 = u[1:-1] - 0.5 * (u[:-2] + u[2:])
    if not np.any(np.isfinite(d2)):
        raise ValueError(f"displacement: the noise floor needs a point with data in 3 consecutive frames; got shape "
                         f"{u.shape} with none")
    sigma = np.sqrt(np.nanmean(d2 ** 2) / 1.5)
    return float(np.sqrt(2.0) * sigma)


@dataclass(eq=False)
class Setup:
    """Mesh, geometry, landmarks and the observed / held-out split of a sequence."""

    seq: Sequence
    spacing: float                  # m per data unit
    frame_interval: float           # s
    nominal: list                   # which of spacing / frame_interval are nominal
    mesh: object
    geometry: object
    node_of_point: np.ndarray       # mesh node of each data point
    landmarks: np.ndarray           # observed boundary landmark points (endo then epi)
    observed: np.ndarray            # all observed points
    heldout: np.ndarray             # points held out for validation
    noise_px: float                 # per-point noise floor (data units), from the observed points only
    n_landmarks: int
    observe: str
    holdout_seed: int
    regions: np.ndarray = field(default=None)   # material region of each element
    mesh_kind: str = "delaunay"                 # how the points were triangulated (MESHES)
    angle_origin_deg: float = 0.0               # where landmarks, sectors and segments start (deg)
    # image-derived data (sfem_filters.frontend): when set, they replace the sequence's own
    # displacements at the observed points, and add velocity rows (Eq. 13)
    obs_displacement: np.ndarray = field(default=None)   # (F, P, 2) data units, NaN if missing
    obs_sigma: np.ndarray = field(default=None)          # (F, P) per-component sd, data units
    obs_confidence: np.ndarray = field(default=None)     # (F, P) in [0, 1]
    velocity_points: np.ndarray = field(default=None)    # points with velocity data
    velocity: np.ndarray = field(default=None)           # (F, V, 2) data units per second
    velocity_sigma: np.ndarray = field(default=None)     # (F, V) per-component sd, units per second
    # the points' own mesh and geometry (contours, landmarks, directions at the points); the same
    # objects as mesh and geometry when the mesh has a node per point (node_of_point), else the
    # mesh is chosen apart from the points (mesh="polar") and ``interpolation`` (sparse (P, n_nodes),
    # the shape functions at each point) carries nodal values to the points
    point_mesh: object = field(default=None)
    point_geometry: object = field(default=None)
    interpolation: object = field(default=None)
    element_px: float | None = None                      # target element edge of mesh="polar", point spacings

    def __post_init__(self):
        if self.point_mesh is None:
            self.point_mesh = self.mesh
        if self.point_geometry is None:
            self.point_geometry = self.geometry


def prepare(seq: Sequence, landmarks: int = 8, observe: str = "boundary", holdout_seed: int = 0,
            n_sectors: int = 6, mesh: str = "delaunay", angle_origin_deg: float = 0.0,
            element_px: float = ELEMENT_PX) -> Setup:
    """Mesh the points and split them into observed and held-out sets.

    Parameters
    ----------
    landmarks : int
        Landmarks per contour (endo- and epicardium), evenly spaced in angle.
    observe : {"boundary", "boundary+midwall"}
        Observe the landmarks only, or also a seeded random half of the mid-wall points.
    holdout_seed : int
        Seed of the mid-wall split.
    n_sectors : int
        Angular sectors of the regional material map (times two transmural layers).
    mesh : {"delaunay", "radial"}
        How the points are triangulated. ``"delaunay"`` (the default, every figure in the docs
        so far): a Delaunay triangulation, whose diagonal in each full cell of a pixel lattice is
        a tie that Qhull breaks by the floating-point coordinates, so the same heart shifted,
        turned or mirrored in the image gets other diagonals (and other numbers: the docs'
        frozen mesh-orientation result). ``"radial"``: points on a pixel lattice are meshed
        by :func:`sfem_filters.fem.mesh.lattice_mesh` with every diagonal pointing towards the
        cavity centre, the same triangles moved with the heart (points off a lattice: an
        error). The cells, the boundary, and so the contours, landmarks and sectors are the same.
        ``"polar"``: a mesh chosen apart from the points (:func:`sfem_filters.cardiac.myocardium.polar_mesh`):
        node rings at equal angles about the cavity centre, layers at equal fractions of the wall,
        edges of about ``element_px``, the wall widened by half the points' spacing so that every
        point lies inside; the points are observed and held out through the elements' shape
        functions (Eq. 12 as an interpolation, :func:`sfem_filters.fem.observation.interpolation_matrix`)
        and the drive's springs pull at the points through them too. Its cost is set by the
        element size, not by the number of points (the filter's cost grows as the cube of the
        nodes); contours, landmarks and held-out points are those of the points' own mesh.
    element_px : float
        Target element edge of ``mesh="polar"``, in the points' spacings (pixels on a pixel
        lattice; > 0). Default :data:`ELEMENT_PX`.
    angle_origin_deg : float
        Where the angles about the cavity centre start (degrees, ``atan2(y, x)`` in the data's
        axes: x to the right, y down the image, so angles grow clockwise on screen): landmark 0 of
        each contour, sector 0 of the regional map and segment 0 of ``active_segments``, for
        example at the anterior right-ventricular insertion, where the clinical segment models
        start (they count the other way round in the usual view, so only segment 0 need agree).
        Default 0, +x.
        With the origin on an anatomical landmark the sectors belong to the heart, not to the
        image axes: the same heart turned by a quarter turn (``moved_on_lattice(quarter_turns=1)``
        maps angle a to a - 90) with its origin turned alike gets the same landmarks and sectors.
    """
    if not isinstance(seq, Sequence):
        raise TypeError(f"seq: expected a Sequence (sfem_filters.cardiac.load_sequence(path) reads one), got "
                        f"{type(seq).__name__}")
    if observe not in OBSERVE:
        raise ValueError(f"observe: expected one of {OBSERVE}, got {observe!r}")
    landmarks = integer("landmarks", landmarks, 3)
    n_sectors = integer("n_sectors", n_sectors, 1)
    holdout_seed = integer("holdout_seed", holdout_seed, 0)
    if mesh not in MESHES:
        raise ValueError(f"mesh: expected one of {MESHES}, got {mesh!r}")
    angle_origin_deg = float(as_float_array("angle_origin_deg", angle_origin_deg, shape=()))
    mesh_kind = mesh
    nominal = []
    if seq.units == "m":
        spacing = 1.0
    elif seq.pixel_spacing is not None:
        spacing = seq.pixel_spacing
    else:
        spacing = NOMINAL["pixel_spacing"]
        nominal.append("pixel_spacing")
    if seq.frame_interval is not None:
        T = seq.frame_interval
    else:
        T = NOMINAL["frame_interval"]
        nominal.append("frame_interval")
    pts = seq.points * spacing
    tri_mesh, _, lattice = tissue_mesh(pts)
    element_px = positive("element_px", element_px, "point spacings")
    # the contours (and so the cavity centre, the radial directions and the wall's nodes) do not
    # depend on the diagonals of full cells: one geometry serves either mesh
    geometry = lv_geometry(tri_mesh)
    if mesh == "radial":
        try:
            radial = lattice_mesh(pts, lattice, geometry.centre)
        except ValueError as exc:
            raise ValueError(f"mesh: 'radial' needs points on a square pixel lattice; {exc}") from None
        if radial.n_nodes != len(pts) or radial.n_elements != tri_mesh.n_elements:
            raise ValueError(f"mesh: 'radial' meshed {radial.n_elements} triangles on {radial.n_nodes} points where "
                             f"Delaunay has {tri_mesh.n_elements} on {tri_mesh.n_nodes}: the points are not a pixel "
                             "lattice's tissue; use mesh='delaunay'")
        tri_mesh = radial
    mesh = tri_mesh
    shortest = min(len(geometry.endo), len(geometry.epi))
    if landmarks > shortest:
        raise ValueError(f"landmarks: expected at most {shortest} per contour (the shorter contour's points), "
                         f"got {landmarks}")
    # a point without data in any frame cannot be a landmark: its spring would pull the tissue to
    # a made-up target; the closest contour point with data takes its place, and the user is told
    has_data = np.any(np.all(np.isfinite(seq.displacement), axis=-1), axis=0)
    ideal = np.concatenate(contour_landmarks(geometry, mesh, landmarks, offset_deg=angle_origin_deg))
    for name, loop in (("endocardial", geometry.endo), ("epicardial", geometry.epi)):
        if landmarks > int(has_data[loop].sum()):
            raise ValueError(f"landmarks: the {name} contour has {int(has_data[loop].sum())} of its {len(loop)} points "
                             f"with data in some frame, fewer than the {landmarks} landmarks asked for (points without "
                             "data cannot be landmarks)")
    endo_l, epi_l = contour_landmarks(geometry, mesh, landmarks, offset_deg=angle_origin_deg, eligible=has_data)
    lm = np.concatenate([endo_l, epi_l])
    moved = np.flatnonzero(~has_data[ideal])
    if moved.size:
        turn = np.degrees(np.abs(np.angle(np.exp(1j * (geometry.angle(mesh.nodes[lm[moved]])
                                                          - geometry.angle(mesh.nodes[ideal[moved]]))))))
        warnings.warn(f"landmarks: {moved.size} contour point(s) {ideal[moved].tolist()} have no data in any frame; "
                      f"the closest contour points with data, {lm[moved].tolist()} ({turn.max():.1f} degrees away at "
                      "most), are the landmarks instead", RuntimeWarning, stacklevel=2)
    observed = lm
    if observe == "boundary+midwall":
        rng = np.random.default_rng(holdout_seed)
        mid = geometry.midwall
        observed = np.union1d(lm, rng.choice(mid, size=len(mid) // 2, replace=False))
    heldout = np.setdiff1d(np.arange(len(pts)), observed)
    point_mesh, point_geometry, interpolation = mesh, geometry, None
    node_of_point = np.arange(len(pts))
    if mesh_kind == "polar":
        # the points' contours (their own mesh's boundary), widened by half a spacing
        mesh = polar_mesh(pts[geometry.endo], pts[geometry.epi], geometry.centre, element_px * lattice,
                          margin=0.5 * lattice)
        geometry = lv_geometry(mesh)
        interpolation = interpolation_matrix(mesh, pts, max_outside=0.5 * lattice)
        node_of_point = None
    # regional map: angular sectors x (inner, outer) halves of the wall
    # (the segments of active_segments, counted the same way from the same origin)
    sector = (segment_labels(mesh, geometry, n_sectors, angle_origin_deg) if n_sectors > 1
              else np.zeros(mesh.n_elements, int))
    layer = (transmural_depth(mesh, geometry) > 0.5).astype(int)
    try:
        noise_px = noise_floor(seq.displacement[:, observed])
    except ValueError:
        raise ValueError(f"displacement: none of the {len(observed)} observed points has data in 3 consecutive "
                         "frames, which the noise floor (and the drive's process noise) is estimated from; expected "
                         "at least one") from None
    return Setup(seq=seq, spacing=spacing, frame_interval=T, nominal=nominal, mesh=mesh, geometry=geometry,
                 node_of_point=node_of_point, landmarks=lm, observed=observed, heldout=heldout,
                 noise_px=noise_px, n_landmarks=landmarks, observe=observe,
                 holdout_seed=holdout_seed, regions=2 * sector + layer, mesh_kind=mesh_kind,
                 angle_origin_deg=angle_origin_deg, point_mesh=point_mesh, point_geometry=point_geometry,
                 interpolation=interpolation, element_px=element_px if mesh_kind == "polar" else None)


def at_points(setup: Setup, nodal) -> np.ndarray:
    """Nodal values (..., n_nodes, k) at the data points (..., P, k): the node of each point, or the
    element shape functions at it (``mesh="polar"``, :func:`prepare`)."""
    a = np.asarray(nodal, float)
    if setup.interpolation is None:
        return a[..., setup.node_of_point, :]
    moved = np.moveaxis(a, -2, 0)
    out = setup.interpolation @ moved.reshape(moved.shape[0], -1)
    return np.moveaxis(out.reshape((-1,) + moved.shape[1:]), 0, -2)


def point_rows(setup: Setup, points) -> sp.csr_matrix:
    """Observation rows (Eq. 12) of the x and y displacement at data points ``points`` (indices, in
    that order; rows point by point, x before y), sparse (2 len(points), n_dofs)."""
    points = np.asarray(points, np.int64)
    if setup.interpolation is None:
        return node_observation_matrix(setup.mesh, setup.node_of_point[points], keep_order=True)
    return sp.csr_matrix(sp.kron(setup.interpolation[points], sp.eye(2)))


def _filled(u):
    """Carry the last valid value forward (then backward) along frames, for drive data."""
    u = np.array(u, float)
    for t in range(1, len(u)):
        bad = np.isnan(u[t])
        u[t][bad] = u[t - 1][bad]
    for t in range(len(u) - 2, -1, -1):
        bad = np.isnan(u[t])
        u[t][bad] = u[t + 1][bad]
    return np.nan_to_num(u)


def smooth_parameterisation(mesh, modes_E: int | None = None, modes_nu: int | None = None,
                            length_fraction: float | None = None) -> Parameterisation:
    """The smooth relative material basis of ``parameterisation="basis"`` (defaults: :data:`BASIS`).

    ``length_fraction`` times the largest distance between element centroids is the
    correlation length of :meth:`Parameterisation.smooth`.
    """
    c = mesh.centroids
    diameter = float(np.sqrt(np.max(np.sum((c[:, None, :] - c[None, :, :]) ** 2, axis=2))))
    frac = BASIS["length_fraction"] if length_fraction is None else length_fraction
    return Parameterisation.smooth(c, frac * diameter, BASIS["modes_E"] if modes_E is None else modes_E,
                                   BASIS["modes_nu"] if modes_nu is None else modes_nu, NOMINAL["E"])


def build_model(setup: Setup, effects=(), drive: str = "penalty", parameterisation: str = "region",
                process_scale: float = 1.0, landmark_step_px: float | None = None,
                beta: float | None = None, model_options: dict | None = None,
                material: Material | None = None, drive_lag: int = 1, effect_rates: bool = False,
                drive_trend: bool = False, spring_scale: float = 1.0) -> tuple:
    """The filter model of a set-up, and the observations it is fed (m, and m/s for velocities).

    Drives (:data:`DRIVES`): ``"penalty"``, confidence-weighted springs (section 2.7) pulling the
    landmark nodes toward their measured positions; ``"contour"``, the same springs on every node
    of both contours, toward the landmarks' motion interpolated along each contour (a periodic
    cubic spline in angle, :func:`sfem_filters.cardiac.reference.contour_interpolant`), as shape
    tracking of the whole border would give; ``"pressure"``, the measured cavity pressure on the
    endocardium (soft ground springs keep K positive definite); ``"none"``, only the effects.
    The springs pull over the interval into frame t toward the data of frame ``t - drive_lag``
    (1: causal, frame t's data enter only through the measurement update; 0: the same frame).
    With ``drive_trend`` (lag 1 only) they pull toward the linear extrapolation ``2 y_{t-1} -
    y_{t-2}`` instead of holding ``y_{t-1}``: a drive that is not a frame behind a steady motion
    (still causal), whose targets are then uncertain by the data's second differences.

    ``spring_scale`` multiplies the springs' stiffness ``NOMINAL["penalty"]`` (soft springs let the
    tissue lag its border; stiff ones on isolated landmarks make tents).

    ``landmark_step_px`` sets the per-frame uncertainty of the spring targets (data units);
    by default it is the RMS frame-to-frame motion of the landmarks in the data (of their second
    differences with ``drive_trend``). ``beta`` (s)
    overrides the Rayleigh stiffness coefficient ``NOMINAL["beta"]``: velocity data inform the
    displacement only when the model's transients last a good part of a frame.
    ``effect_rates``: each effect amplitude also gets a rate state (an integrated random walk,
    :class:`sfem_filters.cardiac.effects.Effect` ``rate_std``, ``EFFECT_STEP`` per frame), so the
    model extrapolates a contraction's trend one frame ahead instead of holding it.
    ``model_options`` are passed on to :class:`sfem_filters.model.SFEMModel` (for example
    ``system_class``). ``material`` is the tissue's material when it is fixed
    (``parameterisation="none"``) and the start of the estimate otherwise (default: uniform
    ``NOMINAL["E"]``, ``NOMINAL["nu"]``); the drive's springs are scaled by the nominal
    material either way.

    Returns ``(model, observations)`` with observations of shape (frames, 2 * n_observed
    [+ 2 * n_velocity_points]): displacement rows, then velocity rows (Eq. 13).
    """
    if drive not in DRIVES:
        raise ValueError(f"drive: expected one of {DRIVES}, got {drive!r}")
    if not setup.noise_px > 0:
        raise ValueError("displacement: the observed points' second differences in time are all zero (no motion, or "
                         "motion exactly linear in time), so the noise floor that sets the measurement and process "
                         f"noise is {setup.noise_px!r}; expected a sequence whose points move")
    seq, mesh, s = setup.seq, setup.mesh, setup.spacing
    F = seq.n_frames
    data = seq.displacement if setup.obs_displacement is None else setup.obs_displacement
    nominal = Material.uniform(mesh.n_elements, NOMINAL["E"], NOMINAL["nu"])
    mat0 = nominal if material is None else material
    Kdiag = np.median(stiffness_matrix(mesh, nominal.E, nominal.nu).diagonal())
    loads = np.zeros((F, mesh.n_dofs))
    penalty = None
    load_std = None
    if int(drive_lag) != drive_lag or drive_lag not in (0, 1):
        raise ValueError(f"drive_lag: expected 0 or 1 frames, got {drive_lag!r}")
    if drive_trend and drive_lag != 1:
        raise ValueError("drive_trend: the trend extrapolates from the previous frames; it needs drive_lag=1")
    if drive in ("penalty", "contour"):
        if drive == "penalty":
            drive_points = setup.landmarks
            targets = _filled(data[:, setup.landmarks]) * s                    # (F, L, 2) m
            conf = _confidence(seq, setup.landmarks, setup.obs_confidence)
            interp = None
        else:
            drive_points, targets, conf, interp = _contour_targets(setup, data)
        held = setup.point_mesh.nodes[drive_points[np.mean(np.atleast_2d(conf), axis=0) > 0]]
        if len(held) < 3 or np.linalg.matrix_rank(held - held[0], tol=1e-9 * np.ptp(mesh.nodes)) < 2:
            raise ValueError(f"confidence: {len(held)} of the drive's {len(drive_points)} landmark nodes have a "
                             "confidence > 0 in some frame, not spread over the plane, so the springs cannot hold the "
                             "tissue's rigid-body motion; expected confidence > 0 on at least 3 landmarks not on one line")
        conf = np.repeat(conf, 2, axis=-1)                                      # per dof
        k = NOMINAL["penalty"] * positive("spring_scale", spring_scale) * Kdiag
        c_mean = conf.mean(axis=0) if conf.ndim == 2 else conf
        if setup.interpolation is None:                                         # a spring on each point's node
            dofs = node_dofs(setup.node_of_point[drive_points])
            penalty = penalty_stiffness(mesh.n_dofs, dofs, k, c_mean)
            spread = None
        else:
            # a spring at each point through the shape functions: energy k c |D u - b|^2 / 2, so the
            # stiffness D^T (k c) D and the load D^T (k c b) (on a node, D selects it: the same springs)
            Dd = point_rows(setup, drive_points)
            penalty = sp.csr_matrix(Dd.T @ sp.diags(k * np.clip(c_mean, 0, 1)) @ Dd)
            spread = Dd.T.tocsr()
        # Zero-order hold of the data: over the interval into frame t the springs pull toward the
        # targets measured at frame t - drive_lag; with the causal lag 1, frame t's data enter only
        # through the measurement update and the innovation stays a one-step-ahead prediction error.
        for t in range(F):
            src = max(t - int(drive_lag), 0)
            c_t = conf[src] if conf.ndim == 2 else conf
            target = 2.0 * targets[src] - targets[src - 1] if drive_trend and src >= 1 else targets[src]
            loads[t] = (penalty_load(mesh.n_dofs, dofs, k, target.reshape(-1), c_t) if spread is None
                        else spread @ (k * np.clip(c_t, 0, 1) * target.reshape(-1)))
        # Process noise: the targets move by an unknown amount between frames, so they are
        # uncertain by the data's own frame-to-frame landmark motion; the random spring loads
        # reach the tissue through the dynamics (elastically correlated noise).
        if landmark_step_px is None:
            landmark_step_px = np.sqrt(np.nanmean(np.diff(data[:, setup.landmarks], n=2 if drive_trend else 1,
                                                          axis=0) ** 2))
        step = landmark_step_px * s
        if interp is None and spread is None:
            load_std = np.zeros(mesh.n_dofs)
            load_std[dofs] = k * step * c_mean
        else:
            # the contour's targets move as the interpolant of independent landmark steps: loads
            # correlated along the contour, one unit-variance pattern per landmark and component
            # (or per spring and component, each spread over its element's nodes)
            W = (np.eye(2 * len(drive_points)) if interp is None else np.kron(interp, np.eye(2))) \
                * (k * step * c_mean)[:, None]                                    # (drive dofs, patterns)
            if spread is None:
                load_std = np.zeros((mesh.n_dofs, W.shape[1]))
                load_std[dofs] = W
            else:
                load_std = np.asarray(spread @ W)
    else:
        ground = NOMINAL["foundation"] * Kdiag
        penalty = penalty_stiffness(mesh.n_dofs, np.arange(mesh.n_dofs), ground)
        if drive == "pressure":
            if seq.pressure is None:
                raise ValueError("drive: 'pressure' needs a sequence with a cavity 'pressure' per frame")
            unit = pressure_load(mesh, setup.geometry.endo_edges, 1.0)
            loads = seq.pressure[:, None] * unit[None]
    D = point_rows(setup, setup.observed)
    y = data[:, setup.observed].reshape(F, -1) * s
    sigma = _sigma(seq, setup) * s                                       # per observed row, m
    Dv = None
    if setup.velocity_points is not None:
        Dv = point_rows(setup, setup.velocity_points)
        y = np.hstack([y, setup.velocity.reshape(F, -1) * s])
        v_sd = np.repeat(_per_frame(setup.velocity_sigma), 2, axis=1)
        sigma = np.hstack([sigma if sigma.ndim == 2 else np.broadcast_to(sigma, (F, sigma.size)), v_sd * s])
    noise_c = setup.noise_px / np.sqrt(2.0) * s                          # per component, m
    if parameterisation not in PARAMETERISATIONS:
        raise ValueError(f"parameterisation: expected one of {PARAMETERISATIONS}, got {parameterisation!r}")
    param = None
    if parameterisation == "region":
        # relative stiffness between regions (mean log E fixed) and nu per region
        param = Parameterisation.relative_regions(setup.regions, NOMINAL["E"])
    elif parameterisation == "basis":
        param = smooth_parameterisation(mesh)
    elif parameterisation == "element":
        param = Parameterisation.per_element(mesh.n_elements)
    prior_cov = None
    if param is not None and drive == "pressure":
        # a measured pressure sets the force scale: the absolute stiffness is identifiable, so the
        # map gets a global level with a wide prior beside its contrasts
        param = param.with_level(NOMINAL["E"])
        sd = np.concatenate([np.full(param.n_E, 0.3), np.full(param.n_params - param.n_E, 1.0)])
        sd[param.level_index] = NOMINAL["E_level_sd"]
        prior_cov = np.diag(sd ** 2)
    effs = build_effects(effects, mesh, setup.geometry, angle_origin_deg=setup.angle_origin_deg,
                         scale=NOMINAL["E"], process_std=EFFECT_STEP * process_scale,
                         initial_std=EFFECT_STEP, rate_std=EFFECT_STEP * process_scale if effect_rates else None
                         ) if effects else []
    # initial state: at rest in equilibrium with the frame-0 drive
    Kt = stiffness_matrix(mesh, mat0.E, mat0.nu) + (penalty if penalty is not None else 0)
    u0 = spla.spsolve(Kt.tocsc(), loads[0]) if drive != "none" else np.zeros(mesh.n_dofs)
    model = SFEMModel(mesh, mat0, loads, D, setup.frame_interval, (), density=NOMINAL["density"],
                      alpha=NOMINAL["alpha"], beta=NOMINAL["beta"] if beta is None else beta,
                      measurement_std=sigma, velocity_operator=Dv,
                      process_std=(0.1 * process_scale * noise_c, 0.1 * process_scale * noise_c / setup.frame_interval),
                      initial_std=(noise_c, noise_c / setup.frame_interval), parameterisation=param,
                      prior_std=(0.3, 1.0), prior_cov=prior_cov, penalty=penalty, effects=effs, initial_displacement=u0,
                      process_load_std=None if load_std is None else process_scale * load_std,
                      outputs={"strain_polar": polar_strain_operator(mesh, setup.geometry)}, **(model_options or {}))
    return model, y


def _contour_targets(setup: Setup, data) -> tuple:
    """Points of both contours (the points' own mesh's boundary), their target trajectories
    (F, N, 2) in m, confidences (N,) or (F, N), and the interpolation matrix (N, L) from the
    landmarks (``setup.landmarks`` order) to the contour points: each contour's landmarks
    interpolated along it in angle (periodic cubic spline, linear in the landmarks' values)."""
    g, mesh, s = setup.point_geometry, setup.point_mesh, setup.spacing
    conf_lm = _confidence(setup.seq, setup.landmarks, setup.obs_confidence)
    nodes, targets, conf = [], [], []
    interp = np.zeros((0, len(setup.landmarks)))
    for loop in (g.endo, g.epi):
        on = np.flatnonzero(np.isin(setup.landmarks, loop))
        lm_nodes = setup.landmarks[on]
        values = _filled(data[:, setup.landmarks[on]]) * s                           # (F, L, 2)
        ang_lm, ang = g.angle(mesh.nodes[lm_nodes]), g.angle(mesh.nodes[loop])
        nodes.append(loop)
        targets.append(contour_interpolant(ang_lm, values, ang))
        rows = np.zeros((len(loop), len(setup.landmarks)))
        rows[:, on] = contour_interpolant(ang_lm, np.eye(len(on))[:, :, None], ang)[..., 0].T
        interp = np.vstack([interp, rows])
        c = conf_lm[..., on]
        conf.append(contour_interpolant(ang_lm, c[..., None], ang)[..., 0] if c.ndim == 2
                    else np.full(len(loop), float(np.mean(c))))
    return (np.concatenate(nodes), np.concatenate(targets, axis=1), np.clip(np.concatenate(conf, axis=-1), 0, 1),
            interp)


def _confidence(seq: Sequence, points, override=None) -> np.ndarray:
    c = seq.confidence if override is None else override
    if c is None:
        return np.ones(len(points))
    return c[:, points] if c.ndim == 2 else c[points]


def _per_frame(sd) -> np.ndarray:
    """(F, n) standard deviations with NaN (no datum that frame) replaced by the column's RMS."""
    sd = np.asarray(sd, float)
    rms = np.sqrt(np.nanmean(sd ** 2, axis=0))
    return np.where(np.isnan(sd), rms[None], sd)


def _sigma(seq: Sequence, setup: Setup) -> np.ndarray:
    """Noise standard deviation per observed row (x, y per point) in data units.

    ``(rows,)``, or ``(frames, rows)`` when the data give one per frame (image-derived
    confidences): then each frame gets its own R.
    """
    if setup.obs_sigma is not None:
        return np.repeat(_per_frame(setup.obs_sigma[:, setup.observed]), 2, axis=1)
    if seq.sigma is not None:
        if seq.sigma.ndim == 2:
            return np.repeat(_per_frame(seq.sigma[:, setup.observed]), 2, axis=1)
        return np.repeat(seq.sigma[setup.observed], 2)
    return np.full(2 * len(setup.observed), setup.noise_px / np.sqrt(2.0))


@dataclass(eq=False)
class Run:
    """A filter run on a set-up and what was measured of it."""

    name: str
    model: SFEMModel
    result: object
    U: np.ndarray            # (frames, n_points, 2) filtered displacement, data units
    metrics: dict
    observations: np.ndarray | None = None   # (frames, dim_obs) what the model was fitted to, model units


def kriged_heldout(setup: Setup, U) -> dict:
    """The model plus a thin-plate spline of its residual at the observed points (regression
    kriging, :func:`sfem_filters.cardiac.reference.residual_spline`), at the held-out points.

    The spline is fitted to what the model observed (the image-derived displacement where the
    set-up has one) and the sum is scored against the measured held-out displacement.

    Parameters
    ----------
    setup : Setup
    U : (F, n_points, 2) array
        The model's prediction of every point (data units).

    Returns
    -------
    dict
        As :func:`~sfem_filters.cardiac.reference.residual_spline` (``U``: the prediction at the
        held-out points, (F, H, 2)).
    """
    seen = np.array(setup.seq.displacement)
    if setup.obs_displacement is not None:
        seen[:, setup.observed] = setup.obs_displacement[:, setup.observed]
    held = setup.heldout
    return residual_spline(setup.seq.points, seen, U, setup.observed, setup.heldout,
                           setup.point_geometry.radial[held], setup.point_geometry.circumferential[held])


def angle_from_origin(setup: Setup, xy) -> np.ndarray:
    """Angle (rad, in [0, 2 pi)) of points ``xy`` (m) about the cavity centre, counted from the
    set-up's ``angle_origin_deg`` as its landmarks and sectors are."""
    return np.mod(setup.point_geometry.angle(xy) - np.radians(setup.angle_origin_deg), 2 * np.pi)


def region_label(setup: Setup, element: int) -> str:
    """Where an element lies: its sector of the regional map and its half of the wall (or its
    number, for a set-up without regions)."""
    if setup.regions is None:
        return f"element {int(element)}"
    r = int(setup.regions[element])
    return f"sector {r // 2} {'endo' if r % 2 == 0 else 'epi'} half"


def material_conflict(setup: Setup, model: SFEMModel, theta, P_theta, top: int = 5) -> dict:
    """The material against its prior: :func:`sfem_filters.filtering.diagnostics.prior_conflict` on
    every element's log E and logit(2 nu) (distinct rows of the parameterisation only).

    Returns the joint test (``chi2``, ``dof``, ``log10_p``, ``threshold``), per element ``E_z`` and
    ``nu_z`` (standard normal when prior and model are right; NaN where the data carry no
    information), and ``flagged``: up to ``top`` entries, by decreasing ``|z|``, with the quantity,
    an element, where it lies, the estimate (E relative to the nominal, or nu) and ``z``.
    ``theta`` and ``P_theta`` must hold the posterior of the data counted once (the smoother's
    Laplace posterior, or one cyclic loop; :func:`evaluate` leaves the check out otherwise).
    """
    par = model.parameterisation
    if par is None:
        raise ValueError("model: expected a model that estimates its material, got one with a fixed material")
    n_el, k, p = setup.mesh.n_elements, par.n_E, par.n_params
    theta = as_float_array("theta", theta, shape=(p,))
    P_theta = as_float_array("P_theta", P_theta, shape=(p, p))
    top = integer("top", top, 0)
    rows = np.zeros((2 * n_el, p))
    rows[:n_el, :k] = par.basis_E.toarray()
    rows[n_el:, k:] = par.basis_nu.toarray()
    _, first, inverse = np.unique(np.round(rows, 12), axis=0, return_index=True, return_inverse=True)
    out = diagnostics.prior_conflict(theta, P_theta, *parameter_prior(model), functionals=rows[first])
    z = out["z"][np.ravel(inverse)]
    mat = model.material_of_theta(theta)
    flagged = []
    for i in out["flagged"][:top]:
        row = int(first[i])
        e, quantity = (row, "log E") if row < n_el else (row - n_el, "nu")
        flagged.append({"quantity": quantity, "element": e, "where": region_label(setup, e), "z": float(out["z"][i]),
                        "estimate": float(mat.E[e] / NOMINAL["E"] if quantity == "log E" else mat.nu[e])})
    return {"chi2": out["chi2"], "dof": out["dof"], "log10_p": float(out["log10_p"]), "threshold": out["threshold"],
            "n_flagged": len(out["flagged"]), "flagged": flagged,
            "E_z": _nan_to_none(z[:n_el]), "nu_z": _nan_to_none(z[n_el:])}


def _nan_to_none(a) -> list:
    return [None if not np.isfinite(v) else float(v) for v in np.asarray(a, float)]


def _laplace_summary(model: SFEMModel, result, sd_logE, sd_nu) -> dict:
    """How the exact Hessian of the profile cost compares with Gauss-Newton's at the mode: the
    range of its eigenvalues relative to Gauss-Newton's, and of the sd ratios (exact / GN) of each
    element's log E and nu (None where the exact Hessian is not positive definite)."""
    curv = result.curvature
    w = curv.relative_eigenvalues()
    out = {"positive_definite": bool(curv.positive_definite()), "gradient_passes": int(curv.evaluations),
           "relative_eigenvalues": [float(w.min()), float(w.max())], "asymmetry": float(curv.asymmetry),
           "E_sd_log_ratio": None, "nu_sd_ratio": None}
    if result.laplace == "exact" and result.P_theta_gauss_newton is not None:
        gn_E, gn_nu = model.material_sd(result.theta, result.P_theta_gauss_newton)
        for key, sd, gn in (("E_sd_log_ratio", sd_logE, gn_E), ("nu_sd_ratio", sd_nu, gn_nu)):
            ratio = np.asarray(sd, float) / np.maximum(np.asarray(gn, float), 1e-300)
            out[key] = [float(ratio.min()), float(ratio.max())]
    return out


def evaluate(setup: Setup, model: SFEMModel, result, seconds: float = 0.0, observations=None) -> tuple:
    """Held-out error, innovations, NIS, material and strain of a run, in data units (pixels).

    The material's posterior sd is the smoother's Laplace covariance, or for the cyclic EKF the
    covariance of one cycle (:func:`sfem_filters.filtering.cyclic.one_cycle_covariance`: the
    carried one counts the cycle once per loop). Smoothed polar strains (E_rr, E_cc, 2 E_rc of
    each point, relative to the data's reference configuration) come with their sd from the
    smoother's displacement covariance.
    """
    s = setup.spacing
    F = setup.seq.n_frames
    U = at_points(setup, model.displacements(result.states).reshape(F, -1, 2)) / s
    meas = setup.seq.displacement
    h = setup.heldout
    r = meas[:, h] - U[:, h]                                              # (F, H, 2)
    er = setup.point_geometry.radial[h]
    ec = setup.point_geometry.circumferential[h]
    errors = heldout_errors(r, er, ec)
    rows = np.arange(2 * len(setup.observed)).reshape(-1, 2)
    nis = diagnostics.nis_summary(result.history)
    white = diagnostics.whiteness(result.history)
    cons = diagnostics.consistency(result.history)
    mat = model.material_of_theta(result.theta)
    smoother = getattr(result, "method", "") == "iterated_smoother"
    kriged = kriged_heldout(setup, U)
    metrics = {
        "estimator": "smoother" if smoother else "cyclic",
        "heldout_rmse_px": errors["heldout_rmse_px"],
        "residual_spline": {k: kriged[k] for k in ("heldout_rmse_px", "heldout_rmse_radial_px",
                                                   "heldout_rmse_circumferential_px")},
        "heldout_rmse_radial_px": errors["heldout_rmse_radial_px"],
        "heldout_rmse_circumferential_px": errors["heldout_rmse_circumferential_px"],
        "heldout_rmse_per_frame_px": errors["heldout_rmse_per_frame_px"],
        "heldout_rmse_worst_frame_px": errors["heldout_rmse_worst_frame_px"],
        "innovation_rms_px": diagnostics.innovation_rms(result.history, rows_of_points=rows) / s,
        "nis_mean_over_dof": nis["nis_mean_over_dof"],
        "nis_fraction_outside_95": nis["nis_fraction_outside_95"],
        "innovation_lag1_autocorrelation": white["lag1"],
        "innovation_whitening": diagnostics.DEFAULT_WHITENING,
        "whiteness_Q": white["Q"], "whiteness_p": white["p_value"],
        "nis_z": cons["nis_z"], "lag1_z": cons["lag1_z"], "inconsistent": cons["inconsistent"],
        "loops": int(result.loops), "converged": bool(result.converged),
        "E_relative_range": [float(mat.E.min() / NOMINAL["E"]), float(mat.E.max() / NOMINAL["E"])],
        "nu_range": [float(mat.nu.min()), float(mat.nu.max())],
        "seconds": float(seconds),
        "material_drift_sd": None,          # the material's last step against its sd (None: material fixed)
    }
    if model.estimates_material:
        if smoother:
            # the last accepted step against the posterior sd, and the Gauss-Newton record
            metrics["material_drift_sd"] = float(result.records[-1]["step_sd"]) if result.records else 0.0
            metrics["stop_reason"] = result.stop_reason
            metrics["iterations"] = [{k: float(v) for k, v in rec.items()} for rec in result.records]
            metrics["map_cost"] = float(result.cost)
        else:
            # how far the last loop moved the material against its carried sd
            metrics["material_drift_sd"] = float(diagnostics.material_drift(model, result.history)["max_sd"][-1])
        P_theta = result.posterior_cov
        sd_logE, sd_nu = model.material_sd(result.theta, P_theta)
        if smoother:
            metrics["material_covariance"] = result.laplace
            if result.curvature is not None:
                metrics["exact_laplace"] = _laplace_summary(model, result, sd_logE, sd_nu)
        # the stiffness level in kPa only where a measured pressure makes it identifiable: a relative
        # map's level is its nominal reference, and an interval on it would read as a measurement
        absolute = model.parameterisation.level_index is not None
        metrics["absolute_stiffness"] = absolute
        if absolute:
            a, c = model.parameterisation.level_functional()
            level, level_sd = float(a @ result.theta + c), float(np.sqrt(max(a @ P_theta @ a, 0.0)))
            metrics.update({"E_level_kPa": float(np.exp(level) / 1e3), "E_level_sd_log": level_sd,
                            "E_level_kPa_95": [float(np.exp(level - 1.96 * level_sd) / 1e3),
                                               float(np.exp(level + 1.96 * level_sd) / 1e3)]})
        # the check needs the data counted once: the smoother's posterior, or a single cyclic loop
        metrics["prior_conflict"] = (material_conflict(setup, model, result.theta, P_theta)
                                     if smoother or result.loops == 1 else None)
        metrics.update({"E_relative": (mat.E / NOMINAL["E"]).tolist(), "nu": mat.nu.tolist(),
                        "E_sd_log": sd_logE.tolist(), "nu_sd": sd_nu.tolist(),
                        "E_sd_log_median": float(np.median(sd_logE)), "nu_sd_median": float(np.median(sd_nu))})
    # transmural shear 2 E_rc at the data's systolic peak (_peak_frame): model vs measured
    # (measured data only: nodes whose strain needs a missing datum are left out)
    peak = _peak_frame(wall_area_ratios(setup, meas))
    shear_data = strain_maps(setup, meas)[peak, :, 2]
    shear_model = strain_maps(setup, U)[peak, :, 2]
    known = np.isfinite(shear_data)          # the nodes the measured figures use, for both
    shear_data, shear_model = shear_data[known], shear_model[known]
    metrics.update({"shear_strain_rms_peak_model": float(np.sqrt(np.mean(shear_model ** 2)))
                    if known.any() else float("nan"),
                    "shear_strain_error_rms_peak": float(np.sqrt(np.mean((shear_model - shear_data) ** 2)))
                    if known.any() else float("nan"),
                    # undefined (null in the JSON, '-' in the report) where either field is constant,
                    # as at a peak frame 0, where every strain is zero; not a correlation of 0
                    "shear_strain_correlation_peak": float(np.corrcoef(shear_model, shear_data)[0, 1])
                    if known.sum() > 1 and np.std(shear_model) > 1e-12 and np.std(shear_data) > 1e-12
                    else float("nan")})
    if smoother:
        metrics["log_evidence"] = float(result.log_likelihood)
    elif observations is not None:
        P0 = parameter_prior(model)[1]
        lp = log_posterior(model, observations, result.theta)
        if P0.size:
            Pc = np.asarray(result.posterior_cov, float)
            lp += 0.5 * (np.linalg.slogdet(Pc)[1] - np.linalg.slogdet(P0)[1])
        metrics["log_evidence"] = float(lp)
    if smoother and "strain_polar" in result.output_sd:
        eps = (model.output_operators()["strain_polar"] @ result.states[:, : model.n_restart].T).T
        sd = result.output_sd["strain_polar"]
        # at a point inside an element: the shape functions' mix of the nodes' strains, and of
        # their sds (an upper bound of the mix's sd, which the nodes' correlation can only lower)
        eps = at_points(setup, eps.reshape(F, -1, 3))
        sd = at_points(setup, sd.reshape(F, -1, 3))
        metrics.update({"strain_polar": eps.tolist(), "strain_polar_sd": sd.tolist(),
                        "strain_sd_median": np.median(sd, axis=(0, 1)).tolist()})
    if model.dim_eta:
        eta = np.array([model.eta_of(x) for x in result.states])
        metrics["effect_states"] = eta.tolist()
        metrics["effect_state_names"] = [f"{e.name}[{i}]" for e in model.effects for i in range(e.n_states)]
        var = np.asarray(result.P_diag, float)[:, model.dim_x:model.n_restart] if smoother else None
        if var is not None and np.all(np.isfinite(var)):
            metrics["effect_states_sd"] = np.sqrt(np.maximum(var, 0.0)).tolist()   # smoothed, per frame
    return U, metrics


def run(setup: Setup, effects=(), drive: str = "penalty", parameterisation: str = "region", max_loops: int = 5,
        process_scale: float = 1.0, tol: float = 1e-3, progress: bool = False, name: str = "",
        landmark_step_px: float | None = None, beta: float | None = None, model_options: dict | None = None,
        estimator: str = "smoother", max_iterations: int | None = None, effect_rates: bool = False,
        drive_trend: bool = False, spring_scale: float = 1.0, measurement_noise: str = "fixed",
        covariance: bool = True, warm_start=None) -> Run:
    """Build the model, estimate and evaluate.

    ``estimator`` (:data:`ESTIMATORS`): ``"smoother"``, the iterated smoother with at most
    ``max_iterations`` Gauss-Newton steps (default :func:`default_max_iterations` of the drive),
    ``"cyclic"``, the paper's cyclic joint EKF with at
    most ``max_loops`` loops and the relative tolerance ``tol``, or ``"roukf"``, Moireau &
    Chapelle's reduced-order UKF in the same cyclic driver (:mod:`sfem_filters.filtering.roukf`). ``beta``, ``model_options``,
    ``effect_rates``, ``drive_trend``, ``spring_scale``: see :func:`build_model`.
    ``measurement_noise``: ``"fixed"``, the measurement noise at the noise floor (or the file's
    ``sigma``); ``"estimate"``, its level (one factor on every frame's R) chosen by the smoother's
    type-II maximum likelihood (:class:`~sfem_filters.filtering.iterated.IteratedSmoother`
    ``measurement_noise``); the factor is ``metrics["measurement_noise_scale"]``. Smoother only.
    ``covariance=False`` (smoother only) leaves out the smoothed variances of the kinematics and
    strains (no ``strain_polar`` / ``_sd`` in the metrics), the dearest part of a fit's final pass;
    the estimate, its evidence and the material's covariance are the same. :func:`with_covariance`
    adds them later. ``warm_start`` (smoother only): a material vector (the model's coordinates, for
    example another fit's ``result.theta`` of the same parameterisation) the Gauss-Newton
    iterations start from instead of the prior mean (:class:`~sfem_filters.filtering.iterated.IteratedSmoother`
    ``start``): the cost and its mode are the same, reached in fewer iterations from a nearby
    model's mode; a vector of another length (another parameterisation) is not used.
    """
    if not isinstance(covariance, (bool, np.bool_)):
        raise TypeError(f"covariance: expected True or False, got {covariance!r}")
    if not covariance and estimator != "smoother":
        raise ValueError(f"covariance: False applies to the iterated smoother; got estimator={estimator!r}")
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator: expected one of {ESTIMATORS}, got {estimator!r}")
    max_iterations = default_max_iterations(drive) if max_iterations is None else integer("max_iterations",
                                                                                          max_iterations, 1)
    if measurement_noise not in NOISE_LEVELS:
        raise ValueError(f"measurement_noise: expected one of {NOISE_LEVELS}, got {measurement_noise!r}")
    if measurement_noise == "estimate" and estimator != "smoother":
        raise ValueError(f"measurement_noise: 'estimate' needs estimator='smoother', got estimator={estimator!r}")
    model, y = build_model(setup, effects, drive, parameterisation, process_scale, landmark_step_px, beta,
                           model_options, effect_rates=effect_rates, drive_trend=drive_trend,
                           spring_scale=spring_scale)
    start = None
    if warm_start is not None and estimator == "smoother":
        theta = np.asarray(warm_start, float).ravel()
        if theta.size == model.dim_state - model.n_restart and theta.size and np.all(np.isfinite(theta)):
            start = np.zeros((setup.seq.n_frames, model.dim_state))
            start[:, model.n_restart:] = theta
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="cyclic_estimate: the material did not converge")
        warnings.filterwarnings("ignore", message="iterated smoother: stopped by")
        if estimator == "smoother":
            result = IteratedSmoother(max_iterations=max_iterations, measurement_noise=measurement_noise,
                                      covariance=bool(covariance)).run(
                model, y, progress=progress, description=name or "dense", start=start)
        else:
            result = cyclic_estimate(model, y, max_loops=max_loops, tol=tol, progress=progress,
                                     description=name or "dense",
                                     engine="roukf" if estimator == "roukf" else "structured")
    if getattr(result, "measurement_noise_scale", 1.0) != 1.0:
        model = model.with_measurement_noise(result.measurement_noise_scale)    # the R the result was made with
    U, metrics = evaluate(setup, model, result, time.perf_counter() - t0, y)
    if measurement_noise == "estimate":
        metrics["measurement_noise_scale"] = float(result.measurement_noise_scale)
        metrics["measurement_noise_search"] = list(result.measurement_noise_search)
    return Run(name, model, result, U, metrics, y)


def with_covariance(setup: Setup, r: Run) -> Run:
    """A smoother run made with ``covariance=False``, completed as if made with ``covariance=True``:
    the final pass again at its mode with the variances of the kinematics and strains
    (:func:`sfem_filters.filtering.iterated.with_covariance`), metrics recomputed, its pass's time
    added to ``seconds``. A run that has them is returned as it is."""
    if getattr(r.result, "method", "") != "iterated_smoother":
        raise ValueError(f"r: expected a run of the iterated smoother (estimator='smoother'), got "
                         f"{type(r.result).__name__}")
    if r.observations is None:
        raise ValueError("r: expected a run made by measured.run (it keeps the observations), got none")
    t0 = time.perf_counter()
    result = smoother_with_covariance(r.model, r.observations, r.result)
    return r if result is r.result else _rerun(setup, r, result, t0)


def _rerun(setup: Setup, r: Run, result, t0: float) -> Run:
    """``r`` with a new result of its model and data: metrics evaluated again, the new work's time
    (since ``t0``) added to ``seconds``, the measurement noise search's metrics kept."""
    seconds = float(r.metrics.get("seconds", 0.0)) + time.perf_counter() - t0
    U, metrics = evaluate(setup, r.model, result, seconds, r.observations)
    for key in ("measurement_noise_scale", "measurement_noise_search"):
        if key in r.metrics:
            metrics[key] = r.metrics[key]
    return Run(r.name, r.model, result, U, metrics, r.observations)


def exact_posterior(setup: Setup, r: Run, progress: bool = False) -> Run:
    """A smoother run with the exact Laplace covariance of its material, metrics recomputed.

    The iterated smoother reports the inverse Gauss-Newton Hessian of the MAP cost as the
    material's covariance. Where the model misfits its data the curvature Gauss-Newton leaves out
    can be large (the docs' frozen Hessian check); this takes the exact Hessian of the profile
    cost at the run's mode (:func:`sfem_filters.filtering.iterated.exact_laplace`, 2 p + 1 gradient
    passes) and reports its inverse: the material's sd maps, the stiffness level's interval and the
    prior check then use it. ``metrics["material_covariance"]`` says which covariance was used
    (``"gauss-newton"`` where the exact Hessian is not positive definite: a warning is given), and
    ``metrics["exact_laplace"]`` how far apart the two are. The kinematics are unchanged.

    Parameters
    ----------
    setup : the run's set-up (:func:`prepare`)
    r : a :func:`run` of the iterated smoother with material parameters
    progress : a progress bar over the gradient passes
    """
    if getattr(r.result, "method", "") != "iterated_smoother":
        raise ValueError(f"r: expected a run of the iterated smoother (estimator='smoother'), got "
                         f"{type(r.result).__name__}")
    if not r.model.estimates_material:
        raise ValueError("r: the run's material is fixed (parameterisation 'none'): no material covariance to refine")
    if r.observations is None:
        raise ValueError("r: expected a run made by measured.run (it keeps the observations), got none")
    t0 = time.perf_counter()
    return _rerun(setup, r, exact_laplace(r.model, r.observations, r.result, progress=progress), t0)


def strain_maps(setup: Setup, U_px, relative_to_first: bool = True) -> np.ndarray:
    """Radial, circumferential and shear strain at each node w.r.t. frame 0, (frames, nodes, 3).

    ``U_px`` (frames, points, 2) displacement in data units; the shear is engineering (2 E_rc).
    ``relative_to_first=False``: w.r.t. the reference configuration (the points) instead.
    Where a datum is missing (NaN, in that frame or in frame 0) the strains of the nodes of every
    triangle it touches are NaN: measured strain is not made up from neighbouring frames.
    """
    U = np.asarray(U_px, float)
    U = U - U[0] if relative_to_first else U
    missing = ~np.all(np.isfinite(U), axis=-1)                                  # (F, P)
    eps = nodal_strains(setup.point_mesh, np.where(missing[..., None], 0.0, U).reshape(len(U), -1) * setup.spacing)
    out = polar_strains(setup.point_geometry, eps)                            # e_xx, e_yy, gamma_xy -> polar
    if missing.any():
        tri = setup.point_mesh.elements
        touched = np.zeros_like(missing)
        for t in np.flatnonzero(missing.any(axis=1)):
            touched[t, tri[missing[t][tri].any(axis=1)].ravel()] = True
        out[touched] = np.nan
    return out


def measured_wall_kinematics(setup: Setup) -> dict:
    """What the data themselves say about the wall, per frame and at the systolic peak.

    Wall area ratio (deformed over reference area of the tissue mesh), mean wall thickness
    (mean over angle, every 2 degrees, of epicardial minus endocardial radius about the cavity
    centre, both contours interpolated in angle), mean radial and circumferential strain w.r.t. frame 0, and
    the mean and RMS over points of the engineering transmural shear 2 E_rc;
    the displacement RMS of the first frame (is it at rest?) and between the last and first
    frames (does the cycle close?). Data units (pixels).
    """
    g, seq = setup.point_geometry, setup.seq
    P = seq.points
    U = np.asarray(seq.displacement, float)
    ok = np.all(np.isfinite(U), axis=-1)                                 # (F, P): a datum
    area_ratio = wall_area_ratios(setup, U)
    # every 2 degrees: quarter turns of the image map the directions onto themselves
    grid = np.linspace(0, 2 * np.pi, 180, endpoint=False)

    def thickness(t):
        endo, epi = g.endo[ok[t][g.endo]], g.epi[ok[t][g.epi]]
        if min(len(endo), len(epi)) < 3:
            return np.nan
        X = P + np.where(ok[t][:, None], U[t], 0.0)
        c = polygon_centroid(X[endo])
        return float(np.mean(radius_by_angle(X[epi], c, grid) - radius_by_angle(X[endo], c, grid)))

    thick = np.array([thickness(t) for t in range(len(U))])
    eps = strain_maps(setup, U)                                           # NaN where a datum is missing
    peak = _peak_frame(area_ratio)

    def mean(x):
        x = x[np.isfinite(x)]
        return float(np.mean(x)) if x.size else np.nan

    both = ok[0] & ok[-1]
    return {"peak_frame": peak, "wall_area_ratio_peak": float(area_ratio[peak]),
            "wall_thickness_px_frame0": float(thick[0]), "wall_thickness_px_peak": float(thick[peak]),
            "mean_radial_strain_peak": mean(eps[peak, :, 0]),
            "mean_circumferential_strain_peak": mean(eps[peak, :, 1]),
            "mean_shear_strain_peak": mean(eps[peak, :, 2]),
            "shear_strain_rms_peak": float(np.sqrt(mean(eps[peak, :, 2] ** 2))),
            "frame0_displacement_rms_px": float(np.sqrt(mean(np.sum(U[0][ok[0]] ** 2, axis=1)))),
            "last_to_first_rms_px": float(np.sqrt(mean(np.sum((U[-1] - U[0])[both] ** 2, axis=1)))),
            "wall_area_ratio": area_ratio.tolist(), "wall_thickness_px": thick.tolist()}


def wall_area_ratios(setup: Setup, U_px) -> np.ndarray:
    """Deformed over reference area of the tissue, per frame, (frames,), from measured data only.

    ``U_px`` (frames, points, 2) displacement in data units, NaN where missing. A frame's ratio is
    taken over the triangles whose three points all have data in that frame (the whole mesh when
    nothing is missing); NaN where none has.
    """
    tri = setup.point_mesh.elements
    U = np.asarray(U_px, float)
    ok = np.all(np.isfinite(U), axis=-1)
    ref = np.abs(triangle_double_areas(setup.seq.points, tri))
    out = np.full(len(U), np.nan)
    for t in range(len(U)):
        full = ok[t][tri].all(axis=1)
        if full.any():
            X = setup.seq.points + np.where(ok[t][:, None], U[t], 0.0)
            out[t] = np.abs(triangle_double_areas(X, tri))[full].sum() / ref[full].sum()
    return out


def _peak_frame(area_ratio) -> int:
    """The systolic peak: the frame of largest wall area, robust to a one-frame outlier (0 when no
    frame has a finite ratio).

    Each frame with a finite ratio is ranked by its three-frame window (itself and its two
    neighbours; a neighbour beyond the ends or without a finite ratio counts as the frame itself):
    first by the window's middle value (a running median), then by its smallest, then by the
    frame's own ratio; the earliest of equals. So an outlier in one frame between two frames with
    data is never the peak. On a curve that only falls away from its maximum, with a symmetric top
    (the maximum's two neighbours equal), the peak is the maximum's frame whatever one interior
    frame at least three frames away carries (an outlier, or no data); on a lopsided top it can be
    the maximum's higher neighbour, whose window is the higher. An outlier in the first or last
    frame, or next to a frame without data, is not recognised.
    """
    a = np.asarray(area_ratio, float)
    ok = np.isfinite(a)
    if not ok.any():
        return 0
    F = len(a)
    keys = []
    for t in np.flatnonzero(ok):
        n = [max(t - 1, 0), t, min(t + 1, F - 1)]
        w = np.sort(np.where(ok[n], a[n], a[t]))
        keys.append((w[1], w[0], a[t], -t))
    return int(-max(keys)[3])


def equivalent_eigenstrain(effect_states, nu: float = None) -> np.ndarray:
    """Stress-free strain (eps_cc, eps_rr) equivalent to ``active_polar`` amplitudes.

    The active stress ``sigma_a = E0 (a_c e_c e_c + a_r e_r e_r)`` (E0 = NOMINAL["E"]) acts
    like an eigenstrain ``eps* = -D^-1 sigma_a`` of a homogeneous plane-strain material with
    Young's modulus E0 and Poisson's ratio nu.
    """
    nu = NOMINAL["nu"] if nu is None else nu
    a = np.asarray(effect_states, float)
    ac, ar = a[..., 0], a[..., 1]
    f = 1.0 + nu
    return np.stack([-f * ((1 - nu) * ac - nu * ar), -f * (-nu * ac + (1 - nu) * ar)], axis=-1)


