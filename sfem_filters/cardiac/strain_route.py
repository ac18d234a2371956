"""DENSE displacements in, Green-Lagrange strain with its uncertainty out, by the finite-element smoother.

The DENSE route of issue 42 (items 3 and 4), as a library function, :func:`dense_strain`:

1. **Mesh.** The reference myocardium (the non-zero pixels of the reference mask) is meshed at
   a chosen element size, apart from the pixels (:func:`reference_mesh`): its marching-squares
   borders (:func:`sfem_filters.imaging.contours.mask_borders`, level 1/2, so every pixel centre
   lies inside) meshed by Gmsh (:func:`sfem_filters.fem.polygon_mesh.polygon_mesh`, default
   element edge 2 px), or the node-per-pixel mesh (``mesh="pixels"``,
   :func:`sfem_filters.cardiac.myocardium.tissue_mesh`).
2. **Observations.** Every tracked reference pixel is observed through the element shape
   functions, ``D`` of Eq. 12 as an interpolation
   (:func:`sfem_filters.fem.observation.point_observation_matrix`), each datum with its own noise sd
   (:class:`sfem_filters.imaging.dense.LagrangianDisplacement` ``sd``), untracked ones missing.
   The likelihood of the ~2P pixel data of a frame is, as a function of the nodal displacements
   ``U``, that of one Gaussian datum per free dof: the weighted least-squares fit ``U_t^ =
   J_t^-1 D^T W_t y_t`` with covariance ``R_t = J_t^-1``, ``J_t = D^T W_t D``, ``W_t`` the data's
   inverse variances (exactly: the two log-likelihoods differ by a constant in ``U``). The model
   observes the nodes with that full per-frame ``R_t`` (:class:`NodalFitModel`, the filters'
   ``R_at`` protocol), so the filter's cost is set by the mesh (n dofs a frame) and not by the
   image (2P rows). A direction of ``U`` no datum sees (a node whose elements hold no tracked
   pixel) gets ``J`` regularised by :data:`INFORMATION_FLOOR` of its mean diagonal: a pseudo-datum
   of zero with a variance ~1e8 times the others', i.e. no information.
3. **Estimator.** :class:`sfem_filters.model.SFEMModel` (plane-strain linear elasticity, Eq. 19)
   estimated by :class:`sfem_filters.filtering.iterated.IteratedSmoother`; with the material
   fixed the model is linear and its MAP is one Kalman-RTS pass. The configuration is chosen for
   dense data, each setting by a principle, none fitted to a case:

   * *material*: fixed; Young's modulus by :func:`compliant_modulus` (elastic relaxation across
     the wall over :data:`RELAXATION_CYCLES` cycles), Poisson's ratio nominal. With the nominal
     10 kPa and Rayleigh damping every mode relaxes to the reference configuration within a
     frame and the near-incompressible plane-strain tissue resists thickening, so the model
     cannot carry the wall's motion from frame to frame and flattens radial strain (measured:
     ``validation_draft/model_dense_sim.py --E 10000``); the compliant tissue lets the state
     carry the motion (mass and mass damping: a damped constant-velocity prior);
   * *effects*: none by default (``effects=`` adds catalogue effects; a compliant tissue has no
     elastic balance for an active stress);
   * *noise*: each datum's sd is the tracks' sd scaled up to the tracks' temporal noise floor
     (:func:`temporal_noise_floor`, which also holds the phase texture the magnitude-based sd
     misses); process noise 0.1 of that floor per frame (the library's rule for measured data,
     :func:`sfem_filters.cardiac.measured.build_model`), on the velocity over the frame interval;
   * *element size*: 2.5 px (:class:`StrainRouteSettings`).
4. **Strain.** ``F = I + grad u`` with ``grad u`` the *recovered* gradient (default,
   ``strain="recovered"``, :func:`gradient_operators`): at each node the area-weighted mean of the
   constant gradients of the linear triangles around it (nodal averaging, Zienkiewicz & Zhu 1992),
   interpolated at each reference pixel by the shape functions. Why, by measurement (one case at
   SNR 30, the error budget of issue 42's strain work, the validation page's ablation rows): the
   linear triangle's own constant gradient (``strain="element"``) jumps from element to element and
   carries the noise of its three nodes alone, so it is the noisiest part of the route (pixel
   RMSE of Ecc worse than the unsmoothed finite differences); a finer mesh is no remedy (at
   1.5 px each element sees fewer data and the smoother's cost, cubic in the nodes, leaves the
   3-minute budget); the recovered gradient averages over about one element edge (2.5 px) and
   reproduces an affine field's constant gradient exactly (the patch test). Both are linear in
   the nodal displacements. ``E = (F^T F - I) / 2`` (Green-Lagrange), projected on the radial and
   circumferential directions about the reference mask's centre of mass
   (:func:`sfem_filters.imaging.strain.mask_centre`) unless a centre is given.
5. **Its uncertainty (delta method).** ``E`` is linearised about the estimate: ``dE = sym(dG) +
   (G^T dG + dG^T G) / 2`` with ``dG = R dU`` (R the gradient operator of step 4), so ``dEcc =
   (F e_c) . (dG e_c)`` and ``dErr = (F e_r) . (dG e_r)``, linear in ``dU`` with coefficients that
   change from frame to frame. The smoother reports smoothed variances only of *static* output
   rows (:func:`sfem_filters.filtering.smoother.smooth` ``outputs``), not of a per-frame operator,
   so the linearised rows are fed to it as follows: (a) per item of the gradient (node, or element
   for ``"element"``), the 4 components of ``dG`` and their 6 pairwise sums (10 static rows), whose
   variances give the item's full 4 x 4 smoothed covariance of ``dG`` at every frame (``cov(a, b)
   = (var(a + b) - var a - var b) / 2``), from which each pixel's Ecc and Err variance follows
   (:func:`point_variance`: exact for an element, a slight upper bound for an interpolation of
   nodal gradients); (b) the global and six segment curves (means of the linearised pixel strains)
   as one static row per curve, component and frame, of which only frame t's variance is read at
   frame t. So the curves' 95% bands (``+- 1.96 sd``) use the full posterior covariance of the
   displacement, not independent pixels. The nonlinearity is handled by this first-order
   linearisation at the posterior mean (its error is second order in the displacement-gradient
   sd, about 1e-2 here, against strains of 1e-1).
6. **Honest bands** (``noise_scale=True``, ``discrepancy=True``). The smoother's variance assumes the model's noise
   levels and a model without error; measured against DENSE-Sim's truth its bands covered the
   true segment curves in a fifth to a half of the segment-frames. Two terms, each from the data
   alone:

   (a) *the noise level*, by type-II maximum likelihood: the common factor ``c`` on R, Q and the
   initial covariance that maximises the evidence, in closed form the mean normalised innovation
   squared (:func:`noise_scale`); it leaves the estimate unchanged and scales every smoothed
   variance by ``c`` (the data's noise is not white: the simulator's phase texture is correlated
   over neighbouring pixels and frames, and the temporal noise floor of step 3 sees only its
   white part). Reported as ``settings["noise_scale_ml"]``;
   (b) *the model discrepancy* (what a smoother of this mesh and prior flattens), empirical Bayes
   by the method of moments (:func:`discrepancy_variance`): against the unsmoothed
   finite-difference strain of the same tracks (:func:`sfem_filters.imaging.strain.strain_on_grid`,
   unbiased for the tracks but noisy), per curve (global and each segment), the cross moment of
   the disagreements over two halves of the curve's pixels (a segment's two 30-degree halves;
   for the global curve the six first halves against the six second), which share the
   discrepancy but not the noise, so that neither the noise's level nor its correlation over
   frames need be known. The discrepancy variance is ``tau0^2 + k^2 m_t^2`` (a constant part and
   one proportional to the curve's square, the bias of a smoothing scaling with what it
   flattens; the data fit both, so they choose the profile over the frames), one model for the
   global curve and one shared by the six segments (fitted to the moments of all six: one
   segment's frames alone give a noisy moment, which the non-negativity clips upwards); each
   pixel takes the segments' ``tau0`` and ``k`` (a pixel's own finite differences are far too
   noisy to tell). Reported as ``settings["discrepancy_sd"]``.

   ``Ecc_sd`` and ``Err_sd`` (and the curves' ``*_sd`` and bands) are the total; the smoother's
   own (with ``c``) stay beside as ``Ecc_sd_model``, ``Err_sd_model`` and the curves'
   ``*_sd_model``. What neither term can see: a bias that the tracks themselves carry (the
   reference shares it), such as the radial strain of the first pixel layers at the
   endocardium, which the tracks of the noise-free images already miss.

Units: pixels for points and displacements at the interface (x = column, y = row), SI inside
(the mesh in metres, from the case's pixel size); strain is a fraction; times in s.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from typing import ClassVar

import numpy as np
import scipy.sparse as sp
from scipy.optimize import nnls

from .._validate import as_float_array, positive
from ..fem.elasticity import stiffness_matrix, strain_displacement
from ..fem.loads import penalty_stiffness
from ..fem.material import Material
from ..fem.mesh import TriMesh
from ..fem.observation import point_observation_matrix
from ..fem.polygon_mesh import polygon_mesh
from ..filtering.iterated import IteratedSmoother
from ..filtering.linearised import linearise
from ..filtering.smoother import smooth
from ..imaging.contours import mask_borders
from ..imaging.dense import LagrangianDisplacement
from ..imaging.strain import N_SEGMENTS, Z95, StrainEstimate, global_curve, green_strain, json_list, mask_centre, \
    project_strain, radial_circumferential, segment_labels, strain_on_grid
from ..model import SFEMModel
from .effects import build_effects
from .measured import EFFECT_STEP, NOMINAL
from .myocardium import lv_geometry, tissue_mesh

__all__ = ["StrainRouteSettings", "DenseStrain", "NodalFitModel", "reference_mesh", "observation_points",
           "nodal_fit", "compliant_modulus", "temporal_noise_floor", "build_dense_model", "element_gradient_operator",
           "linearised_rows", "strain_and_sd", "dense_strain", "MESHES", "INFORMATION_FLOOR",
           "RELAXATION_CYCLES", "Z95", "STRAINS", "gradient_operators", "point_variance", "discrepancy_variance",
           "noise_scale", "DenseRouteStrain"]

#: How the reference myocardium is meshed (``mesh=``).
MESHES = ("gmsh", "pixels")
#: Regularisation of the nodal fit's information matrix, relative to its mean diagonal.
INFORMATION_FLOOR = 1e-8
#: Cycles the elastic relaxation across the wall takes with :func:`compliant_modulus`.
RELAXATION_CYCLES = 10.0
#: Which displacement gradient the strain is computed from (``strain=``).
STRAINS = ("recovered", "element")


@dataclass(frozen=True)
class StrainRouteSettings:
    """Settings of the DENSE route (each with a stated principle; see the module docstring).

    Attributes
    ----------
    mesh : {"gmsh", "pixels"}
        Mesh chosen apart from the pixels, or one node per pixel.
    element_px : float
        Target element edge (pixels) of the ``"gmsh"`` mesh. 2.5 px: two elements or more across
        a 5-7 pixel wall, about six data per node, and a state small enough for the 3-minute
        budget (the filter's cost grows as the cube of the nodes).
    effects : tuple of str
        Effects (:data:`sfem_filters.cardiac.effects.CATALOGUE`) whose loads act on the wall
        (default none: with the compliant tissue below, active stresses have no elastic
        response to balance).
    E : float or None
        Young's modulus (Pa); None: :func:`compliant_modulus` of the wall thickness and the
        cycle (the state carries the motion from frame to frame).
    nu : float
        Poisson's ratio (nominal 0.45).
    alpha : float or None
        Rayleigh mass damping (1/s); None: nominal (:data:`sfem_filters.cardiac.measured.NOMINAL`).
    process_fraction : float
        Process noise per frame as a fraction of the temporal noise floor (0.1, the library's
        rule for measured data, :func:`sfem_filters.cardiac.measured.build_model`).
    start_deg : float
        Start of segment 0 (degrees from the image's +x axis towards +y).
    centre : tuple or None
        Centre (x, y) in pixels of the radial directions and segments; None: the centre of
        mass of the reference mask.
    strain : {"recovered", "element"}
        Displacement gradient the strain is computed from (module docstring, step 4):
        ``"recovered"``, the nodal average of the element gradients interpolated by the shape
        functions (:func:`gradient_operators`); ``"element"``, the linear triangle's own constant
        gradient.
    noise_scale : bool
        Scale the smoother's variances by the maximum-likelihood noise level (:func:`noise_scale`,
        step 6 a).
    discrepancy : bool
        Add the model-discrepancy variance (:func:`discrepancy_variance`, step 6) to the
        smoother's own variance in the reported sd and bands.
    """

    mesh: str = "gmsh"
    element_px: float = 2.5
    effects: tuple = ()
    E: float | None = None
    nu: float = NOMINAL["nu"]
    alpha: float | None = None
    process_fraction: float = 0.1
    start_deg: float = 0.0
    centre: tuple | None = None
    strain: str = "recovered"
    noise_scale: bool = True
    discrepancy: bool = True

    def __post_init__(self):
        if self.mesh not in MESHES:
            raise ValueError(f"mesh: expected one of {MESHES}, got {self.mesh!r}")
        if self.strain not in STRAINS:
            raise ValueError(f"strain: expected one of {STRAINS}, got {self.strain!r}")
        for name in ("noise_scale", "discrepancy"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise TypeError(f"{name}: expected True or False, got {getattr(self, name)!r}")
        positive("element_px", self.element_px, "pixels")
        if self.E is not None:
            positive("E", self.E, "Pa")
        if not 0 < self.nu < 0.5:
            raise ValueError(f"nu: expected a Poisson's ratio in (0, 0.5), got {self.nu!r}")
        positive("process_fraction", self.process_fraction)
        if self.alpha is not None:
            positive("alpha", self.alpha, "1/s")
        object.__setattr__(self, "effects", tuple(self.effects))
        if self.centre is not None:
            object.__setattr__(self, "centre", tuple(float(v) for v in as_float_array("centre", self.centre,
                                                                                      shape=(2,))))


@dataclass(frozen=True, eq=False)
class DenseStrain(StrainEstimate):
    """:class:`~sfem_filters.imaging.strain.StrainEstimate` of a finite-element route (``route`` =
    ``"dense"``): the curves' bands ``+- 1.96 sd`` of the linearised posterior; ``seconds`` the
    wall-clock time of :func:`dense_strain`; ``settings`` also what was derived from the data
    (process noise, mesh size); and the mesh (m)."""

    ROUTE: ClassVar[str] = "dense"

    mesh: TriMesh = field(repr=False)


@dataclass(frozen=True, eq=False)
class DenseRouteStrain(DenseStrain):
    """:class:`DenseStrain` of the DENSE route, with the smoother's own sd beside the total.

    ``Ecc_sd`` and ``Err_sd`` (and the curves' ``*_sd``, ``*_lo``, ``*_hi``) hold the total
    uncertainty, the smoother's variance plus the model-discrepancy variance (module docstring,
    step 6); ``Ecc_sd_model`` and ``Err_sd_model`` (F, P) hold the smoother's alone, as do the
    curves' ``*_sd_model`` entries.
    """

    Ecc_sd_model: np.ndarray = field(repr=False)
    Err_sd_model: np.ndarray = field(repr=False)

    def to_dict(self) -> dict:
        """The issue-42 JSON names, plus ``strain.Ecc_sd_model`` and ``strain.Err_sd_model``."""
        out = super().to_dict()
        for q in ("Ecc", "Err"):
            out["strain"][f"{q}_sd_model"] = json_list(getattr(self, f"{q}_sd_model"))
        return out


# ----------------------------------------------------------------------------------- the mesh
def reference_mesh(mask, pixel_size_m: float, mesh: str = "gmsh", element_px: float = 2.0) -> TriMesh:
    """Mesh of a reference myocardium mask, in metres (pixel (r, c) centred on (c, r) px).

    ``"gmsh"``: the mask's borders (marching squares at level 1/2,
    :func:`sfem_filters.imaging.contours.mask_borders`, taken with about 4 points a pixel so that
    nothing of the border is lost before :func:`sfem_filters.fem.polygon_mesh.polygon_mesh`
    resamples it at the element size) meshed at ``element_px`` pixels. ``"pixels"``: one node per
    pixel centre (:func:`sfem_filters.cardiac.myocardium.tissue_mesh`).
    """
    s = positive("pixel_size_m", pixel_size_m, "m")
    if mesh not in MESHES:
        raise ValueError(f"mesh: expected one of {MESHES}, got {mesh!r}")
    m = np.asarray(mask, bool)
    if mesh == "pixels":
        rows, cols = np.nonzero(m)
        return tissue_mesh(np.column_stack([cols, rows]).astype(float) * s)[0]
    h = positive("element_px", element_px, "pixels")
    n = 4 * int(m.sum()) + 16
    b = mask_borders(m, n_endo=max(16, n // 3), n_epi=max(16, n // 2))
    return polygon_mesh(b.epi * s, [b.endo * s], size=h * s)


def observation_points(mesh: TriMesh, points_m) -> tuple:
    """Points (m) moved into the mesh where they lie outside it (onto the nearest boundary edge).

    Returns the points to observe at and how far each was moved (m). Pixel centres of the
    reference mask lie inside its level-1/2 border, but the mesh's boundary, a polygon through
    resampled border points, cuts the border's corners by up to a small fraction of a pixel.
    """
    pts = as_float_array("points_m", points_m, shape=(None, 2))
    tri = mesh.nodes[mesh.elements]
    v0 = tri[:, 0]
    Tinv = np.linalg.inv(np.stack([tri[:, 1] - v0, tri[:, 2] - v0], axis=2))
    lam12 = np.einsum("eij,pej->pei", Tinv, pts[:, None, :] - v0[None])
    worst = np.minimum(1.0 - lam12.sum(axis=2), lam12.min(axis=2)).max(axis=1)
    outside = np.flatnonzero(worst < -1e-9)
    out = pts.copy()
    moved = np.zeros(len(pts))
    if outside.size:
        edges = mesh.boundary_edges()
        a, b = mesh.nodes[edges[:, 0]], mesh.nodes[edges[:, 1]]
        ab = b - a
        for k in outside:
            t = np.clip(np.einsum("ej,ej->e", pts[k] - a, ab) / np.einsum("ej,ej->e", ab, ab), 1e-6, 1 - 1e-6)
            q = a + t[:, None] * ab
            j = int(np.argmin(np.linalg.norm(q - pts[k], axis=1)))
            # a hair inside: towards the opposite node of the edge's triangle (the tissue is on the left)
            inward = np.array([-ab[j, 1], ab[j, 0]]) / np.linalg.norm(ab[j])
            out[k] = q[j] + 1e-9 * np.linalg.norm(ab[j]) * inward
            moved[k] = float(np.linalg.norm(out[k] - pts[k]))
    return out, moved


# -------------------------------------------------------------------------- the data, compressed
def nodal_fit(D, displacement_m, sd_m) -> tuple:
    """Per frame, the weighted least-squares nodal displacements and their covariance.

    Parameters
    ----------
    D : (2P, n_dofs) sparse matrix
        Point observation operator (rows point by point, x before y).
    displacement_m, sd_m : (F, P, 2) arrays
        Data (m), NaN where untracked, and their sd (m).

    Returns
    -------
    y : (F, n_dofs) array
        ``J_t^-1 D^T W_t y_t`` (m).
    R : (F, n_dofs, n_dofs) array
        ``J_t^-1`` (m^2), ``J_t = D^T W_t D + floor I``, ``floor`` :data:`INFORMATION_FLOOR` of
        the mean diagonal of ``D^T W_t D``.
    """
    D = sp.csr_matrix(D)
    u = np.asarray(displacement_m, float)
    s = np.asarray(sd_m, float)
    F = u.shape[0]
    n = D.shape[1]
    y = np.empty((F, n))
    R = np.empty((F, n, n))
    for t in range(F):
        d = u[t].reshape(-1)
        w = np.where(np.isfinite(d) & np.isfinite(s[t].reshape(-1)) & (s[t].reshape(-1) > 0),
                     1.0 / np.where(s[t].reshape(-1) > 0, s[t].reshape(-1), 1.0) ** 2, 0.0)
        if not np.any(w > 0):
            raise ValueError(f"displacement: expected some tracked point in every frame, got none in frame {t}")
        Dw = D.multiply(w[:, None]).tocsr()
        J = (D.T @ Dw).toarray()
        J[np.diag_indices(n)] += INFORMATION_FLOOR * float(np.mean(np.diag(J)))
        b = Dw.T @ np.where(w > 0, d, 0.0)
        Li = np.linalg.solve(np.linalg.cholesky(J), np.eye(n))        # J^-1 = Li^T Li
        R[t] = Li.T @ Li
        y[t] = R[t] @ b
    return y, R


class NodalFitModel(SFEMModel):
    """:class:`SFEMModel` observing every node, with a full measurement covariance per frame.

    ``R_frames`` (F, m, m), m the observed rows: :meth:`R_at` returns frame t's (the filters'
    per-frame noise protocol); ``R`` is their mean. Everything else is :class:`SFEMModel`'s.
    """

    def __init__(self, *args, R_frames, **kwargs):
        R_frames = np.asarray(R_frames, float)
        super().__init__(*args, **kwargs)
        if R_frames.shape != (self.n_frames, self.dim_obs, self.dim_obs):
            raise ValueError(f"R_frames: expected shape ({self.n_frames}, {self.dim_obs}, {self.dim_obs}), "
                             f"got {R_frames.shape}")
        self._R_full = R_frames
        self.R = R_frames.mean(axis=0)

    def R_at(self, t: int) -> np.ndarray:
        """Measurement noise covariance of frame ``t`` (m^2), full."""
        return self._R_full[t]

    def with_measurement_noise(self, scale: float) -> "NodalFitModel":
        out = super().with_measurement_noise(scale)
        out._R_full = self._R_full * positive("scale", scale)
        return out


def compliant_modulus(wall_m: float, cycle_s: float, density: float = NOMINAL["density"],
                      alpha: float = NOMINAL["alpha"], cycles: float = RELAXATION_CYCLES) -> float:
    """Young's modulus (Pa) whose elastic relaxation across the wall takes ``cycles`` cardiac cycles.

    ``E = alpha rho w^2 / (cycles t)``: a wall mode of wavelength ~ the wall thickness ``w`` has
    ``omega^2 ~ E / (rho w^2)`` and, overdamped by the Rayleigh mass damping ``alpha``, relaxes at
    ``omega^2 / alpha``; this modulus makes that ``1 / (cycles t)``.

    Why: displacement data cannot identify the force scale (:data:`sfem_filters.cardiac.measured.NOMINAL`),
    and an elastic tissue pulls every state back towards the reference configuration (with the
    nominal modulus and Rayleigh damping, every mode relaxes at ``1 / beta`` = 333/s, within a
    frame), while a near-incompressible plane-strain material also resists the wall's
    thickening: the model then forgets where the wall was, cannot average the data over frames,
    and flattens radial strain. With this modulus the elastic forces are negligible over the
    cycle: from frame to frame the state carries the motion (a damped constant-velocity prior
    through the mass and the mass damping), and the data, not the reference shape, hold it.
    """
    w = positive("wall_m", wall_m, "m")
    t = positive("cycle_s", cycle_s, "s")
    return float(positive("alpha", alpha, "1/s") * positive("density", density, "kg/m^3") * w ** 2
                 / (positive("cycles", cycles) * t))


def temporal_noise_floor(displacement) -> float:
    """Noise sd per component (data units) from the second differences in time of the tracks.

    ``u_t - (u_t-1 + u_t+1) / 2`` of white noise of sd ``s`` has variance ``1.5 s^2``; a smooth
    motion adds little. So ``sqrt(mean(d2^2) / 1.5)`` over every point, component and frame
    bounds the noise from above; it holds what the phase-based sd misses (the simulator's or the
    scanner's phase texture, interpolation). The same rule as the library's measured-data
    workflow (:func:`sfem_filters.cardiac.measured.noise_floor`, which reports it per point).
    """
    u = np.asarray(displacement, float)
    d2 = u[1:-1] - 0.5 * (u[:-2] + u[2:])
    if not np.any(np.isfinite(d2)):
        raise ValueError("displacement: expected a point tracked in 3 consecutive frames for the noise floor, got none")
    return float(np.sqrt(np.nanmean(d2 ** 2) / 1.5))


def build_dense_model(mesh: TriMesh, tracks: LagrangianDisplacement, pixel_size_m: float,
                      settings: StrainRouteSettings) -> tuple:
    """The filter model of dense displacement data and its observations (module docstring, steps 2-3).

    Noise, by the data's own level: each datum's sd is the tracks' ``sd`` scaled up (never
    down) so that its RMS equals the temporal noise floor (:func:`temporal_noise_floor`); the
    process noise is ``settings.process_fraction`` of that floor per frame on the displacement,
    and the same over the frame interval on the velocity (the rule of
    :func:`sfem_filters.cardiac.measured.build_model`).

    Returns ``(model, y, info, points)``: a :class:`NodalFitModel`, the observations (F, n_dofs)
    in m, a dict of what was derived, and the observed points (m, moved into the mesh).
    """
    s = positive("pixel_size_m", pixel_size_m, "m")
    X = tracks.points * s
    Xin, moved = observation_points(mesh, X)
    D = point_observation_matrix(mesh, Xin)
    F = tracks.displacement.shape[0]
    if F < 3:
        raise ValueError(f"tracks: expected at least 3 frames, got {F}")
    floor_px = temporal_noise_floor(tracks.displacement)
    sd = np.asarray(tracks.sd, float)
    sd_rms = float(np.sqrt(np.nanmean(sd ** 2)))
    sd_scale = max(1.0, floor_px / sd_rms)
    y, R = nodal_fit(D, tracks.displacement * s, sd * sd_scale * s)
    T = float(np.median(np.diff(tracks.frame_times_s)))
    alpha = NOMINAL["alpha"] if settings.alpha is None else settings.alpha
    E = settings.E if settings.E is not None else compliant_modulus(_wall_thickness(mesh), F * T, alpha=alpha)
    geometry = lv_geometry(mesh)
    effs = build_effects(list(settings.effects), mesh, geometry, scale=NOMINAL["E"],
                         process_std=EFFECT_STEP, initial_std=EFFECT_STEP) if settings.effects else []
    material = Material.uniform(mesh.n_elements, E, settings.nu)
    # soft ground springs (the library's drive-free convention, NOMINAL["foundation"] of K's median
    # diagonal) only remove the rigid-body null space of K; the data hold the position
    ground = NOMINAL["foundation"] * float(np.median(stiffness_matrix(mesh, material.E, material.nu).diagonal()))
    penalty = penalty_stiffness(mesh.n_dofs, np.arange(mesh.n_dofs), ground)
    H = sp.identity(mesh.n_dofs, format="csr")
    q = settings.process_fraction * floor_px * s
    # the initial state: at rest in the reference configuration (encoding time, t = 0), uncertain
    # by the first frame's displacement (frame 0 is 22.5 ms after the encoding, already moved)
    u0_sd = max(float(np.sqrt(np.mean(y[0] ** 2))), floor_px * s)
    model = NodalFitModel(mesh, material, np.zeros((F, mesh.n_dofs)), H, T, (), density=NOMINAL["density"],
                          alpha=alpha, beta=NOMINAL["beta"], measurement_std=1.0,
                          process_std=(q, q / T), initial_std=(u0_sd, u0_sd / T), effects=effs, penalty=penalty,
                          R_frames=R)
    info = {"n_points_moved_into_mesh": int(np.count_nonzero(moved)), "largest_move_px": float(moved.max() / s),
            "noise_floor_px": floor_px, "tracks_sd_rms_px": sd_rms, "sd_scale": sd_scale,
            "process_std_px": q / s, "frame_interval_s": T, "E_Pa": E, "alpha_per_s": alpha,
            "wall_thickness_px": _wall_thickness(mesh) / s,
            "initial_std_px": u0_sd / s}
    return model, y, info, Xin


def _wall_thickness(mesh: TriMesh) -> float:
    """Mean wall thickness (m): the area over the mean of the two borders' lengths."""
    geometry = lv_geometry(mesh)
    lengths = []
    for loop in (geometry.endo, geometry.epi):
        p = mesh.nodes[loop]
        lengths.append(float(np.sum(np.linalg.norm(p - np.roll(p, 1, axis=0), axis=1))))
    return float(mesh.areas.sum() / np.mean(lengths))


