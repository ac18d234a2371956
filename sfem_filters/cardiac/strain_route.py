"""DENSE displacements in, Green-Lagrange strain with its uncertainty out, by the finite-element smoother.

The DENSE route, as a library function, :func:`dense_strain`:

1. **Mesh.** The reference myocardium (the non-zero pixels of the reference mask) is meshed at
   a chosen element size, apart from the pixels (:func:`reference_mesh`): its marching-squares
   borders (:func:`sfem_filters.imaging.contours.mask_borders`, level 1/2, so every pixel centre
   lies inside) meshed by Gmsh (:func:`sfem_filters.fem.polygon_mesh.polygon_mesh`, default
   element edge 2 px), or the node-per-pixel mesh (``mesh="pixels"``,
   :func:`sfem_filters.cardiac.myocardium.tissue_mesh`), with the point observation only: its border
   lies half a pixel inside the mask's, which the point spread would read as background.
2. **Observations.** Every tracked reference pixel is observed through the element shape
   functions, ``D`` of Eq. 12 as an interpolation
   (:func:`sfem_filters.fem.observation.point_observation_matrix`), each datum with its own noise sd
   (:class:`sfem_filters.imaging.dense.LagrangianDisplacement` ``pixel_sd``, step 3), untracked ones missing.
   The likelihood of the ~2P pixel data of a frame is, as a function of the nodal displacements
   ``U``, that of one Gaussian datum per free dof: the weighted least-squares fit ``U_t^ =
   J_t^-1 D^T W_t y_t`` with covariance ``R_t = J_t^-1``, ``J_t = D^T W_t D``, ``W_t`` the data's
   inverse variances (exactly: the two log-likelihoods differ by a constant in ``U``). The model
   observes the nodes with that full per-frame ``R_t`` (:class:`NodalFitModel`, the filters'
   ``R_at`` protocol), so the filter's cost is set by the mesh (n dofs a frame) and not by the
   image (2P rows). A direction of ``U`` no datum sees (a node whose elements hold no tracked
   pixel) gets ``J`` regularised by :data:`INFORMATION_FLOOR` of its mean diagonal: a pseudo-datum
   of zero with a variance ~1e8 times the others', i.e. no information.

   *Resolution-aware* (``resolution_px > 1``, :func:`observation_operator`): a DENSE datum is the
   phase of the signal summed over the acquisition's point spread, so each row of ``D`` becomes
   the point-spread-weighted mean of the shape-function interpolation over sub-pixel samples
   around the pixel (Eq. 12 as a weighted average instead of a point interpolation,
   :func:`sfem_filters.fem.observation.blurred_observation_matrix`), and where the point spread
   reaches outside the reference myocardium the background's coherent signal enters the
   normalisation (one complex level per region and frame, zero where it is no more than the
   region's incoherent floor: :func:`sfem_filters.imaging.dense.background_signal`) and a factor ``sin(theta) / theta`` of
   the datum's own phase (phasors add, phases do not). The width comes from the acquisition
   (:attr:`sfem_filters.imaging.DenseCase.resolution_px`: DENSE-Sim's acquired pixel ``FOV /
   N_im_pre_spiral`` over the images' pixel, a DICOM's matrix over its AcquisitionMatrix) or the
   user, never from a fit; the operator is one
   matrix for every frame (the point spread taken in the reference configuration, see
   :func:`observation_operator`) and the frame's background rescales each datum (``n y = D U``,
   so :func:`nodal_fit` is unchanged). :class:`StrainRouteSettings` default 1 (tracks alone carry
   no acquisition): the point interpolation above; with images, :func:`image_settings` takes the
   acquisition's width (the command line's default; the validation page's ablation row reports
   the point observation beside it).

   *Fused with the masks* (``border_masks=True``, ``masks=`` of every frame; Shi & Liu's fusion of
   shape tracking with phase-contrast data in one filter): the endocardial border of a mask shows
   the wall's thickening directly, free of the cavity signal that leaks into the endocardial pixels'
   phase through the point spread. The masks' datum is each border node's motion *across* the border
   (the masks do not see the sliding along it), sd the larger of the mask's quantisation ``1 /
   sqrt(12)`` px and the data's own temporal noise floor across the border
   (:func:`border_masks_data`, :mod:`sfem_filters.cardiac.border_data`). Which point of a frame's
   border a node has become, the masks alone cannot say; the phase data can. So by default
   (``border_correspondence="phase"``) one filter and RTS pass of the phase data alone
   (:func:`sfem_filters.cardiac.dense_model.phase_only_pass`, which also gives their noise level
   below) places each border point, and the datum is the mask border's offset across itself there
   (:func:`sfem_filters.cardiac.border_data.guided_border_data`: the guide's error across the border
   does not enter, its error along the border only at second order). The contours route's landmarks,
   tracked through the masks by bending-energy matching (``border_correspondence="landmarks"``),
   must find that correspondence from the contours' shape alone and slide along smooth borders,
   where their motion projected on the reference normal misreads the border's (the validation page's
   ablation row). They are stacked below the nodal fit (``H = [I; H_b]``, ``R_t = blockdiag(J_t^-1,
   R_b,t)``, :func:`build_dense_model`): independent data of the same displacement, so the two
   likelihoods add and the smoother weighs each by its own noise. The masks are of the current frame
   and each datum belongs to a material border point, so no Eulerian inversion is involved. Step 6 is unchanged (the
   excess error is still measured against the phase tracks' finite differences, so where the masks
   pull the estimate away from biased tracks the bands widen). At their stated levels the phase
   data, many pixels a node, outweigh the masks' one datum a border node several times over; the
   route's own ML noise scale (step 6 a) says the phase data's stated sd is several times too small,
   and the masks' has no such factor. So ``phase_noise_level="evidence"`` first scales the phase
   data's covariances (R, process, initial) by their own type-II ML level from one filter pass
   without the masks (:func:`phase_noise_level`; alone this factor changes no estimate), then stacks
   the masks. Their stated sd (a binary border's quantisation) says nothing of how well the masks
   were drawn nor of how much a node's datum, a mean over its support, averages out; so
   ``mask_noise_level="evidence"`` scales the masks' covariance by the factor of largest evidence of
   the fused model (:func:`sfem_filters.cardiac.dense_model.mask_noise_level_ml`: variance
   components by type-II ML, one filter pass per candidate of
   :data:`~sfem_filters.cardiac.dense_model.MASK_LEVELS`, the common level profiled out): each
   source weighed by the noise it shows. The evidence sees how the two sources disagree from frame
   to frame, not an error both share or one the motion's smoothness absorbs. With images,
   :func:`image_settings` fuses the masks whenever they move, both at their evidence levels (the
   command line's default, :func:`dense_case_strain`).
3. **Estimator.** :class:`sfem_filters.model.SFEMModel` (plane-strain linear elasticity, Eq. 19)
   estimated by the Kalman filter and RTS smoother (:mod:`sfem_filters.filtering.smoother`): with
   the material fixed the model is linear and its MAP is one Kalman-RTS pass (what
   :class:`sfem_filters.filtering.iterated.IteratedSmoother` returns for a model without
   parameters), so one forward pass keeps what two backward passes need, the smoothed means and
   then the covariances of the strain linearised at them (step 5). The configuration is chosen for
   dense data, each setting by a principle, none fitted to a case:

   * *material*: fixed; Young's modulus by :func:`compliant_modulus` (elastic relaxation across
     the wall over :data:`RELAXATION_CYCLES` cycles), Poisson's ratio nominal. With the nominal
     10 kPa and Rayleigh damping every mode relaxes to the reference configuration within a
     frame and the near-incompressible plane-strain tissue resists thickening, so the model
     cannot carry the wall's motion from frame to frame and flattens radial strain (measured:
     ``StrainRouteSettings(E=10e3)`` on a DENSE-Sim case); the compliant tissue lets the state
     carry the motion (mass and mass damping: a damped constant-velocity prior);
   * *effects*: none by default (``effects=`` adds catalogue effects; a compliant tissue has no
     elastic balance for an active stress);
   * *noise*: each datum's sd is the sd of the pixels behind it (``LagrangianDisplacement.pixel_sd``:
     neighbouring tracks interpolate shared pixels, so a fit smooth over a pixel sees their noise,
     not the smaller noise of each interpolated datum alone) scaled up to the tracks' temporal noise floor
     (:func:`temporal_noise_floor`, which also holds the phase texture the magnitude-based sd
     misses); process noise a fraction ``q`` of that floor per frame, on the velocity over the
     frame interval: 0.1 by default (the library's rule for measured data), or, with
     ``process_fraction=None``, chosen by type-II maximum likelihood (:func:`process_fraction_ml`:
     the evidence of one filter pass per candidate of :data:`PROCESS_FRACTIONS`, the common noise
     level profiled out). What that choice trades, measured (the validation page's error budget,
     row "earlier default with process noise by the evidence", one process level): the evidence asks for a process noise near the noise
     floor itself, the smoother then flattens the curves' peaks in time far less (the global and
     segment peaks of radial strain come much closer to the truth), but the estimate follows
     more of the data's noise (pixel RMSE rises, above the smoothed conventional analysis on the
     in-vivo case) and the bands of step 6 no longer cover (the estimate's noise, shared with the
     reference, escapes the excess-error moment); so it is not the default. One level for every
     frame must do both, and the cycle is not stationary; ``process_profile="data"`` (default) lets each
     frame interval's process sd follow the data's own acceleration at that time, never below the
     constant level (:func:`process_profile_from_data`: the damped second difference of the
     tracks' smooth motion, less the noise's share, by the model's own constant ``kappa``), given
     to the filters as a factor on Q per interval
     (:class:`sfem_filters.filtering.protocol.ProcessNoiseProfile`);
   * *element size*: 2.5 px (:class:`StrainRouteSettings`).
4. **Strain.** ``F = I + grad u`` with ``grad u`` the *recovered* gradient (default,
   ``strain="recovered"``, :func:`gradient_operators`): at each node the area-weighted mean of the
   constant gradients of the linear triangles around it (nodal averaging, Zienkiewicz & Zhu 1992),
   interpolated at each reference pixel by the shape functions. Why, by measurement (one case at
   SNR 30, the error budget of the strain work; ``strain="element"`` reproduces it): the
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
   (b) *the excess error* (what a smoother of this mesh and prior flattens, and the part of its
   noise that (a) misses: the phase texture is correlated over neighbouring pixels and frames),
   empirical Bayes by the method of moments (:mod:`sfem_filters.cardiac.strain_bands`): against
   the unsmoothed finite-difference gradient of the same tracks
   (:func:`sfem_filters.imaging.strain.displacement_gradient`, unbiased for the tracks but noisy),
   per curve (global and each segment), the mean over the curve's pixels of the *linearised*
   disagreement ``(F e) . ((G_fd - G) e)`` (:func:`linearised_disagreement`; the Green difference
   carries the noise's variance as a bias, which widened the bands as the SNR fell), whose
   square, less the noise variance left in the disagreement (the curve's own from its second
   differences in time, :func:`curve_noise_variance`, at the curve's level so that the noise's
   correlation over the pixels is in it, less the estimate's own smoothed variance: the estimate
   follows part of the same data's noise, the smoothed residual's ``R - H P_s H^T``), estimates the
   estimate's excess mean square error. Its variance is
   ``tau0^2 + k^2 m_t^2 + j^2 c_t^2`` (a constant part; one proportional to the curve's square, the
   bias of a smoothing scaling with what it flattens; and one proportional to the curve's bend ``c``,
   its second difference over the frames, :func:`curve_curvature`: a smoother's bias at a kink, such
   as the onset of a contraction, where the strain is still small but the estimate leads it; the
   data fit all three, so they choose the profile over the frames, :func:`discrepancy_variance`),
   one model for the global curve and one for each
   segment, partially pooled with the six segments' common model (:func:`curve_discrepancy`: a
   segment keeps its own model only as far as it differs from the others by more than its moments'
   noise explains, so one segment whose tracks carry a bias of their own does not widen the other
   five's bands); each pixel takes its segment's ``tau0``, ``k`` and ``j`` with its own estimate's
   value and bend (a pixel's own finite differences are far too noisy to tell). Reported as
   ``settings["discrepancy_sd"]``. With the resolution-aware operator (step 2) the tracks see the
   blurred field and the estimate does not, so the finite differences of the data are compared with
   those of the model's prediction of the data (``D U`` through :class:`ObservationScaling`): the
   disagreement is then the blurred error of the estimate, not the blur itself.

   ``Ecc_sd`` and ``Err_sd`` (and the curves' ``*_sd`` and bands) are the total; the smoother's
   own (with ``c``) stay beside as ``Ecc_sd_model``, ``Err_sd_model`` and the curves'
   ``*_sd_model``; the curves' ``*_reference`` are the reference the excess was measured against
   (the estimate plus the mean linearised disagreement: the tracks' finite-difference strain, with
   the blur compensated as above), so a user sees what the bands compared. What neither term can
   see: a bias that the tracks themselves carry (the reference shares it), such as the radial
   strain of the first pixel layers at the endocardium, which the tracks of the noise-free images
   already miss.

   (c) *where the data outrun the model*: after (a), frames whose normalised innovations stay
   above their 99.9% chi-square bound for :data:`NIS_EXCESS_MIN_S` (60 ms) or more in a row, even at the
   fitted level (:func:`sfem_filters.filtering.diagnostics.nis_excess_runs`, the run's length in frames from
   the frame interval: :func:`nis_excess_min_frames`), are frames where the data move
   faster than the model's process noise lets the estimate follow, so the strain there may lag
   the data by more than the bands hold. One warning names them (frames and ms) and
   ``settings["nis_excess_frames"]`` keeps them, beside ``settings["nis_per_row"]`` (each frame's
   NIS per observed row as the pass gives it, not divided by ``c``) and ``settings["nis_excess_min_frames"]``
   (the run's length in frames).

Units: pixels for points and displacements at the interface (x = column, y = row), SI inside
(the mesh in metres, from the case's pixel size); strain is a fraction; times in s.
"""
from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass, field, replace
from typing import ClassVar

