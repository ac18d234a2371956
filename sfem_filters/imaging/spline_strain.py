"""The physics-free yardstick for strain: a thin-plate spline through observed points, frame by frame.

Issue 42 asks every strain route to be reported beside "the thin-plate spline through the same
observed points". :func:`spline_strain` interpolates the observed points' displacements of every
frame with the thin-plate spline (kernel ``r^2 log r`` plus an affine part, no smoothing: it
passes through every datum, as :func:`sfem_filters.cardiac.reference.spline_reference` does for
displacements) and differentiates the interpolant *analytically* at the reference pixels:

``u_i(X) = sum_n w_in phi(|X - X_n|) + a_i0 + a_i1 x + a_i2 y``, ``phi(r) = r^2 log r``, and
``d phi / d X = (X - X_n) (2 log r + 1)`` (0 at ``r = 0``), so ``G = grad u`` is exact for the
interpolant and an affine displacement field is reproduced exactly (its spline has ``w = 0``).
Strain is Green-Lagrange, ``E = (F^T F - I) / 2`` with ``F = I + G``, projected on the radial and
circumferential directions about a centre (:mod:`sfem_filters.imaging.strain`).

The interpolant is linear in the data, ``G = A y``, so when the data's sd is given the strain's sd
follows by the delta method exactly as in the finite-element route: ``dEcc = (F e_c) . (dG e_c)``,
``dErr = (F e_r) . (dG e_r)`` linearised at the estimate, the data independent between points and
components; the global and six segment curves (means over pixels) get their variance from the
same linear map, so their 95% bands hold the correlation between pixels that share data.

Units: pixels for points and displacements (x = column, y = row); strain is a fraction; times in s.

>>> import numpy as np
>>> from sfem_filters.imaging.spline_strain import spline_strain
>>> t = np.linspace(0, 2 * np.pi, 24, endpoint=False)
>>> ring = np.concatenate([np.column_stack([10 + r * np.cos(t), 10 + r * np.sin(t)]) for r in (4, 8)])
>>> u = 0.1 * (ring - 10)                                       # a 10% dilation: affine
>>> pix = np.array([[16.0, 10.0], [10.0, 4.0]])
>>> s = spline_strain(ring, u[None], pix, centre=(10, 10))
>>> np.round(s.Ecc, 6).tolist(), np.round(s.Err, 6).tolist()  # ((1.1)^2 - 1) / 2
([[0.105, 0.105]], [[0.105, 0.105]])
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import scipy.linalg as sla

from .._validate import as_float_array
from .strain import N_SEGMENTS, Z95, StrainEstimate, green_strain, project_strain, radial_circumferential, \
    segment_labels

__all__ = ["SplineStrain", "spline_strain", "tps_gradient_operators"]



@dataclass(frozen=True, eq=False)
class SplineStrain(StrainEstimate):
    """:class:`~sfem_filters.imaging.strain.StrainEstimate` of the thin-plate spline: strain of every
    reference pixel and frame (NaN in a frame with fewer than 3 observed points), its sd by the delta
    method when the data's sd was given (NaN otherwise), ``route`` = ``"spline"``."""

    ROUTE: ClassVar[str] = "spline"


def _phi(r):
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(r > 0, r ** 2 * np.log(np.where(r > 0, r, 1.0)), 0.0)