# ------------------------------------------------------------------------------ strain and its sd
def element_gradient_operator(mesh: TriMesh) -> np.ndarray:
    """(n_elements, 4, 6): ``B[e] @ U_e`` = (G00, G01, G10, G11), ``G_ij = d u_i / d X_j`` of element e
    (dofs x0 y0 x1 y1 x2 y2; dimensionless for U and X in the same unit)."""
    Bv = strain_displacement(mesh)              # rows e_xx = b.ux, e_yy = c.uy, gamma = c.ux + b.uy
    b, c = Bv[:, 0, 0::2], Bv[:, 1, 1::2]
    G = np.zeros((mesh.n_elements, 4, 6))
    G[:, 0, 0::2] = b                           # du_x/dX
    G[:, 1, 0::2] = c                           # du_x/dY
    G[:, 2, 1::2] = b                           # du_y/dX
    G[:, 3, 1::2] = c                           # du_y/dY
    return G


def _element_of(mesh: TriMesh, points_m) -> np.ndarray:
    tri = mesh.nodes[mesh.elements]
    v0 = tri[:, 0]
    Tinv = np.linalg.inv(np.stack([tri[:, 1] - v0, tri[:, 2] - v0], axis=2))
    lam12 = np.einsum("eij,pej->pei", Tinv, np.asarray(points_m, float)[:, None, :] - v0[None])
    worst = np.minimum(1.0 - lam12.sum(axis=2), lam12.min(axis=2))
    return np.argmax(worst, axis=1)