import numpy as np
import scipy.sparse as sp

from .._validate import as_float_array, as_mask, integer, positive, user_stacklevel
from ..imaging.contours import reference_mask_mismatch, repair_myocardium_mask
from ..imaging.dense import check_resolution_px
from ..fem.mesh import TriMesh
from ..fem.observation import point_observation_matrix
from ..filtering.diagnostics import nis_excess_runs
from ..filtering.linearised import linearise
from ..filtering.memory import check_memory, covariance_interval
from ..filtering.safeguards import Safeguards
from ..filtering.smoother import kalman_forward, smooth_backward
from ..imaging.dense import DenseCase, LagrangianDisplacement, background_signal, phase_to_displacement
from ..imaging.strain import N_SEGMENTS, Z95, StrainEstimate, displacement_gradient, global_curve, green_strain, \
    json_list, mask_centre, project_strain, segment_labels
from ..resources import limits_blas_threads
from .border_data import BorderData, contour_landmark_tracks, guided_border_data, mask_border_data, mean_border_data
from .dense_model import INFORMATION_FLOOR, MESHES, PROCESS_FRACTIONS, PROCESS_PROFILES, RELAXATION_CYCLES, \
    NodalFitModel, build_dense_model, compliant_modulus, concentrated_log_evidence, nodal_fit, observation_points, \
    ObservationScaling, mask_noise_level_ml, observation_operator, phase_noise_level, phase_only_pass, \
    process_fraction_ml, process_profile_from_data, reference_mesh, temporal_noise_floor
