"""The rounds' criteria and yardsticks: a model's evidence, its cross-validation, its effects'
time courses (for the tied score test) and its held-out error against the spline's."""
from __future__ import annotations

import numpy as np

from ..crossval import DEFAULT_FOLDS, cross_validate
from ..measured import Run, Setup, angle_from_origin, kriged_heldout
from ..reference import angular_sectors, rmse_difference
from ..specs import ModelSpec

__all__ = ["time_courses", "log_evidence", "round_cross_validation", "versus_spline"]


def time_courses(r: Run):
    """The current effects' amplitudes over the frames, each scaled to a peak of 1, with a constant
    first: the shapes in time of the tied score test (:func:`sfem_filters.filtering.diagnostics.effect_score`).

    A regional or directional refinement of an effect in the model (one segment that does not
    contract, a fibre direction that turns) moves with that effect's time course, so its test
    needs a few coefficients per amplitude, not one per frame. ``None`` when the model has no
    effect (the baseline is tested with free amplitudes only). Shape (n_frames, 1 + effect states
    that move); frames the run did not visit are zero.
    """
    model = r.model
    if not getattr(model, "dim_eta", 0):
        return None
    h = r.result.history
    rows = h.loop_rows()
    eta = np.array([np.asarray(model.eta_of(h.x[i]), float) for i in rows])
    peak = np.max(np.abs(eta), axis=0)
    eta = eta[:, peak > 0] / peak[peak > 0]
    out = np.zeros((int(np.max(np.asarray(h.frame)[rows])) + 1, 1 + eta.shape[1]))
    out[np.asarray(h.frame)[rows]] = np.column_stack([np.ones(len(rows)), eta])
    return out


def log_evidence(r: Run) -> float:
    """``log p(y)`` of a run's model (nats), the criterion of the rounds.

    For the iterated smoother, the log-likelihood of its final pass: the model linearised at the
    mode, parameters integrated over their Gaussian prior, kinematics and effect states over
    theirs (prediction-error decomposition), i.e. the Laplace approximation of the marginal
    likelihood. For the cyclic EKF it is formed from the exact ``log p(y | theta)`` at its
    estimate and the one-cycle covariance ``Sigma``: ``log p(y | theta) + log p(theta) +
    log det(2 pi Sigma) / 2`` (:func:`sfem_filters.cardiac.measured.evaluate` computes both).
    """
    return float(r.metrics["log_evidence"])


def round_cross_validation(setup: Setup, variant: ModelSpec, r: Run,
                           folds: int = DEFAULT_FOLDS) -> dict:
    """Cross-validation over the observed points of a round's model (:func:`sfem_filters.cardiac.crossval.cross_validate`)
    with its material at the run's estimate; plain values (no predictions), data units, and the
    same for the model plus the spline of its residual (``residual_spline``)."""
    mat = r.model.material_of_theta(r.result.theta) if r.model.estimates_material else r.model.material
    cv = cross_validate(setup, mat, variant.effects, variant.drive, folds, drive_trend=variant.drive_trend,
                        effect_rates=variant.effect_rates, process_scale=variant.process_scale,
                        spring_scale=variant.spring_scale)
    return {**{k: cv[k] for k in ("rmse_px", "rmse_radial_px", "rmse_circumferential_px", "per_fold_px")},
            "residual_spline": cv["residual_spline"]}


def versus_spline(setup: Setup, U, spline_U, level: float = 0.95) -> dict | None:
    """The held-out RMSE of a model, and of the model plus the spline of its residual, minus the
    thin-plate spline's, each with a cluster interval (:func:`sfem_filters.cardiac.reference.rmse_difference`).

    The clusters are angular sectors of the held-out points, as many as landmarks per contour,
    so that a cluster spans about one gap between landmarks, the scale over which an
    interpolant's errors are alike. ``None`` when fewer than two sectors hold held-out points.

    Parameters
    ----------
    setup : Setup
    U : (F, n_points, 2) array
        The model's prediction of every point (data units).
    spline_U : (F, H, 2) array
        The spline's prediction at the held-out points (``spline_reference(...)["U"]``).
    level : float
        Confidence level of the intervals.

    Returns
    -------
    dict or None
        ``model`` and ``model_plus_spline``: each a :func:`~sfem_filters.cardiac.reference.rmse_difference`
        (data units; negative: better than the spline); ``sectors``: the number of sectors.
    """
    h = setup.heldout
    meas = setup.seq.displacement[:, h]
    angles = angle_from_origin(setup, setup.point_mesh.nodes[h])
    n = max(int(setup.n_landmarks), 2)
    sectors = angular_sectors(angles, n)
    if len(np.unique(sectors)) < 2:
        return None
    spline_res = meas - np.asarray(spline_U, float)
    out = {"sectors": n}
    for key, pred in (("model", np.asarray(U, float)[:, h]), ("model_plus_spline", kriged_heldout(setup, U)["U"])):
        out[key] = rmse_difference(meas - pred, spline_res, sectors, level)
    return out