def linearised_rows(grad, points, centre) -> tuple:
    """Coefficients ``a`` (..., P, 4) with ``dEcc = a_cc . dG`` and ``dErr = a_rr . dG`` (dG as G00, G01, G10, G11).

    ``dE = (dG^T F + F^T dG) / 2`` (``F = I + G``), so ``e . dE e = (F e) . (dG e)``.
    """
    er, ec = radial_circumferential(points, centre)
    Fd = np.eye(2) + np.asarray(grad, float)
    out = []
    for e in (ec, er):
        Fe = np.einsum("...pij,pj->...pi", Fd, e)
        out.append((Fe[..., :, None] * e[:, None, :]).reshape(Fe.shape[:-1] + (4,)))
    return out[0], out[1]


def strain_and_sd(grad, cov, points, centre) -> tuple:
    """Ecc, Err, Ecr (F, P) from gradients (F, P, 2, 2), and the Ecc, Err sd from their (F, P, 4, 4) covariance."""
    E = green_strain(grad)
    ecc, err, ecr = project_strain(E, points, centre)
    a_cc, a_rr = linearised_rows(grad, points, centre)
    sd_cc = np.sqrt(np.maximum(np.einsum("...i,...ij,...j->...", a_cc, cov, a_cc), 0.0))
    sd_rr = np.sqrt(np.maximum(np.einsum("...i,...ij,...j->...", a_rr, cov, a_rr), 0.0))
    return ecc, err, ecr, sd_cc, sd_rr


