"""The profile cost of the material, its exact gradient, and its exact Hessian by differences.

For a fixed material theta the model is linear-Gaussian in its trajectory, so the smallest MAP
cost over the trajectory, the profile cost

    J_p(theta) = min_r J(r, theta) = 1/2 sum_t e_t^T S_t^-1 e_t + 1/2 |theta - theta0|^2_{P3^-1},

is one linear Kalman pass with theta held fixed (:func:`profile_pass`), and the optimal
trajectory one backward pass more (:func:`optimal_trajectory`). At that trajectory the pass of
the model linearised in theta (:func:`gauss_newton_pass`) gives the exact gradient of J_p
(envelope theorem: the trajectory's own gradient is zero there) and the Gauss-Newton Hessian,
the inverse of the pass's posterior covariance of theta, which the iterated smoother steps with
and reports as its Laplace covariance.

The Gauss-Newton Hessian leaves out the residuals times their second derivatives in theta: the
process noise the trajectory needs (``r_{t+1} - A(theta) r_t``) times the second derivatives of
the transition. When the model fits its data those residuals are noise and the term averages
out (the pinned benchmark: sds within 2% of the exact marginal posterior's); when it does not
(a measured slice and a model without the effect that moves it), the term can dominate.
:func:`profile_hessian` measures it: central differences of the exact gradient, 2 p gradient
passes, each step a fraction of a Gauss-Newton posterior sd. Its inverse is the covariance of
theta under the Laplace approximation of the joint posterior of (trajectory, theta) at the mode
(the theta block of the inverse joint Hessian is the inverse of the profile cost's Hessian, by
the implicit function theorem).

>>> from sfem_filters.benchmark.pinned import benchmark_model, pinned_benchmark
>>> from sfem_filters.fem.material import Parameterisation
>>> from sfem_filters.filtering import IteratedSmoother, profile_hessian
>>> bench = pinned_benchmark(0)
>>> model = benchmark_model(bench, "joint_ekf", parameterisation=Parameterisation.per_region(bench.middle))
>>> mode = IteratedSmoother(covariance=False).run(model, bench.observations)
>>> curv = profile_hessian(model, bench.observations, mode.states)
>>> bool(abs(curv.sd_ratio() - 1).max() < 0.05)     # the model fits: Gauss-Newton is the Laplace
True
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from .._validate import as_float_array, positive
from .cyclic import check_observations
from .linearised import check_static_parameters, linearise
from .protocol import check_model
from .safeguards import Safeguards
from .smoother import kalman_forward, smooth_backward

__all__ = ["profile_pass", "optimal_trajectory", "gauss_newton_pass", "ProfileHessian", "profile_hessian"]


def profile_pass(model, y, theta, like, safeguards: Safeguards, label: int = 0) -> tuple:
    """The data part of ``J_p(theta)`` (half the summed NIS) by one filter pass with theta fixed.

    Parameters
    ----------
    model : a model of the filtering protocol with static parameters
    y : (n_frames, dim_obs) observations (model units, NaN where missing)
    theta : (p,) parameters (model coordinates)
    like : (n_frames, dim_state) a trajectory whose restart part the pass linearises about (the
        model is linear in it for a fixed theta, so only the frames' layout matters)
    safeguards : checks of the pass's covariance

    Returns
    -------
    (fit, found) : ``fit`` (nats), ``inf`` with ``found`` None when the model cannot step at theta;
        ``found`` holds what :func:`optimal_trajectory` needs.
    """
    nr = int(model.n_restart)
    z = np.array(like, float)
    z[:, nr:] = theta
    try:
        lin = linearise(model, z, sensitivity=False)
        fwd = kalman_forward(lin, y, safeguards=safeguards, check_every_frame=False, label=label, store="mean")
    except (FloatingPointError, ValueError, np.linalg.LinAlgError):
        return np.inf, None
    return float(fwd.fit), (lin, fwd, z)


def optimal_trajectory(model, found) -> np.ndarray:
    """The trajectory that attains ``J_p`` at the pass's theta (its RTS smoothed mean), with theta
    in every frame: (n_frames, dim_state)."""
    lin, fwd, z = found
    nr = int(model.n_restart)
    z = np.array(z, float)
    z[:, :nr] = lin.to_model(smooth_backward(lin, fwd).smoothed[:, :nr])
    return z


def gauss_newton_pass(model, y, states, safeguards: Safeguards, label: int = 0) -> tuple:
    """The exact gradient and the Gauss-Newton Hessian of ``J_p`` at the theta of ``states``.

    ``states`` must be the optimal trajectory of its theta (:func:`optimal_trajectory`), else the
    gradient is that of J in theta alone. One undamped pass of the model linearised about it:
    the Hessian is the inverse of the pass's posterior covariance of theta, and the gradient
    ``-H (theta_post - theta)``.

    Returns
    -------
    (g, H, P_theta) : (p,), (p, p), (p, p), model units of theta.
    """
    nr = int(model.n_restart)
    theta = np.asarray(states, float)[0, nr:]
    lin = linearise(model, states)
    fwd = kalman_forward(lin, y, safeguards=safeguards, check_every_frame=False, label=label, store=False)
    P_theta = fwd.engine.P[nr:, nr:].copy()
    H = sla.cho_solve(sla.cho_factor(P_theta, lower=True), np.eye(P_theta.shape[0]))
    H = 0.5 * (H + H.T)
    return -H @ (fwd.filtered[-1, nr:] - theta), H, P_theta


@dataclass
class ProfileHessian:
    """The profile cost's curvature at one theta, exact (by differences) and Gauss-Newton.

    Attributes
    ----------
    theta : (p,) where it was taken (model coordinates)
    hessian : (p, p) central differences of the exact gradient, symmetrised (nats per unit^2)
    gauss_newton : (p, p) the Gauss-Newton Hessian the smoother uses
    gradient : (p,) the exact gradient of J_p there (nats per unit)
    asymmetry : float
        ``max |D - D^T| / max |D|`` of the unsymmetrised differences: the differencing error.
    evaluations : int
        Gradient passes used (2 p + 1).
    """

    theta: np.ndarray
    hessian: np.ndarray
    gauss_newton: np.ndarray
    gradient: np.ndarray
    asymmetry: float
    evaluations: int

    def relative_eigenvalues(self) -> np.ndarray:
        """Eigenvalues of the exact Hessian relative to Gauss-Newton's (``H v = w H_GN v``),
        ascending: 1 where Gauss-Newton is exact, below 0 along directions of negative curvature
        (the cost is not convex there), above 1 where it underestimates the curvature."""
        return sla.eigh(self.hessian, self.gauss_newton, eigvals_only=True)

    def positive_definite(self) -> bool:
        """True when the exact Hessian is positive definite (has a Cholesky factor): the cost is locally convex."""
        try:
            np.linalg.cholesky(self.hessian)
        except np.linalg.LinAlgError:
            return False
        return True

    def covariance(self) -> np.ndarray:
        """The Laplace covariance of theta, the inverse exact Hessian; ValueError where the Hessian
        is not positive definite (not at a minimum)."""
        if not self.positive_definite():
            raise ValueError("profile Hessian: not positive definite at this theta (not a minimum of the MAP cost); "
                             "no Laplace covariance")
        return sla.cho_solve(sla.cho_factor(self.hessian), np.eye(len(self.theta)))

    def sd_ratio(self) -> np.ndarray:
        """Marginal sds of the exact Laplace covariance over the Gauss-Newton ones, per parameter."""
        gn = sla.cho_solve(sla.cho_factor(self.gauss_newton), np.eye(len(self.theta)))
        return np.sqrt(np.diag(self.covariance()) / np.diag(gn))


def profile_hessian(model, observations, states, *, step_sd: float = 0.1, safeguards: Safeguards | None = None,
                    progress: bool = False) -> ProfileHessian:
    """The exact Hessian of the profile cost ``J_p`` at the theta of ``states`` (module docstring).

    Parameters
    ----------
    model : a model of the filtering protocol with static parameters (at least one)
    observations : (n_frames, dim_obs) array, model units (m, m/s), NaN where missing
    states : (n_frames, dim_state) a trajectory with the theta to take the Hessian at in every
        frame (for example ``IteratedSmoother().run(...).states``); its kinematics are replaced by
        the optimal trajectory of that theta
    step_sd : float
        Difference step along each parameter, in Gauss-Newton posterior sds (> 0); the error of
        the central differences is O(step^2).
    safeguards : Safeguards, optional
        Checks of every pass's covariance (default :class:`Safeguards`).
    progress : bool
        A progress bar over the 2 p gradient passes.

    Returns
    -------
    ProfileHessian

    Raises
    ------
    ValueError
        The model has no parameters, or ``states`` has the wrong shape, or the model cannot step
        at theta or at a difference point (``FloatingPointError``).
    """
    check_model(model)
    p = check_static_parameters(model)
    if p == 0:
        raise ValueError("model: expected static parameters (theta) for a profile Hessian, got none")
    y = check_observations(model, observations)
    z = as_float_array("states", states, shape=(model.n_frames, model.dim_state))
    positive("step_sd", step_sd)
    guard = safeguards if safeguards is not None else Safeguards()
    nr = int(model.n_restart)
    theta = z[0, nr:].copy()

    def gradient(th):
        _, found = profile_pass(model, y, th, z, guard)
        if found is None:
            raise FloatingPointError(f"profile Hessian: the model cannot step at theta = {th}")
        return gauss_newton_pass(model, y, optimal_trajectory(model, found), guard)

    g, H_gn, P_gn = gradient(theta)
    h = float(step_sd) * np.sqrt(np.diag(P_gn))
    D = np.empty((p, p))
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=2 * p, desc="profile Hessian", unit="pass", leave=False)
    try:
        for k in range(p):
            e = np.zeros(p)
            e[k] = h[k]
            up = gradient(theta + e)[0]
            if bar is not None:
                bar.update(1)
            down = gradient(theta - e)[0]
            if bar is not None:
                bar.update(1)
            D[:, k] = (up - down) / (2.0 * h[k])
    finally:
        if bar is not None:
            bar.close()
    scale = float(np.abs(D).max()) or 1.0
    return ProfileHessian(theta=theta, hessian=0.5 * (D + D.T), gauss_newton=H_gn, gradient=g,
                          asymmetry=float(np.abs(D - D.T).max() / scale), evaluations=2 * p + 1)