from .measured import NOMINAL
from .strain_bands import STRAINS, _component_rows, _covariance_from_blocks, curve_noise_variance, \
    discrepancy_variance, element_gradient_operator, gradient_operators, linearised_disagreement, linearised_rows, \
    moment_mean_variance, noise_scale, point_variance, pooling_weights, strain_and_sd, curve_curvature, \
    excess_variance
# the contours route takes these rows from here (the same maths): re-exported
from .strain_bands import _covariance_from_rows, _curve_rows, _element_of, _gradient_rows  # noqa: F401

__all__ = ["StrainRouteSettings", "DenseStrain", "NodalFitModel", "reference_mesh", "observation_points",
           "nodal_fit", "compliant_modulus", "temporal_noise_floor", "build_dense_model", "element_gradient_operator",
           "linearised_rows", "strain_and_sd", "dense_strain", "MESHES", "INFORMATION_FLOOR",
           "RELAXATION_CYCLES", "Z95", "STRAINS", "gradient_operators", "point_variance", "discrepancy_variance",
           "noise_scale", "DenseRouteStrain", "linearised_disagreement", "curve_noise_variance", "curve_discrepancy",
           "PROCESS_FRACTIONS", "process_fraction_ml", "concentrated_log_evidence", "observation_operator",
           "ObservationScaling", "border_masks_data", "phase_noise_level", "PHASE_NOISE_LEVELS",
           "BORDER_CORRESPONDENCES", "PROCESS_PROFILES",
           "process_profile_from_data", "image_settings", "route_settings", "dense_case_strain",
           "masks_move", "masks_can_be_fused", "unusable_mask_frames", "NIS_EXCESS_MIN_S", "nis_excess_min_frames"]


#: Shortest time (s) the innovations stay above their 99.9% bound, even at the fitted noise level, for the route
#: to name the frames a lag of the model behind the data (step 6 c): about an isovolumic contraction (50-60 ms),
#: the shortest phase of the cycle whose motion a lagging estimate misreads; 4 frames at DENSE-Sim's 15 ms.
NIS_EXCESS_MIN_S = 0.06


def nis_excess_min_frames(frame_interval_s: float) -> int:
    """Frames in a row that make :data:`NIS_EXCESS_MIN_S` at this frame interval (s), never fewer than 2.

    One frame above its 99.9% bound happens by chance once in a thousand frames; two in a row, once in a
    million. So a sparse sequence (45 ms frames: 2) is checked over the same time as a dense one (15 ms: 4).
    """
    T = positive("frame_interval_s", frame_interval_s, "s")
    return max(2, int(np.ceil(NIS_EXCESS_MIN_S / T - 1e-9)))


#: How the phase data's noise level is set beside the masks (``StrainRouteSettings.phase_noise_level``).
PHASE_NOISE_LEVELS = ("stated", "evidence")
#: How each border node's place along the masks' border is found (``StrainRouteSettings.border_correspondence``).
BORDER_CORRESPONDENCES = ("phase", "landmarks")


@dataclass(frozen=True)
class StrainRouteSettings:
    """Settings of the DENSE route (each with a stated principle; see the module docstring).

    Attributes
    ----------
    mesh : {"gmsh", "pixels"}
        Mesh chosen apart from the pixels, or one node per pixel (its border half a pixel inside the
        mask's, so only with the point observation, ``resolution_px=1``).
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
    process_fraction : float or None
        Process noise per frame as a fraction of the temporal noise floor: 0.1 (default), the
        library's rule for measured data (:func:`sfem_filters.cardiac.measured.build_model`); None:
        chosen by type-II maximum likelihood among :data:`PROCESS_FRACTIONS`
        (:func:`process_fraction_ml`; module docstring, step 3, says what it trades).
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
        Add the excess-error (model-discrepancy) variance (:func:`discrepancy_variance`, step 6 b) to the
        smoother's own variance in the reported sd and bands.
    resolution_px : float
        Acquired resolution of the images the tracks come from, in reconstructed pixels (>= 1; the
        acquisition's pixel, field of view over acquired matrix, over the image's pixel): the
        observation operator blurs the model's displacement by the acquisition's point spread
        (:func:`observation_operator`, step 2). 1 (default): no blur beyond the pixel, point
        interpolation. Callers with images take it from the acquisition
        (:attr:`sfem_filters.imaging.DenseCase.resolution_px`), never from a fit to a case.
    border_masks : bool
        Also observe the myocardium masks of every frame (:func:`dense_strain` ``masks``): each
        border node's motion across the border (where ``border_correspondence`` places it), with the
        contours route's sd rule, stacked with the phase data in one model (module docstring, step 2,
        *fused with the masks*). Default False: the phase alone.
    mask_noise_level : {"stated", "evidence"}
        With ``border_masks``: the level of the masks' data beside the phase data's. ``"stated"``
        (default): their sd by the contours route's rule (a binary border's quantisation or the data's
        own temporal noise floor). ``"evidence"``: that variance times the factor of largest
        evidence of the fused model among :data:`~sfem_filters.cardiac.dense_model.MASK_LEVELS`
        (:func:`~sfem_filters.cardiac.dense_model.mask_noise_level_ml`, one filter pass each, the
        common level profiled out), so that the masks, too, are weighed by the noise they show.
    border_correspondence : {"phase", "landmarks"}
        With ``border_masks``: how each border node's place along the masks' border is found.
        ``"phase"`` (default): named by the phase data's own smoothed motion (one filter and RTS
        pass of the phase data alone), the datum the mask border's offset across itself there
        (:func:`sfem_filters.cardiac.border_data.guided_border_data`). ``"landmarks"``: landmarks
        tracked through the masks by bending-energy matching, the contours route's data
        (:func:`sfem_filters.cardiac.border_data.mask_border_data`; the route's default before the
        validation page measured both: along a smooth border the landmarks slide).
    border_starts : int
        With ``border_correspondence="landmarks"``: the masks' border data are the mean over this
        many contour start angles spread evenly about the cavity
        (:func:`sfem_filters.cardiac.border_data.mean_border_data`), so that they do not depend on
        where the contours happen to start, i.e. on how the heart lies on the image grid. Default
        1: the start at the +x direction alone.
    process_profile : {"data", "constant"}
        How the process noise varies over the frame intervals. ``"data"`` (default): each
        interval's process sd the larger of the level of ``process_fraction`` and the one the
        data's own smooth acceleration at that time asks for (:func:`process_profile_from_data`,
        module docstring step 3): a short systole and early filling move fast, diastasis barely,
        and one level must flatten the one or follow the noise in the other. ``"constant"``: that
        level every interval (the route's default before the validation page measured both).
    phase_noise_level : {"stated", "evidence"}
        With ``border_masks``: the level at which the phase data join the masks. ``"stated"``
        (default): the phase data's sd as the route states it (step 3), the masks' by the contours
        route's rule. ``"evidence"``: the phase data's covariances (R, process, initial) times
        their own maximum-likelihood level from one filter pass of the phase data alone
        (:func:`phase_noise_level`), so that each source is weighed by the noise it shows.
    """

    mesh: str = "gmsh"
    element_px: float = 2.5
    effects: tuple = ()
    E: float | None = None
    nu: float = NOMINAL["nu"]
    alpha: float | None = None
    process_fraction: float | None = 0.1
    start_deg: float = 0.0
    centre: tuple | None = None
    strain: str = "recovered"
    noise_scale: bool = True
    discrepancy: bool = True
    resolution_px: float = 1.0
    border_masks: bool = False
    phase_noise_level: str = "stated"
    process_profile: str = "data"
    border_starts: int = 1
    border_correspondence: str = "phase"
    mask_noise_level: str = "stated"

    def __post_init__(self):
        if self.mesh not in MESHES:
            raise ValueError(f"mesh: expected one of {MESHES}, got {self.mesh!r}")
        if self.strain not in STRAINS:
            raise ValueError(f"strain: expected one of {STRAINS}, got {self.strain!r}")
        for name in ("noise_scale", "discrepancy", "border_masks"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise TypeError(f"{name}: expected True or False, got {getattr(self, name)!r}")
        if self.process_profile not in PROCESS_PROFILES:
            raise ValueError(f"process_profile: expected one of {PROCESS_PROFILES}, got {self.process_profile!r}")
        if self.phase_noise_level not in PHASE_NOISE_LEVELS:
            raise ValueError(f"phase_noise_level: expected one of {PHASE_NOISE_LEVELS}, got {self.phase_noise_level!r}")
        if self.phase_noise_level == "evidence" and not self.border_masks:
            raise ValueError("phase_noise_level: 'evidence' weighs the phase data against the masks; it needs "
                             "border_masks=True (alone, a common level changes no estimate: noise_scale does that)")
        if self.mask_noise_level not in PHASE_NOISE_LEVELS:
            raise ValueError(f"mask_noise_level: expected one of {PHASE_NOISE_LEVELS}, got {self.mask_noise_level!r}")
        if self.mask_noise_level == "evidence" and not self.border_masks:
            raise ValueError("mask_noise_level: 'evidence' weighs the masks against the phase data; it needs "
                             "border_masks=True")
        positive("element_px", self.element_px, "pixels")
        object.__setattr__(self, "border_starts", integer("border_starts", self.border_starts, 1))
        if self.border_starts > 1 and not self.border_masks:
            raise ValueError(f"border_starts: averages the masks' border data over contour starts; it needs "
                             f"border_masks=True, got border_starts={self.border_starts} without the masks")
        if self.border_correspondence not in BORDER_CORRESPONDENCES:
            raise ValueError(f"border_correspondence: expected one of {BORDER_CORRESPONDENCES}, got "
                             f"{self.border_correspondence!r}")
        if self.border_starts > 1 and self.border_correspondence != "landmarks":
            raise ValueError(f"border_starts: averages tracked landmarks over contour starts; it needs "
                             f"border_correspondence='landmarks', got border_starts={self.border_starts} with "
                             f"{self.border_correspondence!r} (guided border data have no contour start)")
        object.__setattr__(self, "resolution_px", check_resolution_px(self.resolution_px))
        if self.mesh == "pixels" and self.resolution_px > 1:
            raise ValueError(f"resolution_px: the point spread's observation needs the mesh to reach the mask's own "
                             f"border (mesh='gmsh'); the node-per-pixel mesh ends at the outer pixels' centres, half a "
                             f"pixel inside it, so the point spread would read that half pixel of tissue as background "
                             f"(measured: a spurious radial strain of several percent at the first frames). Give "
                             f"resolution_px=1 with mesh='pixels', got {self.resolution_px:g}")
        if self.E is not None:
            positive("E", self.E, "Pa")
        if not 0 < self.nu < 0.5:
            raise ValueError(f"nu: expected a Poisson's ratio in (0, 0.5), got {self.nu!r}")
        if self.process_fraction is not None:
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
    uncertainty, the smoother's variance plus the excess-error variance (module docstring,
    step 6); ``Ecc_sd_model`` and ``Err_sd_model`` (F, P) hold the smoother's alone, as do the
    curves' ``*_sd_model`` entries; the curves' ``*_reference`` the finite-difference reference their
    excess error was measured against (module docstring, step 6).
    """

    Ecc_sd_model: np.ndarray = field(repr=False)
    Err_sd_model: np.ndarray = field(repr=False)

    def to_dict(self) -> dict:
        """The strain report's JSON names, plus ``strain.Ecc_sd_model`` and ``strain.Err_sd_model``."""
        out = super().to_dict()
        for q in ("Ecc", "Err"):
            out["strain"][f"{q}_sd_model"] = json_list(getattr(self, f"{q}_sd_model"))
        return out