_PAIRS = [(i, j) for i in range(4) for j in range(i + 1, 4)]


def _gradient_rows(mesh: TriMesh, Ge: np.ndarray, elements=None) -> sp.csr_matrix:
    """10 rows per element on the global dofs: its 4 gradient components, then their 6 pairwise sums.

    ``elements``: the elements to give rows to, in this order (default all)."""
    dofs = mesh.element_dofs
    which = np.arange(mesh.n_elements) if elements is None else np.asarray(elements, int)
    rows, cols, vals = [], [], []
    for i_e, e in enumerate(which):
        comps = [Ge[e, i] for i in range(4)] + [Ge[e, i] + Ge[e, j] for i, j in _PAIRS]
        for k, r in enumerate(comps):
            rows.extend([10 * i_e + k] * 6)
            cols.extend(dofs[e].tolist())
            vals.extend(r.tolist())
    return sp.csr_matrix((vals, (rows, cols)), shape=(10 * len(which), mesh.n_dofs))


def _covariance_from_rows(v: np.ndarray) -> np.ndarray:
    """(F, n_el, 4, 4) covariances from (F, 10 n_el) variances of components and pairwise sums."""
    F = v.shape[0]
    v = v.reshape(F, -1, 10)
    C = np.zeros(v.shape[:2] + (4, 4))
    for i in range(4):
        C[..., i, i] = v[..., i]
    for k, (i, j) in enumerate(_PAIRS):
        c = 0.5 * (v[..., 4 + k] - v[..., i] - v[..., j])
        C[..., i, j] = C[..., j, i] = c
    return C