def tps_gradient_operators(points, query) -> tuple:
    """Linear maps from data at ``points`` to the thin-plate spline's value and gradient at ``query``.

    Parameters
    ----------
    points : (N, 2) array
        Data sites (any length unit), at least 3 not on one line, distinct.
    query : (Q, 2) array
        Where to evaluate (same unit).

    Returns
    -------
    (V, Ax, Ay) : three (Q, N) arrays
        For data ``y`` (N,) at the sites, the interpolant at the query points is ``V @ y`` and its
        derivatives along x and y are ``Ax @ y`` and ``Ay @ y`` (per unit of length).

    Coordinates are shifted to the sites' centroid and scaled by their spread before the solve
    (the spline with the affine part is invariant to both, so this only conditions the system).
    """
    X = as_float_array("points", points, shape=(None, 2))
    Q = as_float_array("query", query, shape=(None, 2))
    N = len(X)
    if N < 3 or np.linalg.matrix_rank(X - X.mean(axis=0), tol=1e-9 * max(float(np.ptp(X)), 1e-300)) < 2:
        raise ValueError(f"points: expected at least 3 sites not on one line, got {N}")
    c = X.mean(axis=0)
    s = float(np.max(np.linalg.norm(X - c, axis=1)))
    x, q = (X - c) / s, (Q - c) / s
    r = np.linalg.norm(x[:, None] - x[None], axis=2)
    if np.any(r[np.triu_indices(N, 1)] < 1e-12):
        raise ValueError("points: expected distinct sites, got repeated ones")
    P = np.column_stack([np.ones(N), x])
    A = np.block([[_phi(r), P], [P.T, np.zeros((3, 3))]])
    S = sla.lu_solve(sla.lu_factor(A), np.vstack([np.eye(N), np.zeros((3, N))]))      # (N + 3, N) coefficients
    d = q[:, None] - x[None]                                                           # (Q, N, 2)
    rq = np.linalg.norm(d, axis=2)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.where(rq > 0, 2.0 * np.log(np.where(rq > 0, rq, 1.0)) + 1.0, 0.0)
    V = np.column_stack([_phi(rq), np.ones(len(q)), q]) @ S
    Ax = np.column_stack([d[..., 0] * g, np.zeros(len(q)), np.ones(len(q)), np.zeros(len(q))]) @ S / s
    Ay = np.column_stack([d[..., 1] * g, np.zeros(len(q)), np.zeros(len(q)), np.ones(len(q))]) @ S / s
    return V, Ax, Ay


def _linearised(grad, points, centre) -> tuple:
    """``a`` (F, P, 2, 2) with ``dEcc = sum_ij a_cc[i, j] dG[i, j]`` (and Err): ``(F e)_i e_j``."""
    er, ec = radial_circumferential(points, centre)
    Fd = np.eye(2) + grad
    out = []
    for e in (ec, er):
        Fe = np.einsum("fpij,pj->fpi", Fd, e)
        out.append(Fe[..., :, None] * e[None, :, None, :])
    return out[0], out[1]