def curve_discrepancy(diffs, estimates, details: bool = False, curvature: bool = True, model_sd=None):
    """(tau0^2, k^2, j^2) of the global curve (row 0) and of each segment (the others), the segments partially pooled.

    Each curve's noise variance is its own (:func:`curve_noise_variance` of its disagreement), and so
    is its bend (:func:`curve_curvature` of its estimate). With ``model_sd``, the disagreement's noise
    variance at frame t is that less the estimate's own variance ``model_sd_t^2`` (clipped at 0): the
    estimate is made from the same data as the reference and follows part of its noise, so the noise
    left in ``reference - estimate`` is the reference's less the estimate's (the smoothed residual's
    covariance ``R - H P_s H^T``); subtracting the reference's whole noise variance understated the
    excess by ``model_sd^2``, the more so the closer the smoother follows the data (at a coarser frame
    rate: the validation pages of the bands and of the variants measure both rules on DENSE-Sim). The
    segments' excess is fitted twice by
    :func:`discrepancy_variance`: once to the moments of all their frames (the pooled model; one
    segment's frames alone give a noisy moment, which the non-negativity clips upwards) and once to
    each segment's own. Each segment then takes ``w_g`` of its own parameters and ``1 - w_g`` of the
    pooled (:func:`pooling_weights`, random effects by moments, with each segment's mean excess's
    sampling variance from its frames' moments allowing for their serial correlation,
    :func:`moment_mean_variance`): segments that differ no more than their moments' noise explains
    share the pooled model; one whose tracks carry a bias of their own (a wider disagreement than the
    others by far more than its noise) keeps it, instead of widening the other five segments' bands
    by it.

    Parameters
    ----------
    diffs, estimates : (F, 1 + S) arrays
        Per curve (global, then the S segments): the mean linearised disagreement
        (:func:`linearised_disagreement`) and the estimated curve, per frame.
    details : bool
        Also return a dict with the pooled segments' ``(tau0^2, k^2, j^2)`` and the weights ``w_g``.
    curvature : bool
        Include the bend term ``j^2 c_t^2`` (False: ``j^2 = 0``, the rule before it).
    model_sd : (F, 1 + S) array, optional
        The smoother's own sd of each curve per frame (with its noise scale), in the units of
        ``diffs``; None: the reference's whole noise variance is subtracted (the rule before).
    """
    d = as_float_array("diffs", diffs, shape=(None, None), allow_nan=True)
    m = as_float_array("estimates", estimates, shape=d.shape, allow_nan=True)
    own_var = (np.zeros_like(d) if model_sd is None
               else as_float_array("model_sd", model_sd, shape=d.shape, allow_nan=True) ** 2)
    c = curve_curvature(m) if curvature else np.zeros_like(m)           # each curve's own bend (columns)
    tau = np.zeros((d.shape[1], 3))
    usable = [g for g in range(d.shape[1]) if np.sum(np.isfinite(d[1:-1, g] - 0.5 * (d[:-2, g] + d[2:, g]))) >= 1]
    v = {g: np.maximum(curve_noise_variance(d[:, g]) - own_var[:, g], 0.0) for g in usable}   # (F,) each
    if 0 in v:
        tau[0] = discrepancy_variance(d[:, 0], m[:, 0], v[0], curvature and c[:, 0])
    segs = [g for g in usable if g > 0]
    pooled, weights = np.zeros(3), np.zeros(d.shape[1] - 1)
    if segs:
        pooled = np.array(discrepancy_variance(np.concatenate([d[:, g] for g in segs]),
                                               np.concatenate([m[:, g] for g in segs]),
                                               np.concatenate([v[g] for g in segs]),
                                               curvature and np.concatenate([c[:, g] for g in segs])))
        tau[1:] = pooled
        own = np.array([discrepancy_variance(d[:, g], m[:, g], v[g], curvature and c[:, g]) for g in segs])
        means = np.array([[1.0, np.nanmean(m[:, g] ** 2), np.nanmean(c[:, g] ** 2)] for g in segs])
        w = pooling_weights(np.sum(own * means, axis=1), means @ pooled,
                            [moment_mean_variance(d[:, g] ** 2 - v[g]) for g in segs])
        for o, g, wg in zip(own, segs, w):
            tau[g] = wg * o + (1 - wg) * pooled
            weights[g - 1] = wg
    if details:
        return tau, {"pooled": pooled, "weights": weights}
    return tau