def gradient_operators(mesh: TriMesh, points_m, kind: str = "recovered") -> tuple:
    """Sparse operators of the displacement gradient: at the mesh's items and at the points.

    ``"element"``: the items are the elements, component k of element e is ``B[e, k] @ U_e``
    (:func:`element_gradient_operator`), and a point takes its element's. ``"recovered"``: the
    items are the nodes, each the area-weighted mean of the gradients of the elements around
    it (nodal averaging, the simplest of the recovered gradients of Zienkiewicz & Zhu 1992),
    and a point takes the shape-function interpolation of its element's three nodal values.
    Both reproduce the constant gradient of an affine displacement exactly (the patch test);
    the recovered one is continuous and averages each gradient over the ring of elements
    around a node (about one element edge, 2.5 px, either way): the linear triangle's constant
    gradient jumps from element to element and carries the noise of its three nodes alone.

    Parameters
    ----------
    mesh : TriMesh
    points_m : (P, 2) array
        Points inside the mesh (m).
    kind : {"recovered", "element"}

    Returns
    -------
    ops : list of 4 sparse (m, n_dofs) matrices
        Components (G00, G01, G10, G11), ``G_ij = d u_i / d X_j``, at the m items.
    weights : sparse (P, m) matrix
        Each point's gradient is ``weights @`` the items' (rows of non-negative weights summing
        to 1).
    """
    if kind not in STRAINS:
        raise ValueError(f"kind: expected one of {STRAINS}, got {kind!r}")
    Ge = element_gradient_operator(mesh)
    ne = mesh.n_elements
    rows = np.repeat(np.arange(ne), 6)
    cols = mesh.element_dofs.ravel()
    ops = [sp.csr_matrix((Ge[:, k].ravel(), (rows, cols)), shape=(ne, mesh.n_dofs)) for k in range(4)]
    pts = as_float_array("points_m", points_m, shape=(None, 2))
    if kind == "element":
        elem = _element_of(mesh, pts)
        weights = sp.csr_matrix((np.ones(len(pts)), (np.arange(len(pts)), elem)), shape=(len(pts), ne))
        return ops, weights
    area = np.repeat(mesh.areas, 3)
    S = sp.csr_matrix((area, (mesh.elements.ravel(), np.repeat(np.arange(ne), 3))), shape=(mesh.n_nodes, ne))
    S = sp.diags(1.0 / np.asarray(S.sum(axis=1)).ravel()) @ S
    weights = sp.csr_matrix(point_observation_matrix(mesh, pts))[0::2, 0::2]
    return [sp.csr_matrix(S @ op) for op in ops], sp.csr_matrix(weights)


