"""Strain from myocardium masks alone: tracked borders as data, the interior from the physics.

The contours route, Shi & Liu (2003) section 2.6 as a strain estimator,
:func:`contour_strain`. No phase is used: the only input is a myocardium mask per frame.

1. **Landmarks.** The reference mask's endo- and epicardial contours (marching squares at level
   1/2, :func:`sfem_filters.imaging.contours.mask_borders`), resampled at equal arc length with
   one point per ``landmark_spacing_px`` of border (default 1 px: a binary mask places its border
   to within a pixel, so denser points add no information and sparser ones discard some), are
   tracked frame to frame through the masks by bending-energy matching with a confidence per
   match (Eqs. 35-37, :func:`sfem_filters.imaging.tracking.track_masks`, its default options
   otherwise). Their Lagrangian displacement (pixels) is the route's data (step 2 says which part).
2. **What the masks say: motion across the border.** A tracked border point is known well
   *across* the border and poorly *along* it (the aperture problem: on a smooth arc every
   candidate fits equally well, and twist is invisible in masks). By default
   (``along_border="none"``) only the motion across the border is data; the tracker's sliding
   along it, a drift correlated along the contour, is not (``along_border="tracked"`` adds it
   with the tracker's own sd, accumulated from the confidences of the chain of matches, Eq. 37,
   :class:`sfem_filters.imaging.tracking.BoundaryTracks` ``sigma``). The sd across the border is
   the larger of the quantisation of a binary border, ``1 / sqrt(12)`` px (uniform within a
   pixel), and the data's own temporal noise floor across the border
   (:func:`sfem_filters.cardiac.strain_route.temporal_noise_floor` of the normal component).
3. **Mesh and observation.** The reference myocardium meshed by Gmsh exactly as the DENSE route
   (:func:`sfem_filters.cardiac.strain_route.reference_mesh`, element edge 2.5 px). Each landmark
   sits in a boundary element with its shape-function weights (Eq. 12 as an interpolation,
   :func:`sfem_filters.fem.observation.point_observation_matrix`); each border node observes its
   own normal displacement, the hat-weighted mean of its landmarks' motion across the border
   (:func:`border_node_data`). Fitting the points to the polygon's nodes instead would read the
   small angle between adjacent edges as information about the nodes' sliding and amplify the
   normals' noise about tenfold into it. Steps 1-3 are :func:`mask_border_data` of
   :mod:`sfem_filters.cardiac.border_data` (re-exported here), which the DENSE route also stacks
   with its phase data (``StrainRouteSettings.border_masks``).
4. **The interior from the physics.** No datum lies inside the wall. The prior says the wall
   moves as an elastic body: each frame's *change* of displacement is a Gaussian field whose
   precision is the stiffness (its log density minus the elastic energy, :func:`elastic_prior`;
   Young's modulus scales out, rigid motion free). Two consequences: given the border, the
   interior's mean is the elastic equilibrium field of that border with no body force (static
   condensation, ``u_I = -K_II^-1 K_IB u_B``, :func:`elastic_extension`), so the interior strain
   comes from the physics; and a border motion costs the elastic energy it puts into the wall, so
   the sliding along the border that no datum sets is the one the wall's elasticity prefers. In
   the state-space model this is the process and initial noise, ``q^2 C`` on displacement and
   ``(q / T)^2 C`` on velocity (``C`` the prior's covariance, scaled to unit mean variance on the
   border), plus a white floor :data:`INTERIOR_FREEDOM` times smaller that only keeps ``Q``
   invertible. The dynamics are the DENSE route's
   (:func:`sfem_filters.cardiac.strain_route.compliant_modulus`: elastic forces negligible over
   the cycle, so the state carries the motion from frame to frame, a damped constant-velocity
   prior through mass and mass damping). The estimator is the DENSE route's
   (:class:`sfem_filters.filtering.iterated.IteratedSmoother`, material fixed: a Kalman-RTS
   pass); the process noise starts at ``process_fraction`` (0.1, the library's rule for measured
   data) of the noise floor across the border per frame and its level is then chosen by the
   data's evidence (``process_noise="estimate"``): how fast the wall may accelerate is the data's
   to say, and a fixed level flattens a short systole's peak.

   The material: the library's nominal tissue (Poisson's ratio 0.45), in *plane stress*. A
   short-axis slice of a ventricle that shortens longitudinally is free through the plane
   (``sigma_zz = 0``), and its in-plane area is not conserved (through-plane shortening thickens
   the wall in the plane). The DENSE route's plane strain with a near-incompressible ratio makes
   every in-plane area change ten times dearer than shear (2D bulk over shear modulus
   ``1 / (1 - 2 nu)``), so the prior would hold back the wall's thickening that the borders
   show; plane stress of the same tissue makes it three times dearer. On the library's
   plane-strain elements this is the exact equivalent ratio ``nu / (1 + nu)`` = 0.31 (Young's
   modulus scales out). Near-incompressibility is not what makes the wall thicken here: both
   borders are data, so the wall's area at every frame is given by them. Unlike a spline through
   both borders, the elastic field knows where the cavity is (the spline couples the two borders
   across it).

4b. **A second pass, guided by the first.** The landmarks are chained from frame to frame, and a
   landmark that slid along a curved border misreads the border's motion across itself (the error
   grows as the slide squared over the border's radius, and the slides accumulate over the cycle).
   On the in-vivo DENSE-Sim case, at its full frame rate, the first pass's global radial strain stays
   well above the truth in diastole, after the masks have come back to the reference shape
   (``tests/cardiac/test_contours_route.py``, slow). So by default (``guided_passes=1``) the route
   runs again on the data the DENSE route's masks give with a phase guide
   (:func:`sfem_filters.cardiac.border_data.guided_border_data`), here guided by the first pass's
   own estimate: each border node is placed where that estimate puts it, and its datum is the frame's
   mask border's offset across itself at that point. Where the guide errs across the border, the datum
   does not change. Where it errs along the border, the datum changes only by that error times the
   border's turn. The elastic prior is shared; the process and initial sd are rebuilt from the new
   data's noise floor and the evidence chooses their level again. The settings' ``passes`` list each
   pass's data, noise floor, process and initial sd, process level and log-likelihood; the other
   keys describe the final pass's data (and the landmarks, where they say so).

5. **Strain and its sd.** As the DENSE route: Green-Lagrange strain of each linear triangle's
   gradient at every reference pixel, projected about the reference mask's centre of mass; sd
   and curve bands by the delta method at the posterior mean with the smoothed covariance
   (:func:`sfem_filters.cardiac.strain_route.strain_and_sd`). The bands say how well the borders
   are known *given* the elastic interior; they do not hold the interior's model error.

Units: pixels for points and displacements at the interface (x = column, y = row), SI inside
(the mesh in metres); strain is a fraction; times in s. Masks carry no phase noise: the route's
only error is the masks' pixel quantisation and the tracking.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass, field
from typing import ClassVar

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .._validate import as_float_array, integer, positive, user_stacklevel
from ..fem.elasticity import stiffness_matrix
from ..fem.loads import penalty_stiffness
from ..fem.material import Material
from ..fem.mesh import TriMesh
from ..fem.observation import point_observation_matrix
from ..filtering.iterated import IteratedSmoother, check_noise_range
from ..filtering.linearised import linearise
from ..filtering.smoother import smooth
from ..imaging.contours import reference_mask_mismatch, repair_myocardium_mask
from ..imaging.spline_strain import SplineStrain, spline_strain
from ..imaging.strain import N_SEGMENTS, mask_centre, segment_labels
from ..imaging.tracking import BoundaryTracks
from ..resources import limits_blas_threads
# the masks' data on the border nodes live in border_data (the DENSE route fuses them too): re-exported here
from .border_data import (LANDMARK_SPACING_PX, MIN_LANDMARKS, QUANTISATION_SD_PX, border_node_data,
                          contour_landmark_tracks, guided_border_data, landmark_sd, mask_border_data)
from .measured import NOMINAL
from .strain_route import (Z95, DenseStrain, NodalFitModel, compliant_modulus, element_gradient_operator,
                           linearised_rows, observation_points, reference_mesh, strain_and_sd)
# the DENSE route's rows of the element gradients and curves for the smoother's variances (the same maths here)
from .strain_route import _check_frame_times, _covariance_from_rows, _curve_rows, _element_of, _gradient_rows

__all__ = ["ContourRouteSettings", "ContourStrain", "contour_strain", "contour_landmark_tracks", "elastic_extension",
           "elastic_prior", "border_node_data", "landmark_sd", "mask_border_data", "contour_spline_strain",
           "QUANTISATION_SD_PX", "INTERIOR_FREEDOM"]

#: White process noise on every dof, relative to the border's: only keeps Q invertible.
INTERIOR_FREEDOM = 1e-3


@dataclass(frozen=True)
class ContourRouteSettings:
    """Settings of the contours route (each by a principle; see the module docstring).

    Attributes
    ----------
    landmark_spacing_px : float
        Border length (pixels) per tracked landmark: 1 px, the mask's resolution.
    element_px : float
        Target element edge (pixels) of the Gmsh mesh of the reference myocardium: the DENSE
        route's 2.5 px.
    nu : float
        Poisson's ratio of the tissue (nominal 0.45).
    plane : {"stress", "strain"}
        The slice's state in the wall's elastic prior. ``"stress"`` (default): free to shorten
        through the plane (sigma_zz = 0), as a short-axis slice of a ventricle that shortens
        longitudinally is; on the plane-strain elements this is Poisson's ratio ``nu / (1 + nu)``
        (the exact plane-stress equivalent; Young's modulus scales out). ``"strain"``: the DENSE
        route's plane strain with ``nu`` itself, whose near-incompressibility makes any in-plane
        area change ten times dearer than shear.
    normal_sd_px : float
        Least sd (pixels) of a landmark across the border: the binary mask's quantisation.
    process_fraction : float
        Process noise per frame as a fraction of the border data's noise floor (0.1, the library's
        rule for measured data).
    min_landmarks : int
        Fewest landmarks per contour (16: a small ring still gets a smooth border).
    along_border : {"none", "tracked"}
        Whether the landmarks' motion *along* the border is data. ``"none"`` (default): only their
        motion across it, the part a mask sequence determines; along a smooth border the masks have
        no grip (the aperture problem) and the tracker's sliding is a drift correlated along the
        contour (a pure dilation of a circular ring: up to ~1 px in 8 frames,
        ``tests/cardiac/test_contours_route.py``), a bias that no independent error sd can hold; the
        elastic prior then sets the sliding. ``"tracked"``: also the tracker's tangential motion,
        with its sd accumulated from the match confidences (Eq. 37).
    process_noise : {"fixed", "estimate"}
        ``"estimate"`` (default): the level above times one factor chosen by maximum evidence (type-II
        maximum likelihood, :class:`sfem_filters.filtering.iterated.IteratedSmoother`
        ``process_noise``): the data judge how fast the wall may accelerate. ``"fixed"``: the level
        as set (it flattens a short systole's peak).
    noise_range : (float, float)
        Smallest and largest factor on the level above that the evidence may choose (default 4^-8 to
        4^6). The wall's change of velocity over one frame interval grows as the frame rate falls, so a
        sparser sequence asks for a larger level; the upper end leaves room for that, and the search
        warns if its best factor still sits at an end.
    guided_passes : int
        Passes after the first whose border data are guided by the previous pass's estimate
        (:func:`sfem_filters.cardiac.border_data.guided_border_data`; module docstring, step 4b).
        1 (default); 0: the landmarks' data alone (the only choice with ``along_border="tracked"``:
        the guided data are across the border only).
    start_deg : float
        Start of segment 0 (degrees from the image's +x axis towards +y).
    centre : tuple or None
        Centre (x, y) in pixels of the radial directions and segments; None: the centre of mass of
        the reference mask.
    """

    landmark_spacing_px: float = LANDMARK_SPACING_PX
    element_px: float = 2.5
    nu: float = NOMINAL["nu"]
    plane: str = "stress"
    normal_sd_px: float = QUANTISATION_SD_PX
    process_fraction: float = 0.1
    min_landmarks: int = MIN_LANDMARKS
    along_border: str = "none"
    process_noise: str = "estimate"
    noise_range: tuple = (4.0 ** -8, 4.0 ** 6)
    guided_passes: int = 1
    start_deg: float = 0.0
    centre: tuple | None = None

    @property
    def nu_plane_strain(self) -> float:
        """Poisson's ratio of the plane-strain elements: ``nu / (1 + nu)`` in plane stress, else ``nu``."""
        return self.nu / (1.0 + self.nu) if self.plane == "stress" else self.nu

    def __post_init__(self):
        positive("landmark_spacing_px", self.landmark_spacing_px, "pixels")
        positive("element_px", self.element_px, "pixels")
        if not 0 < self.nu < 0.5:
            raise ValueError(f"nu: expected a Poisson's ratio in (0, 0.5), got {self.nu!r}")
        if self.plane not in ("stress", "strain"):
            raise ValueError(f"plane: expected 'stress' or 'strain', got {self.plane!r}")
        positive("normal_sd_px", self.normal_sd_px, "pixels")
        positive("process_fraction", self.process_fraction)
        if self.along_border not in ("none", "tracked"):
            raise ValueError(f"along_border: expected 'none' or 'tracked', got {self.along_border!r}")
        if self.process_noise not in ("fixed", "estimate"):
            raise ValueError(f"process_noise: expected 'fixed' or 'estimate', got {self.process_noise!r}")
        object.__setattr__(self, "noise_range", check_noise_range(self.noise_range))
        object.__setattr__(self, "guided_passes", integer("guided_passes", self.guided_passes, 0))
        if self.along_border == "tracked" and self.guided_passes:
            raise ValueError("along_border: 'tracked' adds the landmarks' motion along the border, which the guided "
                             "passes' data do not carry (a mask says where its border is, not where a point went "
                             f"along it); give guided_passes=0 with it, got guided_passes={self.guided_passes}")
        if isinstance(self.min_landmarks, bool) or int(self.min_landmarks) != self.min_landmarks \
                or self.min_landmarks < 8:
            raise ValueError(f"min_landmarks: expected an integer >= 8, got {self.min_landmarks!r}")
        if self.centre is not None:
            object.__setattr__(self, "centre", tuple(float(v) for v in as_float_array("centre", self.centre,
                                                                                      shape=(2,))))


@dataclass(frozen=True, eq=False)
class ContourStrain(DenseStrain):
    """:class:`~sfem_filters.cardiac.strain_route.DenseStrain` of the contours route, with its data.

    Extra attributes: ``tracks`` (the :class:`~sfem_filters.imaging.tracking.BoundaryTracks`
    through the masks, index 0 the reference), ``landmark_sd`` (F, L, 2): the landmarks' normal
    and tangential sd (pixels); ``nodal_displacement`` (F, n_dofs): the estimate at the mesh's
    nodes (pixels, x before y per node).
    """

    tracks: BoundaryTracks = field(repr=False)
    landmark_sd: np.ndarray = field(repr=False)
    nodal_displacement: np.ndarray = field(repr=False)
    ROUTE: ClassVar[str] = "contours"

    def to_dict(self) -> dict:
        """The strain report's JSON names (as the DENSE route), ``route`` = ``"contours"``, and the landmarks."""
        out = super().to_dict()
        L = self.tracks.points
        out["landmarks"] = {"points": L.tolist(), "contour": self.tracks.contour.tolist(),
                            "n_endo": int(np.sum(self.tracks.contour == 0)),
                            "n_epi": int(np.sum(self.tracks.contour == 1))}
        return out


# ------------------------------------------------------------------------------------ checks
def _check_inputs(masks, pixel_size_m, frame_times_s) -> tuple:
    m = np.asarray(masks)
    if m.ndim != 3:
        raise ValueError(f"masks: expected an (F + 1, H, W) mask sequence (index 0 the reference), got shape {m.shape}")
    if m.dtype != bool and not np.isin(m, (0, 1)).all():
        raise ValueError("masks: expected boolean (or 0/1) myocardium masks")
    m = m.astype(bool)
    repair_myocardium_mask(m[0], "masks[0]")          # an error unless a ring, up to a defect of a pixel or two
    s = positive("pixel_size_m", pixel_size_m, "m")
    t = as_float_array("frame_times_s", frame_times_s, shape=(None,))
    if len(t) != len(m) - 1:
        raise ValueError(f"frame_times_s: expected one time per frame after the reference, {len(m) - 1} for "
                         f"masks of shape {m.shape}, got {len(t)}")
    if len(t) < 3:
        raise ValueError(f"frame_times_s: expected at least 3 frames, got {len(t)}")
    return m, s, _check_frame_times(t, len(t), "frame_times_s", after_zero=True)


def elastic_extension(mesh: TriMesh, boundary_dofs, nu: float) -> np.ndarray:
    """(n_dofs, m): each border dof's unit displacement extended into the wall by elastic equilibrium.

    Rows of ``boundary_dofs`` are the identity; the other dofs ``u_I = -K_II^-1 K_IB u_B``
    (plane-strain linear elasticity with Poisson's ratio ``nu``, no body force; Young's modulus
    scales out). This is the conditional mean of the interior under :func:`elastic_prior`.
    """
    K = stiffness_matrix(mesh, 1.0, nu).tocsc()
    B = np.asarray(boundary_dofs, int)
    inner = np.setdiff1d(np.arange(mesh.n_dofs), B)
    X = np.zeros((mesh.n_dofs, len(B)))
    X[B, np.arange(len(B))] = 1.0
    if inner.size:
        from_b = -(K[inner][:, B]).toarray()
        X[inner] = spla.splu(K[inner][:, inner].tocsc()).solve(from_b)
    return X


def elastic_prior(mesh: TriMesh, nu: float, boundary_dofs) -> np.ndarray:
    """(n_dofs, n_dofs) covariance of a displacement whose log density is minus its elastic energy.

    ``C = c K^+ + r Z Z^T``: ``K^+`` the pseudo-inverse of the plane-strain stiffness (Poisson's
    ratio ``nu``, unit Young's modulus) on its elastic modes, ``Z`` its three rigid-body modes;
    ``c`` and ``r`` make each part's mean variance over ``boundary_dofs`` one. So the
    displacement is a Gaussian field whose precision is the stiffness: (i) given the border, the
    interior's mean is the elastic equilibrium field (:func:`elastic_extension`), the interior
    strain comes from the physics; (ii) a border motion costs the elastic energy it puts into
    the wall, so rough motion along the border (what noise in the tracked points' normals would
    imply) is unlikely, and rigid motion is free.
    """
    K = stiffness_matrix(mesh, 1.0, nu).toarray()
    lam, V = np.linalg.eigh(0.5 * (K + K.T))
    Z, Ve, le = V[:, :3], V[:, 3:], lam[3:]
    if not le[0] > 1e3 * max(abs(lam[2]), 1e-300):
        raise ValueError("mesh: expected a stiffness with exactly three rigid-body modes (one connected body)")
    B = np.asarray(boundary_dofs, int)
    Ce = (Ve / le) @ Ve.T
    Cr = Z @ Z.T
    return Ce / float(np.mean(np.diag(Ce)[B])) + Cr / float(np.mean(np.diag(Cr)[B]))


# ----------------------------------------------------------------------------------- the route
@limits_blas_threads
def contour_strain(masks, pixel_size_m: float, frame_times_s, settings: ContourRouteSettings | None = None,
                   progress=None) -> ContourStrain:
    """The contours route: myocardium masks in, Green-Lagrange strain with sd and banded curves out.

    Parameters
    ----------
    masks : (F + 1, H, W) bool array
        Myocardium mask of the reference configuration (index 0) and of each frame (index f + 1).
    pixel_size_m : float
        Pixel size (m).
    frame_times_s : (F,) array
        Time (s) of each frame after the reference (t = 0), strictly increasing.
    settings : ContourRouteSettings, optional
    progress : callable or bool, optional
        ``progress(message)`` called at each step; ``True`` prints.

    Returns
    -------
    ContourStrain
        The DENSE route's result type and JSON names (``route`` = ``"contours"``), strain at the
        reference mask's pixels.
    """
    t0 = time.perf_counter()
    cfg = ContourRouteSettings() if settings is None else settings
    if not isinstance(cfg, ContourRouteSettings):
        raise TypeError(f"settings: expected a ContourRouteSettings, got {type(cfg).__name__}")
    say = (lambda msg: print(msg, flush=True)) if progress is True else (progress or (lambda msg: None))
    m, s, times = _check_inputs(masks, pixel_size_m, frame_times_s)
    mismatch = reference_mask_mismatch(m)              # the wall's zero of radial strain is read from masks[0]
    if mismatch:
        warnings.warn(mismatch, RuntimeWarning, stacklevel=user_stacklevel())
    mask = m[0]
    rows, cols = np.nonzero(mask)
    X = np.column_stack([cols, rows]).astype(float)
    centre = mask_centre(mask) if cfg.centre is None else np.asarray(cfg.centre, float)
    say("tracking the borders through the masks (bending energy, Eqs. 35-37)")
    tracks = contour_landmark_tracks(m, cfg.landmark_spacing_px, cfg.min_landmarks)
    F = len(times)
    L = len(tracks.points)
    say(f"{L} landmarks ({int(np.sum(tracks.contour == 0))} endo, {int(np.sum(tracks.contour == 1))} epi); "
        f"meshing the reference myocardium (gmsh, {cfg.element_px:g} px)")
    mesh = reference_mesh(mask, s, "gmsh", cfg.element_px)
    bd = landmark_bd = mask_border_data(mesh, tracks, s, cfg.normal_sd_px, tangential=cfg.along_border == "tracked")
    T = float(np.median(np.diff(times)))
    alpha = NOMINAL["alpha"]
    wall = float(mask.sum()) * s * s / np.mean([np.sum(np.linalg.norm(np.diff(np.vstack([c, c[:1]]), axis=0), axis=1))
                                                for c in (tracks.borders[0].endo, tracks.borders[0].epi)]) / s
    E = compliant_modulus(wall, F * T, alpha=alpha)
    material = Material.uniform(mesh.n_elements, E, cfg.nu_plane_strain)
    ground = NOMINAL["foundation"] * float(np.median(stiffness_matrix(mesh, material.E, material.nu).diagonal()))
    penalty = penalty_stiffness(mesh.n_dofs, np.arange(mesh.n_dofs), ground)
    bdofs = np.sort(np.concatenate([2 * bd.nodes, 2 * bd.nodes + 1]))
    say(f"mesh: {mesh.n_nodes} nodes, {mesh.n_elements} triangles, {len(bdofs)} border dofs observed; "
        "elastic prior of the wall")
    prior = elastic_prior(mesh, cfg.nu_plane_strain, bdofs)
    # the initial state: at rest in the reference configuration, uncertain by the landmarks' first
    # displacement (the first frame is after the reference); from the data, not from the nodal fit,
    # whose tangential components along a smooth border are barely determined
    u0_px = float(np.sqrt(np.mean(tracks.displacement[1] ** 2)))
    passes = []
    for k in range(1 + int(cfg.guided_passes)):
        if k:
            say(f"pass {k + 1}: the border data at the points the previous pass names (guided)")
            bd = guided_border_data(mesh, m, U.reshape(F, mesh.n_nodes, 2) / s, s, cfg.normal_sd_px)
        model, result, q, u0_sd = _border_fit(mesh, material, penalty, prior, bd, F, T, s, u0_px, cfg, say)
        U = np.zeros((F, mesh.n_dofs))
        U[:, model.dofmap.free] = result.states[:, :model.dofmap.n_free]
        passes.append({"data": "landmarks" if k == 0 else "guided", "normal_noise_floor_px": float(bd.floor_px),
                       "process_std_px": q / s, "initial_std_px": u0_sd / s,
                       "process_noise_scale": float(result.process_noise_scale),
                       "log_likelihood": float(result.log_likelihood)})
    y = bd.y
    s_n, s_t, floor_n, moved = landmark_bd.sd_normal_px, landmark_bd.sd_tangent_px, bd.floor_px, landmark_bd.moved_m
    n = model.dofmap.n_free
    nr = model.n_restart
    free = model.dofmap.free
    P = len(X)
    Xm = X * s
    Xin, _ = observation_points(mesh, Xm)
    Ge = element_gradient_operator(mesh)
    elem = _element_of(mesh, Xin)
    dofs = mesh.element_dofs
    grad = np.einsum("pkd,fpd->fpk", Ge[elem], U[:, dofs[elem]]).reshape(F, P, 2, 2)
    labels = segment_labels(X, centre, cfg.start_deg)
    groups = [np.arange(P)] + [np.flatnonzero(labels == k) for k in range(N_SEGMENTS)]
    a_cc, a_rr = linearised_rows(grad, X, centre)
    curve_rows = np.concatenate([np.concatenate([_curve_rows(Ge, elem, a[t], groups, mesh.n_dofs, dofs)
                                                 for a in (a_cc, a_rr)]) for t in range(F)])
    say("covariance pass (linearised strain)")
    lin = linearise(model, result.states)

    def on_state(op):
        op = sp.csr_matrix(op)[:, free]
        return lin.output_in_xi(sp.hstack([op, sp.csr_matrix((op.shape[0], nr - n))], format="csr"))

    used = np.unique(elem)
    outputs = {"gradient": on_state(_gradient_rows(mesh, Ge, used)), "curves": on_state(curve_rows)}
    sm = smooth(lin, y, outputs=outputs, covariance=True)
    C = np.zeros((F, mesh.n_elements, 4, 4))
    C[:, used] = _covariance_from_rows(sm.variances["gradient"])
    ecc, err, ecr, sd_cc, sd_rr = strain_and_sd(grad, C[:, elem], X, centre)
    k = 2 * (1 + N_SEGMENTS)
    vc = sm.variances["curves"].reshape(F, F, k)[np.arange(F), np.arange(F)]
    sd_curves = np.sqrt(np.maximum(vc, 0.0))
    means = {"Ecc": ecc, "Err": err}
    glob, segs = {}, {}
    for q_i, qn in enumerate(("Ecc", "Err")):
        m_all = np.stack([means[qn][:, g].mean(axis=1) if g.size else np.full(F, np.nan) for g in groups], axis=1)
        sd_all = sd_curves[:, q_i * (1 + N_SEGMENTS):(q_i + 1) * (1 + N_SEGMENTS)]
        for d, sl in ((glob, 0), (segs, slice(1, None))):
            mu, sd = m_all[:, sl].T, sd_all[:, sl].T
            d[qn], d[f"{qn}_sd"], d[f"{qn}_lo"], d[f"{qn}_hi"] = mu, sd, mu - Z95 * sd, mu + Z95 * sd
    disp_px = (point_observation_matrix(mesh, Xin) @ U.T).T.reshape(F, P, 2) / s
    seconds = time.perf_counter() - t0
    info = {"n_landmarks": L, "n_endo": int(np.sum(tracks.contour == 0)), "n_epi": int(np.sum(tracks.contour == 1)),
            "landmarks_moved_into_mesh": int(np.count_nonzero(moved)), "normal_noise_floor_px": floor_n,
            "normal_sd_px_used": float(np.max(bd.sd_normal_px)),
            "landmarks_tangential_sd_px_rms": float(np.sqrt(np.mean(s_t ** 2))),
            "process_std_px": q / s, "initial_std_px": u0_sd / s, "frame_interval_s": T, "fixed_E_Pa": E,
            "alpha_per_s": alpha, "wall_thickness_px": wall / s, "n_nodes": mesh.n_nodes,
            "n_elements": mesh.n_elements, "n_border_dofs": int(len(bdofs)), "dim_state": int(model.dim_state),
            "mean_match_confidence": float(np.mean(tracks.step_confidence[1:])),
            "reference_mask_mismatch": mismatch,
            "process_noise_scale": float(result.process_noise_scale), "passes": passes,
            "nu_plane_strain_elements": cfg.nu_plane_strain,
            "data": "myocardium masks only (no phase): noise-free in phase terms",
            "landmarks": "marching-squares borders of masks[0], one per landmark_spacing_px, tracked by bending "
                         "energy (Eqs. 35-37)",
            "interior": "process and initial noise of precision the plane-strain stiffness (nu as set): the "
                        "interior's mean is the elastic extension of the border",
            "material": "fixed, not estimated: fixed_E_Pa shapes the interior's prior (no stiffness estimate)",
            "estimator": f"IteratedSmoother (material fixed: a Kalman-RTS pass) on the landmarks' data, then on "
                         f"the guided data {cfg.guided_passes} time(s); a covariance pass of the last",
            "strain": "Green-Lagrange of the linear triangles' element gradient",
            "sd": "delta method at the posterior mean, full smoothed covariance of U"}
    say(f"the route's estimate and bands in {seconds:.1f} s")
    return ContourStrain(points=X, frame_times_s=times.copy(), centre=np.asarray(centre, float),
                         start_deg=float(cfg.start_deg), labels=labels, Ecc=ecc, Err=err, Ecr=ecr, Ecc_sd=sd_cc,
                         Err_sd=sd_rr, global_curves=glob, segment_curves=segs, displacement=disp_px,
                         seconds=seconds, settings={**asdict(cfg), **info}, mesh=mesh, tracks=tracks,
                         landmark_sd=np.stack([s_n, s_t], axis=-1), nodal_displacement=U / s)


def _border_fit(mesh, material, penalty, prior, bd, F: int, T: float, s: float, u0_px: float, cfg, say) -> tuple:
    """One smoother run of the contours route on the border data ``bd`` (module docstring, step 4).

    Parameters
    ----------
    mesh, material, penalty
        The route's mesh (m), its fixed compliant material and the ground springs' stiffness.
    prior : (n_dofs, n_dofs) array
        :func:`elastic_prior` of the mesh (unit mean variance on the border).
    bd : BorderData
        The border data: the landmarks' (:func:`mask_border_data`) or guided ones.
    F : int
        Number of frames.
    T : float
        Frame interval (s).
    s : float
        Pixel size (m).
    u0_px : float
        The landmarks' RMS displacement in the first frame (pixels): the initial state's sd.
    cfg : ContourRouteSettings
    say : callable
        Progress messages.

    Returns
    -------
    model : NodalFitModel
        With its process noise at the level the evidence chose (``cfg.process_noise="estimate"``).
    result : IteratedSmoother result
    q, u0_sd : float
        The process and initial sd (m) before that level.
    """
    q = cfg.process_fraction * (bd.floor_px if bd.floor_px > 0 else cfg.normal_sd_px) * s
    u0_sd = max(u0_px, q / s) * s
    fl = INTERIOR_FREEDOM
    model = NodalFitModel(mesh, material, np.zeros((F, mesh.n_dofs)), bd.H, T, (), density=NOMINAL["density"],
                          alpha=NOMINAL["alpha"], beta=NOMINAL["beta"], measurement_std=1.0,
                          process_std=(fl * q, fl * q / T), initial_std=(fl * u0_sd, fl * u0_sd / T),
                          penalty=penalty, R_frames=bd.R)
    free = model.dofmap.free
    XX = prior[np.ix_(free, free)]
    n = model.dofmap.n_free
    model.Q[:n, :n] += q ** 2 * XX
    model.Q[n:2 * n, n:2 * n] += (q / T) ** 2 * XX
    model.P0[:n, :n] += u0_sd ** 2 * XX
    model.P0[n:2 * n, n:2 * n] += (u0_sd / T) ** 2 * XX
    say(f"smoothing {F} frames ({model.dim_state} states)" + (
        "; the process noise level by the evidence (a smoother run per level tried)"
        if cfg.process_noise == "estimate" else ""))
    result = IteratedSmoother(covariance=False, process_noise=cfg.process_noise,
                              noise_range=tuple(cfg.noise_range)).run(model, bd.y)
    if cfg.process_noise == "estimate":
        model = model.with_process_noise(result.process_noise_scale)
    return model, result, q, u0_sd


def contour_spline_strain(result: ContourStrain) -> SplineStrain:
    """The yardstick through the same landmarks: :func:`sfem_filters.imaging.spline_strain.spline_strain`
    of the route's tracked landmark displacements (per frame), at the same reference pixels, about
    the same centre, with the landmarks' sd (the larger of their normal and tangential sd per
    component, the spline's data being independent per component)."""
    if not isinstance(result, ContourStrain):
        raise TypeError(f"result: expected a ContourStrain, got {type(result).__name__}")
    sd = np.repeat(result.landmark_sd.max(axis=-1)[..., None], 2, axis=-1)
    return spline_strain(result.tracks.points, result.tracks.displacement[1:], result.points, sd_px=sd,
                         centre=result.centre, start_deg=result.start_deg, frame_times_s=result.frame_times_s)
