"""The physics-free yardstick: a thin-plate spline through the observed points, frame by frame.

A model of the heart earns its keep only if it predicts held-out points better than an
interpolant that knows no mechanics. :func:`spline_reference` interpolates the observed points'
displacements of every frame with :class:`scipy.interpolate.RBFInterpolator` (kernel
``thin_plate_spline``, no smoothing: it passes through every datum, as the library's own
reports assume) and scores it on the held-out points exactly as
:func:`sfem_filters.cardiac.measured.evaluate` scores a model: total, radial and circumferential
RMSE in the data's unit (pixels).

:func:`contour_interpolant` is the same idea along a contour: a periodic cubic spline in the
angle about the cavity centre through a contour's landmarks, giving the whole border's motion
from sparse points (the contour drive of :func:`sfem_filters.cardiac.measured.build_model`).

:func:`residual_spline` joins the two kinds of prediction (regression kriging): the model's
prediction plus the same spline through the model's own residual at the observed points. If the
model knew nothing (predicted zero), this is the spline; if its error is affine (which the spline
reproduces exactly), the sum is exact. It beats the spline only where the physics captures
structure the spline's interpolation misses, which makes it the fairest test of whether the
physics earns its keep.

:func:`rmse_difference` says how sure a difference of two held-out RMSEs is (a model against
the spline, say): the held-out points' errors are correlated in space (between two landmarks an
interpolant errs the same way at every point) and in time, so the points are grouped into
clusters, contiguous angular sectors of the wall (:func:`angular_sectors`), and the difference
gets a delete-one-cluster jackknife standard error and a Student-t interval with one degree of
freedom fewer than clusters. Both predictions are scored on the same points and frames (paired).
"""
from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline, RBFInterpolator
from scipy.stats import t as student_t

from .._validate import as_float_array

__all__ = ["spline_reference", "heldout_errors", "contour_interpolant", "residual_spline", "rmse_difference",
           "angular_sectors"]


def heldout_errors(residual, radial, circumferential) -> dict:
    """RMSE of residuals (F, H, 2), total and along unit directions (H, 2), NaN ignored."""
    r = np.asarray(residual, float)
    rad = np.sum(r * np.asarray(radial)[None], axis=2)
    circ = np.sum(r * np.asarray(circumferential)[None], axis=2)
    norm2 = np.sum(r ** 2, axis=2)
    count = np.sum(~np.isnan(norm2), axis=1)
    per_frame = np.full(len(norm2), np.nan)           # NaN for a frame with no prediction
    per_frame[count > 0] = np.sqrt(np.nansum(norm2, axis=1)[count > 0] / count[count > 0])
    return {"heldout_rmse_px": float(np.sqrt(np.nanmean(norm2))),
            "heldout_rmse_radial_px": float(np.sqrt(np.nanmean(rad ** 2))),
            "heldout_rmse_circumferential_px": float(np.sqrt(np.nanmean(circ ** 2))),
            "heldout_rmse_per_frame_px": per_frame.tolist(),
            "heldout_rmse_worst_frame_px": float(np.nanmax(per_frame))}


def spline_reference(points, displacement, observed, heldout, radial, circumferential) -> dict:
    """Held-out errors of a thin-plate spline through the observed points, frame by frame.

    Parameters
    ----------
    points : (P, 2) array
        Reference positions (data unit).
    displacement : (F, P, 2) array
        Measured displacements (data unit), NaN where missing: a frame's spline uses the observed
        points it has (at least 3).
    observed, heldout : int arrays
        Indices of the points the spline passes through and of those it is scored on.
    radial, circumferential : (len(heldout), 2) arrays
        Unit directions at the held-out points, for the split of the error.

    Returns
    -------
    dict
        ``heldout_rmse_px`` and its radial and circumferential parts (and per frame), and the
        prediction ``U`` (F, len(heldout), 2).
    """
    pts = as_float_array("points", points, shape=(None, 2))
    disp = as_float_array("displacement", displacement, shape=(None, len(pts), 2), allow_nan=True)
    obs, held = np.asarray(observed, int), np.asarray(heldout, int)
    pred = np.full((len(disp), len(held), 2), np.nan)
    for t in range(len(disp)):
        ok = obs[~np.isnan(disp[t, obs]).any(axis=1)]
        if len(ok) >= 3:
            pred[t] = RBFInterpolator(pts[ok], disp[t, ok], kernel="thin_plate_spline", smoothing=0.0)(pts[held])
    out = heldout_errors(disp[:, held] - pred, radial, circumferential)
    out["U"] = pred
    return out


def residual_spline(points, displacement, model_displacement, observed, heldout, radial, circumferential) -> dict:
    """Held-out errors of a model's prediction plus a thin-plate spline of its observed residual.

    At every frame the residual ``displacement - model_displacement`` at the observed points is
    interpolated by the thin-plate spline (:func:`spline_reference`) and added to the model's
    prediction at the held-out points.

    Parameters
    ----------
    points, displacement, observed, heldout, radial, circumferential :
        As for :func:`spline_reference` (data unit).
    model_displacement : (F, P, 2) array
        The model's prediction of every point (data unit).

    Returns
    -------
    dict
        As :func:`spline_reference`, with ``U`` the corrected prediction at the held-out points.
        In a frame where fewer than 3 observed points have a residual the correction is zero (the
        model's prediction stands); NaN in the model's prediction stays NaN.
    """
    disp = as_float_array("displacement", displacement, shape=(None, None, 2), allow_nan=True)
    model = as_float_array("model_displacement", model_displacement, shape=disp.shape, allow_nan=True)
    held = np.asarray(heldout, int)
    corr = spline_reference(points, disp - model, observed, held, radial, circumferential)["U"]
    # where the residual has fewer than 3 observed points in a frame the spline is undefined: the
    # model's own prediction stands there, so that both errors are over the same frames
    pred = model[:, held] + np.nan_to_num(corr, nan=0.0)
    out = heldout_errors(disp[:, held] - pred, radial, circumferential)
    out["U"] = pred
    return out


