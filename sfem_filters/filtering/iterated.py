"""The iterated extended Kalman smoother: Gauss-Newton on the MAP of one cycle, damped.

The unknowns are the restart trajectory ``r_0..r_T`` (kinematics and effect states) and the
static parameters theta (material); the data of the cycle are counted once. The negative log
posterior (the MAP cost) is

    J = 1/2 |r_0 - x0|^2_{P1^-1} + 1/2 |theta - theta0|^2_{P3^-1}
        + 1/2 sum_t |r_{t+1} - f_r(r_t, theta, t)|^2_{Q^-1} + 1/2 sum_t |y_t - H r_t|^2_{R_t^-1}.

Bell (1994, SIAM J. Optim. 4:626) showed that smoothing the model linearised about a trajectory
(:mod:`sfem_filters.filtering.linearised`, :func:`sfem_filters.filtering.smoother.smooth`) is
exactly a Gauss-Newton step on J. Two things make the steps robust:

* **The trajectory is projected out.** For a fixed theta the model is linear in the trajectory
  (``f_r = A(theta) r + B(theta) w``), so the best trajectory for a theta, and with it the
  profile cost ``J_p(theta) = min_r J``, is one linear smoother pass with theta held fixed
  (variable projection, Golub & Pereyra 1973). Every candidate theta is scored by ``J_p`` and
  the next linearisation is taken at its optimal trajectory; a step is never judged by a
  trajectory the old theta's linearisation left behind.
* **Levenberg-Marquardt damping and a line search** (Sarkka & Svensson 2020, ICASSP,
  "Levenberg-Marquardt and line-search extended Kalman smoothers"): a step is accepted only if
  the MAP cost falls. The damping ``lambda/2 |theta - theta_bar|^2_{P3^-1}`` is a Gaussian
  pseudo-observation of ``theta_bar`` with the prior's shape, so it simply tightens the prior of
  the pass to ``N((theta0 + lambda theta_bar) / (1 + lambda), P3 / (1 + lambda))``. A failed step
  is tried at half its length, then lambda grows (Nielsen's rule, :class:`IteratedSmoother`).
  A full step that lowered the cost by more than the model predicted, where the model predicts
  little more, is doubled while the cost keeps falling (a plateau the Gauss-Newton curvature
  hides; ``max_extrapolation``).

Each iteration relinearises at the optimal trajectory of the last accepted theta and restarts
from the prior. The run stops when an accepted step moves the material by less than ``tol``
(relative, physical units) and by less than ``sd_tol`` posterior standard deviations of every
physical quantity (the step taken and the undamped one alike; :func:`step_in_sd`), when the
cost stops falling (an accepted decrease below ``cost_tol`` with a Newton decrement below it too,
or no damping makes it fall), or at ``max_iterations``. No damping lowering the cost while the
model still predicts a decrease is reported as stuck (``"damping"``), not converged. A secant
correction that makes the quadratic model indefinite is dropped instead of being covered by a
larger damping. The reported posterior is the Laplace approximation at the mode: the mode
itself, and the covariance of an undamped pass linearised there (the inverse Gauss-Newton
Hessian), with smoothed marginal variances of the kinematics and of the model's output
operators (strains).

The process noise Q is a modelling choice the data can judge. With ``process_noise="estimate"``
its level (one factor on every process noise) is chosen by maximum evidence, log p(y | factor)
with the trajectory and the material integrated out by the Laplace approximation at each
factor's mode (type-II maximum likelihood, empirical Bayes); the posterior reported is the one
at that factor. On the calibration spec's check, whose truth moves without process noise, this
is what turns a conservative posterior (the configured Q is too large for the data) into a
calibrated one (``python -m validation run calibration``).
"""
from __future__ import annotations

import math
import os
import time
import warnings
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from .._validate import as_float_array, integer, non_negative, positive
from ..resources import limits_blas_threads
from .checkpoint import load_checkpoint, run_fingerprint, save_checkpoint
from .cyclic import check_observations
from .history import History
from .linearised import check_static_parameters, linearise
from .protocol import (OutputOperators, check_model, measurement_cov, parameter_prior, physical_jacobian,
                       physical_parameters, scaled_measurement_noise, scaled_process_noise)
from .safeguards import Safeguards
from .curvature import ProfileHessian, gauss_newton_pass, optimal_trajectory, profile_hessian, profile_pass
from .smoother import check_memory, smooth

__all__ = ["IteratedSmoother", "SmootherResult", "MapObjective", "iterated_smoother", "open_loop", "exact_laplace",
           "with_covariance", "step_in_sd", "NOISE_LEVELS"]

#: How a noise level is set (``process_noise=``, ``measurement_noise=``): as the model gives it, or
#: by type-II maximum likelihood.
NOISE_LEVELS = ("fixed", "estimate")

