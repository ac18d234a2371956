"""The model contract: what a filter engine may ask of a model, written down.

A *model* is any object with the members of :class:`FilterModel`; the engines, drivers and
diagnostics of :mod:`sfem_filters.filtering` use nothing else of it. The state is
``z = [r; theta]``: a *restart* part ``r`` of length ``n_restart`` (kinematics and any other
states that a cyclic loop restarts) followed by ``theta``, the static parameters (material)
appended to the state for joint estimation. Frames are 0-based: ``fx(z, t)`` moves the state
from frame ``t`` to ``t + 1``. Observations are the measured numbers, an array
``(n_frames, dim_obs)`` with NaN where a value is missing.

Optional capabilities are separate protocols. An engine that can use one asks through the
accessor functions below (``isinstance`` against the protocol, which is ``runtime_checkable``),
never by probing attribute names; every optional member has a documented fallback.

>>> import numpy as np
>>> from sfem_filters.filtering.linear import LinearGaussianModel
>>> m = LinearGaussianModel(np.eye(2), np.eye(2), 0.01 * np.eye(2), np.eye(2), np.zeros(2), np.eye(2), 4)
>>> isinstance(m, FilterModel), isinstance(m, PerFrameNoise)
(True, False)
>>> measurement_cov(m, 0).shape
(2, 2)
"""
from __future__ import annotations

import hashlib
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["FilterModel", "PerFrameNoise", "Fingerprinted", "PhysicalParameters", "PhysicalJacobian",
           "TransitionDerivatives",
           "LoadResponse", "Linearisable", "OutputOperators", "ScalableProcessNoise", "ScalableMeasurementNoise", "check_model", "measurement_cov",
           "model_fingerprint", "physical_parameters", "physical_jacobian", "n_parameters", "parameter_prior", "scaled_process_noise",
           "scaled_measurement_noise", "ProcessNoiseProfile", "process_profile"]


@runtime_checkable
class FilterModel(Protocol):
    """Required members of a model (shapes with n = ``dim_state``, m = ``dim_obs``).

    Attributes
    ----------
    dim_state : int
        Length n of the augmented state ``z = [r; theta]``.
    dim_obs : int
        Number m of observed rows per frame.
    n_restart : int
        Length of the restart part ``r`` (``n - n_restart`` static parameters follow).
    n_frames : int
        Frames in the sequence (a periodic cycle for the cyclic and smoothing drivers).
    estimates_material : bool
        True when the state holds parameters (``n > n_restart``).
    x0 : (n,) array
        Initial state: ``r`` at the first frame and the prior mean of ``theta``.
    P0 : (n, n) array
        Initial covariance (Eq. 34: no cross-covariance between ``r`` and ``theta``).
    Q : (n, n) array
        Process noise per frame (zero on ``theta`` for a static parameter).
    R : (m, m) array
        Measurement noise (the frame average when it varies, see :class:`PerFrameNoise`).
    """

    dim_state: int
    dim_obs: int
    n_restart: int
    n_frames: int
    estimates_material: bool
    x0: np.ndarray
    P0: np.ndarray
    Q: np.ndarray
    R: np.ndarray

    def fx(self, z, t):
        """State at frame ``t + 1`` from state ``z`` at frame ``t`` (same shape as ``z``)."""

    def F_jacobian(self, z, t) -> np.ndarray:
        """(n, n) Jacobian of :meth:`fx` at ``z``: ``[[A, M_t], [0, I]]`` for static parameters."""

    def hx(self, z, t=None):
        """Predicted observation of state ``z`` (m values, same ndim as ``z``)."""

    def H_jacobian(self, z=None, t=None) -> np.ndarray:
        """(m, n) Jacobian of :meth:`hx`."""


@runtime_checkable
class PerFrameNoise(Protocol):
    """Optional: a measurement noise covariance per frame. Fallback: ``model.R`` every frame."""

    def R_at(self, t: int) -> np.ndarray:
        """(m, m) measurement noise covariance of frame ``t``."""