def border_masks_data(masks, reference_mask, n_frames: int, mesh: TriMesh, pixel_size_m: float,
                      starts: int = 1, guide_px=None) -> BorderData:
    """The myocardium masks as border-node data on the DENSE route's mesh (module docstring, step 2).

    With ``guide_px`` (F, n_nodes, 2), the displacement of every node in pixels (the phase data's
    own smoothed motion, :func:`sfem_filters.cardiac.dense_model.phase_only_pass`): each border
    node's datum is the frame's mask border's offset across itself at the point the guide names
    (:func:`sfem_filters.cardiac.border_data.guided_border_data`; ``starts`` must be 1). Without it,
    the contours route's data exactly (:func:`sfem_filters.cardiac.border_data.mask_border_data`,
    its default landmark spacing, least landmarks and sd rule: the larger of the mask's
    quantisation and the landmarks' own temporal noise floor across the border; no number chosen
    here); with ``starts > 1``, their mean over that many contour start angles spread evenly about
    the cavity (:func:`sfem_filters.cardiac.border_data.mean_border_data`,
    ``StrainRouteSettings.border_starts``).

    Parameters
    ----------
    masks : (F + 1, H, W) or (F, H, W) bool array
        Myocardium masks: the reference (``reference_mask``) then each frame's, or each frame's
        alone (the reference is then prepended).
    reference_mask : (H, W) bool array
        The reference myocardium, meshed into ``mesh``.
    n_frames : int
        F, the frames of the phase data.
    mesh : TriMesh
        The route's mesh of ``reference_mask`` (m).
    pixel_size_m : float
    """
    m, _, _ = _fusion_masks(masks, reference_mask, n_frames, every_frame=guide_px is None)
    k = integer("starts", starts, 1)
    if guide_px is not None:
        if k > 1:
            raise ValueError(f"starts: guided border data have no contour start; expected 1, got {k}")
        return guided_border_data(mesh, m, guide_px, pixel_size_m)
    data = [mask_border_data(mesh, contour_landmark_tracks(m), pixel_size_m)]   # warns of a mended mask
    if k > 1:
        mended = np.stack([repair_myocardium_mask(f, f"masks[{t}]")[0] for t, f in enumerate(m)])
        data += [mask_border_data(mesh, contour_landmark_tracks(mended, start_deg=360.0 * j / k), pixel_size_m)
                 for j in range(1, k)]                                          # the same masks, already mended
    return data[0] if k == 1 else mean_border_data(data)


def _fusion_masks(masks, reference_mask, n_frames: int, every_frame: bool = False) -> tuple:
    """The masks to fuse as (F + 1, H, W), the reference first, checked (each error names ``masks``), the
    indices in that stack of the frames' masks that cannot be mended (left out), and whether the reference
    was prepended (``masks`` given as the frames' alone, (F, H, W)).

    The reference's and at least one frame's mask (``every_frame``: every frame's, for landmarks tracked
    from frame to frame) must be rings that can be mended (:func:`unusable_mask_frames`); checked here,
    before any costly pass. The errors index the masks as given: with ``masks`` of (F, H, W), frame f is
    ``masks[f]`` and the reference is ``reference_mask``.
    """
    ref = as_mask("reference_mask", reference_mask, 2, nonempty=True)
    F = int(n_frames)
    m = as_mask("masks", masks, 3)
    if m.shape[1:] != ref.shape or m.shape[0] not in (F, F + 1):
        raise ValueError(f"masks: expected the myocardium masks of the {F} frames, (F + 1, H, W) = ({F + 1}, "
                         f"{ref.shape[0]}, {ref.shape[1]}) with the reference first or (F, H, W) = ({F}, "
                         f"{ref.shape[0]}, {ref.shape[1]}), got shape {m.shape}")
    if m.shape[0] == F + 1 and not np.array_equal(m[0], ref):
        raise ValueError("masks: expected masks[0] to be the reference mask (the one whose pixels are the tracks' "
                         "points), got a different mask")
    shift = int(m.shape[0] == F)                          # (F, H, W): the user's masks[f] is the stack's f + 1
    if shift:
        m = np.concatenate([ref[None], m])
    if not m[1:].any():                 # a frame without myocardium is one whose mask cannot be read (left out)
        raise ValueError("masks: expected myocardium in the frames' masks, got none in any")
    bad, why = unusable_mask_frames(m, offset=shift)
    frames = [f for f in bad if f > 0]
    if 0 in bad:
        where = "reference_mask" if shift else "masks[0]"
        raise ValueError(f"masks: expected the reference mask ({where}) to be one ring around one cavity ({why})")
    if len(frames) == F or (every_frame and frames):
        given = [f - shift for f in frames]
        raise ValueError(f"masks: expected {'every' if every_frame else 'at least one'} frame's mask that can be made "
                         f"one ring around one cavity, got {'none' if len(frames) == F else f'masks{given} not'} "
                         f"({why})")
    return m, frames, bool(shift)


#: Longest frame interval (s) a cine sequence may have: beyond it the times are taken to be in another unit.
MAX_FRAME_INTERVAL_S = 1.0


def _check_frame_times(frame_times_s, n_frames: int, name: str = "tracks.frame_times_s",
                       after_zero: bool = False) -> np.ndarray:
    """``frame_times_s`` checked (both routes): (F,) finite times (s) after the encoding, >= 0 (> 0 with
    ``after_zero``: the reference at t = 0 is not a frame), strictly increasing, with frame intervals of at
    most :data:`MAX_FRAME_INTERVAL_S` (times in ms are the usual slip). ValueError naming ``name`` otherwise."""
    t = as_float_array(name, frame_times_s, shape=(int(n_frames),))
    if np.any(t <= 0 if after_zero else t < 0) or np.any(np.diff(t) <= 0):
        raise ValueError(f"{name}: expected times (s) after the encoding, {'> 0' if after_zero else '>= 0'} and "
                         f"strictly increasing, got {np.round(t[:6], 4).tolist()}{' ...' if len(t) > 6 else ''}")
    if len(t) > 1 and float(np.median(np.diff(t))) > MAX_FRAME_INTERVAL_S:
        raise ValueError(f"{name}: expected seconds (a cine frame interval is well under "
                         f"{MAX_FRAME_INTERVAL_S:g} s), got a median interval of {float(np.median(np.diff(t))):g}: "
                         "milliseconds?")
    return t