#: An accepted full step whose actual decrease is at least this many times the predicted one ...
EXTRAPOLATE_GAIN = 1.25
#: ... while the quadratic model predicts less than this much more (nats) is extended
#: (:class:`IteratedSmoother` ``max_extrapolation``).
EXTRAPOLATE_DECREMENT = 1.0


def step_in_sd(step, P_theta, jacobian=None) -> float:
    """The largest move of a physical quantity in its posterior standard deviations.

    ``max_i |j_i @ step| / sqrt(j_i P j_i^T)`` over the rows ``j_i`` of ``jacobian`` (d physical
    quantity / d theta, :class:`sfem_filters.filtering.protocol.PhysicalJacobian`; ``None``: the
    parameters themselves). A row's scale cancels, and so does any invertible recombination of
    the parameters (renumbered regions, rotated contrasts or basis modes): the rule judges the
    material, not its coordinates. Rows that do not move with theta are left out.

    Parameters
    ----------
    step : (p,) array
        Step in theta.
    P_theta : (p, p) array
        Posterior covariance of theta.
    jacobian : (q, p) array or sparse matrix, optional
        Rows of the physical quantities' derivatives.

    Returns
    -------
    float
        The largest move in sd (0 when no row moves with theta).
    """
    step = as_float_array("step", step, shape=(None,))
    p = len(step)
    P = as_float_array("P_theta", P_theta, shape=(p, p))
    if jacobian is None:
        return float(np.max(np.abs(step) / np.sqrt(np.diag(P))))
    J = sp.csr_matrix(jacobian)
    if J.shape[1] != p:
        raise ValueError(f"jacobian: expected {p} columns (one per parameter), got shape {J.shape}")
    scale = np.asarray(abs(J).max(axis=1).todense(), float).ravel()
    keep = scale > 0.0
    if not np.any(keep):
        return 0.0
    J = sp.diags(1.0 / scale[keep]) @ J[keep]           # rows of unit size: their scale cancels anyway
    moved = np.abs(J @ step)
    var = np.asarray(J.multiply(J @ P).sum(axis=1)).ravel()
    return float(np.max(moved / np.sqrt(np.maximum(var, np.finfo(float).tiny))))


class _InverseRoot:
    """``x -> L^-1 x`` with ``C = L L^T`` (Cholesky), or the pseudo-inverse square root of a
    singular PSD ``C`` (directions of zero variance are left out of the norm)."""

    def __init__(self, C):
        C = np.asarray(C, float)
        try:
            self.L = np.linalg.cholesky(0.5 * (C + C.T))
            self.U = None
        except np.linalg.LinAlgError:
            lam, U = np.linalg.eigh(0.5 * (C + C.T))
            keep = lam > len(lam) * np.finfo(float).eps * max(lam.max(), 1e-300)
            self.L, self.U = None, U[:, keep] / np.sqrt(lam[keep])

    def norm2(self, x) -> float:
        x = np.asarray(x, float)
        if self.L is not None:
            v = sla.solve_triangular(self.L, x.T, lower=True)
        else:
            v = self.U.T @ x.T
        return float(np.sum(v * v))


class MapObjective:
    """The MAP cost J of a trajectory (module docstring), evaluated with the model's own ``fx``.

    Parameters
    ----------
    model : a model of the contract with static parameters and a linear observation
    observations : (n_frames, dim_obs) array, NaN where missing
    """

    def __init__(self, model, observations):
        self.model = model
        self.y = check_observations(model, observations)
        self.nr = nr = int(model.n_restart)
        P0, Q = np.asarray(model.P0, float), np.asarray(model.Q, float)
        self.x0 = np.asarray(model.x0, float)
        self.prior_r = _InverseRoot(P0[:nr, :nr])
        self.prior_theta = _InverseRoot(P0[nr:, nr:]) if P0.shape[0] > nr else None
        self.process = _InverseRoot(Q[:nr, :nr])
        self.H = np.asarray(model.H_jacobian(self.x0, 0), float)[:, :nr]
        self.noise = []
        for t in range(model.n_frames):
            mask = ~np.isnan(self.y[t])
            self.noise.append((mask, _InverseRoot(measurement_cov(model, t)[np.ix_(mask, mask)]) if mask.any()
                               else None))

    def parts(self, states) -> dict:
        """The four sums of J (``prior``, ``parameters``, ``process``, ``data``) and ``total``;
        ``inf`` when the model cannot step a state (a material out of its representable range)."""
        z = np.asarray(states, float)
        nr = self.nr
        out = {"prior": 0.5 * self.prior_r.norm2(z[0, :nr] - self.x0[:nr]),
               "parameters": 0.0 if self.prior_theta is None else
               0.5 * self.prior_theta.norm2(z[0, nr:] - self.x0[nr:])}
        try:
            f = np.array([np.asarray(self.model.fx(z[t], t), float).ravel()[:nr] for t in range(len(z) - 1)])
        except (FloatingPointError, ValueError, np.linalg.LinAlgError):
            f = None
        if f is None or not np.all(np.isfinite(f)):
            return {**out, "process": np.inf, "data": np.inf, "total": np.inf}
        out["process"] = 0.5 * self.process.norm2(z[1:, :nr] - f)
        data = 0.0
        for t, (mask, root) in enumerate(self.noise):
            if root is not None:
                data += 0.5 * root.norm2(self.y[t, mask] - self.H[mask] @ z[t, :nr])
        out["data"] = data
        out["total"] = out["prior"] + out["parameters"] + out["process"] + out["data"]
        return out

    def __call__(self, states) -> float:
        return self.parts(states)["total"]