@runtime_checkable
class ProcessNoiseProfile(Protocol):
    """Optional: the process noise of each frame interval as a factor on ``Q``. Fallback: ``Q`` every interval.

    The interval from frame ``t`` to ``t + 1`` has process noise ``s_t Q`` (``t = 0 .. n_frames - 2``).
    Used by the smoother family (:func:`sfem_filters.filtering.linearised.linearise`, the Kalman
    filter and RTS smoother of the linearised model, :class:`~sfem_filters.filtering.iterated.IteratedSmoother`,
    :class:`~sfem_filters.filtering.map_cost.MapObjective`); the cyclic engines use ``Q`` alone and
    refuse a model with a profile (:func:`sfem_filters.filtering.cyclic.filter_loop`).
    """

    def process_profile(self):
        """(n_frames - 1,) factors ``s_t > 0`` on ``Q`` per interval, or None (every factor 1)."""


@runtime_checkable
class Fingerprinted(Protocol):
    """Optional: a hash of everything that defines the model, for checkpoints.

    Fallback: a hash of ``x0``, ``P0``, ``Q``, ``R`` and ``H`` at ``x0`` (which misses what
    only ``fx`` knows: a model that has one should supply it).
    """

    def fingerprint(self) -> str:
        """Hex digest that changes whenever the model would behave differently."""


@runtime_checkable
class PhysicalParameters(Protocol):
    """Optional: the parameters in physical units, for the relative-change stop rule.

    Fallback: ``theta`` itself.
    """

    def physical_parameters(self, theta) -> np.ndarray:
        """1D array of the physical quantities ``theta`` stands for (e.g. E in Pa and nu)."""


@runtime_checkable
class PhysicalJacobian(Protocol):
    """Optional: how the physical quantities move with ``theta``, for the step-in-sd stop rule.

    The rule measures a step in posterior standard deviations of each physical quantity (a
    row ``j`` moves by ``j @ step`` against an sd of ``sqrt(j P j^T)``), so that it does not
    depend on how the parameters are numbered or combined (relative-region contrasts, basis
    modes). Fallback: the rows of the identity (the step in each parameter's own sd).
    """

    def physical_jacobian(self, theta):
        """(q, p) array or sparse matrix: d physical_parameters / d theta at ``theta``."""


@runtime_checkable
class TransitionDerivatives(Protocol):
    """Optional, needed by Ljung's coupling (Eq. 40): no fallback."""

    def transition_derivatives(self, z, t) -> np.ndarray:
        """(p, n_restart, n_restart): dA/dtheta_i of the restart block of the transition."""


@runtime_checkable
class LoadResponse(Protocol):
    """Optional, needed by the score test of a missing load term: no fallback."""

    def load_response(self, load_matrix, z) -> np.ndarray:
        """(m, k): the change of the next frame's predicted observation per unit of each
        column of ``load_matrix`` (the model's own load representation) held over one frame,
        at the parameters of state ``z``."""


@runtime_checkable
class Linearisable(Protocol):
    """Optional: the model linearised about a trajectory, in coordinates where its transition is
    sparse (used by the smoother). Fallback: dense ``F_jacobian`` at every frame
    (:func:`sfem_filters.filtering.linearised.linearise_dense`)."""

    def linearise(self, states, sensitivity: bool = True) -> object:
        """A :class:`sfem_filters.filtering.linearised.LinearisedModel` about ``states``
        (n_frames, n) sharing one ``theta``; ``sensitivity=False``: theta held fixed (p = 0)."""


@runtime_checkable
class OutputOperators(Protocol):
    """Optional: named linear functions of the restart state whose uncertainty a smoother reports
    (for the SFEM model: nodal strains). Fallback: none."""

    def output_operators(self) -> dict:
        """``{name: (k, n_restart) matrix}``, in model coordinates."""


@runtime_checkable
class ScalableProcessNoise(Protocol):
    """Optional, needed to estimate the process noise level from the data
    (``IteratedSmoother(process_noise="estimate")``): no fallback."""

    def with_process_noise(self, scale: float) -> object:
        """The same model with every process noise covariance multiplied by ``scale`` (> 0):
        ``Q`` becomes ``scale * Q``; everything else, the fingerprint aside, is unchanged."""


@runtime_checkable
class ScalableMeasurementNoise(Protocol):
    """Optional, needed to estimate the measurement noise level from the data
    (``IteratedSmoother(measurement_noise="estimate")``): no fallback."""

    def with_measurement_noise(self, scale: float) -> object:
        """The same model with every measurement noise covariance multiplied by ``scale`` (> 0):
        ``R`` (and each frame's R) becomes ``scale * R``; everything else, the fingerprint aside,
        is unchanged."""