def contour_interpolant(angles_landmarks, values, angles_query) -> np.ndarray:
    """Periodic cubic spline in angle through a contour's landmarks, evaluated at other angles.

    Parameters
    ----------
    angles_landmarks : (L,) array
        Angles (rad) of the landmarks about the cavity centre (any order, distinct modulo 2 pi).
    values : (..., L, k) array
        Values at the landmarks (for example displacements, k = 2), leading axes broadcast.
    angles_query : (Q,) array
        Angles (rad) to evaluate at.

    Returns
    -------
    (..., Q, k) array
    """
    a = np.mod(np.asarray(angles_landmarks, float), 2 * np.pi)
    order = np.argsort(a)
    a = a[order]
    v = np.take(np.asarray(values, float), order, axis=-2)
    if len(a) < 3 or np.any(np.diff(a) <= 0):
        raise ValueError("angles_landmarks: expected at least 3 distinct angles")
    x = np.concatenate([a, [a[0] + 2 * np.pi]])
    y = np.concatenate([v, np.take(v, [0], axis=-2)], axis=-2)
    spline = CubicSpline(x, y, axis=-2, bc_type="periodic")
    q = np.mod(np.asarray(angles_query, float) - a[0], 2 * np.pi) + a[0]
    return spline(q)


def angular_sectors(angles, n: int) -> np.ndarray:
    """Label of each point's sector when the circle is cut into ``n`` equal sectors from angle 0.

    Parameters
    ----------
    angles : (H,) array
        Angles (rad) about the cavity centre.
    n : int
        Number of sectors (>= 2).

    Returns
    -------
    (H,) int array in ``0..n-1``
    """
    a = as_float_array("angles", angles, shape=(None,))
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 2:
        raise ValueError(f"n: expected an integer number of sectors >= 2, got {n!r}")
    return np.minimum((np.mod(a, 2 * np.pi) / (2 * np.pi / n)).astype(int), n - 1)


def rmse_difference(residual_a, residual_b, clusters, level: float = 0.95) -> dict:
    """``RMSE(a) - RMSE(b)`` of two predictions' residuals at the same points, with a cluster interval.

    The RMSE pools every (frame, point) where both residuals are finite. Its uncertainty treats
    clusters of points as the independent units: the delete-one-cluster jackknife gives the
    standard error, ``se^2 = (G - 1) / G sum_g (d_(g) - mean d_(.))^2`` over the G clusters with
    data, and the interval is ``d +- t_{G-1} se`` (a cluster-robust interval with a small-sample
    correction; Efron & Tibshirani 1993, ch. 11). Negative means ``a`` predicts better.

    Parameters
    ----------
    residual_a, residual_b : (F, H, 2) arrays
        Measured minus predicted displacement at H points over F frames (any one unit, for
        example pixels), NaN where there is no datum or no prediction.
    clusters : (H,) array
        Cluster label of each point (for example :func:`angular_sectors`).
    level : float
        Confidence level of the interval, in (0, 1).

    Returns
    -------
    dict
        ``difference`` (same unit as the residuals), ``low``, ``high``, ``se``, ``rmse_a``,
        ``rmse_b``, ``n_clusters``, ``level``, ``method``.
    """
    a = as_float_array("residual_a", residual_a, shape=(None, None, 2), allow_nan=True)
    b = as_float_array("residual_b", residual_b, shape=a.shape, allow_nan=True)
    labels = np.asarray(clusters)
    if labels.shape != (a.shape[1],):
        raise ValueError(f"clusters: expected one label per point, shape ({a.shape[1]},), got shape {labels.shape}")
    if not (0.0 < float(level) < 1.0):
        raise ValueError(f"level: expected a confidence level in (0, 1), got {level!r}")
    sa, sb = np.sum(a ** 2, axis=2), np.sum(b ** 2, axis=2)
    both = np.isfinite(sa) & np.isfinite(sb)
    sa, sb = np.where(both, sa, 0.0), np.where(both, sb, 0.0)
    groups = [g for g in np.unique(labels) if both[:, labels == g].any()]
    if len(groups) < 2:
        raise ValueError(f"clusters: expected data in at least 2 clusters for an interval, got {len(groups)}")
    A = np.array([sa[:, labels == g].sum() for g in groups])
    B = np.array([sb[:, labels == g].sum() for g in groups])
    N = np.array([both[:, labels == g].sum() for g in groups], float)

    def diff(A, B, N):
        return np.sqrt(A.sum() / N.sum()) - np.sqrt(B.sum() / N.sum())

    d = float(diff(A, B, N))
    G = len(groups)
    keep = ~np.eye(G, dtype=bool)
    loo = np.array([diff(A[k], B[k], N[k]) for k in keep])
    se = float(np.sqrt((G - 1) / G * np.sum((loo - loo.mean()) ** 2)))
    half = float(student_t.ppf(0.5 + 0.5 * float(level), G - 1)) * se
    return {"difference": d, "low": d - half, "high": d + half, "se": se,
            "rmse_a": float(np.sqrt(A.sum() / N.sum())), "rmse_b": float(np.sqrt(B.sum() / N.sum())),
            "n_clusters": G, "level": float(level), "method": "delete-one-cluster jackknife, Student t"}