def _component_rows(ops) -> sp.csr_matrix:
    """(10 m, n_dofs): the 4 components of every item, then their 6 pairwise sums (block by block)."""
    return sp.vstack(list(ops) + [ops[i] + ops[j] for i, j in _PAIRS], format="csr")


def _covariance_from_blocks(v: np.ndarray, m: int) -> np.ndarray:
    """(F, m, 4, 4) covariances from (F, 10 m) variances of :func:`_component_rows`."""
    v = v.reshape(v.shape[0], 10, m)
    C = np.zeros((v.shape[0], m, 4, 4))
    for i in range(4):
        C[..., i, i] = v[:, i]
    for k, (i, j) in enumerate(_PAIRS):
        C[..., i, j] = C[..., j, i] = 0.5 * (v[:, 4 + k] - v[:, i] - v[:, j])
    return C


def point_variance(weights, a, C) -> np.ndarray:
    """Variance (F, P) of the linearised strain ``a . dG`` at each point from the items' gradient covariance.

    ``sum_i w_pi a^T C_i a``: exact where a point takes one item's gradient (``"element"``);
    for an interpolation of nodal gradients the exact variance ``a^T cov(sum_i w_i g_i) a`` is
    at most this (Jensen: ``(sum w sd)^2 <= sum w sd^2`` for weights summing to 1, and
    ``var(sum w g) <= (sum w sd)^2``), equal when the three nodes' gradients are perfectly
    correlated, as nearly so as patches sharing most of their elements are. So the pixel sd
    is, if anything, a slight overstatement; the curves' bands use the exact rows.

    Parameters
    ----------
    weights : sparse (P, m)
    a : (F, P, 4) array
    C : (F, m, 4, 4) array
    """
    W = sp.coo_matrix(weights)
    q = np.einsum("fnk,fnkl,fnl->fn", a[:, W.row], C[:, W.col], a[:, W.row]) * W.data[None]
    out = np.zeros(a.shape[:2])
    np.add.at(out, (slice(None), W.row), q)
    return np.maximum(out, 0.0)


