"""Models with a linear observation ``y = H z``: the mixin and a linear-Gaussian template.

:class:`LinearObservation` gives a model ``hx``, ``H_jacobian`` and ``make_ekf`` from its
dense ``_H``; :class:`LinearGaussianModel` is a complete small model of the contract
(:mod:`sfem_filters.filtering.protocol`) for tests and as a template for other models.
"""
from __future__ import annotations

import copy

import numpy as np
import scipy.linalg as sla

from .._validate import as_float_array, positive
from .ekf import SFEMExtendedKalmanFilter
from .unscented import make_ukf

__all__ = ["LinearObservation", "LinearGaussianModel"]


class LinearObservation:
    """The measurement side of a filter model with a linear, state-independent ``y = H z``.

    Mixed into the model classes (they set ``self._H``, the dense (dim_obs, dim_state)
    matrix [D 0] of Eq. 22) so that filterpy's EKF and the engines see one ``hx``,
    ``H_jacobian``, ``make_ekf`` and ``make_ukf``.
    """

    def hx(self, z, t=None):
        """Predicted observation H z (Eq. 21) of state z (m, m/s); same ndim as z."""
        z = np.asarray(z, float)
        y = self._H @ z.ravel()
        return y.reshape(-1, 1) if z.ndim == 2 else y

    def H_jacobian(self, z=None, t=None) -> np.ndarray:
        """H = [D 0] (Eq. 22), dense (dim_obs, dim_state)."""
        return self._H

    def make_ekf(self) -> SFEMExtendedKalmanFilter:
        """A filterpy ``ExtendedKalmanFilter`` set up with this model's x0, P0, Q and R.

        Drive it as::

            ekf = model.make_ekf()
            for t, y in enumerate(observations):
                if t > 0:
                    ekf.predict(u=t - 1)          # u is the frame the step starts from
                ekf.update(y.reshape(-1, 1), model.H_jacobian, model.hx, args=t, hx_args=t)
        """
        return SFEMExtendedKalmanFilter(self)

    def make_ukf(self, **points):
        """filterpy's ``UnscentedKalmanFilter`` on this model.

        See :func:`sfem_filters.filtering.unscented.make_ukf`; ``points``: Merwe's ``alpha``,
        ``beta``, ``kappa``. Drive it as::

            ukf = model.make_ukf()
            for t, y in enumerate(observations):
                if t > 0:
                    ukf.predict(t=t - 1)
                ukf.update(y, t=t)
        """
        return make_ukf(self, **points)