class _StructuredSecant:
    """The curvature Gauss-Newton leaves out, learnt from gradients (Dennis, Gay & Welsch 1981).

    The profile cost's Hessian is the Gauss-Newton part (the smoother's) plus the residuals times
    their second derivatives, which matters when the model does not fit the data (large
    residuals). After a step ``s`` the gradient changes by ``y``; the change the new
    Gauss-Newton Hessian does not explain, ``y# = y - H_GN s``, updates the correction ``S`` by
    the least symmetric change that satisfies ``S s = y#`` (NL2SOL's update, with its sizing of
    the old ``S``). Skipped when ``y^T s <= 0``.
    """

    def __init__(self, p: int):
        self.S = np.zeros((p, p))
        self.s = self.g = None

    def taken(self, step, g):
        self.s, self.g = np.array(step, float), np.array(g, float)

    def state(self) -> dict:
        """Arrays for a checkpoint (``s`` and ``g`` empty before the first step)."""
        empty = np.zeros(0)
        return {"secant_S": self.S, "secant_s": empty if self.s is None else self.s,
                "secant_g": empty if self.g is None else self.g}

    def restore(self, state) -> None:
        self.S = np.array(state["secant_S"], float)
        if np.size(state["secant_s"]):
            self.s, self.g = np.array(state["secant_s"], float), np.array(state["secant_g"], float)

    def update(self, H, g) -> np.ndarray:
        if self.s is not None:
            s, y = self.s, g - self.g
            ys = float(y @ s)
            if ys > 0:
                ysharp = y - H @ s
                sSs = float(s @ self.S @ s)
                if sSs != 0:
                    self.S *= min(1.0, abs(float(s @ ysharp)) / abs(sSs))
                r = ysharp - self.S @ s
                self.S = self.S + (np.outer(r, y) + np.outer(y, r)) / ys - float(r @ s) * np.outer(y, y) / ys ** 2
                self.S = 0.5 * (self.S + self.S.T)
        return self.S


def open_loop(model) -> np.ndarray:
    """The prior's trajectory: ``x0`` stepped by ``fx`` without data, (n_frames, dim_state)."""
    z = np.empty((model.n_frames, model.dim_state))
    z[0] = np.asarray(model.x0, float)
    for t in range(model.n_frames - 1):
        z[t + 1] = np.asarray(model.fx(z[t], t), float).ravel()
    return z


@dataclass(eq=False)
class SmootherResult:
    """Outcome of :class:`IteratedSmoother` (model coordinates throughout).

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
        :func:`step_in_sd`), ``max_abs_step``, ``full_step_sd`` (the same for the undamped step),
        ``newton_decrement`` (nats), ``seconds``.
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
        return [r["rel_change"] for r in self.records]

    @property
    def posterior_cov(self) -> np.ndarray:
        """The material covariance to report: the Laplace covariance ``P_theta``."""
        return self.P_theta


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
    result : SmootherResult of :class:`IteratedSmoother` (not modified)
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


def with_covariance(model, observations, result: SmootherResult, *,
                    safeguards: Safeguards | None = None) -> SmootherResult:
    """A result of a run made with ``covariance=False``, completed with the marginal variances of
    the kinematics and of the model's outputs (``P_diag``, ``output_sd``).

    The final pass is made again at the result's mode, this time with the covariance recursion:
    the same linearisation, the same forward pass (so the same innovations, log-likelihood and
    ``P_theta``, bit for bit), and the variances a run with ``covariance=True`` reports. A search
    that fits many models and keeps few (the rounds of
    :func:`sfem_filters.cardiac.closing.closing_the_loop`) pays for the variances only of those it
    keeps. A result that has them is returned as it is.

    Parameters
    ----------
    model : the model the result was computed with (its noise scales included)
    observations : (n_frames, dim_obs) the same observations (model units, NaN where missing)
    result : SmootherResult of :class:`IteratedSmoother` (not modified)
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
    done = IteratedSmoother(covariance=True)._final(model, y, result.states, result.cost, result.records,
                                                    result.stop_reason, result.converged, guard)
    out = replace(done, process_noise_scale=result.process_noise_scale, noise_search=result.noise_search,
                  measurement_noise_scale=result.measurement_noise_scale,
                  measurement_noise_search=result.measurement_noise_search, laplace=result.laplace,
                  curvature=result.curvature, P_theta_gauss_newton=result.P_theta_gauss_newton)
    # the material's covariance is the result's (an exact Laplace one stays exact)
    out.P_theta = np.array(result.P_theta, float)
    out.P_diag[:, nr:] = np.asarray(result.P_diag, float)[:, nr:]
    return out