@limits_blas_threads
def dense_strain(tracks: LagrangianDisplacement, reference_mask, pixel_size_m: float,
                 settings: StrainRouteSettings | None = None, progress=None, background=None,
                 masks=None) -> DenseRouteStrain:
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
    background : BackgroundSignal, optional
        The complex signal around the myocardium at each frame
        (:func:`sfem_filters.imaging.dense.background_signal`), for the observation operator when
        ``settings.resolution_px > 1``; None: a dark background.
    masks : (F + 1, H, W) or (F, H, W) bool array, optional
        The myocardium masks of the reference and every frame (or of every frame), required with
        ``settings.border_masks`` (and only then): their border nodes' motion across the border
        is stacked with the phase data (:func:`border_masks_data`). With every frame's alone, the
        checks' errors name your index (``masks[f]``, frame f); later warnings index the stack with
        ``reference_mask`` prepended (frame f is ``masks[f + 1]`` there) and say so.

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
    _check_frame_times(tracks.frame_times_s, tracks.displacement.shape[0])
    s = positive("pixel_size_m", pixel_size_m, "m")
    mask = np.asarray(reference_mask, bool)
    rows, cols = np.nonzero(mask)
    X = tracks.points
    if len(rows) != len(X) or not np.array_equal(np.column_stack([cols, rows]).astype(float), X):
        raise ValueError("reference_mask: expected the mask whose pixels (row-major) are tracks.points")
    if cfg.border_masks and masks is None:
        raise ValueError("masks: expected the myocardium masks of the reference and every frame, (F + 1, H, W), with "
                         "settings.border_masks=True, got None")
    if masks is not None and not cfg.border_masks:
        raise ValueError("masks: given, but settings.border_masks is False; set border_masks=True to observe them "
                         "(or leave masks out)")
    centre = mask_centre(mask) if cfg.centre is None else np.asarray(cfg.centre, float)
    tracks, n_stray = _without_stray_pixels(tracks, mask)
    if n_stray:
        say(f"{n_stray} reference pixel(s) outside the mended ring: not observed; their strain is the nearest "
            "tissue's")
    say(f"meshing the reference myocardium ({cfg.mesh}, {cfg.element_px:g} px)")
    mesh = reference_mesh(mask, s, cfg.mesh, cfg.element_px)
    border, guide, c_phase, mismatch = None, None, None, None
    if cfg.border_masks:
        masks, unusable, frames_only = _fusion_masks(     # checked before any costly pass
            masks, mask, tracks.displacement.shape[0], every_frame=cfg.border_correspondence == "landmarks")
        # the masks' zero of the wall's thickness against the phase's, from the frames whose masks are read
        mismatch = reference_mask_mismatch(masks, exclude=unusable)
        if mismatch:
            stack = (" (indices of the masks with reference_mask prepended: your masks[f] is masks[f + 1] here)"
                     if frames_only else "")
            warnings.warn(f"{mismatch}; the masks' borders join the phase data{stack}", RuntimeWarning,
                          stacklevel=user_stacklevel())
    if cfg.border_masks and cfg.border_correspondence == "phase":
        say("the phase data alone (one filter and smoother pass): where each border node is along the masks' "
            "border")
        # with the process level still to be chosen (by evidence, with the masks' rows), the guide takes the default
        q_guide = StrainRouteSettings.process_fraction if cfg.process_fraction is None else cfg.process_fraction
        c_phase, guide = phase_only_pass(mesh, tracks, s, replace(cfg, process_fraction=q_guide), background,
                                         smooth=True)
        if cfg.process_fraction is None:
            c_phase = None                   # the level is re-measured below at the chosen process noise
        say("the myocardium masks' borders at those points: their offset across the border joins the phase data")
        border = border_masks_data(masks, mask, tracks.displacement.shape[0], mesh, s, guide_px=guide)
    elif cfg.border_masks:
        say("tracking the myocardium masks' borders (bending energy, Eqs. 35-37): their motion across the border "
            "joins the phase data")
        border = border_masks_data(masks, mask, tracks.displacement.shape[0], mesh, s, starts=cfg.border_starts)
    q_table = None
    if cfg.process_fraction is None:
        say(f"choosing the process noise by its evidence ({len(PROCESS_FRACTIONS)} filter passes)")
        q_ml, q_table = process_fraction_ml(mesh, tracks, s, cfg, progress=say, background=background, border=border)
        cfg = replace(cfg, process_fraction=q_ml)
    if cfg.phase_noise_level != "evidence":
        c_phase = 1.0
    elif c_phase is None:
        say("the phase data's own noise level by its evidence (one filter pass without the masks)")
        c_phase = phase_noise_level(mesh, tracks, s, cfg, background)
    mask_table, f_mask = None, 1.0
    if cfg.mask_noise_level == "evidence":
        say("the masks' noise level beside the phase data's by their evidence (a filter pass per candidate, three "
            "or more)")
        f_mask, mask_table = mask_noise_level_ml(mesh, tracks, s, cfg, border, c_phase, background, progress=say)
        border = replace(border, R=border.R * f_mask)
    say(f"mesh: {mesh.n_nodes} nodes, {mesh.n_elements} triangles; building the model")
    model, y, info, Xin = build_dense_model(mesh, tracks, s, cfg, background, border, phase_scale=c_phase)
    F, P = tracks.displacement.shape[:2]
    # The material is fixed, so the model is linear and its MAP trajectory is one Kalman-RTS pass (what an
    # iterated smoother with no parameters returns, after two passes): one forward pass keeps what both
    # backward passes need, the means' (the strain's linearisation point) and then the covariances' (step 5)
    observed = int(np.sum(~np.isnan(y)))
    check_memory(model.dim_state, F, covariance=True, observed=observed)
    lin = linearise(model, np.zeros((F, model.dim_state)))
    if lin.n_params:                       # a material to estimate would make the model nonlinear in it
        raise RuntimeError(f"dense_strain: expected a model without static parameters (the material fixed), got "
                           f"{lin.n_params}; the one-pass smoother is exact only for a linear model")
    say(f"smoothing {F} frames ({model.dim_state} states): one Kalman filter pass, then the smoothed means and "
        "the covariances of the linearised strain")
    # the NIS is checked after the pass, at the route's ML noise scale (step 6 a; nis_excess_runs), not as given
    fwd = kalman_forward(lin, y, safeguards=Safeguards(), monitor_nis=False, store="covariance",
                         every=covariance_interval(lin.dim_state, F, observed=observed))
    nr = model.n_restart
    states = lin.to_model(smooth_backward(lin, fwd).smoothed[:, :nr])      # xi, the pass's coordinates, to the model's
    n = model.dim_x // 2
    free = model.dofmap.free
    U = np.zeros((F, mesh.n_dofs))
    U[:, free] = states[:, :n]
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
    say("covariances of the linearised strain (backward pass)")

    def on_state(op):
        op = sp.csr_matrix(op)[:, free]
        return lin.output_in_xi(sp.hstack([op, sp.csr_matrix((op.shape[0], nr - n))], format="csr"))

    outputs = {"gradient": on_state(_component_rows(ops)), "curves": on_state(curve_rows)}
    sm = smooth_backward(lin, fwd, outputs=outputs, covariance=True)
    c_ml = noise_scale(sm.nis, sm.n_obs) if cfg.noise_scale else 1.0         # step 6 (a)
    times = np.asarray(tracks.frame_times_s, float)
    interval = float(np.median(np.diff(times)))                       # F >= 3 (build_dense_model), increasing
    run = nis_excess_min_frames(interval)
    excess = nis_excess_runs(sm.nis, sm.n_obs, scale=c_ml, min_frames=run)
    if excess:
        spans = ", ".join(f"{a}-{b} ({1e3 * times[a]:.0f}-{1e3 * times[b]:.0f} ms)" for a, b in excess)
        warnings.warn(f"dense_strain: the data move faster than the model's motion allows at frames {spans} after "
                      f"the encoding (their innovations stay above the 99.9% bound for {run} frames or more in a row, "
                      f"{1e3 * run * interval:.0f} ms, even at the fitted noise level): the strain there may lag the "
                      f"data, its peaks flattened, by more than the 95% bands hold; read those frames with care (JSON: "
                      f"settings.nis_excess_frames)", RuntimeWarning, stacklevel=user_stacklevel())
    C = c_ml * _covariance_from_blocks(sm.variances["gradient"], ops[0].shape[0])       # (F, m, 4, 4)
    E = green_strain(grad)
    ecc, err, ecr = project_strain(E, X, centre)
    sd_cc = np.sqrt(point_variance(weights, a_cc, C))
    sd_rr = np.sqrt(point_variance(weights, a_rr, C))
    k = 2 * (1 + N_SEGMENTS)
    vc = sm.variances["curves"].reshape(F, F, k)[np.arange(F), np.arange(F)]    # frame t's rows at frame t
    sd_curves = np.sqrt(c_ml * np.maximum(vc, 0.0))                             # (F, 14)
    # step 6 (b): the excess error, against the unsmoothed finite-difference strain of the same tracks, linearised
    g_ref = displacement_gradient(X, tracks.displacement)
    if cfg.resolution_px > 1:
        # the tracks see the blurred field: compare like with like, the finite differences of the data against
        # those of the model's prediction of the data (D U / n), i.e. the blurred error, moved onto our gradient
        Db, scaling = observation_operator(mesh, Xin, tracks, s, cfg.resolution_px, background)
        pred = scaling.predict((Db @ U.T).T.reshape(F, P, 2) / s)
        g_ref = g_ref - displacement_gradient(X, pred) + grad
    diffs = {"Ecc": linearised_disagreement(g_ref, grad, a_cc), "Err": linearised_disagreement(g_ref, grad, a_rr)}
    means = {"Ecc": ecc, "Err": err}
    pixel_sd = {"Ecc": sd_cc, "Err": sd_rr}
    glob, segs, total_sd, tau_report = {}, {}, {}, {}
    for q_i, q in enumerate(("Ecc", "Err")):
        m_all = np.stack([means[q][:, g].mean(axis=1) if g.size else np.full(F, np.nan) for g in groups], axis=1)
        sd_all = sd_curves[:, q_i * (1 + N_SEGMENTS):(q_i + 1) * (1 + N_SEGMENTS)]
        d_all = np.stack([global_curve(diffs[q][:, g]) if g.size else np.full(F, np.nan) for g in groups], axis=1)
        tau, pool = (curve_discrepancy(d_all, m_all, details=True, model_sd=sd_all) if cfg.discrepancy
                     else (np.zeros((len(groups), 3)), {"pooled": np.zeros(3), "weights": np.zeros(N_SEGMENTS)}))
        # a pixel takes its segment's excess (its own finite differences are far too noisy to tell), with its
        # own estimate's value and bend
        tp = tau[1:][labels]
        total_sd[q] = np.sqrt(pixel_sd[q] ** 2 + excess_variance(tp, means[q]))
        tau_report[q] = {"global": np.sqrt(tau[0]).tolist(), "segments": np.sqrt(tau[1:]).tolist(),
                         "segments_pooled": np.sqrt(pool["pooled"]).tolist(),
                         "segment_weights": np.asarray(pool["weights"], float).tolist()}
        for d, sl in ((glob, 0), (segs, slice(1, None))):
            mu, sd_m = m_all[:, sl].T, sd_all[:, sl].T
            sd = np.sqrt(sd_m ** 2 + (excess_variance(tau[1:], mu.T).T if d is segs else excess_variance(tau[0], mu)))
            d[q], d[f"{q}_sd"], d[f"{q}_lo"], d[f"{q}_hi"] = mu, sd, mu - Z95 * sd, mu + Z95 * sd
            d[f"{q}_sd_model"] = sd_m
            d[f"{q}_reference"] = (m_all + d_all)[:, sl].T      # what the excess error was measured against
    Dp = point_observation_matrix(mesh, Xin)
    disp_px = (Dp @ U.T).T.reshape(F, P, 2) / s
    seconds = time.perf_counter() - t0
    edges = np.linalg.norm(np.diff(mesh.nodes[mesh.elements][:, [0, 1, 2, 0]], axis=1), axis=2).mean() / s
    settings_out = {**asdict(cfg), **info, "n_nodes": mesh.n_nodes, "n_elements": mesh.n_elements,
                    "element_px_mean_edge": float(edges), "dim_state": int(model.dim_state),
                    "material": "fixed, not estimated: fixed_E_Pa is compliant_modulus (unless given), a tissue soft "
                                "enough that the data, not a stiffness nobody measured, set the motion (no stiffness "
                                "estimate); nu nominal",
                    "estimator": "Kalman filter and RTS smoother (material fixed: a linear model), one forward pass for the "
                                 "means and the covariances",
                    "strain": ("Green-Lagrange of the recovered (nodal-average) gradient" if cfg.strain == "recovered"
                               else "Green-Lagrange of the linear triangles' element gradient"),
                    "sd": "delta method at the posterior mean, full smoothed covariance of U"
                          + (" (x the ML noise scale)" if cfg.noise_scale else "")
                          + (", plus the excess error variance against the linearised unsmoothed "
                             "finite-difference strain, less its noise variance (the reference's, less the "
                             "estimate's own)" if cfg.discrepancy else ""),
                    "noise_scale_ml": c_ml,
                    "reference_pixels_not_observed": int(n_stray),
                    "reference_mask_mismatch": mismatch,
                    "nis_per_row": (np.asarray(sm.nis, float) / np.maximum(np.asarray(sm.n_obs, float), 1)).tolist(),
                    "nis_excess_frames": [[int(a), int(b)] for a, b in excess], "nis_excess_min_frames": run,
                    "process_fraction_evidence": ({f"{k:g}": v for k, v in q_table.items()} if q_table
                                                  else "fixed by the settings"),
                    "mask_noise_scale": f_mask,
                    "mask_noise_evidence": ({f"{k:g}": v for k, v in mask_table.items()} if mask_table
                                            else "the masks at their stated level" if cfg.border_masks
                                            else "no masks"),
                    "discrepancy_sd": {"what": "[tau0 (fraction), k (relative), j (dimensionless)], tau_t^2 = tau0^2 + "
                                               "k^2 m_t^2 + j^2 c_t^2, c the curve's second difference over the "
                                               "frames; "
                                               "one model for the global curve; segments: one per segment (6 rows), "
                                               "segment_weights of its own fit and the rest from the six segments' "
                                               "pooled fit (segments_pooled)",
                                       **tau_report}}
    say(f"the route's estimate and bands in {seconds:.1f} s")
    return DenseRouteStrain(points=X.copy(), frame_times_s=np.asarray(tracks.frame_times_s, float).copy(),
                            centre=np.asarray(centre, float), start_deg=float(cfg.start_deg), labels=labels, Ecc=ecc,
                            Err=err, Ecr=ecr, Ecc_sd=total_sd["Ecc"], Err_sd=total_sd["Err"], global_curves=glob,
                            segment_curves=segs, displacement=disp_px, seconds=seconds, settings=settings_out,
                            mesh=mesh, Ecc_sd_model=sd_cc, Err_sd_model=sd_rr)


