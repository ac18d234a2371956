"""Filtering with a model object: engines, the cyclic driver, safeguards, checkpoints, diagnostics.

Knows the model only through its written contract, :mod:`sfem_filters.filtering.protocol`
(required members ``fx``, ``F_jacobian``, ``hx``, ``H_jacobian``, ``Q``, ``R``, ``x0``, ``P0``,
dimensions; optional capabilities such as per-frame noise). Any object with those members is a
model; :class:`LinearGaussianModel` is a complete small one:

>>> import numpy as np
>>> from sfem_filters.filtering import CyclicEKF, IteratedSmoother, LinearGaussianModel, diagnostics
>>> def transition(theta):                        # x_{t+1} = a x_t, a = theta[0], dA/da = I
...     return theta[0] * np.eye(1), np.ones((1, 1, 1))
>>> model = LinearGaussianModel(transition, H=np.eye(1), Q=0.01 * np.eye(1), R=0.01 * np.eye(1),
...                             x0=[1.0], P0=np.eye(1), n_frames=20, theta0=[0.5], prior_cov=np.eye(1))
>>> y = 0.9 ** np.arange(20)[:, None]             # noise-free data of a = 0.9
>>> result = CyclicEKF(max_loops=5, engine="structured").run(model, y)
>>> bool(abs(result.theta[0] - 0.9) < 0.05)
True
>>> mode = IteratedSmoother().run(model, y)          # the MAP of one cycle, data counted once
>>> bool(abs(mode.theta[0] - 0.9) < 0.05), mode.stop_reason
(True, 'step')
>>> 0.0 < diagnostics.nis_summary(result.history)["nis_mean_over_dof"] < 1.0
True

Modules: :mod:`~sfem_filters.filtering.protocol` (the model contract),
:mod:`~sfem_filters.filtering.base` (the engine interface), one engine per module
(:mod:`~sfem_filters.filtering.ekf`: filterpy's EKF, the reference;
:mod:`~sfem_filters.filtering.structured`: block structure, Cholesky, Joseph form;
:mod:`~sfem_filters.filtering.ud`: U-D factorised; :mod:`~sfem_filters.filtering.unscented`:
filterpy's UKF on the full state, ``make_ukf``; :mod:`~sfem_filters.filtering.roukf`: Moireau &
Chapelle's reduced-order UKF, simplex sigma points on the parameters), :mod:`~sfem_filters.filtering.ljung`
(Ljung's coupling, Eq. 40), :mod:`~sfem_filters.filtering.safeguards`,
:mod:`~sfem_filters.filtering.cyclic` (the paper's cyclic driver),
:mod:`~sfem_filters.filtering.linearised` and :mod:`~sfem_filters.filtering.smoother` (the model
linearised about a trajectory, and its RTS smoother: smoothed means from the filter's gains alone,
smoothed covariances from every frame's prior covariance or from checkpoints where those do not
fit the memory; its forward pass, :mod:`~sfem_filters.filtering.forward`, and what a run keeps in
memory, :mod:`~sfem_filters.filtering.memory`), :mod:`~sfem_filters.filtering.iterated`
(the iterated smoother: Gauss-Newton on the MAP of one cycle, stopped by the step of the
physical material in its posterior sd, :func:`step_in_sd`; its MAP cost,
:mod:`~sfem_filters.filtering.map_cost`, its damped loop, :mod:`~sfem_filters.filtering.gauss_newton`,
and its result and Laplace posterior, :mod:`~sfem_filters.filtering.laplace`),
:mod:`~sfem_filters.filtering.curvature` (the profile cost of the material, its exact gradient and
its exact Hessian by differences: how far Gauss-Newton's curvature is from the truth),
:mod:`~sfem_filters.filtering.marginal` (the exact marginal posterior of a few parameters),
:mod:`~sfem_filters.filtering.checkpoint`, :mod:`~sfem_filters.filtering.history`,
:mod:`~sfem_filters.filtering.diagnostics` (NIS, whiteness, score test, material drift, prior-data conflict),
:mod:`~sfem_filters.filtering.linear` (linear observations, the linear-Gaussian template model).
"""
from . import diagnostics
from .base import Engine
from .checkpoint import CHECKPOINT_FORMAT, load_checkpoint, run_fingerprint, save_checkpoint
from .curvature import ProfileHessian, gauss_newton_pass, optimal_trajectory, profile_hessian, profile_pass
from .cyclic import CyclicEKF, CyclicResult, check_observations, cyclic_estimate, filter_loop, one_cycle_covariance
from .ekf import FilterpyEngine, SFEMExtendedKalmanFilter
from .engines import ENGINES, make_engine
from .history import History
from .iterated import (IteratedSmoother, MapObjective, SmootherResult, exact_laplace, iterated_smoother, step_in_sd,
                       with_covariance)