class LinearGaussianModel(LinearObservation):
    """A linear-Gaussian state-space model with unknown parameters appended to the state.

    ``x_{t+1} = A(theta) x_t + u_t + w_t``, ``y_t = H x_t + v_t``, ``w ~ N(0, Q)``,
    ``v ~ N(0, R)``, on the augmented state ``z = [x; theta]`` with theta constant. It has the
    interface of :class:`sfem_filters.model.SFEMModel` that the engines use (``fx``,
    ``F_jacobian``, ``transition_derivatives``, ``hx``, ``H_jacobian``, ``Q``, ``R``, ``x0``,
    ``P0``, ``n_restart``, ...), so small systems run through the same engine code: tests of
    the engines, of Ljung's modification, and a template for other models.

    Parameters
    ----------
    transition : callable or (n, n) array
        ``transition(theta) -> (A, dA)`` with ``dA[i] = dA/dtheta_i``, shape (p, n, n); or a
        fixed A (no parameters).
    H : (m, n) array
    Q : (n, n) array
        Process noise covariance (PSD, may be singular).
    R : (m, m) array
        Measurement noise covariance (positive definite).
    x0, P0 : (n,) and (n, n) arrays
        Initial state and covariance of x.
    n_frames : int
        Length of the sequence (>= 2).
    theta0 : (p,) array
        Initial parameter estimate.
    prior_cov : (p, p) array
        Its covariance.
    inputs : (n_frames, n) array, optional
        Known inputs u_t (moving frame t to t + 1 uses ``inputs[t + 1]``, like the loads).
    """

    def __init__(self, transition, H, Q, R, x0, P0, n_frames: int, theta0=(), prior_cov=None, inputs=None):
        theta0 = as_float_array("theta0", theta0, shape=(None,))
        p = len(theta0)
        if callable(transition):
            self._transition = transition
        else:
            A_fixed = as_float_array("transition", transition, shape=(None, None))
            self._transition = lambda th: (A_fixed, np.zeros((0,) + A_fixed.shape))
        A, dA = self._transition(theta0)
        n = np.asarray(A).shape[0]
        if np.asarray(A).shape != (n, n) or np.asarray(dA).shape != (p, n, n):
            raise ValueError(f"transition: expected A of shape ({n}, {n}) and dA of shape ({p}, {n}, {n}), "
                             f"got {np.asarray(A).shape} and {np.asarray(dA).shape}")
        self._Hx = as_float_array("H", H, shape=(None, n))
        m = self._Hx.shape[0]
        Q = as_float_array("Q", Q, shape=(n, n))
        R = as_float_array("R", R, shape=(m, m))
        if np.linalg.eigvalsh(0.5 * (R + R.T)).min() <= 0:
            raise ValueError("R: expected a positive definite measurement noise covariance")
        if int(n_frames) != n_frames or n_frames < 2:
            raise ValueError(f"n_frames: expected an integer >= 2, got {n_frames!r}")
        self._n_frames = int(n_frames)
        self.n_restart = n
        self.dim_x = n
        self.dim_theta = p
        self.dim_state = n + p
        self.dim_obs = m
        self.Q = sla.block_diag(Q, np.zeros((p, p)))
        self.R = R
        P3 = np.zeros((p, p)) if prior_cov is None else as_float_array("prior_cov", prior_cov, shape=(p, p))
        self.x0 = np.concatenate([as_float_array("x0", x0, shape=(n,)), theta0])
        self.P0 = sla.block_diag(as_float_array("P0", P0, shape=(n, n)), P3)
        self._H = np.hstack([self._Hx, np.zeros((m, p))])
        self._u = np.zeros((self._n_frames, n)) if inputs is None else \
            as_float_array("inputs", inputs, shape=(self._n_frames, n))

    @property
    def n_frames(self) -> int:
        """Length of the sequence (frames)."""
        return self._n_frames

    def with_process_noise(self, scale: float) -> "LinearGaussianModel":
        """This model with ``Q`` multiplied by ``scale`` (> 0)."""
        out = copy.copy(self)
        out.Q = self.Q * positive("scale", scale)
        return out

    def with_measurement_noise(self, scale: float) -> "LinearGaussianModel":
        """This model with ``R`` multiplied by ``scale`` (> 0)."""
        out = copy.copy(self)
        out.R = self.R * positive("scale", scale)
        return out

    @property
    def estimates_material(self) -> bool:
        """True when the state carries unknown parameters theta (p > 0)."""
        return self.dim_theta > 0

    def theta_of(self, z) -> np.ndarray:
        """Parameters theta of an augmented state.

        Parameters
        ----------
        z : (dim_state,) array
            An augmented state ``[x; theta]``.

        Returns
        -------
        (p,) array
            Its last p entries (empty when the model has no parameters).
        """
        return np.asarray(z, float).ravel()[self.n_restart:]

    def fx(self, z, t):
        """[A(theta) x + u_{t+1}; theta]."""
        z = np.asarray(z, float)
        flat = z.ravel()
        A, _ = self._transition(flat[self.n_restart:])
        x = np.asarray(A) @ flat[: self.n_restart] + self._u[int(t) + 1]
        return np.concatenate([x, flat[self.n_restart:]]).reshape(z.shape)

    def transition_derivatives(self, z, t) -> np.ndarray:
        """dA/dtheta_i, shape (p, n, n)."""
        return np.asarray(self._transition(np.asarray(z, float).ravel()[self.n_restart:])[1], float)

    def F_jacobian(self, z, t) -> np.ndarray:
        """[[A, [dA_i x]], [0, I]]."""
        flat = np.asarray(z, float).ravel()
        A, dA = self._transition(flat[self.n_restart:])
        F = np.eye(self.dim_state)
        F[: self.n_restart, : self.n_restart] = A
        if self.dim_theta:
            F[: self.n_restart, self.n_restart:] = (np.asarray(dA) @ flat[: self.n_restart]).T
        return F
