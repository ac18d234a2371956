"""The DENSE route's mesh, its data compressed to the nodes, the filter model, and the process noise by its evidence.

Split from :mod:`sfem_filters.cardiac.strain_route` along its seam (steps 1-3 of its module
docstring, which says why each setting); every name stays importable from there. Units: the mesh
in metres; pixels for the tracks.
"""
from __future__ import annotations

import hashlib
import warnings
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp
from scipy import ndimage

from .._validate import as_float_array, positive, user_stacklevel
from ..fem.elasticity import stiffness_matrix
from ..fem.loads import penalty_stiffness
from ..fem.material import Material
from ..fem.mesh import TriMesh
from ..fem.observation import blurred_observation_matrix, point_observation_matrix, sample_interpolation
from ..fem.polygon_mesh import polygon_mesh
from ..filtering.linearised import linearise
from ..filtering.smoother import kalman_forward, smooth_backward
from ..imaging.contours import mask_borders
from ..imaging.dense import LagrangianDisplacement, BackgroundSignal, psf_samples
from ..model import SFEMModel
from .effects import build_effects
from .measured import EFFECT_STEP, NOMINAL
from .myocardium import lv_geometry, tissue_mesh
from .strain_bands import noise_scale

__all__ = ["MESHES", "INFORMATION_FLOOR", "RELAXATION_CYCLES", "PROCESS_FRACTIONS", "reference_mesh",
           "observation_points", "nodal_fit", "NodalFitModel", "compliant_modulus", "temporal_noise_floor",
           "build_dense_model", "concentrated_log_evidence", "process_fraction_ml", "observation_operator",
           "ObservationScaling", "phase_noise_level", "phase_only_pass", "mask_noise_level_ml", "MASK_LEVELS",
           "PROCESS_PROFILES", "PROFILE_HARMONICS", "smooth_motion_basis", "process_profile_from_data"]

