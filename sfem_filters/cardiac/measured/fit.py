"""Step 3, a fit: build the model, estimate kinematics and material with the iterated smoother or
the cyclic filter, and evaluate (:func:`run`, :class:`Run`); a smoother run completed with its
kinematics' variances (:func:`with_covariance`) or the exact Laplace covariance of its material
(:func:`exact_posterior`)."""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np

from ..._validate import integer
from ...filtering.cyclic import cyclic_estimate
from ...filtering.iterated import NOISE_LEVELS, IteratedSmoother, exact_laplace
from ...filtering.iterated import with_covariance as smoother_with_covariance
from ...model import SFEMModel
from .build import build_model
from .evaluation import evaluate
from .settings import ESTIMATORS, default_max_iterations
from .setup import Setup

__all__ = ["Run", "run", "with_covariance", "exact_posterior"]


@dataclass(eq=False)
class Run:
    """A filter run on a set-up and what was measured of it."""

    name: str
    model: SFEMModel
    result: object
    U: np.ndarray            # (frames, n_points, 2) filtered displacement, data units
    metrics: dict
    observations: np.ndarray | None = None   # (frames, dim_obs) what the model was fitted to, model units


def run(setup: Setup, effects=(), drive: str = "penalty", parameterisation: str = "region", max_loops: int = 5,
        process_scale: float = 1.0, tol: float = 1e-3, progress: bool = False, name: str = "",
        landmark_step_px: float | None = None, beta: float | None = None, model_options: dict | None = None,
        estimator: str = "smoother", max_iterations: int | None = None, effect_rates: bool = False,
        drive_trend: bool = False, spring_scale: float = 1.0, measurement_noise: str = "fixed",
        covariance: bool = True, warm_start=None) -> Run:
    """Build the model, estimate and evaluate.

    ``estimator`` (:data:`ESTIMATORS`): ``"smoother"``, the iterated smoother with at most
    ``max_iterations`` Gauss-Newton steps (default :func:`default_max_iterations` of the drive),
    ``"cyclic"``, the paper's cyclic joint EKF with at most ``max_loops`` loops and the relative
    tolerance ``tol``, or ``"roukf"``, Moireau & Chapelle's reduced-order UKF in the same cyclic
    driver (:mod:`sfem_filters.filtering.roukf`). ``beta``, ``model_options``, ``effect_rates``,
    ``drive_trend``, ``spring_scale``: see :func:`build_model`.
    ``measurement_noise``: ``"fixed"``, the measurement noise at the noise floor (or the file's
    ``sigma``); ``"estimate"``, its level (one factor on every frame's R) chosen by the smoother's
    type-II maximum likelihood (:class:`~sfem_filters.filtering.iterated.IteratedSmoother`
    ``measurement_noise``); the factor is ``metrics["measurement_noise_scale"]``. Smoother only.
    ``covariance=False`` (smoother only) leaves out the smoothed variances of the kinematics and
    strains (no ``strain_polar`` / ``_sd`` in the metrics), the dearest part of a fit's final pass;
    the estimate, its evidence and the material's covariance are the same. :func:`with_covariance`
    adds them later. ``warm_start`` (smoother only): a material vector (the model's coordinates, for
    example another fit's ``result.theta`` of the same parameterisation) the Gauss-Newton
    iterations start from instead of the prior mean (:class:`~sfem_filters.filtering.iterated.IteratedSmoother`
    ``start``): the cost and its mode are the same, reached in fewer iterations from a nearby
    model's mode; a vector of another length (another parameterisation) is not used.
    """
    if not isinstance(covariance, (bool, np.bool_)):
        raise TypeError(f"covariance: expected True or False, got {covariance!r}")
    if not covariance and estimator != "smoother":
        raise ValueError(f"covariance: False applies to the iterated smoother; got estimator={estimator!r}")
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator: expected one of {ESTIMATORS}, got {estimator!r}")
    max_iterations = default_max_iterations(drive) if max_iterations is None else integer("max_iterations",
                                                                                          max_iterations, 1)
    if measurement_noise not in NOISE_LEVELS:
        raise ValueError(f"measurement_noise: expected one of {NOISE_LEVELS}, got {measurement_noise!r}")
    if measurement_noise == "estimate" and estimator != "smoother":
        raise ValueError(f"measurement_noise: 'estimate' needs estimator='smoother', got estimator={estimator!r}")
    model, y = build_model(setup, effects, drive, parameterisation, process_scale, landmark_step_px, beta,
                           model_options, effect_rates=effect_rates, drive_trend=drive_trend,
                           spring_scale=spring_scale)
    start = None
    if warm_start is not None and estimator == "smoother":
        theta = np.asarray(warm_start, float).ravel()
        if theta.size == model.dim_state - model.n_restart and theta.size and np.all(np.isfinite(theta)):
            start = np.zeros((setup.seq.n_frames, model.dim_state))
            start[:, model.n_restart:] = theta
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="cyclic_estimate: the material did not converge")
        warnings.filterwarnings("ignore", message="iterated smoother: stopped by")
        if estimator == "smoother":
            result = IteratedSmoother(max_iterations=max_iterations, measurement_noise=measurement_noise,
                                      covariance=bool(covariance)).run(
                model, y, progress=progress, description=name or "dense", start=start)
        else:
            result = cyclic_estimate(model, y, max_loops=max_loops, tol=tol, progress=progress,
                                     description=name or "dense",
                                     engine="roukf" if estimator == "roukf" else "structured")
    if getattr(result, "measurement_noise_scale", 1.0) != 1.0:
        model = model.with_measurement_noise(result.measurement_noise_scale)    # the R the result was made with
    U, metrics = evaluate(setup, model, result, time.perf_counter() - t0, y)
    if measurement_noise == "estimate":
        metrics["measurement_noise_scale"] = float(result.measurement_noise_scale)
        metrics["measurement_noise_search"] = list(result.measurement_noise_search)
    return Run(name, model, result, U, metrics, y)


