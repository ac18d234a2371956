"""From images to confidence-weighted observations, and their fusion in the joint EKF (sec. 2.6).

* :func:`observe` turns an :class:`sfem_filters.imaging.readers.ImageSeries` (masks, or intensity
  images to segment, and optionally phase-contrast velocity) into a sequence file of the
  documented format: shape-tracked border points with their confidence and error standard
  deviation, mid-wall points with velocity, LPC and error standard deviation.
* :func:`fusion_setup` feeds such data to the closing-the-loop pipeline of
  :mod:`sfem_filters.cardiac.measured` in place of a sequence's own displacements, and
  :func:`compare_fusion` runs tracked borders alone against tracked borders plus velocity,
  scored on the same held-out points of a reference motion (for example DENSE).

Units: pixels and pixels per second in sequences (as :mod:`sfem_filters.cardiac.sequence`), m/s in
velocity images, SI inside the filter.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
from scipy.stats import spearmanr

from ..imaging.contours import midwall_pixels
from ..imaging.phase_contrast import VelocityData, sample_velocity
from ..imaging.readers import ImageSeries
from ..imaging.segmentation import segment_sequence
from ..imaging.tracking import BoundaryTracks, TrackingOptions, track_masks
from .measured import prepare, run
from .sequence import Sequence, make_sequence

#: Point kinds stored in a sequence's ``point_kind``.
ENDO, EPI, MIDWALL = 0, 1, 2


@dataclass(frozen=True)
class VelocityOptions:
    """Where velocities are sampled and how their error is modelled (m/s).

    ``depth_range``: transmural depths (0 endocardium, 1 epicardium) of the mid-wall sample
    pixels; ``floor`` and ``scale``: the error model ``sqrt(floor^2 + scale^2 (1 - LPC))``,
    ``scale`` by default ``venc / pi`` (see :func:`sfem_filters.phase_contrast.sample_velocity`).
    """

    depth_range: tuple = (0.25, 0.75)
    floor: float = 0.001
    scale: float | None = None


def observe(series: ImageSeries, tracking: TrackingOptions | None = None,
            velocity: VelocityOptions | None = None, segment_kwargs: dict | None = None) -> tuple:
    """Tracked borders (and mid-wall velocities) of an image series, as a :class:`Sequence`.

    Returns
    -------
    (Sequence, BoundaryTracks, VelocityData or None, masks)
        The sequence holds every tracked border point (``displacement``, ``confidence`` = the
        match confidence c of Eq. 37, ``sigma`` = accumulated tracking error in px) and every
        mid-wall velocity point (``velocity`` px/s, ``velocity_confidence`` = LPC,
        ``velocity_sigma`` px/s); a point has NaN where it has no datum of a kind.
    """
    masks = series.masks
    if masks is None:
        masks = segment_sequence(series.magnitude, series.velocity, series.venc, **(segment_kwargs or {}))
    tracks = track_masks(masks, tracking)
    F, P = tracks.positions.shape[:2]
    vel = None
    points = tracks.points
    disp = tracks.displacement
    conf = tracks.step_confidence
    sigma = tracks.sigma
    kind = np.where(tracks.contour == 0, ENDO, EPI)
    extra = {}
    if series.velocity is not None:
        if series.pixel_spacing is None:
            raise ValueError("pixel_spacing: velocity images (m/s) need the pixel spacing (m) to give px/s")
        vopt = velocity or VelocityOptions()
        mid = midwall_pixels(masks[0], vopt.depth_range)
        if len(mid) == 0:
            raise ValueError("masks: no mid-wall pixels in the frame-0 mask to sample velocities at")
        vel = sample_velocity(series.velocity, mid, series.venc, series.pixel_spacing, vopt.floor, vopt.scale)
        V = len(mid)
        points = np.vstack([points, mid])
        disp = np.concatenate([disp, np.full((F, V, 2), np.nan)], axis=1)
        conf = np.concatenate([conf, np.zeros((F, V))], axis=1)
        # velocity-only points have no displacement (NaN); the format wants a positive sigma
        # everywhere, and the largest tracking sigma is never used for a missing datum
        sigma = np.concatenate([sigma, np.full((F, V), tracks.sigma.max())], axis=1)
        kind = np.concatenate([kind, np.full(V, MIDWALL)])
        v_all = np.concatenate([np.full((F, P, 2), np.nan), vel.velocity], axis=1)
        extra = {"velocity": v_all,
                 "velocity_confidence": np.concatenate([np.full((F, P), np.nan), vel.lpc], axis=1),
                 "velocity_sigma": np.concatenate([np.full((F, P), np.nan), vel.sigma], axis=1)}
    seq = make_sequence(points, disp, confidence=conf, sigma=sigma, frame_interval=series.frame_interval,
                        pixel_spacing=series.pixel_spacing, frame_masks=masks, reference_mask=masks[0],
                        point_kind=kind, provenance=f"sfem_filters observe: {series.provenance}", **extra)
    return seq, tracks, vel, masks


# ------------------------------------------------------------------ fusion in the joint EKF
def rereference(seq: Sequence) -> Sequence:
    """The sequence's motion measured from frame 0 (``displacement - displacement[0]``).

    Shape tracking starts at frame 0's contour, DENSE at a reference before it: comparing them
    needs a common origin.
    """
    d0 = np.nan_to_num(seq.displacement[0])
    return replace(seq, displacement=seq.displacement - d0[None])


def track_to_nodes(tracks: BoundaryTracks, node_xy, contour: int) -> tuple:
    """Tracked displacement, sigma and confidence at nodes of one border (pixels).

    Each node takes the trajectory of the tracked point of the same border (0 endo, 1 epi)
    closest to it in frame 0.

    Returns ``(displacement (F, n, 2), sigma (F, n), confidence (F, n), distance (n,))``.
    """
    sel = np.flatnonzero(tracks.contour == contour)
    d = np.linalg.norm(np.asarray(node_xy)[:, None] - tracks.points[sel][None], axis=2)
    k = sel[np.argmin(d, axis=1)]
    return tracks.displacement[:, k], tracks.sigma[:, k], tracks.step_confidence[:, k], d.min(axis=1)


def pseudo_phase_contrast(seq: Sequence, venc: float | None = None) -> tuple:
    """Velocity images (m/s) of a pixel-lattice sequence by central differences of its motion.

    For measured displacement data without a phase-contrast acquisition (DENSE): each tissue
    pixel gets the time derivative of its measured displacement (central differences, one-sided
    at the ends); pixels outside the tissue get uniformly random phase (no signal). Returns
    ``(velocity (F, H, W, 2) m/s, venc m/s)``; ``venc`` defaults to 1.5 x the largest speed.
    """
    if seq.reference_mask is None or seq.frame_interval is None or seq.pixel_spacing is None:
        raise ValueError("seq: expected reference_mask, frame_interval and pixel_spacing")
    u = seq.displacement * seq.pixel_spacing
    v = np.gradient(u, seq.frame_interval, axis=0)
    venc = 1.5 * float(np.nanmax(np.abs(v))) if venc is None else venc
    H, W = seq.reference_mask.shape
    rng = np.random.default_rng(0)
    img = rng.uniform(-venc, venc, size=(seq.n_frames, H, W, 2))
    c = np.rint(seq.points).astype(int)
    img[:, c[:, 1], c[:, 0]] = np.nan_to_num(v)
    return img, venc


def fusion_setup(seq: Sequence, tracks: BoundaryTracks, velocity: VelocityData | None = None,
                 landmarks: int = 8, velocity_fraction: float = 0.5, holdout_seed: int = 0,
                 with_velocity: bool = True):
    """A :class:`sfem_filters.cardiac.measured.Setup` fed by tracked borders (and velocities).

    ``seq`` is the reference motion on a pixel lattice (its points are the mesh nodes). The
    landmarks (``landmarks`` per border) observe the tracked displacement of the nearest
    tracked border point, weighted by its confidence and sigma; a seeded ``velocity_fraction``
    of the mid-wall points observe velocity, when ``velocity`` (sampled at ``seq.points``) is
    given and ``with_velocity``. Every other point is held out, the same points whether or not
    velocities are used, so that runs with and without them are scored alike.
    """
    setup = prepare(seq, landmarks, "boundary", holdout_seed)
    F, P = seq.n_frames, seq.n_points
    obs = np.full((F, P, 2), np.nan)
    sig = np.full((F, P), np.nan)
    conf = np.zeros((F, P))
    geo = setup.point_geometry
    for contour, loop in ((0, geo.endo), (1, geo.epi)):
        lm = np.intersect1d(setup.landmarks, loop)
        d, s, c, _ = track_to_nodes(tracks, seq.points[lm], contour)
        obs[:, lm], sig[:, lm], conf[:, lm] = d, s, c
    setup.obs_displacement, setup.obs_sigma, setup.obs_confidence = obs, sig, conf
    rng = np.random.default_rng(holdout_seed)
    mid = geo.midwall
    vpts = np.sort(rng.choice(mid, size=int(round(velocity_fraction * len(mid))), replace=False))
    setup.heldout = np.setdiff1d(np.arange(P), np.concatenate([setup.landmarks, vpts]))
    if velocity is not None and with_velocity:
        setup.velocity_points = vpts
        setup.velocity = velocity.velocity[:, vpts]
        setup.velocity_sigma = velocity.sigma[:, vpts]
    return setup


def compare_fusion(seq: Sequence, tracks: BoundaryTracks, velocity: VelocityData, landmarks: int = 8,
                   holdout_seed: int = 0, parameterisation: str = "region", max_loops: int = 3, beta: float = 0.03,
                   progress: bool = False, estimator: str = "smoother", max_iterations: int | None = None) -> dict:
    """Tracked borders alone and tracked borders plus velocity, estimated jointly (the iterated
    smoother, or ``estimator="cyclic"`` with ``max_loops``), scored on the same held-out points.

    ``beta`` (s) is the Rayleigh stiffness coefficient of both runs: velocity data inform the
    displacement only through transients that last a good part of a frame (see
    :func:`sfem_filters.cardiac.measured.build_model`).
    """
    out = {}
    for name, with_v in (("borders", False), ("borders+velocity", True)):
        setup = fusion_setup(seq, tracks, velocity, landmarks, holdout_seed=holdout_seed, with_velocity=with_v)
        r = run(setup, (), "penalty", parameterisation, max_loops, progress=progress, name=name, beta=beta,
                estimator=estimator, max_iterations=max_iterations)
        out[name] = {"heldout_rmse_px": r.metrics["heldout_rmse_px"],
                     "heldout_rmse_per_frame_px": r.metrics["heldout_rmse_per_frame_px"],
                     "nis_mean_over_dof": r.metrics["nis_mean_over_dof"],
                     "n_heldout": int(len(setup.heldout)), "seconds": r.metrics["seconds"],
                     "n_velocity_points": 0 if setup.velocity_points is None else int(len(setup.velocity_points))}
    return out


def interpolate_motion(seq: Sequence, xy) -> np.ndarray:
    """A sequence's displacement (F, n, 2) at positions ``xy`` (px, frame 0): linear inside the
    points' convex hull, nearest point outside it (border points lie half a pixel outside the
    tissue pixel centres)."""
    out = np.empty((seq.n_frames, len(xy), 2))
    for t in range(seq.n_frames):
        vals = np.nan_to_num(seq.displacement[t])
        lin = LinearNDInterpolator(seq.points, vals)(xy)
        near = NearestNDInterpolator(seq.points, vals)(xy)
        out[t] = np.where(np.isnan(lin), near, lin)
    return out


def tracking_error(seq: Sequence, tracks: BoundaryTracks) -> dict:
    """Tracked border displacements against a reference motion of the same points (pixels).

    ``seq`` should be referenced to frame 0 (:func:`rereference`). Returns per-frame RMS errors,
    their split into the border-normal and tangential components, the RMS of the reference
    motion itself (the error of reporting no motion), and Spearman rank correlations between
    ``1 - c`` and the error of each tracking step, and between the accumulated sigma and the
    accumulated error.
    """
    ref = interpolate_motion(seq, tracks.points)
    err = tracks.displacement - ref
    normals = []
    for k, b in ((0, tracks.borders[0].endo), (1, tracks.borders[0].epi)):
        tg = np.roll(b, -1, axis=0) - np.roll(b, 1, axis=0)
        tg /= np.linalg.norm(tg, axis=1, keepdims=True)
        normals.append(np.column_stack([tg[:, 1], -tg[:, 0]]))
    n = np.concatenate(normals)
    tang = np.column_stack([-n[:, 1], n[:, 0]])
    e_n, e_t = np.sum(err * n, axis=2), np.sum(err * tang, axis=2)
    r_n, r_t = np.sum(ref * n, axis=2), np.sum(ref * tang, axis=2)
    norm = np.linalg.norm(err, axis=2)
    step = np.linalg.norm(np.diff(err, axis=0), axis=2)
    rho_step = spearmanr((1 - tracks.step_confidence[1:]).ravel(), step.ravel())
    rho_acc = spearmanr(tracks.sigma[1:].ravel(), norm[1:].ravel())
    rms = lambda a: float(np.sqrt(np.mean(a ** 2)))        # noqa: E731
    return {
        "n_points": int(len(tracks.points)), "n_frames": int(seq.n_frames),
        "rmse_px": rms(norm[1:]), "rmse_per_frame_px": np.sqrt(np.mean(norm ** 2, axis=1)).tolist(),
        "rmse_normal_px": rms(e_n[1:]), "rmse_tangential_px": rms(e_t[1:]),
        "motion_rms_px": rms(np.linalg.norm(ref[1:], axis=2)),
        "motion_rms_normal_px": rms(r_n[1:]), "motion_rms_tangential_px": rms(r_t[1:]),
        "step_rmse_px": rms(step),
        "spearman_1_minus_c_vs_step_error": {"rho": float(rho_step.statistic), "p": float(rho_step.pvalue)},
        "spearman_sigma_vs_error": {"rho": float(rho_acc.statistic), "p": float(rho_acc.pvalue)},
    }