def spline_strain(points_px, displacement_px, reference_pixels, sd_px=None, centre=None, start_deg: float = 0.0,
                  frame_times_s=None) -> SplineStrain:
    """Thin-plate spline through observed displacements, its Green-Lagrange strain at reference pixels.

    Parameters
    ----------
    points_px : (N, 2) array
        Reference positions of the observed points (pixels, x = column, y = row).
    displacement_px : (F, N, 2) array
        Their displacements (pixels), NaN where missing: a frame's spline uses its finite points
        (at least 3, not on one line; otherwise that frame's strain is NaN).
    reference_pixels : (P, 2) array
        Where the strain is reported (pixels), e.g. the reference mask's pixel centres.
    sd_px : (N, 2) or (F, N, 2) array, optional
        Sd of each datum's components (pixels); gives the strain's delta-method sd and the curves'
        95% bands. Without it those are NaN (``None`` in the JSON): the spline has no error model.
    centre : (2,) array, optional
        Centre (pixels) of radial directions and segments; default the mean of
        ``reference_pixels`` (for a mask's pixels, its centre of mass, as the scoring spec says).
    start_deg : float
        Start of segment 0 (degrees from +x towards +y).
    frame_times_s : (F,) array, optional
        Frame times (s), carried into the result.

    Returns
    -------
    SplineStrain
    """
    t0 = time.perf_counter()
    X = as_float_array("points_px", points_px, shape=(None, 2))
    u = as_float_array("displacement_px", displacement_px, shape=(None, len(X), 2), allow_nan=True)
    Xp = as_float_array("reference_pixels", reference_pixels, shape=(None, 2))
    if len(Xp) == 0:
        raise ValueError("reference_pixels: expected at least one pixel, got none")
    F, P = len(u), len(Xp)
    if F == 0:
        raise ValueError("displacement_px: expected at least one frame, got none")
    sd = None
    if sd_px is not None:
        sd = as_float_array("sd_px", sd_px, allow_nan=True)
        if sd.shape == (len(X), 2):
            sd = np.broadcast_to(sd, u.shape)
        if sd.shape != u.shape:
            raise ValueError(f"sd_px: expected shape ({len(X)}, 2) or {u.shape} pixels, got {sd.shape}")
        if np.any(sd[np.isfinite(sd)] < 0):
            raise ValueError("sd_px: expected non-negative standard deviations (pixels)")
    c = Xp.mean(axis=0) if centre is None else as_float_array("centre", centre, shape=(2,))
    times = np.full(F, np.nan) if frame_times_s is None else as_float_array("frame_times_s", frame_times_s,
                                                                            shape=(F,))
    labels = segment_labels(Xp, c, start_deg)
    groups = [np.arange(P)] + [np.flatnonzero(labels == k) for k in range(N_SEGMENTS)]
    grad = np.full((F, P, 2, 2), np.nan)
    disp = np.full((F, P, 2), np.nan)
    ops = {}
    ok_frames = np.isfinite(u).all(axis=2)
    for f in range(F):
        key = ok_frames[f].tobytes()
        if key not in ops:
            sel = np.flatnonzero(ok_frames[f])
            try:
                ops[key] = (sel, tps_gradient_operators(X[sel], Xp))
            except ValueError:
                ops[key] = (sel, None)
        sel, op = ops[key]
        if op is None:
            continue
        V, Ax, Ay = op
        y = u[f, sel]
        disp[f] = V @ y
        grad[f, :, :, 0] = (Ax @ y)
        grad[f, :, :, 1] = (Ay @ y)
    ecc, err, ecr = project_strain(green_strain(grad), Xp, c)
    sd_cc = np.full((F, P), np.nan)
    sd_rr = np.full((F, P), np.nan)
    curve_sd = {q: np.full((F, 1 + N_SEGMENTS), np.nan) for q in ("Ecc", "Err")}
    if sd is not None:
        a_cc, a_rr = _linearised(np.nan_to_num(grad), Xp, c)
        for f in range(F):
            sel, op = ops[ok_frames[f].tobytes()]
            if op is None:
                continue
            _, Ax, Ay = op
            v = sd[f, sel] ** 2                                            # (n, 2) per component
            for q, a, out in (("Ecc", a_cc[f], sd_cc), ("Err", a_rr[f], sd_rr)):
                # dE_p = sum_i (a[p, i, 0] Ax[p] + a[p, i, 1] Ay[p]) . dy_i: one (P, n) row block per component
                rows = [a[:, i, 0, None] * Ax + a[:, i, 1, None] * Ay for i in range(2)]
                out[f] = np.sqrt(sum((r ** 2) @ v[:, i] for i, r in enumerate(rows)))
                for g, idx in enumerate(groups):
                    if idx.size:
                        curve_sd[q][f, g] = np.sqrt(sum((r[idx].mean(axis=0) ** 2) @ v[:, i]
                                                        for i, r in enumerate(rows)))
    glob, segs = {}, {}
    for q, vals in (("Ecc", ecc), ("Err", err)):
        m = np.stack([vals[:, g].mean(axis=1) if g.size else np.full(F, np.nan) for g in groups], axis=1)
        for d, sl in ((glob, 0), (segs, slice(1, None))):
            mu, s = m[:, sl].T, curve_sd[q][:, sl].T
            d[q], d[f"{q}_sd"], d[f"{q}_lo"], d[f"{q}_hi"] = mu, s, mu - Z95 * s, mu + Z95 * s
    settings = {"kernel": "thin_plate_spline (r^2 log r) + affine, no smoothing",
                "gradient": "analytic derivative of the interpolant", "n_observed_points": int(len(X)),
                "sd": "delta method of the linear interpolant, independent data" if sd is not None else "none given"}
    return SplineStrain(points=Xp.copy(), frame_times_s=times, centre=np.asarray(c, float), start_deg=float(start_deg),
                        labels=labels, Ecc=ecc, Err=err, Ecr=ecr, Ecc_sd=sd_cc, Err_sd=sd_rr, global_curves=glob,
                        segment_curves=segs, displacement=disp, seconds=time.perf_counter() - t0, settings=settings)
