"""Step 2, the filter model of a set-up: the drive (springs toward landmarks or contours, a
measured pressure, or none), the material map's parameterisation, the effects, and the
observations with their noise (:func:`build_model`)."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..._validate import positive
from ...fem.dofs import node_dofs
from ...fem.elasticity import stiffness_matrix
from ...fem.loads import penalty_load, penalty_stiffness, pressure_load
from ...fem.material import Material, Parameterisation
from ...model import SFEMModel
from ..effects import build_effects
from ..myocardium import polar_strain_operator
from ..reference import contour_interpolant
from ..sequence import Sequence
from .settings import BASIS, DRIVES, EFFECT_STEP, NOMINAL, PARAMETERISATIONS
from .setup import Setup, point_rows

__all__ = ["smooth_parameterisation", "build_model"]


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
                             "tissue's rigid-body motion; expected confidence > 0 on at least 3 landmarks not on one "
                             "line")
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