def check_model(model, name: str = "model"):
    """Raise ``TypeError`` naming ``name`` and the missing members unless ``model`` satisfies
    :class:`FilterModel`."""
    if isinstance(model, FilterModel):
        return model
    need = [k for k in ("dim_state", "dim_obs", "n_restart", "n_frames", "estimates_material", "x0", "P0",
                        "Q", "R", "fx", "F_jacobian", "hx", "H_jacobian") if not hasattr(model, k)]
    raise TypeError(f"{name}: expected a model with the members of sfem_filters.filtering.FilterModel, "
                    f"got a {type(model).__name__} without {need}")


def measurement_cov(model, t: int) -> np.ndarray:
    """R of frame ``t``: ``model.R_at(t)`` for :class:`PerFrameNoise` models, else ``model.R``."""
    return np.asarray(model.R_at(t) if isinstance(model, PerFrameNoise) else model.R, float)


def process_profile(model):
    """The model's :class:`ProcessNoiseProfile` factors, checked, as an (n_frames - 1,) array; None
    when it has none (``Q`` every interval). A ``ValueError`` names ``process_profile`` otherwise."""
    if not isinstance(model, ProcessNoiseProfile):
        return None
    s = model.process_profile()
    if s is None:
        return None
    s = np.asarray(s, float)
    n = int(model.n_frames) - 1
    if s.shape != (n,) or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"process_profile: expected {n} finite factors > 0 on Q (one per frame interval), got "
                         f"shape {s.shape}" + (f", minimum {float(np.min(s))!r}" if s.size else ""))
    return s


def model_fingerprint(model) -> str:
    """The model's own :class:`Fingerprinted` hash, or the fallback over its matrices."""
    if isinstance(model, Fingerprinted):
        return model.fingerprint()
    h = hashlib.sha256()
    for a in (model.x0, model.P0, model.Q, model.R, model.H_jacobian(model.x0, 0)):
        h.update(np.ascontiguousarray(np.asarray(a, float)).tobytes())
    profile = process_profile(model)
    if profile is not None:
        h.update(profile.tobytes())
    h.update(f"{type(model).__qualname__},{model.dim_state},{model.n_restart},{model.n_frames}".encode())
    return h.hexdigest()


def physical_parameters(model, theta) -> np.ndarray:
    """:meth:`PhysicalParameters.physical_parameters` of ``theta``, or ``theta`` itself."""
    if isinstance(model, PhysicalParameters):
        return np.asarray(model.physical_parameters(theta), float)
    return np.asarray(theta, float)


def physical_jacobian(model, theta):
    """:meth:`PhysicalJacobian.physical_jacobian` at ``theta``, or ``None`` (the identity)."""
    if isinstance(model, PhysicalJacobian):
        return model.physical_jacobian(theta)
    return None


def scaled_process_noise(model, scale: float):
    """``model.with_process_noise(scale)`` of a :class:`ScalableProcessNoise` model; ``TypeError``
    naming the model's type otherwise."""
    if not isinstance(model, ScalableProcessNoise):
        raise TypeError(f"model: estimating the process noise level needs a model with "
                        f"with_process_noise(scale) (sfem_filters.filtering.ScalableProcessNoise), got a "
                        f"{type(model).__name__} without it")
    return model.with_process_noise(scale)


def scaled_measurement_noise(model, scale: float):
    """``model.with_measurement_noise(scale)`` of a :class:`ScalableMeasurementNoise` model;
    ``TypeError`` naming the model's type otherwise."""
    if not isinstance(model, ScalableMeasurementNoise):
        raise TypeError(f"model: estimating the measurement noise level needs a model with "
                        f"with_measurement_noise(scale) (sfem_filters.filtering.ScalableMeasurementNoise), got a "
                        f"{type(model).__name__} without it")
    return model.with_measurement_noise(scale)


def n_parameters(model) -> int:
    """Number of static parameters in the state, ``dim_state - n_restart``."""
    return int(model.dim_state) - int(model.n_restart)


def parameter_prior(model) -> tuple:
    """The static parameters' prior: their mean and covariance, the parameter blocks of ``x0`` and
    ``P0`` (``(p,)`` and ``(p, p)`` arrays, model units)."""
    nr = int(model.n_restart)
    return np.asarray(model.x0, float)[nr:], np.asarray(model.P0, float)[nr:, nr:]
