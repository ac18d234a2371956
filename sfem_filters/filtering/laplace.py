"""The iterated smoother's result and its Laplace posterior at the mode.

:class:`SmootherResult` is what :class:`~sfem_filters.filtering.iterated.IteratedSmoother`
returns. The posterior it reports is the Laplace approximation at the mode of the MAP cost
(:mod:`sfem_filters.filtering.map_cost`): the mode itself, and the covariance of an undamped pass
of the model linearised there (:func:`laplace_at_mode`, the inverse Gauss-Newton Hessian), with
smoothed marginal variances of the kinematics and of the model's output operators (strains).
:func:`exact_laplace` replaces the Gauss-Newton Hessian by the profile cost's exact one, and
:func:`with_covariance` completes a result of a run made without the variances.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from .curvature import ProfileHessian, profile_hessian
from .cyclic import check_observations
from .history import History
from .linearised import linearise
from .memory import check_memory
from .protocol import OutputOperators
from .safeguards import Safeguards
from .smoother import smooth
from ..resources import limits_blas_threads

__all__ = ["SmootherResult", "laplace_at_mode", "exact_laplace", "with_covariance"]


@dataclass(eq=False)
class SmootherResult:
    """Outcome of :class:`~sfem_filters.filtering.iterated.IteratedSmoother` (model coordinates throughout).

    Attributes
    ----------
    states : (n_frames, dim_state)
        The MAP trajectory and parameters (the mode of the posterior).
    theta, P_theta :
        The parameters and their Laplace covariance (the undamped smoother's at the mode).
    P_diag : (n_frames, dim_state)
        Smoothed marginal variances (restart part: NaN unless computed; parameters: P_theta's).
    iterations : int
        Accepted Gauss-Newton steps.
    converged : bool
    stop_reason : str
        ``"step"`` (the material step met the stop rule), ``"cost"`` (the cost stopped falling
        and the model predicts no more), ``"damping"`` (no damping made the cost fall while the
        model still predicted a decrease: stuck, not converged), ``"max_iterations"`` or
        ``"no parameters"``.
    records : list of dict
        Per accepted iteration: ``cost``, ``decrease`` (nats), ``damping``, ``rejected``
        (damped retries), ``step_length`` (the multiple of the damped step taken: 0.1-0.5 after
        the line search, 1, or 2, 4, 8 when extended), ``gain_ratio`` (actual over predicted
        decrease of the damped step before any extension, the ratio Nielsen's rule uses),
        ``rel_change``, ``step_sd`` (the largest move of a physical quantity in its posterior sd,
        :func:`~sfem_filters.filtering.gauss_newton.step_in_sd`), ``max_abs_step``, ``full_step_sd``
        (the same for the undamped step), ``newton_decrement`` (nats), ``seconds``.
    history : History
        One row per frame (loop 0): the reported states (``states``, the trajectory the final pass
        was linearised at), the final pass's marginal variances, and its forward innovations, S
        and NIS (for the diagnostics).
    log_likelihood : float
        log p(y) of the model linearised at the mode (prediction-error decomposition).
    output_sd : dict
        Smoothed standard deviations of the model's output operators, name -> (n_frames, k).
    cost : float
        The MAP cost J at the mode.
    process_noise_scale : float
        The factor on the model's Q the result was computed with (1 unless estimated).
    noise_search : list of dict
        With ``process_noise="estimate"``: per scale tried, ``scale``, ``log_evidence`` (log p(y)
        of the model linearised at that scale's mode), ``iterations``, ``converged``; by scale.
    measurement_noise_scale : float
        The factor on the model's R the result was computed with (1 unless estimated).
    measurement_noise_search : list of dict
        With ``measurement_noise="estimate"``: as ``noise_search``, for the factor on R.
    laplace : str
        Which Hessian ``P_theta`` inverts: ``"gauss-newton"`` or ``"exact"`` (``laplace="exact"``
        and the exact Hessian positive definite at the mode).
    P_theta_gauss_newton : (p, p) array or None
        With ``laplace="exact"``: the Gauss-Newton covariance, for comparison.
    curvature : ProfileHessian or None
        With ``laplace="exact"``: the exact and Gauss-Newton Hessians of the profile cost at the
        mode (:func:`sfem_filters.filtering.curvature.profile_hessian`).
    """

    states: np.ndarray
    theta: np.ndarray
    P_theta: np.ndarray
    P_diag: np.ndarray
    iterations: int
    converged: bool
    stop_reason: str
    records: list
    history: History
    log_likelihood: float
    output_sd: dict = field(default_factory=dict)
    cost: float = np.nan
    method: str = "iterated_smoother"
    process_noise_scale: float = 1.0
    noise_search: list = field(default_factory=list)
    measurement_noise_scale: float = 1.0
    measurement_noise_search: list = field(default_factory=list)
    laplace: str = "gauss-newton"
    P_theta_gauss_newton: np.ndarray | None = None
    curvature: ProfileHessian | None = None

    @property
    def loops(self) -> int:
        """Passes over the data of the accepted iterations (for tables shared with the cyclic EKF)."""
        return self.iterations

    @property
    def rel_changes(self) -> list:
        """Relative change of the physical parameters (E in Pa and nu) at each accepted iteration (for tables
        shared with the cyclic EKF)."""
        return [r["rel_change"] for r in self.records]

    @property
    def posterior_cov(self) -> np.ndarray:
        """The material covariance to report: the Laplace covariance ``P_theta``."""
        return self.P_theta


def laplace_at_mode(model, y, z, cost, records, stop, converged, guard, *, covariance: bool = True) -> SmootherResult:
    """The Laplace approximation at the mode: an undamped pass linearised there.

    Parameters
    ----------
    model : the model the mode was found with (its noise scales included)
    y : (n_frames, dim_obs) checked observations (model units, NaN where missing)
    z : (n_frames, dim_state) the mode (the trajectory and parameters)
    cost, records, stop, converged :
        The MAP cost at the mode and the run's records, stop reason and verdict, kept in the result.
    guard : Safeguards
        Covariance checks of the pass, NIS monitoring.
    covariance : bool
        Compute the smoothed marginal variances of the kinematics and of the model's output
        operators (``P_diag``, ``output_sd``); without, ``P_diag``'s kinematic columns are NaN.

    Returns
    -------
    SmootherResult
    """
    nr = int(model.n_restart)
    lin = linearise(model, z)
    outputs = {}
    if covariance:
        outputs["state"] = lin.output_in_xi(np.eye(nr))
        if isinstance(model, OutputOperators):
            outputs.update({k: lin.output_in_xi(v) for k, v in model.output_operators().items()})
    sm = smooth(lin, y, safeguards=guard, covariance=covariance, outputs=outputs, monitor_nis=True,
                label=len(records))
    T, n = z.shape
    P_diag = np.full((T, n), np.nan)
    if covariance:
        P_diag[:, :nr] = sm.variances.pop("state")
    P_diag[:, nr:] = np.diag(sm.P_theta)
    # The history's states are the reported estimate z, the trajectory the pass was linearised
    # at (its innovations and S belong to it), not the pass's own smoothed mean: that is one
    # more undamped Gauss-Newton step, never checked against the cost, and stopped short of the
    # mode it can be anywhere (a material that makes K singular). At the mode the two agree.
    history = History()
    for t in range(T):
        history.append(0, t, z[t], P_diag[t], sm.innovation[t], sm.S[t], sm.nis[t], int(sm.n_obs[t]))
    return SmootherResult(states=z, theta=z[0, nr:].copy(), P_theta=sm.P_theta, P_diag=P_diag,
                          iterations=len(records), converged=converged, stop_reason=stop, records=records,
                          history=history, log_likelihood=sm.log_likelihood,
                          output_sd={k: np.sqrt(np.maximum(v, 0.0)) for k, v in sm.variances.items()},
                          cost=cost)


def exact_laplace(model, observations, result: SmootherResult, *, safeguards: Safeguards | None = None,
                  progress: bool = False) -> SmootherResult:
    """The smoother's result with the exact Laplace covariance of theta (``laplace="exact"``).

    The profile cost's exact Hessian at the result's mode
    (:func:`~sfem_filters.filtering.curvature.profile_hessian`, 2 p + 1 gradient passes) replaces
    the Gauss-Newton Hessian whose inverse the smoother reports: ``P_theta`` becomes its inverse
    (and the parameters' columns of ``P_diag`` its diagonal), the Gauss-Newton covariance is kept
    as ``P_theta_gauss_newton`` and the Hessians as ``curvature``. Where the exact Hessian is not
    positive definite (the run stopped short of a minimum) a warning is given and the result keeps
    the Gauss-Newton covariance (``laplace`` stays ``"gauss-newton"``, ``curvature`` says why).
    The kinematics' marginal variances are the final pass's, at the material's mode.

    Parameters
    ----------
    model : the model the result was computed with (its process noise scale included)
    observations : (n_frames, dim_obs) the same observations (model units, NaN where missing)
    result : SmootherResult of :class:`~sfem_filters.filtering.iterated.IteratedSmoother` (not modified)
    safeguards : Safeguards, optional
        Covariance checks of the gradient passes.

    Returns
    -------
    SmootherResult, a copy.
    """
    if not isinstance(result, SmootherResult):
        raise TypeError(f"result: expected a SmootherResult of the iterated smoother, got {type(result).__name__}")
    if not result.theta.size:
        raise ValueError("result: the model has no static parameters, so there is no covariance of theta to replace")
    curv = profile_hessian(model, observations, result.states, safeguards=safeguards, progress=progress)
    out = replace(result, curvature=curv, P_theta_gauss_newton=np.array(result.P_theta, float), laplace="gauss-newton")
    if not curv.positive_definite():
        warnings.warn("iterated smoother: the exact Hessian of the MAP cost is not positive definite at the "
                      "estimate (not a minimum); the Gauss-Newton covariance is reported", RuntimeWarning)
        return out
    nr = int(model.n_restart)
    out.P_theta = curv.covariance()
    out.P_diag = np.array(result.P_diag, float)
    out.P_diag[:, nr:] = np.diag(out.P_theta)
    out.laplace = "exact"
    return out


@limits_blas_threads
def with_covariance(model, observations, result: SmootherResult, *,
                    safeguards: Safeguards | None = None) -> SmootherResult:
    """A result of a run made with ``covariance=False``, completed with the marginal variances of
    the kinematics and of the model's outputs (``P_diag``, ``output_sd``).

    The final pass is made again at the result's mode, this time with the covariance recursion:
    the same linearisation, the same forward pass (so the same innovations, log-likelihood and
    ``P_theta``, bit for bit), and the variances a run with ``covariance=True`` reports. A search
    that fits many models and keeps few (the rounds of
    :func:`sfem_filters.cardiac.closing.closing_the_loop`) pays for the variances only of those it
    keeps. A result that has them is returned as it is. It runs on the estimators' BLAS threads
    (:func:`~sfem_filters.resources.blas_threads`, as :class:`~sfem_filters.filtering.iterated.IteratedSmoother`
    runs), so its figures are those of a run with ``covariance=True`` to the last bit.

    Parameters
    ----------
    model : the model the result was computed with (its noise scales included)
    observations : (n_frames, dim_obs) the same observations (model units, NaN where missing)
    result : SmootherResult of :class:`~sfem_filters.filtering.iterated.IteratedSmoother` (not modified)
    safeguards : Safeguards, optional
        Covariance checks of the pass (default: a fresh :class:`Safeguards`).

    Returns
    -------
    SmootherResult, a copy (with the search's records, stop reason and noise levels).
    """
    if not isinstance(result, SmootherResult):
        raise TypeError(f"result: expected a SmootherResult of the iterated smoother, got {type(result).__name__}")
    nr = int(model.n_restart)
    if np.all(np.isfinite(np.asarray(result.P_diag, float)[:, :nr])):
        return result
    y = check_observations(model, observations)
    check_memory(model.dim_state, model.n_frames, covariance=True,      # the search's passes kept no covariances
                 observed=int(np.sum(~np.isnan(y))))
    guard = safeguards if safeguards is not None else Safeguards()
    done = laplace_at_mode(model, y, result.states, result.cost, result.records, result.stop_reason, result.converged,
                           guard, covariance=True)
    out = replace(done, process_noise_scale=result.process_noise_scale, noise_search=result.noise_search,
                  measurement_noise_scale=result.measurement_noise_scale,
                  measurement_noise_search=result.measurement_noise_search, laplace=result.laplace,
                  curvature=result.curvature, P_theta_gauss_newton=result.P_theta_gauss_newton)
    # the material's covariance is the result's (an exact Laplace one stays exact)
    out.P_theta = np.array(result.P_theta, float)
    out.P_diag[:, nr:] = np.asarray(result.P_diag, float)[:, nr:]
    return out