#: How the reference myocardium is meshed (``mesh=``).
MESHES = ("gmsh", "pixels")
#: Regularisation of the nodal fit's information matrix, relative to its mean diagonal.
INFORMATION_FLOOR = 1e-8
#: Cycles the elastic relaxation across the wall takes with :func:`compliant_modulus`.
RELAXATION_CYCLES = 10.0
#: Candidates of the process noise fraction compared by their evidence (:func:`process_fraction_ml`).
PROCESS_FRACTIONS = (0.1, 0.3, 1.0, 3.0)
#: Candidate factors on the masks' variance compared by their evidence (:func:`mask_noise_level_ml`): from
#: masks far better than their stated sd (a border node's datum averages its support) to masks drawn worse.
MASK_LEVELS = (1.0 / 64, 1.0 / 16, 1.0 / 4, 1.0, 4.0, 16.0)
#: Where :func:`mask_noise_level_ml` starts its search among :data:`MASK_LEVELS` (it evaluates this candidate and its
#: two neighbours first, then walks outwards only while the best is at an end).
MASK_LEVEL_START = 0.25
#: How the process noise varies over the frame intervals (``StrainRouteSettings.process_profile``).
PROCESS_PROFILES = ("constant", "data")
#: Angular harmonics of the smooth motion whose acceleration sets the ``"data"`` profile: up to 3, what six
#: equal segments resolve around the centre (their Nyquist), with a linear trend across the wall.
PROFILE_HARMONICS = 3


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
    b = mask_borders(m, n_endo=max(16, n // 3), n_epi=max(16, n // 2), name="reference_mask")
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


# ------------------------------------------------------------------------ the observation operator
def observation_operator(mesh: TriMesh, points_m, tracks: LagrangianDisplacement, pixel_size_m: float,
                         resolution_px: float = 1.0, background=None) -> tuple:
    """The DENSE route's ``D`` of Eq. 12 with the acquisition's point spread, and each datum's scaling.

    A DENSE datum is the phase of the complex signal summed over the point spread function
    (PSF), so it reports the signal-weighted mean displacement of what the PSF reaches, not the
    displacement at the pixel centre: deeper tissue, and at the borders what surrounds the
    myocardium (the cavity, the tissue around the heart), with its own signal and phase. With the
    PSF of the acquired resolution (:func:`sfem_filters.imaging.dense.psf_samples`, a Gaussian of
    FWHM ``resolution_px``, sampled at a third of a pixel), datum ``y_pt`` (pixels) of point p at
    frame t is modelled, per component, as

    ``y_pt sum_in w_s - offset_pt = sum_in w_s N(X_p + o_s) U_t``,

    ``N`` the shape functions (:func:`sfem_filters.fem.observation.blurred_observation_matrix`),
    "in" the sample points inside the reference mesh, and ``offset`` the pull of the signal
    outside the tissue on the datum's phase (:func:`_background_terms`: the phasors add, so a
    static background pulls a large phase less than a linear average says), read from the
    background's complex signal (:func:`sfem_filters.imaging.dense.background_signal`; None: a
    dark background, no offset) at the samples' positions now, ``x_pt + o_s``, ``x_pt = X_p +
    d_pt`` the datum's tracked position. With ``resolution_px = 1`` this is the point
    interpolation.

    The Eulerian-to-Lagrangian approximation: the phase is blurred in the *current* image, around
    the tissue's position now; the operator blurs the model's *Lagrangian* field around the
    reference position with the same PSF, i.e. it takes the deformation gradient as the identity
    across the PSF (a kernel about one pixel wide, where the strain changes its shape by up to
    the strain itself) and ignores that the tracked position is itself displaced by the blur's
    bias (a second-order effect: the bias times the displacement gradient). Both are what the
    tracks' inversion of a blurred field already assumes (the datum belongs to the reference
    pixel it was tracked from); in exchange ``D`` is one matrix for every frame, and each frame
    only rescales and shifts its data (:class:`ObservationScaling`). Measured on a thickening
    ring rendered through a known point spread (``tests/cardiac/test_strain_route_psf.py``), the
    route through this operator recovers the radial strain the blur takes off: the approximation
    is not what limits it there. Nor on DENSE-Sim: a probe that took the point spread in the current
    configuration (each sample reweighted by ``w((I + G) o) det(I + G)``, ``G`` the route's own
    recovered gradient per pixel and frame, one ``D_t`` a frame) moved the segments' radial peaks
    slightly *lower* on both given cases and on the in-vivo case resampled to a coarser grid, and
    doubled the run's time. Thickening narrows the point spread's footprint across the wall, so
    the reference-configuration operator credits an endocardial datum with somewhat more of the
    deeper wall's motion than it holds: it leans, if anything, towards reading the thickening
    larger, and the route's under-read of the radial peaks comes from elsewhere.

    Returns
    -------
    D : (2 P, n_dofs) sparse matrix
        ``sum_in w_s N(X_p + o_s)``, rows point by point, x before y.
    scaling : ObservationScaling
        ``tissue``, ``offset`` and ``gain``, each (F, P, 2).
    """
    s = positive("pixel_size_m", pixel_size_m, "m")
    pts = as_float_array("points_m", points_m, shape=(None, 2))
    F, P = tracks.displacement.shape[:2]
    offsets, weights = psf_samples(resolution_px)
    if len(offsets) == 1:
        ones = np.ones((F, P, 2))
        return point_observation_matrix(mesh, pts), ObservationScaling(tissue=ones, offset=np.zeros_like(ones),
                                                                       gain=ones)
    if background is not None and not isinstance(background, BackgroundSignal):
        raise TypeError(f"background: expected a BackgroundSignal (sfem_filters.imaging.dense.background_signal) or "
                        f"None, got {type(background).__name__}")
    if background is not None and background.signal.shape[0] != F:
        raise ValueError(f"background: expected the signal of F = {F} frames, got shape {background.signal.shape}")
    samples = sample_interpolation(mesh, pts, offsets * s)
    D = blurred_observation_matrix(mesh, pts, offsets * s, weights, background=1.0, samples=samples)
    inside = samples[1]
    tissue = np.repeat(np.sum(np.where(inside, weights, 0.0), axis=1)[None, :, None], F, axis=0).repeat(2, axis=2)
    offset = np.zeros((F, P, 2))
    gain = tissue.copy()
    if background is not None:
        out_p, out_s = np.nonzero(~inside)
        for t in range(F):
            q = tracks.points[out_p] + offsets[out_s] + np.nan_to_num(tracks.displacement[t])[out_p]
            off_t, gain_t = _background_terms(background, tracks, t, out_p, weights[out_s], q, P)
            offset[t] = off_t
            gain[t] += gain_t
    return D, ObservationScaling(tissue=tissue, offset=offset, gain=gain)


def _background_terms(background: BackgroundSignal, tracks, t: int, out_p, w_out, q_px, P: int) -> tuple:
    """(P, 2) the background's offset (pixels) and gain of each datum at frame ``t``, per component.

    The phase ``theta`` of a sum of phasors ``sum_k c_k exp(i phi_k)`` solves ``sum_k c_k
    sin(phi_k - theta) = 0``. With the tissue's phases near ``theta`` (``sin(phi - theta) ~ phi -
    theta``) and the background's complex signal ``z_s = b_s exp(i psi_s)`` at the samples outside
    the tissue (bilinear in the image at the samples' positions ``q_px``): ``theta sum_in w_s =
    sum_in w_s phi_s + sum_out w_s Im(z_s exp(-i theta))``. In displacement (``theta = p y``, ``p``
    the phase per pixel): ``y sum_in w = D U + offset``, ``offset = sum_out w_s Im(z_s exp(-i
    theta)) / p``; the datum's noise passes with the gain ``sum_in w + sum_out w_s Re(z_s exp(-i
    theta))``. A static background (``psi = 0``) gives ``y (sum_in w + b sinc(theta)) = D U``: it
    pulls a large phase less than a linear average says. The encodings are taken along x and y.
    """
    theta = background.phase_per_px * np.nan_to_num(tracks.displacement[t])             # (P, 2) rad
    offset, gain = np.zeros((P, 2)), np.zeros((P, 2))
    for c in range(2):
        zc = background.signal[t, ..., c]
        z = (ndimage.map_coordinates(zc.real, [q_px[:, 1], q_px[:, 0]], order=1, mode="nearest")
             + 1j * ndimage.map_coordinates(zc.imag, [q_px[:, 1], q_px[:, 0]], order=1, mode="nearest"))
        rot = z * np.exp(-1j * theta[out_p, c])
        offset[:, c] = np.bincount(out_p, weights=w_out * rot.imag, minlength=P) / background.phase_per_px
        gain[:, c] = np.bincount(out_p, weights=w_out * rot.real, minlength=P)
    return offset, gain


@dataclass(frozen=True)
class ObservationScaling:
    """How each DENSE datum relates to ``D U`` (:func:`observation_operator`): ``tissue * y - offset = D U``.

    Each attribute is an (F, P, 2) array: per frame, point and component.

    Attributes
    ----------
    tissue : array
        ``sum_in w_s``, the point spread's weight on the tissue.
    offset : array
        The background's pull (pixels): ``sum_out w_s Im(z_s exp(-i theta)) / p``.
    gain : array
        ``d(tissue y - offset) / dy``: the datum's noise sd is multiplied by ``|gain|``.
    """

    tissue: np.ndarray
    offset: np.ndarray
    gain: np.ndarray

    def transform(self, y):
        """``tissue * y - offset``: the datum as ``D U`` sees it (pixels)."""
        return self.tissue * np.asarray(y, float) - self.offset

    def predict(self, DU):
        """The datum ``D U`` predicts (pixels): ``(D U + offset) / tissue``."""
        return (np.asarray(DU, float) + self.offset) / self.tissue


# -------------------------------------------------------------------------- the data, compressed
def nodal_fit(D, displacement_m, sd_m) -> tuple:
    """Per frame, the weighted least-squares nodal displacements and their covariance.

    Parameters
    ----------
    D : (2P, n_dofs) sparse matrix
        Observation operator (rows point by point, x before y).
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
    u = np.asarray(displacement_m, float)
    s = np.asarray(sd_m, float)
    F = u.shape[0]
    D = sp.csr_matrix(D)
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
    per-frame noise protocol); ``R`` is their mean. ``process_profile`` (F - 1,) factors > 0 on
    ``Q`` per frame interval, or None (``Q`` every interval): :meth:`process_profile`, the filters'
    :class:`~sfem_filters.filtering.protocol.ProcessNoiseProfile`. Everything else is :class:`SFEMModel`'s.
    """

    def __init__(self, *args, R_frames, process_profile=None, **kwargs):
        R_frames = np.asarray(R_frames, float)
        super().__init__(*args, **kwargs)
        if process_profile is not None:
            process_profile = as_float_array("process_profile", process_profile, shape=(self.n_frames - 1,))
            if np.any(process_profile <= 0):
                raise ValueError(f"process_profile: expected factors > 0 on Q, got minimum "
                                 f"{float(process_profile.min())!r}")
        self._profile = process_profile
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

    def with_block_noise(self, first: int, scale: float) -> "NodalFitModel":
        """This model with the covariance of the observed rows ``first:`` times ``scale`` (> 0), the rows before
        unchanged: a second source's block (the masks' rows below the nodal fit), which must be independent of
        the rows before it. Shares all else with this model, as :meth:`with_measurement_noise` does."""
        first = int(first)
        if not 0 <= first < self.dim_obs:
            raise ValueError(f"first: expected a row in [0, {self.dim_obs}), got {first}")
        if np.any(self._R_full[:, :first, first:]):
            raise ValueError(f"first: expected rows {first}: independent of the rows before them, got a covariance "
                             f"between the two")
        out = self.with_measurement_noise(1.0)
        out._R_full[:, first:, first:] *= positive("scale", scale)
        out.R = out._R_full.mean(axis=0)
        return out

    def process_profile(self):
        """(F - 1,) factors on ``Q`` per frame interval, or None (``Q`` every interval)."""
        return None if self._profile is None else self._profile.copy()

    def fingerprint(self) -> str:
        """:meth:`SFEMModel.fingerprint` with the process profile (a model with another profile behaves differently)."""
        base = super().fingerprint()
        if self._profile is None:
            return base
        return hashlib.sha256(base.encode() + self._profile.tobytes()).hexdigest()


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


def smooth_motion_basis(points_px, centre_px, harmonics: int = PROFILE_HARMONICS) -> np.ndarray:
    """(P, 2 (2 harmonics + 1)) smooth fields over the points: ``{1, rho} x {1, cos k phi, sin k phi}``, k <= harmonics.

    ``phi`` the angle about ``centre_px`` and ``rho = (r - r_mean) / r_mean`` the relative radius
    (a linear trend across the wall): the motion the route's curves resolve, six segments around
    the centre and the wall's thickening, and nothing finer.
    """
    X = as_float_array("points_px", points_px, shape=(None, 2))
    c = as_float_array("centre_px", centre_px, shape=(2,))
    d = X - c
    r = np.hypot(d[:, 0], d[:, 1])
    if not np.mean(r) > 0:
        raise ValueError("points_px: expected points around the centre, got all of them at it")
    phi = np.arctan2(d[:, 1], d[:, 0])
    rho = (r - r.mean()) / r.mean()
    ang = [np.ones_like(phi)]
    for k in range(1, int(harmonics) + 1):
        ang += [np.cos(k * phi), np.sin(k * phi)]
    A = np.column_stack(ang)
    return np.hstack([A, A * rho[:, None]])


def process_profile_from_data(displacement_px, sd_px, points_px, frame_interval_s: float, alpha: float,
                              q_floor_px: float) -> tuple:
    """Process noise sd of each frame interval from the data's own acceleration (method of moments).

    The model (:func:`build_dense_model`) moves each dof, over a frame of ``T`` s, as a damped
    constant-velocity prior: ``v_t+1 = phi v_t + w^v_t`` and ``u_t+1 = u_t + tau v_t + w^u_t``,
    ``phi = exp(-alpha T)``, ``tau = (1 - phi) / alpha`` (mass damping; the compliant tissue's
    elastic and ground forces are negligible over the cycle, :func:`compliant_modulus`), with
    process sd ``q`` on ``u`` and ``q / T`` on ``v``. So the damped second difference
    ``delta_t = u_t+1 - (1 + phi) u_t + phi u_t-1 = tau w^v_t-1 + w^u_t - phi w^u_t-1`` has variance
    ``kappa q^2``, ``kappa = (tau / T)^2 + 1 + phi^2`` (3 without damping): the model's own
    constant, no number chosen here. Reading ``delta_t`` off the data gives ``q`` per frame:

    1. the tracks of each frame are projected, weighted by ``1 / sd^2``, on the smooth fields of
       :func:`smooth_motion_basis` about the points' centroid (least squares): at the pixel level the
       acceleration is a few percent of the noise's share (the second differences' power per frame
       is flat within +-20% over a DENSE-Sim cycle), while the smooth fields average the noise of
       hundreds of pixels and keep the motion the curves report;
    2. ``a_t^2``, the mean over the points and components of ``delta_t`` of that smooth field
       squared, less the noise's own share, clipped at 0. The share's course over the frames is
       the white noise's, ``w_t = mean diag(B (C_t+1 + (1 + phi)^2 C_t + phi^2 C_t-1) B^T)`` with
       ``C_t`` the projection's covariance from the data's sd (for ``phi = 1`` the familiar
       ``6 sigma^2`` of a second difference), which follows the signal's fading over the cycle;
       its level is the data's: the median over the frames of ``power_t / w_t``. Why not ``w_t``
       alone: noise correlated over the pixels (the simulator's and the scanner's phase texture)
       is averaged far less by the projection than white noise, and on DENSE-Sim the smooth
       field's ``delta`` of the quiet frames is several times ``w_t`` (measured: every interval of
       the in-vivo case then asked for 2.5 to 6.5 times the constant level, and the bands lost
       coverage). The median assumes that at least half the frames are quiet (diastasis and the
       slow phases; where more move, the level is too high and the profile falls back towards the
       constant level, never below it); it also sits a little below the mean of a frame's noise
       power (a weighted sum of many chi-square terms), which errs towards more process noise;
    3. ``q_t^2 = a_t^2 / kappa`` at frames 1 .. F - 2; interval t (frame t to t + 1) takes the
       mean over the two frames whose ``delta`` it enters (t and t + 1, where they exist);
    4. ``q_t = max(q_floor, q_t)``: never below the constant level.

    What it cannot see: acceleration at finer scales than the basis (the per-dof process noise
    is then taken at the smooth motion's level), and a noise whose course over the frames is not
    the stated sd's.

    Parameters
    ----------
    displacement_px, sd_px : (F, P, 2) arrays
        Tracks (pixels; NaN where untracked) and the sd the route gives them (pixels).
    points_px : (P, 2) array
        Their reference positions (pixels).
    frame_interval_s, alpha : float
        ``T`` (s) and the model's mass damping (1/s, >= 0).
    q_floor_px : float
        The constant level (pixels): ``process_fraction`` of the noise floor.

    Returns
    -------
    q_px : (F - 1,) array
        Process sd on the displacement per interval (pixels), ``>= q_floor_px``.
    accel_px : (F,) array
        ``sqrt(a_t^2)`` per frame after the noise's share (pixels; NaN at the first and last).
    noise_level : float
        The noise's share of the smooth field's ``delta`` over its white share (step 2).
    """
    u = as_float_array("displacement_px", displacement_px, shape=(None, None, 2), allow_nan=True)
    sd = as_float_array("sd_px", sd_px, shape=u.shape, allow_nan=True)
    F, P = u.shape[:2]
    if F < 3:
        raise ValueError(f"displacement_px: expected at least 3 frames for an acceleration, got {F}")
    X = as_float_array("points_px", points_px, shape=(P, 2))
    T = positive("frame_interval_s", frame_interval_s, "s")
    a = float(alpha)
    if not np.isfinite(a) or a < 0:
        raise ValueError(f"alpha: expected a mass damping >= 0 (1/s), got {alpha!r}")
    q0 = positive("q_floor_px", q_floor_px, "pixels")
    B = smooth_motion_basis(X, X.mean(axis=0))
    k = B.shape[1]
    coef = np.zeros((F, 2, k))
    cov = np.zeros((F, 2, k, k))
    for t in range(F):
        for c in range(2):
            w = np.where(np.isfinite(u[t, :, c]) & np.isfinite(sd[t, :, c]) & (sd[t, :, c] > 0),
                         1.0 / np.where(sd[t, :, c] > 0, sd[t, :, c], 1.0) ** 2, 0.0)
            J = B.T @ (B * w[:, None])
            Ji = np.linalg.pinv(J, hermitian=True)
            coef[t, c] = Ji @ (B.T @ (w * np.nan_to_num(u[t, :, c])))
            cov[t, c] = Ji
    phi = np.exp(-a * T)
    tau_T = (1.0 - phi) / (a * T) if a * T > 0 else 1.0
    kappa = tau_T ** 2 + 1.0 + phi ** 2
    power, white = np.full(F, np.nan), np.full(F, np.nan)
    for t in range(1, F - 1):
        field = (coef[t + 1] - (1 + phi) * coef[t] + phi * coef[t - 1]) @ B.T           # (2, P)
        C = cov[t + 1] + (1 + phi) ** 2 * cov[t] + phi ** 2 * cov[t - 1]                 # (2, k, k)
        power[t] = float(np.mean(field ** 2))
        white[t] = float(np.mean(np.einsum("pi,cij,pj->cp", B, C, B)))
    inner = slice(1, F - 1)
    if not np.all(white[inner] > 0):
        raise ValueError("sd_px: expected a positive sd of some tracked point in every frame")
    level = float(np.median(power[inner] / white[inner]))             # the noise's share, over its white share
    accel2 = np.maximum(0.0, power - level * white)
    q2 = accel2 / kappa
    q2_int = np.array([np.nanmean(q2[[t, t + 1]]) for t in range(F - 1)])             # frames t, t + 1 (NaN ends)
    return np.maximum(q0, np.sqrt(q2_int)), np.sqrt(accel2), level


def build_dense_model(mesh: TriMesh, tracks: LagrangianDisplacement, pixel_size_m: float,
                      settings: StrainRouteSettings, background=None, border=None, phase_scale: float = 1.0) -> tuple:
    """The filter model of dense displacement data and its observations (module docstring, steps 2-3).

    Noise, by the data's own level: each datum's sd is the tracks' ``sd`` scaled up (never
    down) so that its RMS equals the temporal noise floor (:func:`temporal_noise_floor`); the
    process noise is ``settings.process_fraction`` of that floor per frame on the displacement,
    and the same over the frame interval on the velocity (the rule of
    :func:`sfem_filters.cardiac.measured.build_model`). With ``settings.process_profile ==
    "data"`` each frame interval's process sd is the larger of that level and the data's own
    smooth acceleration's (:func:`process_profile_from_data`), passed to the filters as factors on
    ``Q`` (:class:`NodalFitModel` ``process_profile``).

    Observations through :func:`observation_operator` with ``settings.resolution_px`` and
    ``background`` (a :class:`~sfem_filters.imaging.dense.BackgroundSignal`, or None: a dark background).

    ``border`` (a :class:`sfem_filters.cardiac.border_data.BorderData` on this mesh, or None): the
    myocardium masks' data, each border node's motion across the border with the contours route's
    sd (quantisation or their own temporal noise floor), stacked below the nodal fit in one model
    (Shi & Liu's fusion of shape tracking with phase data): ``H = [I; H_b]``, ``y_t = [U^_t;
    y_b,t]``, ``R_t = blockdiag(J_t^-1, R_b,t)``. The two are independent data of the same
    displacement, so their log-likelihoods add; the phase data's noise rules above do not touch
    the masks' rows (the masks carry no phase noise), and the process noise stays the phase
    data's. ``phase_scale`` multiplies every covariance set from the phase data's noise (the nodal
    fit's ``R``, the process and the initial covariance; 1: as stated), the masks' rows excepted:
    :func:`phase_noise_level` gives it.

    Returns ``(model, y, info, points)``: a :class:`NodalFitModel`, the observations (F, n_dofs),
    or (F, n_dofs + m_b) with ``border``, in m, a dict of what was derived, and the observed
    points (m, moved into the mesh).
    """
    s = positive("pixel_size_m", pixel_size_m, "m")
    X = tracks.points * s
    Xin, moved = observation_points(mesh, X)
    D, scaling = observation_operator(mesh, Xin, tracks, s, getattr(settings, "resolution_px", 1.0), background)
    F = tracks.displacement.shape[0]
    if F < 3:
        raise ValueError(f"tracks: expected at least 3 frames, got {F}")
    floor_px = temporal_noise_floor(tracks.displacement)
    sd = np.asarray(tracks.pixel_sd, float)      # the tracks share pixels: a smooth fit sees the pixels' noise
    sd_rms = float(np.sqrt(np.nanmean(sd ** 2)))
    sd_scale = max(1.0, floor_px / sd_rms)
    gain = np.maximum(np.abs(scaling.gain), 0.1 * scaling.tissue)      # a datum the background all but cancels
    y, R = nodal_fit(D, scaling.transform(tracks.displacement) * s, sd * sd_scale * gain * s)
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
    # the initial state's sd from the phase data's nodal fit (before any border rows join y)
    u0_sd = max(float(np.sqrt(np.mean(y[0] ** 2))), floor_px * s)
    c = positive("phase_scale", phase_scale)
    R = R * c
    u0_sd *= np.sqrt(c)
    border_info = {}
    if border is not None:
        H, y, R, border_info = _stack_border(H, y, R, border, mesh, s)
    if settings.process_fraction is None:
        raise ValueError("settings: expected a process_fraction (None is resolved by process_fraction_ml)")
    q = settings.process_fraction * floor_px * s * np.sqrt(c)
    profile, profile_info = None, {}
    if settings.process_profile == "data":
        q_t, accel, level = process_profile_from_data(tracks.displacement, sd * sd_scale, tracks.points, T, alpha,
                                               settings.process_fraction * floor_px)
        profile = (q_t / (settings.process_fraction * floor_px)) ** 2        # on Q: its sds are q and q / T
        profile_info = {"process_profile_std_px": (q_t * np.sqrt(c)).tolist(),
                        "process_profile_factor_range": [float(profile.min()), float(profile.max())],
                        "process_profile_intervals_above_floor": int(np.count_nonzero(profile > 1.0)),
                        "smooth_acceleration_px": [None if not np.isfinite(v) else float(v) for v in accel],
                        "process_profile_noise_over_white": level}
    # the initial state: at rest in the reference configuration (encoding time, t = 0), uncertain
    # by the first frame's displacement (frame 0 is 22.5 ms after the encoding, already moved): u0_sd above
    model = NodalFitModel(mesh, material, np.zeros((F, mesh.n_dofs)), H, T, (), density=NOMINAL["density"],
                          alpha=alpha, beta=NOMINAL["beta"], measurement_std=1.0,
                          process_std=(q, q / T), initial_std=(u0_sd, u0_sd / T), effects=effs, penalty=penalty,
                          R_frames=R, process_profile=profile)
    seen = np.any(np.isfinite(tracks.displacement[..., 0]), axis=0)     # points with data (observed)
    moved_seen = np.where(seen, moved, 0.0)
    info = {"n_points_moved_into_mesh": int(np.count_nonzero(moved_seen)),
            "largest_move_px": float(moved_seen.max() / s),
            "noise_floor_px": floor_px, "tracks_sd_rms_px": sd_rms, "sd_scale": sd_scale,
            "process_std_px": q / s, "frame_interval_s": T, "fixed_E_Pa": E, "alpha_per_s": alpha,
            "wall_thickness_px": _wall_thickness(mesh) / s,
            "initial_std_px": u0_sd / s, "observation_tissue_weight_mean": float(scaling.tissue.mean()),
            "observation_background_offset_rms_px": float(np.sqrt(np.mean(scaling.offset ** 2))),
            "phase_noise_scale": c, **border_info, **profile_info}
    return model, y, info, Xin


def _stack_border(H, y, R, border, mesh: TriMesh, pixel_size_m: float) -> tuple:
    """``[H; H_b]``, ``[y, y_b]`` and ``blockdiag(R, R_b)`` per frame, and what the border rows are."""
    for name in ("H", "y", "R", "nodes", "tracks", "floor_px"):
        if not hasattr(border, name):
            raise TypeError(f"border: expected a BorderData (sfem_filters.cardiac.border_data.mask_border_data), "
                            f"got {type(border).__name__}")
    Hb = sp.csr_matrix(border.H)
    yb = np.asarray(border.y, float)
    Rb = np.asarray(border.R, float)
    F, n = y.shape
    m = Hb.shape[0]
    if Hb.shape[1] != mesh.n_dofs:
        raise ValueError(f"border: expected rows on this mesh's {mesh.n_dofs} dofs, got H of shape {Hb.shape}")
    if yb.shape != (F, m) or Rb.shape != (F, m, m):
        raise ValueError(f"border: expected the data of F = {F} frames, got y {yb.shape} and R {Rb.shape} for "
                         f"{m} rows")
    if not (np.all(np.isfinite(yb) | np.isnan(yb)) and np.all(np.isfinite(Rb))):
        raise ValueError("border: expected finite covariances and data finite or NaN (missing), got infinity")
    Rs = np.zeros((F, n + m, n + m))
    Rs[:, :n, :n] = R
    Rs[:, n:, n:] = Rb
    sd = np.sqrt(np.diagonal(Rb, axis1=1, axis2=2))
    info = {"border_rows": int(m), "border_nodes": int(len(border.nodes)),
            "border_landmarks": None if border.tracks is None else int(len(border.tracks.points)),
            "border_sd_px_range": [float(sd.min() / pixel_size_m), float(sd.max() / pixel_size_m)],
            "border_normal_noise_floor_px": float(border.floor_px)}
    return sp.vstack([H, Hb], format="csr"), np.hstack([y, yb]), Rs, info


def phase_noise_level(mesh: TriMesh, tracks: LagrangianDisplacement, pixel_size_m: float,
                      settings: StrainRouteSettings, background=None) -> float:
    """The phase data's own noise level by type-II maximum likelihood, from one filter pass without the masks.

    The phase-only model (:func:`build_dense_model`) sets R, the process and the initial
    covariance from the phase data's noise floor; scaling all three by one factor leaves its
    estimate unchanged, and the factor of largest evidence is the mean normalised innovation
    squared per observed row (closed form, Harvey 1989 sec. 3.4; the DENSE route's step 6 a). So
    a model that fuses the masks can take the phase data at their *own* level (this factor, the
    masks' rows at theirs: the quantisation or their temporal floor) instead of at the stated one:
    then the two sources are weighed by the noise each shows, not by the phase data's nominal sd
    (which holds neither the phase texture's correlation nor the tracks' bias, and so comes out
    several times too small on DENSE-Sim: the route's ``noise_scale_ml``).
    """
    return phase_only_pass(mesh, tracks, pixel_size_m, settings, background)[0]


def phase_only_pass(mesh: TriMesh, tracks: LagrangianDisplacement, pixel_size_m: float,
                    settings: StrainRouteSettings, background=None, smooth: bool = False) -> tuple:
    """One filter pass of the phase data alone: their own noise level and, with ``smooth``, their smoothed motion.

    The noise level is :func:`phase_noise_level`'s (the mean normalised innovation squared); the
    smoothed nodal displacements (RTS means of the same pass, which no common noise level changes)
    are the guide of the masks' border data (:func:`sfem_filters.cardiac.border_data.guided_border_data`:
    where each border node is along the border).

    Returns
    -------
    (c, U)
        ``c`` the level (dimensionless); ``U`` (F, n_nodes, 2) the smoothed displacement of every
        node in pixels, or None without ``smooth``.
    """
    s = positive("pixel_size_m", pixel_size_m, "m")
    model, y, _, _ = build_dense_model(mesh, tracks, s, settings, background)
    lin = linearise(model, np.zeros((y.shape[0], model.dim_x)))
    fw = kalman_forward(lin, y, store="mean" if smooth else False, check_every_frame=False)
    c = noise_scale(fw.nis, fw.n_obs)
    if not smooth:
        return c, None
    states = lin.to_model(smooth_backward(lin, fw).smoothed[:, :model.n_restart])
    U = np.zeros((y.shape[0], mesh.n_dofs))
    U[:, model.dofmap.free] = states[:, :model.dim_x // 2]
    return c, U.reshape(y.shape[0], mesh.n_nodes, 2) / s


def _wall_thickness(mesh: TriMesh) -> float:
    """Mean wall thickness (m): the area over the mean of the two borders' lengths."""
    geometry = lv_geometry(mesh)
    lengths = []
    for loop in (geometry.endo, geometry.epi):
        p = mesh.nodes[loop]
        lengths.append(float(np.sum(np.linalg.norm(p - np.roll(p, 1, axis=0), axis=1))))
    return float(mesh.areas.sum() / np.mean(lengths))


def concentrated_log_evidence(log_likelihood: float, nis_sum: float, n_obs: int) -> tuple:
    """Log-evidence with the common noise scale ``c`` profiled out, and that ``c``.

    With R, Q and the initial covariance all scaled by ``c`` (:func:`noise_scale`), ``log p(y | c) =
    -1/2 sum_t (log|c S_t| + e_t^T S_t^-1 e_t / c + m_t log 2 pi)``, maximised by ``c = sum nis / N``
    (``N`` the observed rows), where it is ``log p(y | 1) + sum nis / 2 - N log c / 2 - N / 2``.
    Comparing settings by this value compares their noise *shapes* (the split between process
    and measurement noise) at each one's best overall level.
    """
    n = int(n_obs)
    if n <= 0 or not nis_sum > 0:
        raise ValueError(f"nis_sum, n_obs: expected a positive NIS sum over some observed rows, got {nis_sum}, {n}")
    c = float(nis_sum) / n
    return float(log_likelihood) + 0.5 * float(nis_sum) - 0.5 * n * np.log(c) - 0.5 * n, c


def _concentrated_evidence_of(model, y) -> tuple:
    """One Kalman filter pass of ``model`` (nothing stored): its :func:`concentrated_log_evidence` and ``c``."""
    fw = kalman_forward(linearise(model, np.zeros((y.shape[0], model.dim_x))), y, store=False, check_every_frame=False)
    return concentrated_log_evidence(fw.log_likelihood, float(np.nansum(fw.nis)), int(np.sum(fw.n_obs)))


def _best_on_log_grid(values, evidence) -> float:
    """The candidate of largest evidence, refined by the vertex of the parabola through it and its two neighbours
    in log (kept within them) when it is not at an end of the grid."""
    k = int(np.argmax(evidence))
    if 0 < k < len(values) - 1:
        x = np.log(values[k - 1:k + 2])
        a, b, _ = np.polyfit(x, evidence[k - 1:k + 2], 2)
        return float(np.exp(np.clip(-b / (2 * a), x[0], x[2]))) if a < 0 else float(values[k])
    return float(values[k])


def mask_noise_level_ml(mesh: TriMesh, tracks: LagrangianDisplacement, pixel_size_m: float,
                        settings: StrainRouteSettings, border, phase_scale: float = 1.0, background=None,
                        candidates=MASK_LEVELS, progress=None) -> tuple:
    """The masks' noise level beside the phase data's, by type-II maximum likelihood (variance components).

    The fused model (:func:`build_dense_model` with ``border``) is run, one Kalman filter pass each,
    with the masks' covariance ``R_b`` times each candidate factor, the phase data's covariances at
    ``phase_scale`` (their own level, :func:`phase_noise_level`); the common noise level is profiled
    out (:func:`concentrated_log_evidence`), so what is compared is how the data's variance divides
    between the two sources. The best candidate is refined by the parabola in ``log`` factor through
    it and its neighbours. The evidence is taken to be unimodal in the factor, so the search starts
    at :data:`MASK_LEVEL_START` and its two neighbours and walks outwards while the best is at an
    end of what was evaluated (three to five passes: three where the best is the start, five where the
    masks are worse than stated). The masks' stated sd (a binary
    border's quantisation, or the border data's own temporal noise floor) says nothing of how well
    the masks were drawn, nor of how much the averaging over a border node's support removes; the
    evidence of both sources together does (a mask whose border disagrees with the phase data's
    motion from frame to frame is given less weight, one that agrees more). What it cannot see is an
    error the masks and the phase data share, or one the motion's smoothness absorbs.

    Parameters
    ----------
    border : BorderData
        The masks' data on this mesh (:func:`sfem_filters.cardiac.border_data.guided_border_data` or
        :func:`~sfem_filters.cardiac.border_data.mask_border_data`).
    phase_scale : float
        The phase data's level (dimensionless).
    candidates : sequence of float
        Factors on the masks' variance (dimensionless, > 0).

    Returns
    -------
    (factor, table)
        The chosen factor on ``R_b`` and ``{candidate: [log-evidence, c]}`` of the candidates evaluated.
        When the evidence is largest at the largest candidate (the masks disagree with the phase data
        more than any level tried), a ``RuntimeWarning`` says so.
    """
    say = progress if progress is not None else (lambda msg: None)
    fs = sorted(float(positive("candidates", v)) for v in candidates)
    if not fs:
        raise ValueError("candidates: expected at least one factor on the masks' variance, got none")
    if not hasattr(border, "R"):
        raise TypeError(f"border: expected a BorderData, got {type(border).__name__}")
    table = {}
    model, y, _, _ = build_dense_model(mesh, tracks, pixel_size_m, settings, background, border,
                                       phase_scale=phase_scale)
    first = y.shape[1] - np.asarray(border.y).shape[1]                    # the masks' rows, below the nodal fit

    def evidence(i):
        f = fs[i]
        if f not in table:
            table[f] = list(_concentrated_evidence_of(model.with_block_noise(first, f), y))
            say(f"masks' variance x {f:g}: log-evidence {table[f][0]:.1f}")
        return table[f][0]

    # the evidence is taken to be unimodal in the factor: start at the three candidates around the one nearest
    # MASK_LEVEL_START and walk outwards while the best is at an end of what was evaluated
    i0 = int(np.argmin(np.abs(np.log(fs) - np.log(MASK_LEVEL_START))))
    lo, hi = max(i0 - 1, 0), min(i0 + 1, len(fs) - 1)
    while True:
        ev = [evidence(i) for i in range(lo, hi + 1)]
        k = int(np.argmax(ev))
        if k == 0 and lo > 0:
            lo -= 1
        elif k == len(ev) - 1 and hi < len(fs) - 1:
            hi += 1
        else:
            break
    if len(fs) > 1 and k == len(ev) - 1 and hi == len(fs) - 1:
        warnings.warn(f"masks: their evidence still rises at the largest factor on their variance tried (x {fs[-1]:g}): "
                      "the masks' borders disagree with the phase data's motion more than any level allows, so they "
                      "get the least weight offered, which may still be too much; check that the masks belong to "
                      "these images (the reference mask at the encoding, then each frame's), or run without them "
                      "(--no-masks; border_masks=False)", RuntimeWarning, stacklevel=user_stacklevel())
    return _best_on_log_grid(np.array(fs[lo:hi + 1]), np.array(ev)), table


def process_fraction_ml(mesh: TriMesh, tracks: LagrangianDisplacement, pixel_size_m: float,
                        settings: StrainRouteSettings, candidates=PROCESS_FRACTIONS, progress=None,
                        background=None, border=None) -> tuple:
    """The process noise fraction of largest evidence (type-II maximum likelihood), from the data alone.

    For each candidate, one Kalman filter pass (no smoothing, nothing stored) of the route's
    model (:func:`build_dense_model`) gives the log-likelihood of the data by the
    prediction-error decomposition; the common noise level is profiled out
    (:func:`concentrated_log_evidence`), so what is compared is how the data's variance divides
    between the motion's frame-to-frame change (process noise) and the data's noise. The best
    candidate is refined by the vertex of the parabola through it and its two neighbours in
    ``log q`` (kept within them), when it is not at an end of the grid.

    Why not the fixed 0.1 of the measured-data rule: on dense data that prior is stiff in time,
    the smoother flattens the peaks of the strain curves and the ML noise scale of step 6 a
    comes out far above 1 (the innovations are larger than the model allows); the evidence
    prefers a process noise near the noise floor itself. Held-out pixels are no cleaner
    referee here: the phase texture is correlated over neighbouring pixels, so a held-out
    pixel's noise is partly predictable from its neighbours and the cross-validation error keeps
    falling as the smoothing weakens.

    ``background`` and ``border`` as :func:`build_dense_model`'s (the masks' border rows, when given,
    are part of the data whose evidence is compared).

    Returns ``(q, table)``: the chosen fraction and ``{candidate: [log-evidence, c]}``.
    """
    say = progress if progress is not None else (lambda msg: None)
    qs = sorted(float(positive("candidates", v)) for v in candidates)
    if not qs:
        raise ValueError("candidates: expected at least one process fraction, got none")
    table, evid = {}, []
    for q in qs:
        model, y, _, _ = build_dense_model(mesh, tracks, pixel_size_m, replace(settings, process_fraction=q),
                                           background, border)
        ev, c = _concentrated_evidence_of(model, y)
        table[q] = [ev, c]
        evid.append(ev)
        say(f"process fraction {q:g}: log-evidence {ev:.1f} (noise scale {c:.2f})")
    return _best_on_log_grid(np.array(qs), np.array(evid)), table