def _without_stray_pixels(tracks: LagrangianDisplacement, reference_mask) -> tuple:
    """The tracks with the data of the reference pixels that the mask's repair removed set missing, and how many.

    A stray piece of the reference mask (a pixel or two apart from the ring,
    :func:`sfem_filters.imaging.repair_myocardium_mask`) is not meshed: its pixel centre lies outside
    the mesh, and observing its phase at the nearest boundary point would put another place's motion
    there. So it is not observed (NaN, as an untracked point); its strain is still reported, at that
    nearest point, and scored.
    """
    mask = np.asarray(reference_mask, bool)
    try:
        repaired, changes = repair_myocardium_mask(mask, "reference_mask")
    except ValueError:
        return tracks, 0                  # not mendable: the mesher's own error names the mask
    rows, cols = np.nonzero(mask)
    stray = ~repaired[rows, cols]
    if not stray.any():
        return tracks, 0
    disp = np.array(tracks.displacement, float)
    disp[:, stray] = np.nan
    conf = np.array(tracks.confidence, float)
    conf[:, stray] = np.nan
    sd = np.array(tracks.sd, float)
    sd[:, stray] = np.nan
    psd = np.array(tracks.pixel_sd, float)
    psd[:, stray] = np.nan
    return replace(tracks, displacement=disp, sd=sd, pixel_sd=psd, confidence=conf,
                   n_untracked=int(np.count_nonzero(np.isnan(disp[..., 0])))), int(stray.sum())


def masks_move(masks) -> bool:
    """Whether the myocardium masks of the frames differ from the reference (so their borders carry motion).

    Parameters
    ----------
    masks : (F + 1, H, W) bool array
        The reference mask (index 0) then each frame's.

    Returns
    -------
    bool
        False when every frame's mask is the reference's (one mask given for all frames: its
        borders would say the wall never moves).
    """
    m = as_mask("masks", masks, ndim=3)
    return bool(np.any(m[1:] != m[:1]))


