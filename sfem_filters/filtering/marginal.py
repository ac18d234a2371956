"""The exact marginal posterior of the parameters, for small parameter vectors: a check of the smoother.

Given the parameters theta, the model is linear-Gaussian in its trajectory, so one Kalman pass
gives the exact log-likelihood ``log p(y | theta)`` by the prediction-error decomposition
(:func:`log_likelihood`). Adding the prior and maximising over theta gives the marginal MAP;
the inverse of the negative log posterior's Hessian there (central finite differences) is its
Laplace covariance. :func:`laplace_check` compares both with an
:class:`~sfem_filters.filtering.iterated.IteratedSmoother` result, whose estimate is the *joint*
mode of (trajectory, theta) and whose covariance is the Gauss-Newton one: they agree to the
accuracy the linearisation allows, which the check measures. Costs O(p^2) filter passes: meant
for p up to a few tens.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from scipy import optimize

from .._validate import as_float_array, integer, positive
from .cyclic import check_observations
from .linearised import check_static_parameters, linearise
from .protocol import check_model, n_parameters, parameter_prior
from .smoother import kalman_forward

__all__ = ["log_likelihood", "log_posterior", "MarginalCheck", "laplace_check"]


def log_likelihood(model, observations, theta) -> float:
    """``log p(y | theta)`` of the model with its parameters held at ``theta`` (exact: one
    Kalman pass of the linear model, prediction-error decomposition); ``-inf`` where the model
    cannot be built (a material outside its representable range)."""
    check_model(model)
    nr = int(model.n_restart)
    theta = as_float_array("theta", theta, shape=(n_parameters(model),))
    z = np.tile(np.asarray(model.x0, float), (model.n_frames, 1))
    z[:, nr:] = theta
    try:
        lin = linearise(model, z, sensitivity=False)
        return float(kalman_forward(lin, check_observations(model, observations), store=False).log_likelihood)
    except (FloatingPointError, ValueError, np.linalg.LinAlgError):
        return -np.inf


def log_posterior(model, observations, theta) -> float:
    """``log p(y | theta) + log p(theta)`` up to a constant (the Gaussian prior of ``model``)."""
    theta0, P3 = parameter_prior(model)
    d = np.asarray(theta, float) - theta0
    return log_likelihood(model, observations, theta) - 0.5 * float(d @ sla.cho_solve(sla.cho_factor(P3), d))


@dataclass
class MarginalCheck:
    """Marginal MAP and Laplace covariance against a smoother's estimate and covariance.

    ``z_mode``: (smoother theta - marginal MAP) / marginal sd, per parameter; ``sd_ratio``:
    smoother sd / marginal sd per parameter; ``kl``: KL divergence of the marginal Laplace
    Gaussian from the smoother's (nats).
    """

    theta_map: np.ndarray
    cov_map: np.ndarray
    z_mode: np.ndarray
    sd_ratio: np.ndarray
    kl: float
    evaluations: int


def laplace_check(model, observations, theta_hat, P_theta, step: float = 1e-3, max_params: int = 30) -> MarginalCheck:
    """Maximise the exact marginal posterior from ``theta_hat`` and compare (module docstring).

    Parameters
    ----------
    theta_hat, P_theta : the smoother's parameters and covariance
    step : float
        Finite-difference step in units of the smoother's sd of each parameter (> 0).
    max_params : int
        Refuse more parameters than this (the check costs O(p^2) filter passes).
    """
    check_model(model)
    p = check_static_parameters(model)
    integer("max_params", max_params, 1)
    if p > max_params:
        raise ValueError(f"model: expected at most {max_params} parameters for the exact marginal check, got {p}")
    y = check_observations(model, observations)
    theta_hat = as_float_array("theta_hat", theta_hat, shape=(p,))
    P_theta = as_float_array("P_theta", P_theta, shape=(p, p))
    positive("step", step)
    sd = np.sqrt(np.diag(P_theta))
    count = [0]

    def f(u):                       # negative log posterior in units of the smoother's sd
        count[0] += 1
        return -log_posterior(model, y, theta_hat + sd * u)

    res = optimize.minimize(f, np.zeros(p), method="BFGS", options={"gtol": 1e-7, "eps": step})
    u0 = res.x
    Hu = np.empty((p, p))
    f0 = f(u0)
    h = step * 10
    for i in range(p):
        for j in range(i, p):
            ei, ej = np.eye(p)[i] * h, np.eye(p)[j] * h
            if i == j:
                Hu[i, i] = (f(u0 + ei) - 2 * f0 + f(u0 - ei)) / h ** 2
            else:
                Hu[i, j] = Hu[j, i] = (f(u0 + ei + ej) - f(u0 + ei - ej) - f(u0 - ei + ej) + f(u0 - ei - ej)) / (4 * h ** 2)
    cov_u = np.linalg.inv(0.5 * (Hu + Hu.T))
    theta_map = theta_hat + sd * u0
    cov = cov_u * np.outer(sd, sd)
    sd_map = np.sqrt(np.diag(cov))
    # KL(N(theta_map, cov) || N(theta_hat, P_theta))
    cho = sla.cho_factor(P_theta)
    d = theta_map - theta_hat
    kl = 0.5 * (np.trace(sla.cho_solve(cho, cov)) + d @ sla.cho_solve(cho, d) - p
                + 2 * np.sum(np.log(np.diag(cho[0]))) - np.linalg.slogdet(cov)[1])
    return MarginalCheck(theta_map=theta_map, cov_map=cov, z_mode=(theta_hat - theta_map) / sd_map,
                         sd_ratio=sd / sd_map, kl=float(kl), evaluations=count[0])