@dataclass
class IteratedSmoother:
    """Settings of the iterated extended Kalman smoother (module docstring), one entry point :meth:`run`.

    Parameters
    ----------
    max_iterations : int
        Accepted Gauss-Newton steps at most (>= 1).
    tol : float
        Relative change of the physical parameters below which a step may end the run (> 0).
    sd_tol : float
        ... and the largest move of a physical quantity in its posterior standard deviations
        (> 0; :func:`step_in_sd`, per parameter for a model without ``physical_jacobian``), for the
        step taken and for the undamped step of the quadratic model from the same point (a step
        shortened by a large damping says nothing about the distance to the mode).
    cost_tol : float
        An accepted step that lowers the MAP cost by less than this (nats, > 0), when the undamped
        quadratic model also predicts less (its Newton decrement ``g^T H^-1 g / 2``), ends the
        run: the cost has stopped falling. The default is ``sd_tol^2 / 2``, what a move of
        ``sd_tol`` posterior sd along one direction changes the cost by near the mode.
    damping : float
        Initial Levenberg-Marquardt lambda, in units of the prior precision of theta (>= 0;
        0 starts with an undamped Gauss-Newton step).
    max_damping : float
        A step rejected at this damping ends the run: converged (``"cost"``) if the undamped
        quadratic model predicts a decrease below ``cost_tol`` too, else stuck (``"damping"``,
        reported as not converged).
    covariance : bool
        Compute the smoothed marginal variances of the kinematics and of the model's output
        operators in the final pass (O(k n^2) a frame per output).
    safeguards : Safeguards, optional
        Covariance check and repair in every pass, NIS monitoring in the final one.
    process_noise : {"fixed", "estimate"}
        ``"fixed"``: the model's Q as given. ``"estimate"``: Q's level from the data, by type-II
        maximum likelihood (empirical Bayes) of one factor ``s`` on every process noise: the MAP
        of the trajectory and material is found for each ``s`` tried and scored by its evidence
        log p(y | s), the prediction-error log-likelihood of the model linearised at that mode
        (theta integrated out by the same linearisation, i.e. the Laplace evidence). ``s`` walks
        from 1 in factors of 4 (down first, then up) while the evidence rises by more than
        ``noise_tol``, then one parabolic step in log s between the best and its neighbours; each
        run starts from the previous scale's mode. The reported posterior is the one at the best
        ``s`` (plug-in: the uncertainty of ``s`` itself is not propagated). Needs a model with
        ``with_process_noise`` (:class:`~sfem_filters.filtering.protocol.ScalableProcessNoise`).
    measurement_noise : {"fixed", "estimate"}
        The same for the measurement noise: ``"estimate"`` chooses one factor on R (every frame's)
        by the same walk over factors of 4 and the same evidence (needs ``with_measurement_noise``,
        :class:`~sfem_filters.filtering.protocol.ScalableMeasurementNoise`). Where R is set from
        a floor that can hold motion as well as noise (the ``dense`` workflow's), the data judge
        the level. With both ``"estimate"``: R's level first at the model's Q, then Q's level at
        that R (one sweep of coordinate ascent, each warm-started from the previous mode).
    noise_range : (float, float)
        Smallest and largest factor on Q (and on R) tried (0 < low <= 1 <= high).
    noise_tol : float
        Evidence gain (nats, > 0) below which the walk over scales stops.
    laplace : {"gauss-newton", "exact"}
        The Hessian whose inverse is the reported covariance of theta. ``"gauss-newton"``: the
        final pass's (free). ``"exact"``: the profile cost's exact Hessian at the mode by central
        differences of its exact gradient (:func:`~sfem_filters.filtering.curvature.profile_hessian`,
        2 p more gradient passes), the Laplace approximation proper; where the model misfits its
        data the residual curvature Gauss-Newton leaves out can be large (the docs' frozen
        result of the Hessian check). Not positive definite there (a run stopped short of a minimum): a
        warning, and the Gauss-Newton covariance is kept.

    max_extrapolation : float
        Longest multiple of an accepted full step tried (>= 1; 1 turns extrapolation off). When
        the cost fell by at least :data:`EXTRAPOLATE_GAIN` times the decrease the quadratic model
        predicted and the model's Newton decrement is below :data:`EXTRAPOLATE_DECREMENT` nats,
        the Gauss-Newton curvature along the step is too large (the model misses a falling
        stretch of the cost, as on a plateau), and the step is doubled while the cost keeps
        falling (2, 4, 8, ...: powers of two up to this multiple), one profile pass per try. Near
        a start far from the mode (a large decrement) steps are not extended. The records keep
        the extended step's decrease and length, and the unextended step's gain ratio.

    The damping follows Nielsen's rule: after an accepted full step lambda is multiplied by
    ``max(1/3, 1 - (2 rho - 1)^3)``, rho the ratio of the cost's actual to its predicted decrease;
    after an accepted half step it doubles; after a rejection it grows by a factor that doubles
    with every rejection in a row. The settings that shape the iterates (damping, max_damping,
    max_extrapolation unless it is 1, the safeguards) enter the checkpoint fingerprint; the
    stopping rules (max_iterations, tol, sd_tol, cost_tol) and ``covariance`` do not, so a
    finished run can be resumed with a stricter rule.
    """

    max_iterations: int = 20
    tol: float = 1e-3
    sd_tol: float = 0.1
    cost_tol: float = 5e-3
    damping: float = 1.0
    max_damping: float = 1e8
    covariance: bool = True
    safeguards: Safeguards | None = None
    process_noise: str = "fixed"
    measurement_noise: str = "fixed"
    noise_range: tuple = (4.0 ** -8, 4.0 ** 3)
    noise_tol: float = 0.05
    laplace: str = "gauss-newton"
    max_extrapolation: float = 8.0

    def __post_init__(self):
        integer("max_iterations", self.max_iterations, 1)
        positive("tol", self.tol)
        positive("sd_tol", self.sd_tol)
        positive("cost_tol", self.cost_tol)
        non_negative("damping", self.damping)
        positive("max_damping", self.max_damping)
        if not isinstance(self.covariance, (bool, np.bool_)):
            raise TypeError(f"covariance: expected True or False, got {self.covariance!r}")
        if self.safeguards is not None and not isinstance(self.safeguards, Safeguards):
            raise TypeError(f"safeguards: expected a Safeguards, got {type(self.safeguards).__name__}")
        if self.process_noise not in NOISE_LEVELS:
            raise ValueError(f"process_noise: expected 'fixed' or 'estimate', got {self.process_noise!r}")
        if self.measurement_noise not in NOISE_LEVELS:
            raise ValueError(f"measurement_noise: expected 'fixed' or 'estimate', got {self.measurement_noise!r}")
        try:
            low, high = (float(v) for v in self.noise_range)
        except (TypeError, ValueError):
            raise ValueError(f"noise_range: expected two factors (low, high), got {self.noise_range!r}") from None
        if not (0.0 < low <= 1.0 <= high < np.inf):
            raise ValueError(f"noise_range: expected 0 < low <= 1 <= high (factors on Q), got {self.noise_range!r}")
        positive("noise_tol", self.noise_tol)
        if self.laplace not in ("gauss-newton", "exact"):
            raise ValueError(f"laplace: expected 'gauss-newton' or 'exact', got {self.laplace!r}")
        if not (isinstance(self.max_extrapolation, (int, float, np.integer, np.floating))
                and not isinstance(self.max_extrapolation, bool) and 1.0 <= float(self.max_extrapolation) < np.inf):
            raise ValueError(f"max_extrapolation: expected a finite multiple >= 1 of a step (1: never extend a "
                             f"step), got {self.max_extrapolation!r}")

    def trajectory_settings(self) -> dict:
        guard = self.safeguards if self.safeguards is not None else Safeguards()
        out = {"method": "iterated_smoother", "damping": float(self.damping), "max_damping": float(self.max_damping),
               **guard.settings()}
        if float(self.max_extrapolation) != 1.0:
            # without extrapolation the iterates are those of earlier versions: their checkpoints resume
            out["max_extrapolation"] = float(self.max_extrapolation)
        return out

    @limits_blas_threads
    def run(self, model, observations, *, progress: bool = False, checkpoint=None,
            description: str = "iterated smoother", start=None) -> SmootherResult:
        """Estimate from one cycle's ``observations`` (n_frames, dim_obs), NaN where missing.

        ``checkpoint``: a path saved after every accepted iteration; an existing checkpoint of
        the same run is resumed and the run ends exactly as an uninterrupted one would (with
        ``process_noise="estimate"``, one checkpoint per scale tried, ``<checkpoint>.noise<k>``;
        with ``measurement_noise="estimate"``, ``<checkpoint>.Rnoise<k>``).
        ``start``: a warm start, a trajectory (n_frames, dim_state) whose material (any frame's,
        model coordinates) is the first iterate instead of the prior mean, for example another
        run's ``states``; the MAP cost, and so the mode, are unchanged. A start where the model
        cannot step falls back to the prior mean.
        """
        check_model(model)
        rows = int(np.sum(~np.isnan(check_observations(model, observations))))
        check_memory(model.dim_state, model.n_frames, covariance=self.covariance, observed=rows)   # before any pass
        if start is not None:
            start = as_float_array("start", start, shape=(model.n_frames, model.dim_state))
        if self.measurement_noise == "estimate":
            # R's level first, at the model's Q; then, if asked, Q's level at the R chosen
            inner = replace(self, covariance=self.covariance and self.process_noise == "fixed")
            first = inner._estimate_noise(model, observations, progress, checkpoint, description, start,
                                          kind="measurement")
            result = first
            if self.process_noise == "estimate":
                scaled = scaled_measurement_noise(model, first.measurement_noise_scale)
                cp = None if checkpoint is None else f"{checkpoint}.R{math.log(first.measurement_noise_scale, 4.0):+.4f}"
                result = self._estimate_noise(scaled, observations, progress, cp, description, first.states)
                result.measurement_noise_scale = first.measurement_noise_scale
                result.measurement_noise_search = first.measurement_noise_search
        elif self.process_noise == "estimate":
            result = self._estimate_noise(model, observations, progress, checkpoint, description, start)
        else:
            result = self._fit(model, observations, progress=progress, checkpoint=checkpoint, description=description,
                               start=start)
        if self.laplace == "exact" and result.theta.size:
            used = model
            if result.measurement_noise_scale != 1.0:
                used = scaled_measurement_noise(used, result.measurement_noise_scale)
            if result.process_noise_scale != 1.0:
                used = scaled_process_noise(used, result.process_noise_scale)
            result = exact_laplace(used, observations, result, safeguards=self.safeguards, progress=progress)
        return result

    def _estimate_noise(self, model, observations, progress, checkpoint, description, start=None,
                        kind: str = "process") -> SmootherResult:
        """Type-II maximum likelihood of one factor on Q (``kind="process"``) or on R
        (``"measurement"``): ``process_noise`` and ``measurement_noise`` in the class docstring."""
        check_model(model)
        y = check_observations(model, observations)
        kmin = math.ceil(math.log(self.noise_range[0], 4.0) - 1e-9)
        kmax = math.floor(math.log(self.noise_range[1], 4.0) + 1e-9)
        inner = replace(self, process_noise="fixed", measurement_noise="fixed", covariance=False)
        scaled_noise, symbol, tag = ((scaled_process_noise, "Q", "noise") if kind == "process"
                                     else (scaled_measurement_noise, "R", "Rnoise"))
        fits, evidence = {}, {}
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(desc=f"{description}: {kind} noise level", unit="scale", leave=False)

        def at(k, start):
            cp = None if checkpoint is None else f"{checkpoint}.{tag}{k:+.4f}"
            fits[k] = inner._fit(scaled_noise(model, 4.0 ** k), y, progress=progress, checkpoint=cp,
                                 description=f"{description} ({symbol} x {4.0 ** k:.3g})", start=start)
            evidence[k] = fits[k].log_likelihood
            if bar is not None:
                bar.update(1)
                bar.set_postfix(scale=f"{4.0 ** k:.3g}", log_evidence=f"{evidence[k]:.2f}")
            return evidence[k]

        try:
            at(0.0, start)
            for direction in (-1.0, 1.0):
                k = 0.0
                while kmin <= k + direction <= kmax:
                    at(k + direction, fits[k].states)
                    if not evidence[k + direction] > evidence[k] + self.noise_tol:
                        break
                    k += direction
                if k != 0.0:
                    break                       # the evidence rose downwards: no need to look up
            best = max(evidence, key=evidence.get)
            if best - 1.0 in evidence and best + 1.0 in evidence:
                lo, mid, hi = evidence[best - 1.0], evidence[best], evidence[best + 1.0]
                curvature = hi - 2.0 * mid + lo
                if curvature < 0.0:
                    vertex = best - 0.5 * (hi - lo) / curvature
                    if abs(vertex - best) > 0.05:
                        at(vertex, fits[best].states)
                        best = max(evidence, key=evidence.get)
        finally:
            if bar is not None:
                bar.close()
        scale = 4.0 ** best
        chosen, scaled = fits[best], scaled_noise(model, scale)
        guard = self.safeguards if self.safeguards is not None else Safeguards()
        result = self._final(scaled, y, chosen.states, chosen.cost, chosen.records, chosen.stop_reason,
                             chosen.converged, guard) if self.covariance else chosen
        search = [{"scale": 4.0 ** k, "log_evidence": float(evidence[k]),
                   "iterations": int(fits[k].iterations), "converged": bool(fits[k].converged)}
                  for k in sorted(evidence)]
        if kind == "process":
            result.process_noise_scale, result.noise_search = scale, search
        else:
            result.measurement_noise_scale, result.measurement_noise_search = scale, search
        return result

    def _fit(self, model, observations, *, progress: bool = False, checkpoint=None,
             description: str = "iterated smoother", start=None) -> SmootherResult:
        """One run at the model's Q; ``start``: a trajectory (n_frames, dim_state) whose material
        is the first iterate instead of the prior mean."""
        check_model(model)
        p = check_static_parameters(model)
        y = check_observations(model, observations)
        guard = self.safeguards if self.safeguards is not None else Safeguards()
        nr = int(model.n_restart)
        theta0, P3 = parameter_prior(model)
        fp = run_fingerprint(model, y, self.trajectory_settings())
        records: list = []

        P3_root = _InverseRoot(P3) if p else None

        def profile(theta, like):
            """J_p(theta) = min over the trajectory of J, by one linear filter pass with theta held
            fixed (completing the square: the minimum is half the summed NIS plus theta's prior
            term), with what the backward pass needs to recover the optimal trajectory."""
            fit, found = profile_pass(model, y, theta, like, guard, label=len(records))
            return fit + (0.5 * P3_root.norm2(theta - theta0) if p and found is not None else 0.0), found

        secant = _StructuredSecant(p)
        if checkpoint is not None and os.path.exists(checkpoint):
            state = load_checkpoint(checkpoint, fp)
            secant.restore(state)
            z, lam, nu = np.array(state["trajectory"]), float(state["damping"]), float(state["nu"])
            records = [dict(zip(state["record_keys"].tolist(), map(float, row))) for row in state["records"]]
            cost, stop = float(state["cost"]), str(state["stop_reason"])
        else:
            lam, nu, stop = float(self.damping), 2.0, ""
            cost, found = (np.inf, None) if start is None else profile(np.asarray(start, float)[0, nr:], start)
            if found is None or not np.isfinite(cost):
                cost, found = profile(theta0, open_loop(model))
            if found is None or not np.isfinite(cost):
                raise FloatingPointError("the prior's material gives no finite MAP cost: the model cannot step its "
                                         "initial state")
            z = optimal_trajectory(model, found)
        if p == 0:
            stop = "no parameters"
        bar = None
        if progress and not stop:
            from tqdm import tqdm
            bar = tqdm(total=self.max_iterations, initial=len(records), desc=description, unit="it", leave=False)
        try:
            P3_inv = sla.cho_solve(sla.cho_factor(P3), np.eye(p)) if p else None
            while not stop and len(records) < self.max_iterations:
                t0 = time.perf_counter()
                theta_bar = z[0, nr:]
                # One undamped pass of the linearised model gives the Gauss-Newton quadratic model
                # of the profile cost about theta_bar: its Hessian is the inverse of the pass's
                # posterior covariance of theta, and its gradient is exact (the linearisation is
                # exact to first order and the trajectory part is at its optimum). Damped steps and
                # rejections are then p x p solves, not further passes.
                g, H, P_theta = gauss_newton_pass(model, y, z, guard, label=len(records))
                S = secant.update(H, g)
                H_model = H + S
                try:
                    cho_model = sla.cho_factor(H_model, lower=True)
                except np.linalg.LinAlgError:
                    # the secant correction made the model indefinite: drop it rather than let the
                    # damping grow to cover it (a large lambda shortens the steps, not the distance)
                    secant.S[:] = 0.0
                    H_model = H
                    cho_model = sla.cho_factor(H, lower=True)
                # the undamped step of the quadratic model and its predicted decrease (the Newton
                # decrement): how far the mode still is, whatever the damping does to the step taken
                full = -sla.cho_solve(cho_model, g)
                J = physical_jacobian(model, theta_bar)
                full_sd = step_in_sd(full, P_theta, J)
                newton_decrement = float(-0.5 * g @ full)
                rejected = 0
                while True:
                    try:
                        step = -sla.cho_solve(sla.cho_factor(H_model + lam * P3_inv, lower=True), g)
                    except np.linalg.LinAlgError:
                        lam, nu = max(lam, 1e-3) * nu, 2.0 * nu
                        continue
                    predicted = -(g @ step + 0.5 * step @ H_model @ step)
                    lam_used, alpha = lam, 1.0
                    new_cost, found = profile(theta_bar + step, z)
                    gain = (cost - new_cost) / max(predicted, 1e-300)
                    if new_cost < cost:
                        # Nielsen's factor; a gain ratio >= 1 (also a vanishing predicted decrease,
                        # where the ratio overflows) gives its floor 1/3
                        lam *= 1.0 / 3.0 if gain >= 1.0 else max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
                        nu = 2.0
                        break
                    # line search: the minimum of the quadratic through J(0), J'(0) and J(1), in [0.1, 0.5]
                    slope = g @ step
                    curv = new_cost - cost - slope if np.isfinite(new_cost) else np.inf
                    alpha = float(np.clip(-slope / (2.0 * curv), 0.1, 0.5)) if curv > 0 else 0.1
                    new_cost, found = profile(theta_bar + alpha * step, z)
                    if new_cost < cost:
                        lam *= 2.0
                        break
                    rejected += 1
                    if lam >= self.max_damping:
                        # no damping lowers the cost: the end, converged only if the model also
                        # predicts no worthwhile decrease (else the run is stuck, and says so)
                        stop = "cost" if newton_decrement < self.cost_tol else "damping"
                        break
                    lam, nu = max(lam, 1e-3) * nu, 2.0 * nu
                if stop:
                    break
                if (alpha == 1.0 and gain >= EXTRAPOLATE_GAIN and newton_decrement < EXTRAPOLATE_DECREMENT
                        and self.max_extrapolation > 1.0):
                    # the cost fell by more than the model predicted, and the model predicts
                    # little more: its curvature along the step is too large (a plateau the
                    # Gauss-Newton model cannot see), so the mode lies further along; double the
                    # step while the cost keeps falling
                    factor = 2.0
                    while factor <= self.max_extrapolation:
                        trial_cost, trial_found = profile(theta_bar + factor * step, z)
                        if not trial_cost < new_cost:
                            break
                        new_cost, found, alpha = trial_cost, trial_found, factor
                        factor *= 2.0
                taken = alpha * step
                secant.taken(taken, g)
                before = physical_parameters(model, theta_bar)
                moved, size = np.linalg.norm(physical_parameters(model, theta_bar + taken) - before), np.linalg.norm(before)
                rel = float(moved / size) if size > 0 else np.inf    # no relative change from zero parameters
                step_sd = step_in_sd(taken, P_theta, J)
                records.append({"iteration": len(records) + 1, "cost": new_cost, "decrease": cost - new_cost,
                                "damping": lam_used, "step_length": alpha, "gain_ratio": float(gain), "rejected": rejected,
                                "rel_change": rel, "step_sd": step_sd, "max_abs_step": float(np.max(np.abs(taken))),
                                "full_step_sd": full_sd, "newton_decrement": newton_decrement, "seconds": 0.0})
                z, cost = optimal_trajectory(model, found), new_cost
                records[-1]["seconds"] = time.perf_counter() - t0
                # the rules judge the undamped step too: a step shortened by a large lambda says
                # nothing about the distance to the mode
                if rel < self.tol and step_sd < self.sd_tol and full_sd < self.sd_tol:
                    stop = "step"
                elif records[-1]["decrease"] < self.cost_tol and newton_decrement < self.cost_tol:
                    stop = "cost"
                if checkpoint is not None:
                    keys = list(records[0])
                    save_checkpoint(checkpoint, fp, z[0, nr:], P3, [r["rel_change"] for r in records], History(),
                                    len(records), trajectory=z, damping=lam, nu=nu, cost=cost, stop_reason=stop,
                                    **secant.state(),
                                    record_keys=np.array(keys), records=np.array([[r[k] for k in keys]
                                                                                  for r in records]))
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(cost=f"{cost:.6g}", damping=f"{records[-1]['damping']:.0e}",
                                    step_sd=f"{step_sd:.2g}")
        finally:
            if bar is not None:
                bar.close()
        if not stop:
            stop = "max_iterations"
        converged = stop in ("step", "cost", "no parameters")
        if not converged:
            warnings.warn(f"iterated smoother: stopped by '{stop}' after {len(records)} iterations before the "
                          f"material step met the rule (tol {self.tol:g}, {self.sd_tol:g} sd)", RuntimeWarning)
        return self._final(model, y, z, cost, records, stop, converged, guard)

    def _final(self, model, y, z, cost, records, stop, converged, guard) -> SmootherResult:
        """The Laplace approximation at the mode: an undamped pass linearised there."""
        nr = int(model.n_restart)
        lin = linearise(model, z)
        outputs = {}
        if self.covariance:
            outputs["state"] = lin.output_in_xi(np.eye(nr))
            if isinstance(model, OutputOperators):
                outputs.update({k: lin.output_in_xi(v) for k, v in model.output_operators().items()})
        sm = smooth(lin, y, safeguards=guard, covariance=self.covariance, outputs=outputs, monitor_nis=True,
                    label=len(records))
        T, n = z.shape
        P_diag = np.full((T, n), np.nan)
        if self.covariance:
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


def iterated_smoother(model, observations, *, progress: bool = False, checkpoint=None,
                      description: str = "iterated smoother", **settings) -> SmootherResult:
    """``IteratedSmoother(**settings).run(model, observations, ...)``; see :class:`IteratedSmoother`."""
    return IteratedSmoother(**settings).run(model, observations, progress=progress, checkpoint=checkpoint,
                                            description=description)