def discrepancy_variance(diff_a, diff_b, estimate) -> tuple:
    """Model-discrepancy variance of a curve from two noisy, unbiased looks at it (empirical Bayes).

    ``diff_a`` and ``diff_b`` are, frame by frame, an unbiased but noisy reference minus the
    estimate over two halves of the curve's pixels (for a segment its two 30-degree halves):
    ``d_t = -b_t + e_t``, the estimate's discrepancy ``b`` (what the model lacks), shared by the
    halves, plus noise ``e`` that the halves do not share (the phase texture is correlated over a
    few pixels, not across a half-segment). The cross moment ``E[d_a,t d_b,t] = b_t^2`` holds
    whatever the noise's level and its correlation over frames, so no noise level need be
    estimated (a noise floor from temporal differences misses the texture's correlation over
    frames and would call it discrepancy). The discrepancy's variance at frame t is modelled as
    ``tau_t^2 = tau0^2 + k^2 m_t^2`` (``m`` the estimate): a part that does not depend on the
    strain, and one proportional to it (the bias of a smoothing scales with the field it
    flattens), both fitted by non-negative least squares to the moment equations ``d_a,t d_b,t =
    tau0^2 + k^2 m_t^2``, so the data choose the profile over the frames; both are zero (in the
    mean) when the estimate agrees with the reference within the noise. Where the halves' biases
    differ the cross moment is their product, at most the mean of their squares.

    Parameters
    ----------
    diff_a, diff_b : (F,) arrays
        Reference minus estimate over each half, per frame (NaN where missing); F >= 2 frames
        where both are finite. Several curves sharing one model: their frames concatenated.
    estimate : (F,) array
        The estimate of the whole curve (curves).

    Returns
    -------
    tau0_2 : float
        The constant part (units of the values squared), >= 0.
    k2 : float
        The relative part (dimensionless), >= 0.
    """
    a = as_float_array("diff_a", diff_a, shape=(None,), allow_nan=True)
    b = as_float_array("diff_b", diff_b, shape=a.shape, allow_nan=True)
    m = as_float_array("estimate", estimate, shape=a.shape, allow_nan=True)
    ok = np.isfinite(a) & np.isfinite(b) & np.isfinite(m)
    if ok.sum() < 2:
        raise ValueError(f"diff_a, diff_b, estimate: expected at least 2 frames where all are finite, got {ok.sum()}")
    A = np.column_stack([np.ones(int(ok.sum())), m[ok] ** 2])
    scale = np.maximum(np.abs(A).max(axis=0), 1e-300)                      # column scaling for nnls
    sol, _ = nnls(A / scale, a[ok] * b[ok])
    tau0_2, k2 = sol / scale
    return float(tau0_2), float(k2)


def noise_scale(nis, n_obs) -> float:
    """Maximum-likelihood common scale of every covariance of a linear-Gaussian state-space model.

    Scaling R, Q and the initial covariance by one factor ``c`` leaves the Kalman gains and the
    smoothed means unchanged and multiplies every innovation covariance ``S_t`` by ``c``; the
    log-likelihood is then maximised in closed form by ``c = sum_t e_t^T S_t^-1 e_t / sum_t m_t``,
    the mean normalised innovation squared per observed row (Harvey 1989, sec. 3.4: the
    concentrated likelihood), and every smoothed covariance scales by ``c``. Type-II maximum
    likelihood of the noise level, at no extra pass.

    Parameters
    ----------
    nis : (F,) array
        Each frame's ``e_t^T S_t^-1 e_t`` (NaN where nothing was observed).
    n_obs : (F,) array
        Rows observed in each frame.
    """
    nis = np.asarray(nis, float)
    n = np.asarray(n_obs, float)
    ok = np.isfinite(nis) & (n > 0)
    if not ok.any():
        raise ValueError("nis, n_obs: expected some observed frame, got none")
    return float(np.sum(nis[ok]) / np.sum(n[ok]))


def _curve_rows(Ge, elem, a, groups, ndofs, dofs) -> np.ndarray:
    """(len(groups), n_dofs) rows: the mean over each group's points of ``a_p . (B_e(p) U)``."""
    out = np.zeros((len(groups), ndofs))
    per_point = np.einsum("pk,pkd->pd", a, Ge[elem])          # (P, 6) coefficients on the element dofs
    for g, sel in enumerate(groups):
        if sel.size:
            np.add.at(out[g], dofs[elem[sel]].ravel(), (per_point[sel] / sel.size).ravel())
    return out


