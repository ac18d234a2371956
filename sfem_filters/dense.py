"""Closing the loop on measured point-wise motion (DENSE, tagging, tracking).

The paper's section 3.2 workflow on a :class:`sfem_filters.datasets.Sequence`:

1. mesh the myocardium on the measured points, find endo- and epicardium, the cavity centre
   and the radial / circumferential directions;
2. observe sparse landmarks on each contour (as shape tracking gives) and, optionally, a
   seeded half of the mid-wall points; hold every other point out for validation;
3. drive the elastic model with the landmarks through confidence-weighted penalty springs
   (section 2.7), with a measured cavity pressure, or with nothing but its effects;
4. run the joint EKF over cyclic loops (kinematics and a regional material map);
5. diagnose the residual (innovations, NIS, whiteness, held-out error), rank candidate
   missing effects by a score test, add the best one and run again.

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

from . import diagnostics
from .datasets import Sequence
from .effects import CATALOGUE, build_effects
from .fem import node_dofs, penalty_load, penalty_stiffness, pressure_load, stiffness_matrix
from .filters import cyclic_estimate
from .material import Material, Parameterisation
from .myocardium import _polygon_centroid, contour_landmarks, lv_geometry, mesh_from_points
from .model import SFEMModel
from .strain import nodal_strains

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
}

#: Per-frame random-walk step of effect amplitudes (units of NOMINAL["E"]): a myocardial active
#: strain of ~0.4 builds up over ~10 frames.
EFFECT_STEP = 0.04

#: The smooth material basis (``estimate="basis"``): leading modes of a squared-exponential
#: correlation over element centroids, its length a fraction of the mesh's diameter; relative
#: stiffness (mean log E fixed, as with the regions), Poisson's ratio absolute.
BASIS = {"modes_E": 6, "modes_nu": 3, "length_fraction": 0.25}

ESTIMATES = ("region", "basis", "element", "none")
DRIVES = ("penalty", "pressure", "none")
OBSERVE = ("boundary", "boundary+midwall")


def noise_floor(displacement) -> float:
    """Measurement noise estimated from the data (per-point vector RMS, data units).

    The second difference of a smooth trajectory is small, that of white noise has variance
    1.5 sigma^2 per component for ``u_t - (u_{t-1} + u_{t+1}) / 2``; the per-point figure is
    ``sqrt(2) sigma``.
    """
    u = np.asarray(displacement, float)
    d2 = u[1:-1] - 0.5 * (u[:-2] + u[2:])
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
    noise_px: float                 # per-point noise floor (data units)
    n_landmarks: int
    observe: str
    holdout_seed: int
    regions: np.ndarray = field(default=None)   # material region of each element
    # image-derived data (sfem_filters.frontend): when set, they replace the sequence's own
    # displacements at the observed points, and add velocity rows (Eq. 13)
    obs_displacement: np.ndarray = field(default=None)   # (F, P, 2) data units, NaN if missing
    obs_sigma: np.ndarray = field(default=None)          # (F, P) per-component sd, data units
    obs_confidence: np.ndarray = field(default=None)     # (F, P) in [0, 1]
    velocity_points: np.ndarray = field(default=None)    # points with velocity data
    velocity: np.ndarray = field(default=None)           # (F, V, 2) data units per second
    velocity_sigma: np.ndarray = field(default=None)     # (F, V) per-component sd, units per second


def prepare(seq: Sequence, landmarks: int = 8, observe: str = "boundary", holdout_seed: int = 0,
            n_sectors: int = 6) -> Setup:
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
    """
    if observe not in OBSERVE:
        raise ValueError(f"observe: expected one of {OBSERVE}, got {observe!r}")
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
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    np.fill_diagonal(d, np.inf)
    lattice = np.median(d.min(axis=1))
    mesh = mesh_from_points(pts, 1.5 * lattice)
    if mesh.n_nodes != len(pts):
        raise ValueError(f"points: {len(pts) - mesh.n_nodes} points lie in no triangle of the tissue mesh "
                         "(isolated pixels?); remove them")
    node_of_point = np.arange(len(pts))
    geometry = lv_geometry(mesh)
    endo_l, epi_l = contour_landmarks(geometry, mesh, landmarks)
    lm = np.concatenate([endo_l, epi_l])
    observed = lm
    if observe == "boundary+midwall":
        rng = np.random.default_rng(holdout_seed)
        mid = geometry.midwall
        observed = np.union1d(lm, rng.choice(mid, size=len(mid) // 2, replace=False))
    heldout = np.setdiff1d(np.arange(len(pts)), observed)
    # regional map: angular sectors x (inner, outer) halves of the wall
    from .effects import transmural_depth
    c = mesh.centroids - geometry.centre
    sector = np.floor(np.mod(np.arctan2(c[:, 1], c[:, 0]), 2 * np.pi) / (2 * np.pi / n_sectors)).astype(int)
    layer = (transmural_depth(mesh, geometry) > 0.5).astype(int)
    return Setup(seq=seq, spacing=spacing, frame_interval=T, nominal=nominal, mesh=mesh, geometry=geometry,
                 node_of_point=node_of_point, landmarks=lm, observed=observed, heldout=heldout,
                 noise_px=noise_floor(seq.displacement), n_landmarks=landmarks, observe=observe,
                 holdout_seed=holdout_seed, regions=2 * sector + layer)


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
    """The smooth relative material basis of ``estimate="basis"`` (defaults: :data:`BASIS`).

    ``length_fraction`` times the largest distance between element centroids is the
    correlation length of :meth:`Parameterisation.smooth`.
    """
    c = mesh.centroids
    diameter = float(np.sqrt(np.max(np.sum((c[:, None, :] - c[None, :, :]) ** 2, axis=2))))
    frac = BASIS["length_fraction"] if length_fraction is None else length_fraction
    return Parameterisation.smooth(c, frac * diameter, BASIS["modes_E"] if modes_E is None else modes_E,
                                   BASIS["modes_nu"] if modes_nu is None else modes_nu, NOMINAL["E"])


def build_model(setup: Setup, effects=(), drive: str = "penalty", estimate: str = "region",
                process_scale: float = 1.0, landmark_step_px: float | None = None,
                beta: float | None = None) -> tuple:
    """The filter model of a set-up, and the observations it is fed (m, and m/s for velocities).

    ``landmark_step_px`` sets the per-frame uncertainty of the spring targets (data units);
    by default it is the RMS frame-to-frame motion of the landmarks in the data. ``beta`` (s)
    overrides the Rayleigh stiffness coefficient ``NOMINAL["beta"]``: velocity data inform the
    displacement only when the model's transients last a good part of a frame.

    Returns ``(model, observations)`` with observations of shape (frames, 2 * n_observed
    [+ 2 * n_velocity_points]): displacement rows, then velocity rows (Eq. 13).
    """
    if drive not in DRIVES:
        raise ValueError(f"drive: expected one of {DRIVES}, got {drive!r}")
    seq, mesh, s = setup.seq, setup.mesh, setup.spacing
    F = seq.n_frames
    data = seq.displacement if setup.obs_displacement is None else setup.obs_displacement
    mat0 = Material.uniform(mesh.n_elements, NOMINAL["E"], NOMINAL["nu"])
    Kdiag = np.median(stiffness_matrix(mesh, mat0.E, mat0.nu).diagonal())
    loads = np.zeros((F, mesh.n_dofs))
    penalty = None
    nodes = setup.node_of_point
    load_std = None
    if drive == "penalty":
        lm_nodes = nodes[setup.landmarks]
        dofs = node_dofs(lm_nodes)
        conf = np.repeat(_confidence(seq, setup.landmarks, setup.obs_confidence), 2, axis=-1)  # per dof
        k = NOMINAL["penalty"] * Kdiag
        penalty = penalty_stiffness(mesh.n_dofs, dofs, k, conf.mean(axis=0) if conf.ndim == 2 else conf)
        b = _filled(data[:, setup.landmarks]) * s                          # (F, L, 2) m
        # Causal zero-order hold of the data: over the interval into frame t the springs pull
        # toward the landmarks measured at frame t - 1, so frame t's data enter only through
        # the measurement update and the innovation stays a one-step-ahead prediction error.
        for t in range(F):
            c_t = conf[max(t - 1, 0)] if conf.ndim == 2 else conf
            loads[t] = penalty_load(mesh.n_dofs, dofs, k, b[max(t - 1, 0)].reshape(-1), c_t)
        # Process noise: the landmarks move by an unknown amount between frames, so the spring
        # targets are uncertain by the data's own frame-to-frame landmark motion; the random
        # spring loads reach the tissue through the dynamics (elastically correlated noise).
        if landmark_step_px is None:
            landmark_step_px = np.sqrt(np.nanmean(np.diff(data[:, setup.landmarks], axis=0) ** 2))
        step = landmark_step_px * s
        load_std = np.zeros(mesh.n_dofs)
        load_std[dofs] = k * step * (conf.mean(axis=0) if conf.ndim == 2 else conf)
    else:
        ground = NOMINAL["foundation"] * Kdiag
        penalty = penalty_stiffness(mesh.n_dofs, np.arange(mesh.n_dofs), ground)
        if drive == "pressure":
            if seq.pressure is None:
                raise ValueError("drive: 'pressure' needs a sequence with a cavity 'pressure' per frame")
            unit = pressure_load(mesh, setup.geometry.endo_edges, 1.0)
            loads = seq.pressure[:, None] * unit[None]
    obs_nodes = nodes[setup.observed]
    D = sp.csr_matrix((np.ones(2 * len(obs_nodes)), (np.arange(2 * len(obs_nodes)), node_dofs(obs_nodes))),
                      shape=(2 * len(obs_nodes), mesh.n_dofs))
    y = data[:, setup.observed].reshape(F, -1) * s
    sigma = _sigma(seq, setup) * s                                       # per observed row, m
    Dv = None
    if setup.velocity_points is not None:
        v_nodes = nodes[setup.velocity_points]
        Dv = sp.csr_matrix((np.ones(2 * len(v_nodes)), (np.arange(2 * len(v_nodes)), node_dofs(v_nodes))),
                           shape=(2 * len(v_nodes), mesh.n_dofs))
        y = np.hstack([y, setup.velocity.reshape(F, -1) * s])
        v_sd = np.repeat(_per_frame(setup.velocity_sigma), 2, axis=1)
        sigma = np.hstack([sigma if sigma.ndim == 2 else np.broadcast_to(sigma, (F, sigma.size)), v_sd * s])
    noise_c = setup.noise_px / np.sqrt(2.0) * s                          # per component, m
    param = None
    if estimate == "region":
        # relative stiffness between regions (mean log E fixed) and nu per region
        param = Parameterisation.relative_regions(setup.regions, NOMINAL["E"])
    elif estimate == "basis":
        param = smooth_parameterisation(mesh)
    elif estimate == "element":
        param = Parameterisation.per_element(mesh.n_elements)
    elif estimate != "none":
        raise ValueError(f"estimate: expected one of {ESTIMATES}, got {estimate!r}")
    effs = build_effects(effects, mesh, setup.geometry, scale=NOMINAL["E"], process_std=EFFECT_STEP * process_scale,
                         initial_std=EFFECT_STEP) if effects else []
    # initial state: at rest in equilibrium with the frame-0 drive
    Kt = stiffness_matrix(mesh, mat0.E, mat0.nu) + (penalty if penalty is not None else 0)
    u0 = sp.linalg.spsolve(Kt.tocsc(), loads[0]) if drive != "none" else np.zeros(mesh.n_dofs)
    model = SFEMModel(mesh, mat0, loads, D, setup.frame_interval, (), density=NOMINAL["density"],
                      alpha=NOMINAL["alpha"], beta=NOMINAL["beta"] if beta is None else beta,
                      measurement_std=sigma, velocity_observation=Dv,
                      process_std=(0.1 * process_scale * noise_c, 0.1 * process_scale * noise_c / setup.frame_interval),
                      initial_std=(noise_c, noise_c / setup.frame_interval), estimate=param,
                      prior_std=(0.3, 1.0), penalty=penalty, effects=effs, initial_displacement=u0,
                      process_load_std=None if load_std is None else process_scale * load_std)
    return model, y


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


def evaluate(setup: Setup, model: SFEMModel, result, seconds: float = 0.0) -> tuple:
    """Held-out error, innovations and NIS of a run, in data units (pixels)."""
    s = setup.spacing
    U = model.displacements(result.states).reshape(setup.seq.n_frames, -1, 2)[:, setup.node_of_point] / s
    meas = setup.seq.displacement
    h = setup.heldout
    r = meas[:, h] - U[:, h]                                              # (F, H, 2)
    er = setup.geometry.radial[setup.node_of_point[h]]
    ec = setup.geometry.circumferential[setup.node_of_point[h]]
    rad = np.sum(r * er[None], axis=2)
    circ = np.sum(r * ec[None], axis=2)
    norm2 = np.sum(r ** 2, axis=2)
    per_frame = np.sqrt(np.nanmean(norm2, axis=1))
    rows = np.arange(2 * len(setup.observed)).reshape(-1, 2)
    nis = diagnostics.nis_summary(result.history)
    white = diagnostics.whiteness(result.history)
    cons = diagnostics.consistency(result.history)
    mat = model.material_of_theta(result.theta)
    metrics = {
        "heldout_rmse_px": float(np.sqrt(np.nanmean(norm2))),
        "heldout_rmse_radial_px": float(np.sqrt(np.nanmean(rad ** 2))),
        "heldout_rmse_circumferential_px": float(np.sqrt(np.nanmean(circ ** 2))),
        "heldout_rmse_per_frame_px": per_frame.tolist(),
        "heldout_rmse_worst_frame_px": float(np.nanmax(per_frame)),
        "innovation_rms_px": diagnostics.innovation_rms(result.history, rows_of_points=rows) / s,
        "nis_mean_over_dof": nis["nis_mean_over_dof"],
        "nis_fraction_outside_95": nis["nis_fraction_outside_95"],
        "innovation_lag1_autocorrelation": white["lag1"],
        "whiteness_Q": white["Q"], "whiteness_p": white["p_value"],
        "nis_z": cons["nis_z"], "lag1_z": cons["lag1_z"], "inconsistent": cons["inconsistent"],
        "loops": int(result.loops), "converged": bool(result.converged),
        # how far the last loop moved the material against its carried sd (None: material fixed)
        "material_drift_sd": (float(diagnostics.material_drift(model, result.history)["max_sd"][-1])
                              if model.estimates_material else None),
        "E_relative_range": [float(mat.E.min() / NOMINAL["E"]), float(mat.E.max() / NOMINAL["E"])],
        "nu_range": [float(mat.nu.min()), float(mat.nu.max())],
        "seconds": float(seconds),
    }
    if model.dim_eta:
        eta = np.array([model.eta_of(x) for x in result.states])
        metrics["effect_states"] = eta.tolist()
        metrics["effect_state_names"] = [f"{e.name}[{i}]" for e in model.effects for i in range(e.n_states)]
    return U, metrics


def run(setup: Setup, effects=(), drive: str = "penalty", estimate: str = "region", max_loops: int = 5,
        process_scale: float = 1.0, tol: float = 1e-3, progress: bool = False, name: str = "",
        landmark_step_px: float | None = None, beta: float | None = None) -> Run:
    """Build the model, run the cyclic joint EKF and evaluate it (``beta``: see :func:`build_model`)."""
    model, y = build_model(setup, effects, drive, estimate, process_scale, landmark_step_px, beta)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="cyclic_estimate: the material did not converge")
        result = cyclic_estimate(model, y, max_loops=max_loops, tol=tol, progress=progress,
                                 description=name or "dense")
    U, metrics = evaluate(setup, model, result, time.perf_counter() - t0)
    return Run(name, model, result, U, metrics)


def candidate_loads(setup: Setup, names=None) -> list:
    """(name, load matrix) of every catalogue effect, for scoring."""
    names = sorted(CATALOGUE) if names is None else names
    effs = build_effects(names, setup.mesh, setup.geometry, scale=NOMINAL["E"])
    return [(e.name, e.loads) for e in effs]


def closing_the_loop(seq: Sequence, effects="auto", drive: str = "penalty", landmarks: int = 8,
                     observe: str = "boundary", holdout_seed: int = 0, estimate: str = "region",
                     max_loops: int = 5, progress: bool = False) -> dict:
    """Baseline run, residual diagnostics, effect ranking, extended run: the whole loop.

    Parameters
    ----------
    effects : "auto", "none" or a sequence of effect names
        ``auto`` adds the effect the score test ranks first.
    """
    setup = prepare(seq, landmarks, observe, holdout_seed)
    base = run(setup, (), drive, estimate, max_loops, progress=progress, name="baseline")
    ranking = diagnostics.rank_effects(base.model, base.result.history, candidate_loads(setup))
    if isinstance(effects, str):
        if effects == "auto":
            chosen = [ranking[0]["effect"]]
        elif effects == "none":
            chosen = []
        else:
            chosen = [e.strip() for e in effects.split(",") if e.strip()]
    else:
        chosen = list(effects)
    ext = run(setup, chosen, drive, estimate, max_loops, progress=progress, name="extended") if chosen else base
    return {
        "setup": setup, "baseline_run": base, "extended_run": ext,
        "report": {
            "noise_floor_px": setup.noise_px,
            "measured": measured_wall_kinematics(setup),
            "nominal": {k: NOMINAL[k] for k in setup.nominal},
            "config": {"drive": drive, "landmarks": landmarks, "observe": observe, "holdout_seed": holdout_seed,
                       "estimate": estimate, "max_loops": max_loops, "n_points": int(seq.n_points),
                       "n_frames": int(seq.n_frames), "n_observed": int(len(setup.observed)),
                       "n_heldout": int(len(setup.heldout)), "mesh_nodes": int(setup.mesh.n_nodes),
                       "mesh_elements": int(setup.mesh.n_elements)},
            "baseline": base.metrics,
            "extended": {"effects": chosen, **ext.metrics},
            "ranking": [{"effect": r["effect"], "score": r["score"], "lm": r["lm"], "df": r["df"],
                         "explained": r["explained"]} for r in ranking],
        },
    }


def strain_maps(setup: Setup, U_px) -> np.ndarray:
    """Radial, circumferential and shear strain at each node w.r.t. frame 0, (frames, nodes, 3)."""
    mesh, g = setup.mesh, setup.geometry
    U = np.asarray(U_px, float) - np.asarray(U_px, float)[0]
    eps = nodal_strains(mesh, U.reshape(len(U), -1) * setup.spacing)   # e_xx, e_yy, gamma_xy
    exx, eyy, gxy = eps[..., 0], eps[..., 1], eps[..., 2]
    er, ec = g.radial, g.circumferential

    def proj(a, b):
        return (exx * a[:, 0] * b[:, 0] + eyy * a[:, 1] * b[:, 1]
                + 0.5 * gxy * (a[:, 0] * b[:, 1] + a[:, 1] * b[:, 0]))

    return np.stack([proj(er, er), proj(ec, ec), 2 * proj(er, ec)], axis=-1)


def measured_wall_kinematics(setup: Setup) -> dict:
    """What the data themselves say about the wall, per frame and at the systolic peak.

    Wall area ratio (deformed over reference area of the tissue mesh), mean wall thickness
    (mean over angle of epicardial minus endocardial radius about the cavity centre, both
    contours interpolated in angle), mean radial and circumferential strain w.r.t. frame 0;
    the displacement RMS of the first frame (is it at rest?) and between the last and first
    frames (does the cycle close?). Data units (pixels).
    """
    mesh, g, seq = setup.mesh, setup.geometry, setup.seq
    P = seq.points
    U = _filled(seq.displacement)
    tri = mesh.elements
    def areas(X):
        p = X[tri]
        return 0.5 * np.abs((p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
                            - (p[:, 2, 0] - p[:, 0, 0]) * (p[:, 1, 1] - p[:, 0, 1]))
    a0 = areas(P).sum()
    area_ratio = np.array([areas(P + U[t]).sum() / a0 for t in range(len(U))])
    grid = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    def thickness(X):
        c = _polygon_centroid(X[g.endo])
        out = []
        for loop in (g.endo, g.epi):
            d = X[loop] - c
            ang = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
            o = np.argsort(ang)
            out.append(np.interp(grid, ang[o], np.linalg.norm(d, axis=1)[o], period=2 * np.pi))
        return float(np.mean(out[1] - out[0]))
    thick = np.array([thickness(P + U[t]) for t in range(len(U))])
    eps = strain_maps(setup, U)
    peak = int(np.argmax(area_ratio))
    return {"peak_frame": peak, "wall_area_ratio_peak": float(area_ratio[peak]),
            "wall_thickness_px_frame0": float(thick[0]), "wall_thickness_px_peak": float(thick[peak]),
            "mean_radial_strain_peak": float(eps[peak, :, 0].mean()),
            "mean_circumferential_strain_peak": float(eps[peak, :, 1].mean()),
            "frame0_displacement_rms_px": float(np.sqrt(np.mean(np.sum(U[0] ** 2, axis=1)))),
            "last_to_first_rms_px": float(np.sqrt(np.mean(np.sum((U[-1] - U[0]) ** 2, axis=1)))),
            "wall_area_ratio": area_ratio.tolist(), "wall_thickness_px": thick.tolist()}


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


def format_report(report: dict) -> str:
    """Text summary of :func:`closing_the_loop`."""
    b, e = report["baseline"], report["extended"]
    cfg = report["config"]
    lines = [f"{cfg['n_points']} points, {cfg['n_frames']} frames; mesh {cfg['mesh_nodes']} nodes, "
             f"{cfg['mesh_elements']} triangles; {cfg['n_observed']} observed, {cfg['n_heldout']} held out "
             f"({cfg['landmarks']} landmarks per contour, observe {cfg['observe']}, drive {cfg['drive']}, "
             f"material {cfg['estimate']})",
             f"noise floor {report['noise_floor_px']:.3f} px" + (
                 f"; nominal (not in the file): {report['nominal']}" if report["nominal"] else ""),
             "data: wall area x{w:.3f} and wall thickness {t0:.2f} -> {tp:.2f} px at frame {f} (peak area); mean strain "
             "there E_rr {er:+.3f}, E_cc {ec:+.3f} (w.r.t. frame 0); frame 0 displacement RMS {r0:.2f} px, last-to-first "
             "{rl:.2f} px".format(w=report["measured"]["wall_area_ratio_peak"], t0=report["measured"]["wall_thickness_px_frame0"],
                                  tp=report["measured"]["wall_thickness_px_peak"], f=report["measured"]["peak_frame"],
                                  er=report["measured"]["mean_radial_strain_peak"],
                                  ec=report["measured"]["mean_circumferential_strain_peak"],
                                  r0=report["measured"]["frame0_displacement_rms_px"],
                                  rl=report["measured"]["last_to_first_rms_px"]),
             "", "ranking of candidate effects (score test on the baseline innovations; -log10 p, higher = stronger):"]
    for r in report["ranking"]:
        lines.append(f"  {r['effect']:<24} {r['score']:9.1f}   LM = {r['lm']:9.1f} on {r['df']:3d} dof, "
                     f"explains {100 * r['explained']:5.1f}% of the NIS")
    lines += ["", f"{'':<34}{'baseline':>12}{'extended':>18}", f"{'effects':<34}{'none':>12}{','.join(e['effects']) or 'none':>18}"]
    for key, label in (("heldout_rmse_px", "held-out RMSE [px]"), ("heldout_rmse_radial_px", "  radial [px]"),
                       ("heldout_rmse_circumferential_px", "  circumferential [px]"),
                       ("heldout_rmse_worst_frame_px", "  worst frame [px]"),
                       ("innovation_rms_px", "innovation RMS [px]"), ("nis_mean_over_dof", "mean NIS / dof (1 = consistent)"),
                       ("nis_fraction_outside_95", "frames outside 95% NIS band"),
                       ("innovation_lag1_autocorrelation", "innovation lag-1 autocorrelation"),
                       ("nis_z", "NIS z (|z| > 3: inconsistent)"), ("lag1_z", "whiteness z (|z| > 3: correlated)")):
        lines.append(f"{label:<34}{b[key]:>12.3f}{e[key]:>18.3f}")
    lines.append(f"{'loops (* material not converged)':<34}"
                 + "".join(f"{str(r['loops']) + ('' if r['converged'] else '*'):>{w}}" for r, w in ((b, 12), (e, 18))))
    if b.get("material_drift_sd") is not None and e.get("material_drift_sd") is not None:
        lines.append(f"{'last loop material step / sd':<34}{b['material_drift_sd']:>12.3f}{e['material_drift_sd']:>18.3f}")
    if "active_polar[0]" in e.get("effect_state_names", []):
        offset = e["effect_state_names"].index("active_polar[0]")
        st = np.array(e["effect_states"])[:, offset:offset + 2]
        peak = int(np.argmax(np.abs(st[:, 1])))
        eps = equivalent_eigenstrain(st[peak])
        lines.append(f"active_polar at frame {peak}: a_c = {st[peak, 0]:.3f}, a_r = {st[peak, 1]:.3f} (x E0), "
                     f"equivalent eigenstrain eps_cc = {eps[0]:+.3f}, eps_rr = {eps[1]:+.3f}")
    return "\n".join(lines)