from .linear import LinearGaussianModel, LinearObservation
from .linearised import LinearisedModel, linearise, linearise_dense
from .ljung import LJUNG_MAX_PARAMS, LjungCoupling
from .marginal import MarginalCheck, laplace_check, log_likelihood, log_posterior
from .roukf import ROUKFEngine, simplex_points
from .protocol import (FilterModel, Fingerprinted, Linearisable, LoadResponse, OutputOperators, PerFrameNoise,
                       PhysicalJacobian, PhysicalParameters, ProcessNoiseProfile, ScalableMeasurementNoise,
                       ScalableProcessNoise, TransitionDerivatives, check_model, measurement_cov, process_profile,
                       scaled_measurement_noise, scaled_process_noise)
from .safeguards import FilterDivergence, Safeguards, nearest_psd
from .smoother import ForwardPass, SmoothedPass, kalman_forward, rts_reference, smooth, smooth_backward
from .structured import StructuredEngine, joseph_update
from .ud import UDEngine, bierman_update, mwgs, psd_factor, ud_factor
from .unscented import UKFEngine, make_ukf

from .base import DenseEngine
from .gauss_newton import EXTRAPOLATE_DECREMENT, EXTRAPOLATE_GAIN
from .iterated import NOISE_LEVELS
from .memory import check_memory, covariance_interval
__all__ = ["ROUKFEngine", "simplex_points", "UKFEngine", "make_ukf", "diagnostics", "Engine", "CyclicEKF", "CyclicResult", "cyclic_estimate", "filter_loop", "check_observations",
           "FilterpyEngine", "SFEMExtendedKalmanFilter", "StructuredEngine", "UDEngine", "ENGINES", "make_engine",
           "History", "LinearGaussianModel", "LinearObservation", "LjungCoupling", "LJUNG_MAX_PARAMS",
           "FilterModel", "PerFrameNoise", "Fingerprinted", "PhysicalParameters", "PhysicalJacobian",
           "TransitionDerivatives",
           "LoadResponse", "check_model", "measurement_cov", "Safeguards", "FilterDivergence", "nearest_psd",
           "joseph_update", "ud_factor", "psd_factor", "mwgs", "bierman_update", "CHECKPOINT_FORMAT",
           "save_checkpoint", "load_checkpoint", "run_fingerprint", "one_cycle_covariance", "IteratedSmoother",
           "SmootherResult", "MapObjective", "iterated_smoother", "LinearisedModel", "linearise", "linearise_dense",
           "smooth", "kalman_forward", "smooth_backward", "rts_reference", "ForwardPass", "SmoothedPass",
           "Linearisable", "OutputOperators", "ScalableProcessNoise", "scaled_process_noise",
           "ScalableMeasurementNoise", "scaled_measurement_noise", "MarginalCheck", "laplace_check", "log_likelihood", "log_posterior",
           "ProfileHessian", "profile_hessian", "profile_pass", "optimal_trajectory", "gauss_newton_pass", "exact_laplace",
           "with_covariance", "step_in_sd", "ProcessNoiseProfile", "process_profile",
           "DenseEngine", "EXTRAPOLATE_DECREMENT", "EXTRAPOLATE_GAIN", "NOISE_LEVELS", "covariance_interval",
           "check_memory"]