def dense_strain(tracks: LagrangianDisplacement, reference_mask, pixel_size_m: float,
                 settings: StrainRouteSettings | None = None, progress=None) -> DenseRouteStrain:
    """The DENSE route: tracks in, Green-Lagrange strain with sd and curves with 95% bands out.

    Parameters
    ----------
    tracks : LagrangianDisplacement
        Displacements (pixels) of the reference pixels with their sd
        (:func:`sfem_filters.imaging.dense.phase_to_displacement`).
    reference_mask : (H, W) bool array
        The reference myocardium; its pixels are ``tracks.points``.
    pixel_size_m : float
        Pixel size (m).
    settings : StrainRouteSettings, optional
    progress : callable, optional
        ``progress(message)`` called at each step (from the first second).

    Returns
    -------
    DenseRouteStrain
        A :class:`DenseStrain` with the smoother's own sd beside the total.
    """
    t0 = time.perf_counter()
    cfg = StrainRouteSettings() if settings is None else settings
    say = progress if progress is not None else (lambda msg: None)
    if not isinstance(tracks, LagrangianDisplacement):
        raise TypeError(f"tracks: expected a LagrangianDisplacement, got {type(tracks).__name__}")
    s = positive("pixel_size_m", pixel_size_m, "m")
    mask = np.asarray(reference_mask, bool)
    rows, cols = np.nonzero(mask)
    X = tracks.points
    if len(rows) != len(X) or not np.array_equal(np.column_stack([cols, rows]).astype(float), X):
        raise ValueError("reference_mask: expected the mask whose pixels (row-major) are tracks.points")
    centre = mask_centre(mask) if cfg.centre is None else np.asarray(cfg.centre, float)
    say(f"meshing the reference myocardium ({cfg.mesh}, {cfg.element_px:g} px)")
    mesh = reference_mesh(mask, s, cfg.mesh, cfg.element_px)
    say(f"mesh: {mesh.n_nodes} nodes, {mesh.n_elements} triangles; building the model")
    model, y, info, Xin = build_dense_model(mesh, tracks, s, cfg)
    F, P = tracks.displacement.shape[:2]
    say(f"smoothing {F} frames ({model.dim_state} states)")
    result = IteratedSmoother(covariance=False).run(model, y)
    nr = model.n_restart
    n = model.dim_x // 2
    free = model.dofmap.free
    U = np.zeros((F, mesh.n_dofs))
    U[:, free] = result.states[:, :n]
    # gradients at the points: G = R_k U, R_k = weights @ ops[k] (element or recovered, step 4)
    ops, weights = gradient_operators(mesh, Xin, cfg.strain)
    R = [sp.csr_matrix(weights @ op) for op in ops]
    grad = np.stack([(Rk @ U.T).T for Rk in R], axis=-1).reshape(F, P, 2, 2)
    labels = segment_labels(X, centre, cfg.start_deg)
    groups = [np.arange(P)] + [np.flatnonzero(labels == k) for k in range(N_SEGMENTS)]
    A = np.zeros((len(groups), P))
    for g, sel in enumerate(groups):
        A[g, sel] = 1.0 / max(sel.size, 1)
    a_cc, a_rr = linearised_rows(grad, X, centre)
    curve_rows = np.concatenate([np.concatenate([sum(sp.csr_matrix(A * a[t][:, k]) @ R[k] for k in range(4)).toarray()
                                                 for a in (a_cc, a_rr)]) for t in range(F)])   # (F * 14, n_dofs)
    say("covariance pass (linearised strain)")
    lin = linearise(model, result.states)

    def on_state(op):
        op = sp.csr_matrix(op)[:, free]
        return lin.output_in_xi(sp.hstack([op, sp.csr_matrix((op.shape[0], nr - n))], format="csr"))

    outputs = {"gradient": on_state(_component_rows(ops)), "curves": on_state(curve_rows)}
    sm = smooth(lin, y, outputs=outputs, covariance=True)
    c_ml = noise_scale(sm.nis, sm.n_obs) if cfg.noise_scale else 1.0         # step 6 (a)
    C = c_ml * _covariance_from_blocks(sm.variances["gradient"], ops[0].shape[0])       # (F, m, 4, 4)
    E = green_strain(grad)
    ecc, err, ecr = project_strain(E, X, centre)
    sd_cc = np.sqrt(point_variance(weights, a_cc, C))
    sd_rr = np.sqrt(point_variance(weights, a_rr, C))
    k = 2 * (1 + N_SEGMENTS)
    vc = sm.variances["curves"].reshape(F, F, k)[np.arange(F), np.arange(F)]    # frame t's rows at frame t
    sd_curves = np.sqrt(c_ml * np.maximum(vc, 0.0))                             # (F, 14)
    # step 6: the model discrepancy, against the unsmoothed finite-difference strain of the same tracks
    ref = strain_on_grid(X, tracks.displacement, centre)
    half = segment_labels(X, centre, cfg.start_deg + 30.0) == labels             # second 30 degrees of a segment
    means = {"Ecc": ecc, "Err": err}
    refs = {"Ecc": ref.Ecc, "Err": ref.Err}
    pixel_sd = {"Ecc": sd_cc, "Err": sd_rr}
    glob, segs, total_sd, tau_report = {}, {}, {}, {}
    for q_i, q in enumerate(("Ecc", "Err")):
        m_all = np.stack([means[q][:, g].mean(axis=1) if g.size else np.full(F, np.nan) for g in groups], axis=1)
        r_all = np.stack([global_curve(refs[q][:, g]) if g.size else np.full(F, np.nan) for g in groups], axis=1)
        sd_all = sd_curves[:, q_i * (1 + N_SEGMENTS):(q_i + 1) * (1 + N_SEGMENTS)]
        tau = np.zeros((len(groups), 2))                  # (tau0^2, k^2): the global curve's, then the segments'
        if cfg.discrepancy:
            looks = []
            for g, sel in enumerate(groups):
                halves = [sel[half[sel] == h] for h in (False, True)]
                da, db = ((global_curve(refs[q][:, hv]) - means[q][:, hv].mean(axis=1)) if hv.size
                          else np.full(F, np.nan) for hv in halves)
                enough = np.sum(np.isfinite(da) & np.isfinite(db)) >= 2
                looks.append((da, db, m_all[:, g]) if enough else None)
            if looks and looks[0] is not None:
                tau[0] = discrepancy_variance(*looks[0])
            segs_looks = [lk for lk in looks[1:] if lk is not None]
            if segs_looks:                                # one model for the six segments: 6 F moments
                tau[1:] = discrepancy_variance(*(np.concatenate(parts) for parts in zip(*segs_looks)))
        # a pixel takes its segment's discrepancy (its own finite differences are far too noisy to tell)
        tp = tau[1:][labels]
        total_sd[q] = np.sqrt(pixel_sd[q] ** 2 + tp[None, :, 0] + tp[None, :, 1] * means[q] ** 2)
        tau_report[q] = {"global": np.sqrt(tau[0]).tolist(), "segments": np.sqrt(tau[1]).tolist()}
        for d, sl in ((glob, 0), (segs, slice(1, None))):
            mu, sd_m = m_all[:, sl].T, sd_all[:, sl].T
            c0, k2 = (tau[1:, :1], tau[1:, 1:]) if d is segs else (tau[0, 0], tau[0, 1])
            sd = np.sqrt(sd_m ** 2 + c0 + k2 * mu ** 2)
            d[q], d[f"{q}_sd"], d[f"{q}_lo"], d[f"{q}_hi"] = mu, sd, mu - Z95 * sd, mu + Z95 * sd
            d[f"{q}_sd_model"] = sd_m
    Dp = point_observation_matrix(mesh, Xin)
    disp_px = (Dp @ U.T).T.reshape(F, P, 2) / s
    seconds = time.perf_counter() - t0
    edges = np.linalg.norm(np.diff(mesh.nodes[mesh.elements][:, [0, 1, 2, 0]], axis=1), axis=2).mean() / s
    settings_out = {**asdict(cfg), **info, "n_nodes": mesh.n_nodes, "n_elements": mesh.n_elements,
                    "element_px_mean_edge": float(edges), "dim_state": int(model.dim_state),
                    "material": "fixed: E of compliant_modulus unless given, nu nominal",
                    "estimator": "IteratedSmoother (material fixed: one Kalman-RTS pass), then a covariance pass",
                    "strain": ("Green-Lagrange of the recovered (nodal-average) gradient" if cfg.strain == "recovered"
                               else "Green-Lagrange of the linear triangles' element gradient"),
                    "sd": "delta method at the posterior mean, full smoothed covariance of U"
                          + (" (x the ML noise scale)" if cfg.noise_scale else "")
                          + (", plus the discrepancy variance against the unsmoothed finite-difference strain"
                             if cfg.discrepancy else ""),
                    "noise_scale_ml": c_ml,
                    "discrepancy_sd": {"what": "[tau0 (fraction), k (relative)], tau_t^2 = tau0^2 + k^2 m_t^2; "
                                               "one model for the global curve, one for the six segments",
                                       **tau_report}}
    say(f"done in {seconds:.1f} s")
    return DenseRouteStrain(points=X.copy(), frame_times_s=np.asarray(tracks.frame_times_s, float).copy(),
                            centre=np.asarray(centre, float), start_deg=float(cfg.start_deg), labels=labels, Ecc=ecc,
                            Err=err, Ecr=ecr, Ecc_sd=total_sd["Ecc"], Err_sd=total_sd["Err"], global_curves=glob,
                            segment_curves=segs, displacement=disp_px, seconds=seconds, settings=settings_out,
                            mesh=mesh, Ecc_sd_model=sd_cc, Err_sd_model=sd_rr)