def with_covariance(setup: Setup, r: Run) -> Run:
    """A smoother run made with ``covariance=False``, completed as if made with ``covariance=True``:
    the final pass again at its mode with the variances of the kinematics and strains
    (:func:`sfem_filters.filtering.iterated.with_covariance`), metrics recomputed, its pass's time
    added to ``seconds``. A run that has them is returned as it is."""
    if getattr(r.result, "method", "") != "iterated_smoother":
        raise ValueError(f"r: expected a run of the iterated smoother (estimator='smoother'), got "
                         f"{type(r.result).__name__}")
    if r.observations is None:
        raise ValueError("r: expected a run made by measured.run (it keeps the observations), got none")
    t0 = time.perf_counter()
    result = smoother_with_covariance(r.model, r.observations, r.result)
    return r if result is r.result else _rerun(setup, r, result, t0)


def _rerun(setup: Setup, r: Run, result, t0: float) -> Run:
    """``r`` with a new result of its model and data: metrics evaluated again, the new work's time
    (since ``t0``) added to ``seconds``, the measurement noise search's metrics kept."""
    seconds = float(r.metrics.get("seconds", 0.0)) + time.perf_counter() - t0
    U, metrics = evaluate(setup, r.model, result, seconds, r.observations)
    for key in ("measurement_noise_scale", "measurement_noise_search"):
        if key in r.metrics:
            metrics[key] = r.metrics[key]
    return Run(r.name, r.model, result, U, metrics, r.observations)


def exact_posterior(setup: Setup, r: Run, progress: bool = False) -> Run:
    """A smoother run with the exact Laplace covariance of its material, metrics recomputed.

    The iterated smoother reports the inverse Gauss-Newton Hessian of the MAP cost as the
    material's covariance. Where the model misfits its data the curvature Gauss-Newton leaves out
    can be large (the docs' frozen Hessian check); this takes the exact Hessian of the profile
    cost at the run's mode (:func:`sfem_filters.filtering.iterated.exact_laplace`, 2 p + 1 gradient
    passes) and reports its inverse: the material's sd maps, the stiffness level's interval and the
    prior check then use it. ``metrics["material_covariance"]`` says which covariance was used
    (``"gauss-newton"`` where the exact Hessian is not positive definite: a warning is given), and
    ``metrics["exact_laplace"]`` how far apart the two are. The kinematics are unchanged.

    Parameters
    ----------
    setup : the run's set-up (:func:`prepare`)
    r : a :func:`run` of the iterated smoother with material parameters
    progress : a progress bar over the gradient passes
    """
    if getattr(r.result, "method", "") != "iterated_smoother":
        raise ValueError(f"r: expected a run of the iterated smoother (estimator='smoother'), got "
                         f"{type(r.result).__name__}")
    if not r.model.estimates_material:
        raise ValueError("r: the run's material is fixed (parameterisation 'none'): no material covariance to refine")
    if r.observations is None:
        raise ValueError("r: expected a run made by measured.run (it keeps the observations), got none")
    t0 = time.perf_counter()
    return _rerun(setup, r, exact_laplace(r.model, r.observations, r.result, progress=progress), t0)