def unusable_mask_frames(masks, offset: int = 0) -> tuple:
    """The masks that cannot be made one ring around one cavity, and the first reason.

    Parameters
    ----------
    masks : (F + 1, H, W) bool array
        The reference mask (index 0) then each frame's.
    offset : {0, 1}
        Subtracted from a frame's index where the reason names it: 1 when the caller's masks are the
        frames' alone, (F, H, W), so that the reason names the caller's ``masks[f]``.

    Returns
    -------
    (bad, reason) : (list of int, str or None)
        ``bad``: indices in the (F + 1, H, W) stack (0 the reference, frame index + 1 a frame) of the
        masks that :func:`sfem_filters.imaging.repair_myocardium_mask` cannot mend (an empty one
        included); ``reason``: its error for the first of them (None when there is none).
    """
    m = as_mask("masks", masks, ndim=3)
    shift = integer("offset", offset, 0)
    bad, first = [], None
    for f in range(len(m)):
        try:
            repair_myocardium_mask(m[f], "reference_mask" if f == 0 else f"masks[{f - shift}]")
        except ValueError as exc:
            bad.append(f)
            first = first or str(exc)
    return bad, first


def masks_can_be_fused(masks, every_frame: bool = False) -> bool:
    """Whether the frames' masks can join the DENSE route's data: a ring around one cavity where they are used.

    The masks' data come from their borders (:mod:`sfem_filters.cardiac.border_data`), read
    against the reference mask's, which needs a ring in the reference and in the frames used;
    :func:`sfem_filters.imaging.repair_myocardium_mask` mends small defects. Guided border data (the
    default, ``border_correspondence="phase"``) read each frame's mask on its own, so a frame whose
    mask cannot be mended only leaves its border rows out (that frame observes the phase alone;
    :func:`sfem_filters.cardiac.border_data.guided_border_data` warns, naming it); the masks are
    fused while the reference's and at least one frame's can be read. Landmarks tracked from frame to
    frame (``every_frame=True``, ``border_correspondence="landmarks"``) need every frame's. When the
    masks cannot be fused this warns (naming the masks) and returns False, so that a default that
    would fuse them does without them instead of stopping.

    Parameters
    ----------
    masks : (F + 1, H, W) bool array
        The reference mask (index 0) then each frame's.
    every_frame : bool
        Whether every frame's mask must be a ring (landmark tracking), not only one.
    """
    bad, first = unusable_mask_frames(masks)
    frames = [f for f in bad if f > 0]
    n = len(masks) - 1
    if 0 in bad:
        why = "the reference mask cannot be made one ring around one cavity, so no border can be read against it"
    elif frames and (every_frame or len(frames) == n):
        need = "landmarks tracked from frame to frame need every frame's" if every_frame else "no frame's is left"
        why = (f"the mask(s) of frame(s) {[f - 1 for f in frames]} (index {frames} in the (F + 1, H, W) stack) "
               f"cannot be made one ring around one cavity, and {need}")
    else:
        return True
    warnings.warn(f"masks: {why} ({first}); the DENSE route does without the masks (border_masks=False; on the "
                  f"command line --with-masks makes this an error)", RuntimeWarning, stacklevel=user_stacklevel())
    return False


def image_settings(case, **overrides) -> StrainRouteSettings:
    """The DENSE route's settings for a case with images: the acquisition's point spread, the masks fused.

    The route's defaults for what images carry beyond the tracks (the command line's ``strain``
    default; the validation page's main row, measured against every variant it leaves out):

    * ``resolution_px``: the case's acquired resolution
      (:attr:`sfem_filters.imaging.DenseCase.resolution_px`), so each datum is observed as the
      point-spread-weighted mean over the tissue with the images' background mixed in at the
      borders (module docstring, step 2), not at the pixel centre;
    * ``border_masks``: True when the frames' masks move (:func:`masks_move`): their borders'
      motion across the border joins the phase data, which the point spread biases at the
      endocardium; with one mask for every frame there is nothing to fuse; False, with a warning,
      when the reference's or no frame's mask is a ring that can be mended, or, with
      ``border_correspondence="landmarks"`` (tracked from frame to frame), any frame's
      (:func:`masks_can_be_fused`; with the default, a frame whose mask cannot be only leaves its
      border rows out);
    * ``phase_noise_level`` and ``mask_noise_level``: ``"evidence"`` with the masks (each source
      weighed by the noise it shows: the phase data's level from a pass of their own, the masks'
      beside it from the fused model's evidence);
    * ``process_profile``: ``"data"`` (the :class:`StrainRouteSettings` default).

    Parameters
    ----------
    case : DenseCase
        The images (:func:`sfem_filters.imaging.read_dense_sim`,
        :func:`sfem_filters.imaging.read_dense_dicom`).
    **overrides
        Any :class:`StrainRouteSettings` field, which wins over the above (e.g.
        ``resolution_px=1.0`` for the point observation, ``border_masks=False`` for the phase alone).

    Returns
    -------
    StrainRouteSettings
    """
    _check_case(case)
    resolution = overrides.pop("resolution_px", case.resolution_px)
    every = overrides.get("border_correspondence", StrainRouteSettings.border_correspondence) == "landmarks"
    fuse = masks_move(case.masks) and ("border_masks" in overrides or masks_can_be_fused(case.masks, every))
    return route_settings(resolution, fuse, **overrides)


def route_settings(resolution_px: float = 1.0, moving_masks: bool = False, **overrides) -> StrainRouteSettings:
    """The DENSE route's settings for what its input carries (:func:`image_settings` for images).

    Parameters
    ----------
    resolution_px : float
        Acquired resolution of the images (reconstructed pixels, >= 1; 1 for tracks without an
        acquisition: point observation).
    moving_masks : bool
        Whether the input holds a mask of every frame that moves (:func:`masks_move`): then they
        are fused, the phase data and the masks each at their evidence level.
    **overrides
        Any :class:`StrainRouteSettings` field, which wins; ``border_masks`` given alone also sets
        the two levels that go with it.

    Returns
    -------
    StrainRouteSettings
    """
    unknown = sorted(set(overrides) - set(StrainRouteSettings.__dataclass_fields__))
    if unknown:
        raise TypeError(f"overrides: expected StrainRouteSettings fields, got {unknown}")
    fuse = bool(overrides.get("border_masks", moving_masks))
    level = "evidence" if fuse else "stated"
    base = {"resolution_px": resolution_px, "border_masks": fuse, "phase_noise_level": level, "mask_noise_level": level}
    return StrainRouteSettings(**{**base, **overrides})


def _check_case(case) -> None:
    if not isinstance(case, DenseCase):
        raise TypeError(f"case: expected a DenseCase (sfem_filters.imaging.read_dense_sim, read_dense_dicom), "
                        f"got {type(case).__name__}")


def dense_case_strain(case, settings: StrainRouteSettings | None = None, tracks: LagrangianDisplacement | None = None,
                      progress=None) -> DenseRouteStrain:
    """The DENSE route from images: phase to tracks, the images' background and masks, then :func:`dense_strain`.

    Parameters
    ----------
    case : DenseCase
        The images, with every frame's mask.
    settings : StrainRouteSettings, optional
        Default :func:`image_settings` of the case.
    tracks : LagrangianDisplacement, optional
        The case's tracks (pixels) if already computed
        (:func:`sfem_filters.imaging.phase_to_displacement`, the costly step).
    progress : callable, optional
        ``progress(message)`` at each step.

    Returns
    -------
    DenseRouteStrain
        As :func:`dense_strain`; its settings name the background used.
    """
    _check_case(case)
    cfg = image_settings(case) if settings is None else settings
    say = progress if progress is not None else (lambda msg: None)
    if tracks is None:
        say("phase to Lagrangian displacement")
        tracks = phase_to_displacement(case)
    background = None
    if cfg.resolution_px > 1:
        say("the images' signal around the myocardium (the point spread's reach outside the tissue)")
        background = background_signal(case, cfg.resolution_px)
    return dense_strain(tracks, case.reference_mask, case.pixel_size_m, cfg, progress=progress,
                        background=background, masks=case.masks if cfg.border_masks else None)
